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


REPLAY = FIRMWARE / "build" / "fw-replay"


def build(target: str = "host", exe: Path = EXE) -> Path:
    """`make -C firmware host` (or another target); raises RuntimeError with the reason when it
    cannot be built."""
    if not (FIRMWARE / "Makefile").exists() or shutil.which("make") is None:
        raise RuntimeError("the firmware sources or make are missing")
    r = subprocess.run(["make", "-s", "-C", str(FIRMWARE), target], capture_output=True, text=True)
    if r.returncode != 0 or not exe.exists():
        raise RuntimeError(f"cannot build the firmware's {target} (needs make and a C compiler): "
                           f"{r.stderr.strip()[:300]}")
    return exe


def build_replay() -> Path:
    """build/fw-replay: the firmware core run on a scenario (see firmware/tests/replay.c)."""
    return build("replay", REPLAY)


def read_log(path: str | Path) -> np.ndarray:
    return np.frombuffer(Path(path).read_bytes(), dtype=LOG_DTYPE)
