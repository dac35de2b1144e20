"""`hostd bench cli`: what a command-line call costs, as the CPU time of the child process.

A command line pays for its imports on every call; `hostd encode synthetic:wood:3 -o /dev/null
--target-iobj 0.05` (a rate-controlled encode with its SPQI check) is the measured call. Each run
starts `python -m hostd` anew and reads its user + system CPU time from
resource.getrusage(RUSAGE_CHILDREN) (the child's own figure: the load of other processes on the
machine moves it less than wall time); the median of the runs is the figure.

The calls run with their modules' bytecode cached, as an installed hostd has it (pip compiles
it at install; a checkout writes __pycache__ on its first call): a run where nothing may be
cached (PYTHONDONTWRITEBYTECODE, set on this machine's shells and some CI runners) would
compile every module on every call, 0.08 s of the figure that no user pays. The bytecode goes
to a temporary PYTHONPYCACHEPREFIX, filled by a first call that is not counted, so the tree
is left as it is.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile

ENCODE = ["encode", "synthetic:wood:3", "-o", "/dev/null", "--target-iobj", "0.05"]


def child_cpu_s(argv: list[str], env: dict | None = None) -> float:
    """User + system CPU time of one `python -m hostd ARGV` (its output discarded)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-m", "hostd", *argv], check=True, env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def run(runs: int = 5) -> dict:
    import numpy as np

    with tempfile.TemporaryDirectory(prefix="hostd-bench-pyc-") as cache:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        env["PYTHONPYCACHEPREFIX"] = cache
        child_cpu_s(ENCODE, env)  # (bytecode written, the page cache warm, for every run alike)
        times = [child_cpu_s(ENCODE, env) for _ in range(runs)]
        bare = [child_cpu_s(["--version"], env) for _ in range(max(1, runs // 2))]
    return {"bench": "cli", "command": "hostd " + " ".join(ENCODE), "runs": runs,
            "cpu_s": round(float(np.median(times)), 3), "cpu_min_s": round(min(times), 3),
            "cpu_max_s": round(max(times), 3),
            "version_cpu_s": round(float(np.median(bare)), 3)}  # the interpreter and the parser
