"""Shared helpers: CPU-time medians and a description of the machine."""

from __future__ import annotations

import platform
import time

import numpy as np


def cpu_median_s(fn, repeat: int, inner: int = 1) -> float:
    """Median over `repeat` runs of the CPU time (process_time) of `inner` calls, per call."""
    times = []
    for _ in range(repeat):
        t0 = time.process_time_ns()
        for _ in range(inner):
            fn()
        times.append((time.process_time_ns() - t0) / inner)
    return float(np.median(times)) * 1e-9


def machine() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            model = next(line.split(":", 1)[1].strip() for line in fh if "model name" in line)
    except (OSError, StopIteration):
        model = platform.processor() or "unknown CPU"
    import os

    return (f"{model}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
            f"numpy {np.__version__}")
