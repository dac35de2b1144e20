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
                           f"pip install 'hostd[{extra}]'") from None


def have(module: str) -> bool:
    try:
        importlib.import_module(module)
        return True
    except ImportError:
        return False
