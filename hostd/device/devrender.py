"""The host side of device rendering (protocol v2): the messages that set a display up to render
a texture from its own encoder, from the same RenderConfig the host renderer uses, and scenarios
that run the firmware (C, firmware/build/fw-replay) and its model (hostd.device.fwmodel) on the
same inputs (tests and `hostd bench accuracy`).

    msgs = setup_messages(coeffs, n, length_mm, RenderConfig(), slot=1)
    send_and_confirm(link.t, [*msgs, pr.encode("START_RENDER", host_lost_ms=1000)], on_other=link._take)
"""

from __future__ import annotations

import math
import subprocess
from dataclasses import replace

import numpy as np

from hostd.device import protocol as pr
from hostd.device.fwmodel import EDGE_HZ, hand_edges
from hostd.render.equalizer import Equalizer
from hostd.render.height import band_edges_hz
from hostd.render.pipeline import RenderConfig

GRAY = (0, 1, 3, 2)
EDGE_GRID_HZ = 24_000  # hand samples per second for the edge times (linear in between)


def device_params(cfg: RenderConfig | None = None) -> dict:
    """What the display needs besides the texture, from the host renderer's config."""
    cfg = cfg or RenderConfig()
    fs = cfg.sample_rate_hz
    if fs != pr.SAMPLE_RATE_HZ:
        raise ValueError(f"device rendering runs at {pr.SAMPLE_RATE_HZ} Hz, render.sample_rate_hz is {fs:g}")
    eq = Equalizer(cfg.actuator, cfg.equalizer)
    latency_s = eq.chain_delay_ms() * 1e-3 if cfg.latency_s is None else float(cfg.latency_s)
    out = cfg.output
    f_pass, f_stop = band_edges_hz(replace(cfg.band, sample_rate_hz=fs))  # the host's own band
    return {
        "sos": eq.sos,
        "f_stop_hz": f_stop,
        "fade_start": f_pass / f_stop,
        "codes_per_um": 1.0 / out.um_per_code,
        "delay_us": round(latency_s * 1e6),
        "limit_code": min(out.limit_code, pr.LIMIT_CODE),
        "max_step_code": max(1, min(math.floor(out.slew_um_s / fs / out.um_per_code), pr.MAX_STEP_CODE)),
    }


def setup_messages(coeffs, n: int, length_mm: float, cfg: RenderConfig | None = None,
                   slot: int = 1, params: dict | None = None) -> list[bytes]:
    """Limits, equalizer, band, scale, delay, then the texture (LOAD_TEXTURE ... LOAD_END). Each
    render message is answered by an ACK (LOAD_CHUNK only when refused): result 0 = accepted.
    params: device_params(cfg), when the caller has them already."""
    p = device_params(cfg) if params is None else params
    msgs = [pr.encode("SET_LIMITS", limit_code=p["limit_code"], max_step_code=p["max_step_code"])]
    msgs += pr.eq_messages(p["sos"])
    msgs.append(pr.encode("SET_BAND", f_stop_hz=p["f_stop_hz"], fade_start=p["fade_start"]))
    msgs.append(pr.encode("SET_SCALE", codes_per_um=p["codes_per_um"]))
    msgs.append(pr.encode("SET_DELAY", delay_us=p["delay_us"]))
    msgs += pr.texture_messages(slot, coeffs, n, length_mm)
    return msgs


def expects_ack(msg: bytes) -> bool:
    """Whether the device answers this message with an ACK when it accepts it (LOAD_CHUNK and a
    SET_EQ that is not the last section are answered only when refused)."""
    if msg[0] == pr.IDS["LOAD_CHUNK"] or msg[0] == pr.IDS["LOAD_TEXTURE"]:
        return False
    if msg[0] == pr.IDS["SET_EQ"]:
        return msg[1] + 1 >= msg[2]  # index + 1 >= n_sections: the last (or n_sections = 0)
    return 0x20 <= msg[0] < 0x30


class UploadAborted(Exception):
    """The process is stopping: an upload waiting for its answers gives way (what was sent may
    already play; the caller's stop path says STOP_RENDER)."""


def send_and_confirm(transport, msgs: list[bytes], timeout_s: float = 1.0, on_other=None,
                     busy_retries: int = 20, abort=None, alive=None) -> list[dict]:
    """Send render messages and wait for their ACKs; a LOAD_END answered BUSY (a crossfade in
    progress) is resent after 60 ms. Messages other than ACK go to on_other(bytes) (the link's
    STATUS handling). Raises DeviceError naming the refused message and the reason, DeviceTimeout
    when no answer came within timeout_s, UploadAborted as soon as abort() (if given) is true.
    alive() (if given) is called for each message that arrives: the upload's progress (a slow
    display's upload can outlast a watchdog period; its answers show it is moving)."""
    import time

    from hostd.errors import DeviceError, DeviceTimeout

    acks = []
    for m in msgs:
        transport.send(m)
        if not expects_ack(m):
            continue
        deadline = time.monotonic() + timeout_s
        retries = busy_retries
        while True:
            if abort is not None and abort():
                raise UploadAborted("stopping")
            # (checked whatever arrives: an idle display's 1 ms reports never leave the line
            # quiet, and an answer it could not send, its queue to the host full, never comes)
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"{transport.describe()}: no ACK for {pr.NAMES[m[0]]} within "
                                    f"{timeout_s:g} s: is the firmware protocol v2?")
            r = transport.recv(0.005)
            if r is None:
                continue
            if alive is not None:
                alive()
            try:
                name, f = pr.decode(r)
            except pr.ProtocolError:
                continue
            if name != "ACK":
                if on_other is not None:
                    on_other(r)
                continue
            if f["result"] == pr.RESULTS["BUSY"] and m[0] == pr.IDS["LOAD_END"] and retries > 0:
                retries -= 1
                time.sleep(0.06)
                transport.send(m)
                deadline = time.monotonic() + timeout_s
                continue
            if f["result"] != pr.RESULTS["OK"]:
                raise DeviceError(f"{transport.describe()} refused {pr.NAMES.get(f['for_id'], f['for_id'])} "
                                  f"({pr.RESULT_NAMES.get(f['result'], f['result'])}, detail {f['detail']}): "
                                  "the upload was not applied, the display plays as before")
            if f["for_id"] == m[0]:
                acks.append(f)
                break
    return acks


# ---------------------------------------------------------------- scenarios (tests, bench)
def scenario(hand, duration_s: float, at_tick: dict[int, list[bytes]]) -> list[tuple]:
    """Events for fw-replay and the model: messages before given ticks (tick 0 = before the
    first), the hand's encoder edges at their true times, and the ticks. Events are
    ("m", bytes), ("e", count, t_edge) and ("t", n)."""
    fs = pr.SAMPLE_RATE_HZ
    n_ticks = round(duration_s * fs)
    t = np.arange(0.0, duration_s + 2.0 / EDGE_GRID_HZ, 1.0 / EDGE_GRID_HZ)
    te, counts = hand_edges(t, hand.position_mm(t), pr.P["um_per_count_nm"] * 1e-3)
    # an edge at te goes in before tick k, the first whose instant (k - 1) / fs is >= te
    before = np.ceil(te * fs - 1e-9).astype(np.int64)  # 0-based index of that tick
    te_clk = (np.rint(te * EDGE_HZ).astype(np.int64) & 0xFFFFFFFF).tolist()
    counts_l = counts.tolist()
    ev: list[tuple] = []
    j = 0
    run = 0
    for k in range(n_ticks):
        msgs = at_tick.get(k, ())
        has_edges = j < len(before) and before[j] <= k
        if (msgs or has_edges) and run:
            ev.append(("t", run))
            run = 0
        ev += [("m", m) for m in msgs]
        while j < len(before) and before[j] <= k:
            ev.append(("e", counts_l[j], te_clk[j]))
            j += 1
        run += 1
    ev.append(("t", run))
    return ev


def run_c(events: list[tuple], timed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The firmware (fw-replay) on a scenario: (DAC code per tick, ns per fw_tick)."""
    from hostd.device import hostport

    exe = hostport.build_replay()
    lines = []
    for e in events:
        if e[0] in ("m", "r"):
            lines.append(f"{e[0]} " + e[1].hex())
        elif e[0] == "e":
            lines.append(f"e {GRAY[e[1] & 3]} {e[2]}")
        else:
            lines.append(f"t {e[1]}")
    r = subprocess.run([str(exe)] + (["--time"] if timed else []), input="\n".join(lines) + "\n",
                       capture_output=True, text=True, check=True)
    out = np.array(r.stdout.split(), dtype=np.int64).reshape(-1, 2)
    return out[:, 0], out[:, 1]


def read_scenario(path) -> list[tuple]:
    """A scenario file (the host port's --scenario, fw-replay's input) as events; the edges'
    A/B pin states become counts (4x quadrature from 0, as the firmware decodes them)."""
    from pathlib import Path

    def step_of(a: int, b: int) -> int:
        i = GRAY.index(a)
        return 1 if GRAY[(i + 1) % 4] == b else -1 if GRAY[(i - 1) % 4] == b else 0

    step = {(a, b): step_of(a, b) for a in GRAY for b in GRAY}
    ev: list[tuple] = []
    ab, count = 0, 0
    for line in Path(path).read_text().splitlines():
        kind, _, rest = line.partition(" ")
        if kind in ("m", "r"):
            ev.append((kind, bytes.fromhex(rest)))
        elif kind == "e":
            pins, t = (int(v) for v in rest.split())
            count += step[(ab, pins)]
            ab = pins
            ev.append(("e", count, t))
        elif kind == "t":
            n = int(rest)
            if ev and ev[-1][0] == "t":
                ev[-1] = ("t", ev[-1][1] + n)
            else:
                ev.append(("t", n))
    return ev


def run_model(events: list[tuple]) -> tuple[np.ndarray, object]:
    """The Python model (a SimDevice without a hand) on a scenario: (DAC code per tick, device)."""
    from hostd.device.fastlink import deframer as make_deframer
    from hostd.device.simdev import SimDevice

    dev = SimDevice()
    deframer = make_deframer()
    codes = []
    for e in events:
        if e[0] == "m":
            dev.on_message(e[1])
        elif e[0] == "r":
            for m in deframer.feed(e[1]):
                dev.on_message(m)
        elif e[0] == "e":
            dev.render.edge(e[1], e[2])
        else:
            for _ in range(e[1]):
                dev.tick()
                codes.append(dev.out)
    return np.array(codes, dtype=np.int64), dev


def worst_case_events(duration_s: float = 3.0, seed: int = 1) -> list[tuple]:
    """The firmware's most expensive tick, sustained: N' = max_components, max_sections
    equalizer sections, the hand at the speed where every component is computed and the top
    fifth is in the band limit's fade, and a texture swap (two series per tick) all the time."""
    from hostd.sim.hand import Constant

    rng = np.random.default_rng(seed)
    nmax, length_mm = pr.R["max_components"], 10.0
    cfg = RenderConfig()
    p = device_params(cfg)
    speed = 0.99 * p["f_stop_hz"] * 2 * length_mm / nmax  # f_N' just below f_stop
    sos = [[0.5, 0.1, 0.05, 1.0, -0.3, 0.1]] * pr.R["max_sections"]
    msgs = [*pr.eq_messages(sos), pr.encode("SET_BAND", f_stop_hz=p["f_stop_hz"], fade_start=p["fade_start"]),
            pr.encode("SET_SCALE", codes_per_um=p["codes_per_um"])]
    tex = [rng.normal(0, 0.01, nmax) for _ in range(2)]
    at = {0: [*msgs, *pr.texture_messages(1, tex[0], 2 * nmax, length_mm), pr.encode("START_RENDER")]}
    every = pr.R["xfade_ticks"] + 1
    for i, k in enumerate(range(1, round(duration_s * pr.SAMPLE_RATE_HZ), every)):
        at[k] = pr.texture_messages(2 + i % 2, tex[(i + 1) % 2], 2 * nmax, length_mm)
    return scenario(Constant(speed_mm_s=speed), duration_s, at)


def tick_cost(events: list[tuple], skip_ticks: int = 300) -> dict:
    """Time of one fw_tick on this machine (fw-replay, -O2), after a warm-up: percentiles in µs
    and the share of a 3 kHz period the p99 and the maximum use."""
    _codes, ns = run_c(events, timed=True)
    us = ns[skip_ticks:] / 1e3
    period_us = 1e6 / pr.SAMPLE_RATE_HZ
    return {"ticks": int(us.size), "p50_us": float(np.percentile(us, 50)),
            "p99_us": float(np.percentile(us, 99)), "p999_us": float(np.percentile(us, 99.9)),
            "max_us": float(us.max()),
            "p99_share_pct": float(100 * np.percentile(us, 99) / period_us),
            "max_share_pct": float(100 * us.max() / period_us)}


if __name__ == "__main__":  # python -m hostd.device.devrender: the worst-case tick on this machine
    r = tick_cost(worst_case_events())
    print(f"fw_tick, worst case (N'={pr.R['max_components']}, {pr.R['max_sections']} sections, crossfade, "
          f"fade): {r['ticks']} ticks, p50 {r['p50_us']:.2f} µs, p99 {r['p99_us']:.2f} µs, "
          f"p99.9 {r['p999_us']:.2f} µs, max {r['max_us']:.1f} µs; p99 = {r['p99_share_pct']:.2f} % and "
          f"max = {r['max_share_pct']:.1f} % of the 333 µs period")
