"""The optional compiled modules (C extensions built by setup.py with optional=True): one loader.

Each compiled module has a pure-Python reference it is tested against; the compiled one is used
only when it was built, carries the revision its wrapper was written for, and HOSTD_PURE_PYTHON
is unset (or 0). `hostd doctor` reports which implementation each wrapper uses.
"""

from __future__ import annotations

import importlib
import os
from types import ModuleType


def load(module: str, revision: int) -> ModuleType | None:
    """The compiled `module` (e.g. "hostd.codec._rangecoder") if usable, else None."""
    if os.environ.get("HOSTD_PURE_PYTHON", "") not in ("", "0"):
        return None
    try:
        mod = importlib.import_module(module)
    except ImportError:
        return None
    return mod if getattr(mod, "REVISION", None) == revision else None
