"""`hostd bench cli`: what a command-line call costs, as the CPU time of the child process.

A command line pays for its imports on every call; `hostd encode synthetic:wood:3 -o /dev/null
--target-iobj 0.05` (a rate-controlled encode with its SPQI check) is the measured call. Each run
starts `python -m hostd` anew and reads its user + system CPU time from
resource.getrusage(RUSAGE_CHILDREN) (the child's own figure: the load of other processes on the
machine moves it less than wall time); the median of the runs is the figure.
"""

from __future__ import annotations

import resource
import subprocess
import sys

ENCODE = ["encode", "synthetic:wood:3", "-o", "/dev/null", "--target-iobj", "0.05"]


def child_cpu_s(argv: list[str]) -> float:
    """User + system CPU time of one `python -m hostd ARGV` (its output discarded)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "hostd", *argv], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def run(runs: int = 5) -> dict:
    import numpy as np

    child_cpu_s(["--version"])  # (the page cache warm for every run alike)
    times = [child_cpu_s(ENCODE) for _ in range(runs)]
    bare = [child_cpu_s(["--version"]) for _ in range(max(1, runs // 2))]
    return {"bench": "cli", "command": "hostd " + " ".join(ENCODE), "runs": runs,
            "cpu_s": round(float(np.median(times)), 3), "cpu_min_s": round(min(times), 3),
            "cpu_max_s": round(max(times), 3),
            "version_cpu_s": round(float(np.median(bare)), 3)}  # the interpreter and the parser
