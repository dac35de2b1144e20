"""The pump process's set-up: what it imports first, its real-time settings, its death with the
daemon, the host renderer loaded only when it renders, and its compiled cycle loaded at first use."""

from __future__ import annotations

import os
import signal
import sys
import time

from hostd.service.pumpstate import STAT_INDEX

# the kernel's notice of the daemon's death (PR_SET_PDEATHSIG): a signal of its own, not SIGTERM
PARENT_DEATH_SIGNAL = signal.SIGUSR2


def _realtime(rt, log) -> None:
    if rt.cpu >= 0:
        try:
            os.sched_setaffinity(0, {rt.cpu})
            log(f"pump pinned to CPU {rt.cpu}")
        except OSError as e:
            log(f"pump: cannot pin to CPU {rt.cpu} ({e.strerror}); running unpinned")
    # (rt.sched_fifo_priority: the pump takes it while it streams, hostd.device.realtime)
    if rt.mlockall:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(3) != 0:  # MCL_CURRENT | MCL_FUTURE
            log(f"pump: mlockall failed ({os.strerror(ctypes.get_errno())}); memory may page: "
                "raise LimitMEMLOCK")
        else:
            log("pump memory locked (mlockall)")


def _die_with_parent() -> None:
    """Linux: the pump gets PARENT_DEATH_SIGNAL (it ramps to zero, says "daemon gone" and exits)
    when the daemon dies, even by SIGKILL outside systemd, so no orphaned pump keeps driving the
    display. Not SIGTERM: the kernel sends it when the daemon's thread that started the pump
    exits, and under SIGKILL that can come before the daemon's other threads are gone; the pump's
    parent is then one of them (getppid() still the daemon's pid) and its pipe not yet at EOF, so
    a SIGTERM would look like a stop (systemctl kill, terminate()) and the line would be lost."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(PARENT_DEATH_SIGNAL))  # PR_SET_PDEATHSIG
        # PR_SET_NAME: `ps` and a refused raw-USB claim ("busy: pid N (hostd-pump) ...") name it
        libc.prctl(15, ctypes.c_char_p(b"hostd-pump"))
        if os.getppid() == 1:  # the parent died before prctl took effect
            os.kill(os.getpid(), PARENT_DEATH_SIGNAL)
    except (OSError, AttributeError):
        pass


LOADING_ALLOWANCE_S = 120.0  # the daemon's watchdog allowance while the pump loads the host renderer


def preload_host_rendering(stats=None) -> None:
    """Import the host renderer and scipy.signal (its equalizer) now: a pump that will render on
    the host loads them before it plays; device mode never does. Seconds on a slow or emulated
    CPU with no progress to show: `stats` (the shared counters) carries a deadline meanwhile,
    busy_until_s (CLOCK_MONOTONIC), that the daemon's watchdog takes as liveness (bounded)."""
    if "hostd.render.pipeline" in sys.modules and "scipy.signal" in sys.modules:
        return
    if stats is not None:
        stats[STAT_INDEX["busy_until_s"]] = time.monotonic() + LOADING_ALLOWANCE_S
    try:
        from hostd.render import equalizer, pipeline  # noqa: F401

        equalizer.preload()
    finally:
        if stats is not None:
            stats[STAT_INDEX["busy_until_s"]] = 0.0


def poll_of(fd: int | None):
    """A poll object watching `fd` for input (the udev monitor's); None when there is no fd."""
    if fd is None:
        return None
    import select

    p = select.poll()
    p.register(fd, select.POLLIN)
    return p


def prepare_rendering(where: str, rcfg, stats):
    """Before the first connection (PumpProcess.start): where = "host", the host renderer loaded (a
    selection plays at once) and None; else the display's parameters designed now, not between a
    display's arrival and playing (devrender.device_params: Python arithmetic, no scipy.signal),
    or None for a setting the display cannot render (said when one connects, as before)."""
    if where == "host":
        preload_host_rendering(stats)
        return None
    from hostd.device import devrender

    try:
        return devrender.device_params(rcfg)
    except ValueError:
        return None


class CompiledCycle:
    """The pump's compiled cycle (hostd.device.fastpump), imported at its first use: host
    rendering and stimuli load it, device rendering never does (the supervisor stays lean)."""

    def usable(self, pump) -> bool:
        from hostd.device import fastpump

        return fastpump.usable(pump)

    def run(self, pump, start_s: float, k: int, duration_s, fds=()):
        from hostd.device import fastpump

        return fastpump.run(pump, start_s, k, duration_s, fds)


# what the pump process runs on, imported first thing (PumpProcess): before its signals, and
# frozen by gc.freeze() with the rest of the set-up; never at this module's import, which the
# daemon does for its constants. (The renderer, scipy and hostd.device.fastpump are host
# rendering's and the stimuli's, imported where they start: device mode never loads them)
DEVICE_SIDE = ("resource", "numpy", "hostd.device.devrender", "hostd.device.protocol", "hostd.device.devmode",
               "hostd.device.health", "hostd.device.hotplug", "hostd.device.link", "hostd.device.pump",
               "hostd.device.realtime", "hostd.device.transport", "hostd.errors", "hostd.service.pumpguards")

