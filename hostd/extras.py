"""Optional dependencies, imported where they are used: `hostd[plot]` (matplotlib: the report's and
benchmarks' PNGs), `hostd[sim]` (finufft: the scene simulator's series fits), `hostd[device]`
(hidapi, pyusb), `hostd[peer]` (vibromaf), `hostd[metrics]` (prometheus_client). A display PC
installs `hostd[device]` and stays small; a command that needs an extra it lacks says which, in
one line, exit code 2."""

from __future__ import annotations

import importlib
from types import ModuleType

from hostd.errors import HostdError


class MissingExtra(HostdError):
    """An optional dependency is not installed."""


def need(module: str, extra: str, what: str) -> ModuleType:
    """import `module`, or MissingExtra naming the extra that provides it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtra(f"{what} needs {module.split('.')[0]}, which is in the {extra!r} extra: "
                           f"{pip_install(extra)}") from None


def install_source() -> str | None:
    """Where this hostd comes from, as pip takes it: the checkout it runs from (an editable
    install, PYTHONPATH), else the wheel or directory it was installed from (PEP 610's
    direct_url.json of the installed distribution); None when unknown (e.g. from an index)."""
    import json
    from pathlib import Path
    from urllib.parse import unquote, urlparse

    root = Path(__file__).resolve().parent.parent
    if _is_checkout(root):
        return str(root)
    try:
        from importlib.metadata import PackageNotFoundError, distribution

        info = json.loads(distribution("hostd").read_text("direct_url.json") or "{}")
    except (PackageNotFoundError, ValueError, OSError):
        return None
    url = urlparse(info.get("url", ""))
    return unquote(url.path) if url.scheme == "file" and url.path else None


def _is_checkout(root) -> bool:
    try:
        return 'name = "hostd"' in (root / "pyproject.toml").read_text()
    except OSError:
        return False


def pip_install(extra: str | None = None, pip: str = "pip") -> str:
    """The command that installs this hostd (with `extra`) from what the user has: the checkout
    or the wheel it came from; hostd is not on a package index."""
    from hostd import __version__

    src = install_source()
    suffix = f"[{extra}]" if extra else ""
    if src:
        return f"{pip} install '{src}{suffix}'"
    return (f"{pip} install './hostd-{__version__}-cp311-cp311-manylinux2014_x86_64.manylinux_2_17_x86_64"
            f".whl{suffix}' (the wheel you installed hostd from; a checkout builds it: pip wheel --no-deps "
            "-w dist .)")


def have(module: str) -> bool:
    try:
        importlib.import_module(module)
        return True
    except ImportError:
        return False
