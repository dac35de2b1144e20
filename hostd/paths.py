"""Where hostd finds its configuration data (threshold curves, actuators, scenes, the unit files).

The data ships inside the package (``hostd/data``, ``hostd/systemd``: read with
importlib.resources, so a wheel installed anywhere finds it). A site can override any file:
a file of the same name under the override directory, ``/etc/hostd`` (or ``$HOSTD_CONFIG_DIR``),
is used in its place; ``hostd/data/thresholds/default.csv`` is overridden by
``/etc/hostd/thresholds/default.csv``.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

ETC = Path("/etc/hostd")


def _package_dir(name: str) -> Path:
    p = resources.files("hostd").joinpath(name)
    if not isinstance(p, Path):  # a zipped install: the data must be on disk
        raise RuntimeError(f"hostd's {name} files are not on disk ({p}): install hostd unzipped")
    return p


def shipped_dir() -> Path:
    """The package's own data directory (config/ in a source checkout, via hostd/data)."""
    return _package_dir("data")


def systemd_dir() -> Path:
    """The package's unit, udev rule, sysusers and tmpfiles files."""
    return _package_dir("systemd")


def override_dir() -> Path:
    """The site's override directory: $HOSTD_CONFIG_DIR or /etc/hostd."""
    env = os.environ.get("HOSTD_CONFIG_DIR")
    return Path(env) if env else ETC


def config_dir() -> Path:
    """Kept for callers that want one directory: the shipped data."""
    return shipped_dir()


def search_dirs(sub: str) -> list[Path]:
    """The directories searched for files of one kind, the override first."""
    return [override_dir() / sub, shipped_dir() / sub]


def find(sub: str, filename: str) -> Path:
    """The override's file if it exists, else the shipped one (which may not exist: callers
    report the shipped path in their error)."""
    for d in search_dirs(sub):
        p = d / filename
        if p.is_file():
            return p
    return shipped_dir() / sub / filename


def thresholds_dir() -> Path:
    return shipped_dir() / "thresholds"


def actuators_dir() -> Path:
    return shipped_dir() / "actuators"


def scenes_dir() -> Path:
    return shipped_dir() / "scenes"
