"""`hostd bench cycle`: what the host-rendering pump's cycle costs, compiled and not.

The pump (hostd.device.pump, the daemon's own code) streams to the firmware's host port over
its pty for `seconds`, in this process, twice: with the compiled cycle (hostd.device.fastpump,
the daemon's default where it is built) and with the Python reference alone, whose parts are
wrapped in thread-CPU timers: reading the transport, deframing, handling each message
(decode, clock and flow control, health, motion), rendering, encoding and writing SAMPLES,
and the sleep to the next deadline (the kernel's wake-up costs are charged to the thread).
Figures are per cycle; the wrappers add about 1 µs per call. The compiled row counts the
cycles it handed to the reference, by cause. Played fraction from the firmware's DAC log.
First, for scale, the same deadline loop with nothing in it (idle_loop_us_per_wake).
"""

from __future__ import annotations

import gc
import tempfile
import time
from collections import Counter
from pathlib import Path


def idle_loop(seconds: float, period_s: float) -> float:
    """Thread CPU (µs) per wake-up of the pump's deadline schedule with nothing to do: the
    floor any Python loop that wakes every period_s pays on this machine."""
    start, k = time.monotonic(), 0
    c0 = time.thread_time()
    while (now := time.monotonic()) - start < seconds:
        k += 1
        due = start + k * period_s
        if due > now:
            time.sleep(due - now)
    return (time.thread_time() - c0) / max(1, k) * 1e6


PARTS = (("transport read", "read"), ("deframe", "deframe"), ("messages in", "take"),
         ("render", "render"), ("SAMPLES out", "send"), ("sleep", "sleep"))


def run(seconds: float = 8.0, host_cycle_ms: int = 1, texture: str = "wood", compiled: bool = False) -> dict:
    """One run; compiled: the daemon's compiled cycle (no part timers), else the reference."""
    from hostd.bench.accuracy import texture_coeffs
    from hostd.device import fastlink, fastpump, hostport
    from hostd.device import protocol as pr
    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.device.seriallink import SerialTransport
    from hostd.render import fastrender
    from hostd.render.pipeline import RenderConfig, Renderer
    from hostd.texture import synth

    acc: Counter = Counter()

    def wrap(obj, name: str, label: str) -> None:
        f = getattr(obj, name)

        def timed(*a, **k):
            c0 = time.thread_time_ns()
            try:
                return f(*a, **k)
            finally:
                acc[label] += time.thread_time_ns() - c0

        setattr(obj, name, timed)

    floor_us = idle_loop(min(2.0, seconds), host_cycle_ms / 1000)
    with tempfile.TemporaryDirectory(prefix="hostd-cycle-") as tmp:
        log = Path(tmp) / "dac.bin"
        hp = hostport.HostPort(["--motion", "metronome", "--duration", str(seconds + 30)], log=log)
        try:
            t = SerialTransport(hp.pty)
            link = DeviceLink(t, 12)
            link.handshake(2.0)
            link.set_limits(pr.LIMIT_CODE, pr.MAX_STEP_CODE)
            link.set_timeout(50)
            coeffs, n, length = texture_coeffs(synth.make(texture, seed=1))
            r = Renderer(coeffs, n, length, RenderConfig())
            r.start()
            pump = Pump(link, None, period_s=host_cycle_ms / 1000, cycle=fastpump)
            pump.begin(r)
            compiled = compiled and fastpump.usable(pump)
            real_sleep = time.sleep
            if not compiled:
                wrap(t.ser, "read", "read")
                wrap(t.deframer, "feed", "deframe")
                wrap(link, "_take", "take")
                wrap(r, "render_codes", "render")
                wrap(link, "send_samples", "send")
                wrap(time, "sleep", "sleep")
            gc.collect()
            gc.freeze()
            hand0 = fastpump._C.handovers() if compiled else {}
            try:
                c0, w0 = time.thread_time(), time.monotonic()
                pump.run(seconds, compiled=compiled)
                c1, w1 = time.thread_time(), time.monotonic()
            finally:
                time.sleep = real_sleep
                gc.unfreeze()
            pump.end()
        finally:
            hp.close()
        fig = hostport.playback_figures(hostport.read_log(log), to_last_played=True)
    cycles = max(1, pump.stats.cycles)
    total = (c1 - c0) / cycles * 1e6
    row = {"bench": "cycle", "cycle": "compiled" if compiled else "reference",
           "host_cycle_ms": host_cycle_ms, "seconds": seconds,
           "link": fastlink.IMPLEMENTATION, "render_tail": fastrender.IMPLEMENTATION,
           "cycles_per_s": round(cycles / (w1 - w0), 1),
           "thread_cpu_share": round((c1 - c0) / (w1 - w0), 4), "cpu_us_per_cycle": round(total, 1)}
    if compiled:
        p50, p99, _ = pump.step_percentiles_us()
        hand = {k: v - hand0.get(k, 0) for k, v in fastpump._C.handovers().items()}
        done = hand.pop("compiled")
        row |= {"step_p50_us": round(p50, 1), "step_p99_us": round(p99, 1), "compiled_cycles": done,
                "handed_over_per_s": round(sum(hand.values()) / (w1 - w0), 1),
                "handed_over": {k: v for k, v in hand.items() if v}}
    else:
        per = {label: acc[key] / cycles / 1e3 for label, key in PARTS}
        row |= {**{f"{label.replace(' ', '_')}_us": round(v, 1) for label, v in per.items()},
                "other_us": round(total - sum(per.values()), 1)}
    return row | {"idle_loop_us_per_wake": round(floor_us, 1),
                  "played_fraction": round(fig["played_fraction"], 5),
                  "underrun_episodes": fig["underrun_episodes"]}


def run_both(seconds: float = 8.0, host_cycle_ms: int = 1) -> list[dict]:
    """The reference, then the compiled cycle (where it is built), in one invocation; the
    compiled row carries the ratio of the two CPU times per cycle."""
    from hostd.device import fastpump

    rows = [run(seconds, host_cycle_ms, compiled=False)]
    if fastpump.IMPLEMENTATION == "c":
        c = run(seconds, host_cycle_ms, compiled=True)
        ratio = rows[0]["cpu_us_per_cycle"] / max(c["cpu_us_per_cycle"], 1e-9)
        c["reference_over_compiled"] = round(ratio, 2)
        rows.append(c)
    return rows
