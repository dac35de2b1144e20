"""Shared helpers: CPU-time medians and a description of the machine."""

from __future__ import annotations

import platform
import time

import numpy as np


def one_blas_thread():
    """A context in which BLAS/OpenMP pools run one thread (threadpoolctl), so that the CPU time
    of the calling thread is all the work: an idle second BLAS thread spinning on another core
    is neither charged nor needed. A no-op context when threadpoolctl is missing."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        import contextlib

        return contextlib.nullcontext()
    return threadpool_limits(limits=1)


def cpu_median_s(fn, repeat: int, inner: int = 1, limit_blas: bool = True) -> float:
    """Median over `repeat` runs of the CPU time of this thread (time.thread_time) for `inner`
    calls, per call, with BLAS limited to this thread (see one_blas_thread). limit_blas=False
    when the caller already holds one_blas_thread() around many calls (entering it costs ~10 ms:
    threadpoolctl scans the loaded libraries)."""
    return float(np.median(cpu_times_s(fn, repeat, inner, limit_blas)))


def cpu_times_s(fn, repeat: int, inner: int = 1, limit_blas: bool = True) -> list[float]:
    """Every run's CPU time of `cpu_median_s` (s per call), for a median and its spread."""
    import contextlib

    times = []
    with one_blas_thread() if limit_blas else contextlib.nullcontext():
        for _ in range(repeat):
            t0 = time.thread_time_ns()
            for _ in range(inner):
                fn()
            times.append((time.thread_time_ns() - t0) / inner * 1e-9)
    return times


def machine() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            model = next(line.split(":", 1)[1].strip() for line in fh if "model name" in line)
    except (OSError, StopIteration):
        model = platform.processor() or "unknown CPU"
    import os

    return (f"{model}, {os.cpu_count()} CPUs, Python {platform.python_version()}, "
            f"numpy {np.__version__}")


def progress(total: int, desc: str, enabled: bool | None = None):
    """A progress bar on stderr for a benchmark of several steps (tqdm), off when stderr is not a
    terminal (pipes, CI logs; whatever `enabled` says) or with --json; update(1) after each step.
    The steps are seconds long, so the bar costs nothing measured (the timings are CPU medians
    inside each step)."""
    from hostd.tty import progress_bar

    return progress_bar(enabled is not False, total=total, desc=desc, unit="step", leave=False)
