"""The daemon's side of the pump process: the one writer of its pipe (PumpWriter), its counters
read from shared memory as one snapshot, and a play's figures bounded by what the host knows."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque

from hostd.device.health import CLOCK_TOLERANCE, REPORT_SLACK_S, fault_names
from hostd.device.health import STATE_NAMES as DEVICE_STATES
from hostd.device.protocol import BUFFER_CAPACITY, SAMPLE_RATE_HZ
from hostd.errors import HostdError
from hostd.service.pumpstate import FLOAT_FIELDS, PUBLISH_SEQ, RENDER_REASONS, STAT_FIELDS, STATE_NAMES

log = logging.getLogger("hostd")


class PumpWriter:
    """The one writer of the pump's pipe. Handler threads hand their commands to this thread, so
    no two messages ever interleave on the pipe (a texture of N' = 16,000 pickles to more than
    a pipe's atomic write). A select or stop still waiting to be sent is superseded by a newer
    one: only the latest choice matters to the pump."""

    def __init__(self, conn) -> None:
        self.conn = conn
        self.cv = threading.Condition()
        self.pending: deque = deque()
        self.closed = False
        self.thread = threading.Thread(target=self._run, name="pump-writer", daemon=True)
        self.thread.start()

    def send(self, msg: tuple) -> None:
        with self.cv:
            if self.closed:
                raise HostdError("hostd is stopping")
            if msg[0] in ("select", "stop"):
                kept = [m for m in self.pending if m[0] not in ("select", "stop")]
                self.pending.clear()
                self.pending.extend(kept)
            self.pending.append(msg)
            self.cv.notify()

    def _run(self) -> None:
        while True:
            with self.cv:
                while not self.pending:
                    self.cv.wait()
                msg = self.pending.popleft()
            if msg is None:
                return
            try:
                self.conn.send(msg)
            except (OSError, ValueError) as e:  # the pump is gone: the main loop says so and stops
                log.error("cannot send %s to the pump: %s", msg[0], e)

    def close(self, last: tuple = ("quit",), timeout_s: float = 3.0) -> None:
        with self.cv:
            if self.closed:
                return
            self.pending.append(last)
            self.pending.append(None)
            self.closed = True
            self.cv.notify()
        self.thread.join(timeout_s)


# what a device's counters may claim over a play, beyond the host's own clock: the device's
# clock runs at most this much fast (crystal tolerance, with margin), plus its report's age


def bound_play(c0: dict, c1: dict, host_s: float) -> tuple[dict, list[str]]:
    """What a play delivered, from the device's counters at its start (c0) and end (c1), bounded by
    what the host knows: its own clock, the samples it sent and the device's buffer. Returns the
    plays row's device_s, played_s, played_fraction and underruns, and the counters that claimed
    the impossible (empty when none did), each said in a few words.

    Like is compared with like: the device's time between the reports the two snapshots hold
    against the host's time between their arrivals (device_report_host_s), not the play's host_s;
    a snapshot is as old as the pump's last publish (0.5 s in device mode, more on a loaded host),
    so an honest device's clock ran on well past host_s. host_s: without those times."""
    bad: list[str] = []
    rx0, rx1 = c0.get("device_report_host_s"), c1.get("device_report_host_s")
    if rx0 is not None and rx1 is not None and rx1 >= rx0:
        host_s = rx1 - rx0  # (rx0 0.0: no report before the play; the pump bounds its first ones)
    limit_s = max(host_s, 0.0) * (1 + CLOCK_TOLERANCE) + REPORT_SLACK_S
    # device time elapsed between its reports, summed over links (the pump's, never going back;
    # bounded there by the links' time up): a play that began before the device's first report,
    # or spans a replug, compares no two clocks
    device_s = c1["device_elapsed_s"] - c0["device_elapsed_s"]
    if not math.isfinite(device_s) or device_s < 0:
        bad.append(f"its clock went from {c0['device_elapsed_s']:.3f} s to {c1['device_elapsed_s']:.3f} s")
        device_s = 0.0
    elif device_s > limit_s:
        bad.append(f"{device_s:.1f} s of its clock in {host_s:.1f} s")
        device_s = max(host_s, 0.0)
    fraction = c1["played_fraction"] if device_s > 0 else None
    if fraction is not None and not (math.isfinite(fraction) and 0.0 <= fraction <= 1.0):
        bad.append(f"a played fraction of {fraction}")
        fraction = min(max(fraction, 0.0), 1.0) if math.isfinite(fraction) else None
    if c1["render_at"] == "device":  # the display renders: nothing is played from its buffer,
        played_s = (fraction or 0.0) * device_s  # the share of device time it reported rendering
    else:
        played = c1["device_samples_played"] - c0["device_samples_played"]
        # at most what was sent meanwhile, plus what the buffer held at the start
        most = max(c1["samples"] - c0["samples"], 0) + BUFFER_CAPACITY
        if played < 0:
            bad.append(f"samples played went back by {-played}")
            played = 0
        elif played > most:
            bad.append(f"{played} samples played of at most {most} sent and buffered")
            played = most
        played_s = played / SAMPLE_RATE_HZ
        if played_s > limit_s:
            bad.append(f"{played_s:.1f} s played in {host_s:.1f} s")
            played_s = max(host_s, 0.0)
    underruns = c1["device_underruns"] - c0["device_underruns"]
    most_underruns = int(limit_s * SAMPLE_RATE_HZ / 2) + 1  # an episode: a sample missed, one played
    if underruns < 0:
        bad.append(f"underruns went back by {-underruns}")
        underruns = 0
    elif underruns > most_underruns:
        bad.append(f"{underruns} underruns in {host_s:.1f} s")
        underruns = most_underruns
    return {"device_s": device_s, "played_s": played_s, "played_fraction": fraction,
            "underruns": underruns}, bad



def read_counters(stats) -> dict:
    """The pump's counters, from shared memory (`stats`): one snapshot of one publish (the pump's
    seqlock), so the device's counters and its clock agree; a pump stopped in the middle of
    a publish (SIGSTOP) leaves a torn one after 10 ms of retries rather than a hang."""
    for _ in range(20):
        seq = stats[PUBLISH_SEQ]
        vals = stats[:]
        if seq % 2 == 0 and stats[PUBLISH_SEQ] == seq:
            break
        time.sleep(0.0005)
    st = dict(zip(STAT_FIELDS, vals, strict=True))
    del st["publish_seq"]
    for k in st:
        if k not in FLOAT_FIELDS:
            st[k] = int(st[k])
    st["state"] = STATE_NAMES.get(st["state"], "?")
    st["connected"] = bool(st["connected"])
    # from the device's own STATUS counters (hostd.device.health)
    code = st["device_state"]
    st["device_state"] = DEVICE_STATES.get(code, "unknown") if st["connected"] else "unknown"
    st["device_faults"] = fault_names(st.pop("device_fault_bits"))
    st["underruns"] = st["device_underruns"]  # the name older clients read
    st["render_at"] = "device" if st["render_at"] else "host"  # who renders the texture now
    st["render_reason"] = RENDER_REASONS[st["render_reason"]] if 0 <= st["render_reason"] < len(
        RENDER_REASONS) else "?"  # and why there ([render] where, the display's version and CAPS)
    st["target_fill_ms"] = round(st["target_fill"] / SAMPLE_RATE_HZ * 1e3, 2)
    pf = st["played_fraction"]  # a share: whatever a device says, shown within [0, 1]
    st["played_fraction"] = min(max(pf, 0.0), 1.0) if math.isfinite(pf) else 0.0
    return st
