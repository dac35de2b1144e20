"""The pump's real-time policy (`[realtime]`, hostd.service.pumpproc._realtime): SCHED_FIFO 10 by
default where permitted, nothing it starts inherits it, and where it is not permitted one line says
what to do and the pump runs as before."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

import pytest

PROBE = r"""
import os, resource, sys
from hostd.service.config import RealtimeCfg
from hostd.service.pumpproc import _realtime
if sys.argv[1] == "drop":  # a user without the right: no RLIMIT_RTPRIO, not root
    resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
    os.setresgid(65534, 65534, 65534)
    os.setresuid(65534, 65534, 65534)
lines = []
_realtime(RealtimeCfg(), lines.append)
pid = os.fork()
if pid == 0:
    os._exit(0 if os.sched_getscheduler(0) == os.SCHED_OTHER else 3)
_, status = os.waitpid(pid, 0)
print(os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.waitstatus_to_exitcode(status))
print("\n".join(lines))
"""


def _probe(mode: str) -> tuple[list[int], list[str]]:
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p))
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, env=env,
                         timeout=60, cwd=root)
    assert out.returncode == 0, out.stderr
    first, *lines = out.stdout.splitlines()
    return [int(x) for x in first.split()], lines


@pytest.mark.skipif(os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_RTPRIO)[0] < 10,
                    reason="SCHED_FIFO 10 is not permitted to this user (the not-permitted case runs below)")
def test_the_pump_runs_sched_fifo_10_by_default_and_nothing_it_starts_inherits_it():
    (policy, prio, child), lines = _probe("keep")
    assert policy == os.SCHED_FIFO | os.SCHED_RESET_ON_FORK and prio == 10
    assert child == 0  # the forked child runs SCHED_OTHER
    assert lines == ["pump runs SCHED_FIFO priority 10"]


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping to an unprivileged user needs root")
def test_a_pump_not_permitted_sched_fifo_says_what_to_do_and_runs_as_before():
    (policy, prio, child), lines = _probe("drop")
    assert policy == os.SCHED_OTHER and prio == 0 and child == 0
    assert len(lines) == 1 and lines[0].startswith("pump: SCHED_FIFO 10 not permitted (")
    assert "LimitRTPRIO" in lines[0] and "sched_fifo_priority = 0" in lines[0]
