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
