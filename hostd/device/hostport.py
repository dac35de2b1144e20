"""The firmware's host port (firmware/port/host): building it and reading its DAC log."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"
EXE = FIRMWARE / "build" / "hostd-fw-host"
# one record per 3 kHz tick (port/host/main.c, log_tick); flags bit 0: from the buffer, bit 1: underrun
LOG_DTYPE = np.dtype([("tick", "<u4"), ("code", "<i2"), ("enc", "<u4"), ("flags", "<u2")])


def build() -> Path:
    """`make -C firmware host`; raises RuntimeError with the reason when it cannot be built."""
    if not (FIRMWARE / "Makefile").exists() or shutil.which("make") is None:
        raise RuntimeError("the firmware sources or make are missing")
    r = subprocess.run(["make", "-s", "-C", str(FIRMWARE), "host"], capture_output=True, text=True)
    if r.returncode != 0 or not EXE.exists():
        raise RuntimeError(f"cannot build the firmware host port (needs make and a C compiler): "
                           f"{r.stderr.strip()[:300]}")
    return EXE


def read_log(path: str | Path) -> np.ndarray:
    return np.frombuffer(Path(path).read_bytes(), dtype=LOG_DTYPE)
