"""Supervision of the daemon's worker threads: one that dies is restarted with a log line, unless it
died too often within a minute (then it stays dead and the watchdog is no longer fed)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger("hostd")
RESTARTS_PER_MINUTE = 3  # a worker that dies more often stays dead and the watchdog starves


class Supervisor:
    """The worker threads by name; `wake` wakes the daemon's main loop (which calls supervise)
    when one ends, `stop_event` is the daemon's stop (no restart then)."""

    def __init__(self, stop_event: threading.Event, wake: Callable[[], None]) -> None:
        self.stop_event = stop_event
        self._wake = wake
        self.workers: dict[str, tuple[Callable[[], None], threading.Thread | None, list[float]]] = {}
        self.dead_workers: set[str] = set()

    def start_worker(self, name: str, target: Callable[[], None]) -> None:
        def body() -> None:
            try:
                target()
            except Exception as e:
                log.error("worker %s failed: %s: %s", name, type(e).__name__, e)
            finally:
                self._wake()  # the main loop restarts it (supervise), not a timer

        t = threading.Thread(target=body, name=name, daemon=True)
        prev = self.workers.get(name)
        self.workers[name] = (target, t, prev[2] if prev else [])
        t.start()

    def supervise(self) -> bool:
        """Restart a worker thread that died (with a log line); False when one stays dead."""
        now = time.monotonic()
        for name, (target, t, restarts) in list(self.workers.items()):
            if t is None or t.is_alive() or self.stop_event.is_set() or name in self.dead_workers:
                continue
            restarts[:] = [r for r in restarts if now - r < 60.0]
            if len(restarts) >= RESTARTS_PER_MINUTE:
                self.dead_workers.add(name)
                log.error("worker %s stopped %d times within a minute: left stopped; the watchdog is no "
                          "longer fed, so systemd restarts hostd", name, len(restarts) + 1)
                continue
            restarts.append(now)
            log.error("worker %s stopped; restarted", name)
            self.start_worker(name, target)
        return not self.dead_workers

