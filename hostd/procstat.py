"""A process's figures as the kernel counts them (/proc): CPU time of every thread, voluntary
context switches, PSS, threads, children. The benches (`hostd bench soak`, the fleet shipper's)
measure the daemon, its pump and the shipper with these."""

from __future__ import annotations

import os
from pathlib import Path


def _task_cpu_ns(pid: int) -> dict[int, int]:
    """Every thread's time on a CPU so far, in ns (/proc/PID/task/*/schedstat)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out[int(task.name)] = int((task / "schedstat").read_text().split()[0])
        except (OSError, IndexError, ValueError):
            pass
    return out


class CpuClock:
    """A process's CPU time over a run, in ns from every thread's schedstat (utime + stime come in
    10 ms ticks: 0.125 % of a core over 8 s, too coarse for device mode's 0.15 % goal). A thread
    that ends takes its schedstat with it, so each thread's latest value is kept (sample() once a
    second): one that ends loses at most its last second (a control handler idle 30 s: nothing)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.base = _task_cpu_ns(pid)
        self.seen = dict(self.base)
        self.wake_base = _task_wakeups(pid)  # (the same for the threads' voluntary switches)
        self.wake_seen = dict(self.wake_base)

    def sample(self) -> None:
        try:
            self.seen.update(_task_cpu_ns(self.pid))
            self.wake_seen.update(_task_wakeups(self.pid))
        except OSError:
            pass

    def elapsed_s(self) -> float:
        self.sample()
        return (sum(self.seen.values()) - sum(self.base.values())) * 1e-9

    def wakeups(self) -> int:
        """Voluntary context switches of all its threads since the start (after elapsed_s)."""
        return sum(self.wake_seen.values()) - sum(self.wake_base.values())


def child_pids(pid: int) -> list[int]:
    """The process's children, from /proc (every thread's list)."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _task_wakeups(pid: int) -> dict[int, int]:
    """Voluntary context switches of each thread of a process: the times it went to sleep."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            for line in (task / "status").read_text().splitlines():
                if line.startswith("voluntary_ctxt_switches:"):
                    out[int(task.name)] = int(line.split()[1])
        except OSError:
            pass
    return out


def _wakeups(pid: int) -> int:
    """Voluntary context switches of every thread of a process, now."""
    return sum(_task_wakeups(pid).values())


def pss_kb(pid: int) -> int:
    """Proportional set size of a process in kB (/proc/PID/smaps_rollup): its private pages plus
    its share of the pages it maps with other processes (a shared library mapped by the daemon and
    its pump counts half in each)."""
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
        if line.startswith("Pss:"):
            return int(line.split()[1])
    raise OSError(f"no Pss in /proc/{pid}/smaps_rollup")


def threads(pid: int) -> int:
    """Threads of a process (/proc/PID/task)."""
    return len(os.listdir(f"/proc/{pid}/task"))


def descendants(pid: int) -> set[int]:
    """pid and every process below it, children's children included (from /proc/*/stat: a child
    reparented away, its parent gone, is no longer counted)."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, grew = {pid}, True
    while grew:
        new = {p for p, pp in parent.items() if pp in out} - out
        out |= new
        grew = bool(new)
    return out
