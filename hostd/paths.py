"""Where hostd finds its shipped configuration (threshold curves, actuators, scenes)."""

from __future__ import annotations

import os
from pathlib import Path


def config_dir() -> Path:
    """The shipped config directory: $HOSTD_CONFIG_DIR, the source tree's config/, or /etc/hostd."""
    env = os.environ.get("HOSTD_CONFIG_DIR")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parent.parent / "config"
    if here.is_dir():
        return here
    return Path("/etc/hostd")


def thresholds_dir() -> Path:
    return config_dir() / "thresholds"


def actuators_dir() -> Path:
    return config_dir() / "actuators"


def scenes_dir() -> Path:
    return config_dir() / "scenes"


def bundled_profile():
    """The bundled real instrument profile (config/profiles/dektak-1.csv), or None."""
    from hostd.texture.load import LoadOptions, load_profile

    p = config_dir() / "profiles" / "dektak-1.csv"
    if not p.exists():
        return None
    return load_profile(p, LoadOptions(x_unit="um", y_unit="um", length_mm=None, detrend="linear"))
