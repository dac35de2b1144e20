"""systemd's sd_notify for `hostd run`: readiness, status, the watchdog, and its start-up budget.

systemd arms a Type=notify unit's watchdog when the process starts, not at READY=1 (seen under
systemd 252 in the VM rig, tests/hil): a start slower than WatchdogSec= (imports, the pump
process's own imports on a slow board or an emulated CPU) was killed before it could be ready.
So `hostd run` asks for START_WATCHDOG_S while it starts (sd_notify's WATCHDOG_USEC=, systemd
>= 236) and gives the unit's own WatchdogSec= back at READY=1; TimeoutStartSec= still bounds
the start itself.
"""

from __future__ import annotations

import logging
import os

log = logging.getLogger("hostd")
START_WATCHDOG_S = 120.0  # the watchdog's allowance until READY=1


def service_unit(cgroup_file: str = "/proc/self/cgroup", environ=None) -> str | None:
    """The systemd service this process is the main process of ("hostd.service"), or None: its
    cgroup is a .service (a shell's is a .scope or a session) and systemd gave it an
    INVOCATION_ID. `hostd stop --daemon` is refused then: systemd would not start a cleanly
    exited service again (Restart=on-failure), so only `systemctl stop` may stop it."""
    environ = os.environ if environ is None else environ
    if not environ.get("INVOCATION_ID"):
        return None
    try:
        lines = open(cgroup_file, encoding="utf-8").read().splitlines()
    except OSError:
        return None
    for line in lines:  # cgroup v2 ("0::/system.slice/hostd.service"), else v1's name=systemd
        hid, _, rest = line.partition(":")
        controllers, _, path = rest.partition(":")
        if (hid == "0" and controllers == "") or controllers == "name=systemd":
            leaf = path.rstrip("/").rsplit("/", 1)[-1]
            if leaf.endswith(".service"):
                return leaf
    return None


class Notifier:
    """sd_notify, a no-op outside systemd (no NOTIFY_SOCKET)."""

    def __init__(self) -> None:
        self.n = None
        if os.environ.get("NOTIFY_SOCKET"):
            try:
                import sdnotify

                self.n = sdnotify.SystemdNotifier()
                if self.n.socket is not None:  # never block the main loop on a full notify queue
                    self.n.socket.setblocking(False)
            except ImportError:
                log.warning("sdnotify is not installed: systemd readiness and watchdog disabled")
        # the unit's WatchdogSec= (µs), given back at READY=1; None: no watchdog
        self.watchdog_usec = os.environ.get("WATCHDOG_USEC") if self.n is not None else None

    def notify(self, msg: str) -> None:
        if self.n is not None:
            self.n.notify(msg)

    def starting(self) -> None:
        """Before the slow part of the start: the watchdog waits START_WATCHDOG_S."""
        if self.watchdog_usec:
            self.notify(f"WATCHDOG_USEC={int(START_WATCHDOG_S * 1e6)}\nWATCHDOG=1")

    def ready(self) -> None:
        """READY=1, and the unit's own watchdog timeout from now on."""
        self.notify("READY=1" + (f"\nWATCHDOG_USEC={self.watchdog_usec}\nWATCHDOG=1"
                                 if self.watchdog_usec else ""))
