"""The host side of device rendering (protocol v2): the messages that set a display up to render
a texture from its own encoder, from the same RenderConfig the host renderer uses, and scenarios
that run the firmware (C, firmware/build/fw-replay) and its model (hostd.device.fwmodel) on the
same inputs (tests and `hostd bench accuracy`).

    msgs = setup_messages(coeffs, n, length_mm, RenderConfig(), slot=1)  # send each, check ACKs
    link.t.send(pr.encode("START_RENDER", host_lost_ms=1000))
"""

from __future__ import annotations

import math
import subprocess

import numpy as np

from hostd.device import protocol as pr
from hostd.device.fwmodel import EDGE_HZ, hand_edges
from hostd.render.equalizer import Equalizer
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
    return {
        "sos": eq.sos,
        "f_stop_hz": min(cfg.band.display_band_hz, cfg.band.nyquist_fraction * fs / 2.0),
        "fade_start": cfg.band.fade_start,
        "codes_per_um": 1.0 / out.um_per_code,
        "delay_us": round(latency_s * 1e6),
        "limit_code": min(out.limit_code, pr.LIMIT_CODE),
        "max_step_code": max(1, min(math.floor(out.slew_um_s / fs / out.um_per_code), pr.MAX_STEP_CODE)),
    }


def setup_messages(coeffs, n: int, length_mm: float, cfg: RenderConfig | None = None,
                   slot: int = 1) -> list[bytes]:
    """Limits, equalizer, band, scale, delay, then the texture (LOAD_TEXTURE ... LOAD_END). Each
    render message is answered by an ACK (LOAD_CHUNK only when refused): result 0 = accepted."""
    p = device_params(cfg)
    msgs = [pr.encode("SET_LIMITS", limit_code=p["limit_code"], max_step_code=p["max_step_code"])]
    msgs += pr.eq_messages(p["sos"])
    msgs.append(pr.encode("SET_BAND", f_stop_hz=p["f_stop_hz"], fade_start=p["fade_start"]))
    msgs.append(pr.encode("SET_SCALE", codes_per_um=p["codes_per_um"]))
    msgs.append(pr.encode("SET_DELAY", delay_us=p["delay_us"]))
    msgs += pr.texture_messages(slot, coeffs, n, length_mm)
    return msgs


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
        if e[0] == "m":
            lines.append("m " + e[1].hex())
        elif e[0] == "e":
            lines.append(f"e {GRAY[e[1] & 3]} {e[2]}")
        else:
            lines.append(f"t {e[1]}")
    r = subprocess.run([str(exe)] + (["--time"] if timed else []), input="\n".join(lines) + "\n",
                       capture_output=True, text=True, check=True)
    out = np.array(r.stdout.split(), dtype=np.int64).reshape(-1, 2)
    return out[:, 0], out[:, 1]


def run_model(events: list[tuple]) -> tuple[np.ndarray, object]:
    """The Python model (a SimDevice without a hand) on a scenario: (DAC code per tick, device)."""
    from hostd.device.simdev import SimDevice

    dev = SimDevice()
    codes = []
    for e in events:
        if e[0] == "m":
            dev.on_message(e[1])
        elif e[0] == "e":
            dev.render.edge(e[1], e[2])
        else:
            for _ in range(e[1]):
                dev.tick()
                codes.append(dev.out)
    return np.array(codes, dtype=np.int64), dev
