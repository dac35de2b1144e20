"""What accuracy costs in time: every knob of the render pipeline, its error and CPU cost.

Each setting changes one knob from the shipped default. Every setting is run, in one
process, on every texture under the paper's hand motion (metronome strokes of 40 mm at
1.25 Hz, forward over one beat, back over two; minimum-jerk) through the closed-loop
simulation of hostd.sim.chain: quantized encoder at 1 kHz, 1 ms transport, the device's
buffer, the DAC's hold and the actuator model. The error is the displacement delivered
minus the ideal display's (the exact series at the true position, true speed and true
instant), RMS over the run after a settling time; `rms_error_pct` is relative to the RMS of
the ideal displacement. A setting's row reports the worst texture. CPU is the renderer's
thread CPU time per second of 3 kHz output (median over textures); every host setting is
run `repeats` times (default 3) and the row also gives the spread: the smallest and largest
of the per-run figures (each run's median over textures), which shows how much of a
difference between two rows is the machine's load.

The knob render_at = device renders on the display instead (protocol v2): the firmware core
itself (firmware/build/fw-replay, the C code) runs on the same hand, with encoder edges at the
hand's true times, set up by the same RenderConfig (hostd.device.devrender). Its host CPU is 0
(the host only uploads and supervises); its cost is the firmware's: instructions per render
tick counted by QEMU on the emulated Cortex-M4F (`make -C firmware qemu-bench`, the worst case
N' = 512 with 4 equalizer sections), given as ms per second of output on a 170 MHz core at
one instruction per cycle (a lower bound: loads, branches and flash wait states cost more).
Without QEMU or the ARM compiler the figure is None with the reason; the firmware's time per
tick on this machine (fw-replay) is the extra column either way.
"""

from __future__ import annotations

import functools
import math
import re
import subprocess
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from hostd.codec import transform
from hostd.render.pipeline import RenderConfig, Renderer
from hostd.sim import chain
from hostd.sim.hand import Metronome
from hostd.texture.load import Profile

SETTLE_S = 0.2  # soft start (50 ms) and the filters settle before the error is measured
REPEATS = 3  # runs per host setting and texture, for the CPU figure's spread
FW_CORE_HZ = 170e6  # the board's Cortex-M4F (STM32G4)


@dataclass
class Setting:
    knob: str
    setting: str
    apply: Callable[[RenderConfig], RenderConfig]
    default: bool = False
    where: str = "host"  # render_at: the host pipeline, or the display's firmware


def _same(c: RenderConfig) -> RenderConfig:
    return c


def settings() -> list[Setting]:
    d = RenderConfig()
    s: list[Setting] = []
    for m in ("series", "table-cubic", "table-linear", "nearest"):
        s.append(Setting("height_method", m, lambda c, m=m: replace(c, height_method=m),
                         m == d.height_method))
    for t in ("float64", "float32"):
        s.append(Setting("dtype", t, lambda c, t=t: replace(c, dtype=t), t == d.dtype))
    s.append(Setting("prediction", "off (hold last position)", lambda c: replace(c, predict=False)))
    for order, win in ((1, 4), (1, 8), (2, 8), (2, 16), (2, 24), (3, 24), (3, 32), (3, 40), (3, 48)):
        s.append(Setting("prediction", f"order {order}, window {win}",
                         lambda c, o=order, w=win: replace(c, motion=replace(c.motion, order=o, window=w)),
                         d.predict and (order, win) == (d.motion.order, d.motion.window)))
    s.append(Setting("latency_comp", "none", lambda c: replace(c, latency_s=0.0)))
    s.append(Setting("latency_comp", "chain delay (auto)", _same, d.latency_s is None))
    s.append(Setting("equalizer", "off", lambda c: replace(c, equalizer=replace(c.equalizer, enabled=False))))
    for hz, order in ((800, 2), (1200, 2), (1300, 2), (1400, 2), (1400, 4)):
        s.append(Setting("equalizer", f"reg {hz} Hz, order {order}",
                         lambda c, hz=hz, o=order: replace(c, equalizer=replace(c.equalizer, reg_hz=float(hz),
                                                                               reg_order=o)),
                         (hz, order) == (d.equalizer.reg_hz, d.equalizer.reg_order)))
    for ov in (4, 16, 64):
        s.append(Setting("table_oversample", f"table-cubic, {ov}x",
                         lambda c, ov=ov: replace(c, height_method="table-cubic", table_oversample=ov)))
    for b in (3, 6, 15, 30):
        s.append(Setting("samples_per_batch", f"{b} ({b / 3:g} ms)",
                         lambda c, b=b: replace(c, samples_per_batch=b), b == d.samples_per_batch))
    # the daemon's default ([render] where = "auto") renders on a v2 display: that row is the
    # default; the host row is what a v1 display (or a texture it cannot hold) gets
    s.append(Setting("render_at", "host", _same))
    s.append(Setting("render_at", "device", _same, True, where="device"))
    return s


def link_for(cfg: RenderConfig) -> chain.LinkConfig:
    """The device buffer holds two batches plus 2 ms of margin for transport jitter."""
    batch_s = cfg.samples_per_batch / cfg.sample_rate_hz
    return chain.LinkConfig(transport_s=0.001, buffer_s=0.002 + batch_s)


def texture_coeffs(p: Profile, speed_mm_s: float = 50.0) -> tuple[np.ndarray, int, float]:
    geom = transform.Geometry(p.n, p.length_mm, speed_mm_s=speed_mm_s)
    return transform.analyze(p.heights_um, geom.n_keep), p.n, p.length_mm


def _score(coeffs, n, length_mm, hand: Metronome, r: Renderer, t_play: np.ndarray,
           delivered: np.ndarray, ref_cache: dict) -> dict:
    """RMS error of the delivered displacement against the ideal display after SETTLE_S."""
    key = (id(coeffs), t_play.size, t_play[0])
    if key not in ref_cache:
        ref_cache[key] = chain.reference(coeffs, n, length_mm, hand, t_play + r.eq.model.delay_s, r)
    ideal = ref_cache[key]
    keep = t_play >= SETTLE_S
    err = delivered[keep] - ideal[keep]
    rms_ideal = float(np.sqrt(np.mean(ideal[keep] ** 2)))
    rms_err = float(np.sqrt(np.mean(err**2)))
    pct = 100.0 * rms_err / rms_ideal if rms_ideal > 0 else math.inf
    return {"rms_error_um": rms_err, "rms_error_pct": pct, "ideal_rms_um": rms_ideal}


def measure(coeffs, n, length_mm, cfg: RenderConfig, duration_s: float, hand: Metronome,
            ref_cache: dict, repeats: int = 1) -> dict:
    """The error of one run (the simulation is deterministic) and the renderer's CPU of each
    of `repeats` runs (the median and every run's figure)."""
    link = link_for(cfg)
    runs = []
    for _ in range(max(1, repeats)):
        r = Renderer(coeffs, n, length_mm, cfg)
        runs.append((r, chain.run_loop(r, hand, duration_s, link)))
    r, res = runs[0]
    delivered = chain.actuate(res.command_um, r.eq.model, cfg.sample_rate_hz)
    cpu = [x.cpu_ms_per_s for _, x in runs]
    return {**_score(coeffs, n, length_mm, hand, r, res.t_play_s, delivered, ref_cache),
            "cpu_ms_per_s": float(np.median(cpu)), "cpu_runs_ms_per_s": cpu,
            "batch_p99_us": float(np.median([np.percentile(x.batch_cpu_ns, 99) for _, x in runs])) / 1e3}


@functools.lru_cache(maxsize=1)
def firmware_tick_cost() -> dict:
    """Instructions per device-renderer tick on QEMU's Cortex-M4F (bench_tick.elf, -icount:
    its SysTick counts instructions), run once per process: {'insn_mean', 'insn_swap',
    'insn_max', 'ms_per_s', 'source'}, or {'error': reason} when it cannot be run."""
    from hostd.device import hostport

    try:
        r = subprocess.run(["make", "-s", "-C", str(hostport.FIRMWARE), "qemu-bench"],
                           capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {"error": f"make -C firmware qemu-bench did not run: {exc}"}
    text = r.stdout
    got = {}
    for key, label in (("insn_mean", "device renderer tick, N'=512, 4 sections (mean):"),
                       ("insn_swap", "device renderer tick during a swap (mean):"),
                       ("insn_max", "device renderer, slowest tick (+-40):")):
        m = re.search(re.escape(label) + r"\s+([0-9.]+) instructions", text)
        if m:
            got[key] = float(m.group(1))
    if r.returncode != 0 or len(got) < 3:
        last = (r.stderr.strip() or r.stdout.strip() or "no output").splitlines()[-1]
        return {"error": f"make -C firmware qemu-bench failed (needs qemu-system-arm and "
                         f"gcc-arm-none-eabi with newlib): {last}"}
    fs = RenderConfig().sample_rate_hz
    got["ms_per_s"] = got["insn_mean"] * fs / FW_CORE_HZ * 1e3
    got["source"] = ("QEMU mps2-an386 -icount (instructions), N'=512, 4 sections; ms per s at "
                     f"{FW_CORE_HZ / 1e6:g} MHz and 1 instruction per cycle (a lower bound)")
    return got


def measure_device(coeffs, n, length_mm, cfg: RenderConfig, duration_s: float, hand: Metronome,
                   ref_cache: dict) -> dict:
    """The firmware renders (C, fw-replay) from edges at the hand's true times; tick k plays at
    (k - 1) / fs on the device clock, held by the DAC, then the same actuator and reference."""
    from hostd.device import devrender
    from hostd.device import protocol as pr

    r = Renderer(coeffs, n, length_mm, cfg)  # for the band and the models only
    msgs = [*devrender.setup_messages(coeffs, n, length_mm, cfg), pr.encode("START_RENDER")]
    codes, ns = devrender.run_c(devrender.scenario(hand, duration_s, {0: msgs}), timed=True)
    fs = cfg.sample_rate_hz
    t_play = np.arange(codes.size) / fs
    delivered = chain.actuate(codes * r.out.cfg.um_per_code, r.eq.model, fs)
    us = ns[round(SETTLE_S * fs):] / 1e3
    return {**_score(coeffs, n, length_mm, hand, r, t_play, delivered, ref_cache),
            "cpu_ms_per_s": 0.0, "batch_p99_us": 0.0,
            "fw_tick_p99_us": float(np.percentile(us, 99)), "fw_tick_max_us": float(us.max())}


def run(textures: dict[str, Profile], duration_s: float = 4.8, progress: bool = True,
        repeats: int = REPEATS, knobs: tuple[str, ...] | None = None,
        firmware_cost: bool = True) -> list[dict]:
    """The rows of every setting (of `knobs` only, when given). firmware_cost=False leaves out
    the QEMU instruction count of the device row (it builds the ARM firmware: minutes on a fresh
    machine), which `--check` does not hold."""
    from hostd.tty import progress_bar

    hand = Metronome()
    base = RenderConfig()
    coeffs = {name: texture_coeffs(p) for name, p in textures.items()}
    rows = []
    done: dict[str, dict] = {}  # the default setting is measured once and reused per knob
    ref_cache: dict = {}
    todo = [st for st in settings() if knobs is None or st.knob in knobs]
    bar = progress_bar(progress, total=len(todo) * len(coeffs), desc="bench accuracy", unit="run",
                       leave=False)
    for st in todo:
        cfg = st.apply(base)
        key = repr(cfg) + st.where
        if key not in done:
            per = {}
            for name, (c, n, length) in coeffs.items():
                if st.where == "device":
                    per[name] = measure_device(c, n, length, cfg, duration_s, hand, ref_cache)
                else:
                    per[name] = measure(c, n, length, cfg, duration_s, hand, ref_cache, repeats)
                bar.update(1)
            done[key] = per
        else:
            bar.update(len(coeffs))
        per = done[key]
        worst = max(per, key=lambda k: per[k]["rms_error_pct"])
        row = {"knob": st.knob, "setting": st.setting, "default": st.default,
               "rms_error_um": per[worst]["rms_error_um"],
               "rms_error_pct": per[worst]["rms_error_pct"], "worst_texture": worst,
               "cpu_ms_per_s": float(np.median([v["cpu_ms_per_s"] for v in per.values()])),
               "batch_p99_us": float(np.median([v["batch_p99_us"] for v in per.values()])),
               "fw_tick_p99_us": (max(v["fw_tick_p99_us"] for v in per.values())
                                  if st.where == "device" else None),
               "per_texture": per}
        if st.where == "device":
            fw = firmware_tick_cost() if firmware_cost else {"error": "not counted (--check)"}
            row.update(repeats=1, cpu_min_ms_per_s=0.0, cpu_max_ms_per_s=0.0,
                       fw_cpu_ms_per_s=fw.get("ms_per_s"), fw_insn_per_tick=fw.get("insn_mean"),
                       fw_insn_per_tick_max=fw.get("insn_max"),
                       fw_cost_source=fw.get("source", fw.get("error")))
        else:
            # the spread over repeats: run i's median over textures, smallest and largest
            per_run = [float(np.median([v["cpu_runs_ms_per_s"][i] for v in per.values()]))
                       for i in range(min(len(v["cpu_runs_ms_per_s"]) for v in per.values()))]
            row.update(repeats=len(per_run), cpu_ms_per_s=float(np.median(per_run)),
                       cpu_min_ms_per_s=min(per_run),
                       cpu_max_ms_per_s=max(per_run), fw_cpu_ms_per_s=None,
                       fw_insn_per_tick=None, fw_insn_per_tick_max=None, fw_cost_source=None)
        rows.append(row)
    bar.close()
    return rows


def plot(rows: list[dict], path: str) -> None:
    """Error against CPU, one panel per texture, one point per setting (* = default)."""
    from hostd.extras import need

    matplotlib = need("matplotlib", "plot", "hostd bench accuracy --plot")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    textures = list(rows[0]["per_texture"])
    fig, axes = plt.subplots(1, len(textures), figsize=(5.2 * len(textures), 5), sharex=True,
                             squeeze=False)
    knobs = list(dict.fromkeys(r["knob"] for r in rows))
    markers = "osD^v<>p"
    labels: list[list[tuple[float, float, str]]] = []
    for ax, tex in zip(axes[0], textures, strict=True):
        labels.append([])
        for i, k in enumerate(knobs):
            rs = [r for r in rows if r["knob"] == k]
            xs = [_plot_cpu(r, tex) for r in rs]
            ys = [r["per_texture"][tex]["rms_error_pct"] for r in rs]
            sc = ax.scatter(xs, ys, marker=markers[i % len(markers)], label=k, s=30)
            for r, y in zip(rs, ys, strict=True):  # the spread over repeats
                runs = r["per_texture"][tex].get("cpu_runs_ms_per_s") or []
                if len(runs) > 1:
                    ax.plot([min(runs), max(runs)], [y, y], color=sc.get_facecolor()[0], lw=1.2,
                            alpha=0.7)
            for r, x, y in zip(rs, xs, ys, strict=True):
                if r["knob"] == "render_at" and r["setting"] == "device":
                    labels[-1].append((x, y, "on the device (M4 firmware, QEMU count)"
                                       if r.get("fw_cpu_ms_per_s") is not None
                                       else "on the device (host CPU 0)"))
                elif not r["default"] and y > 1.3 * min(ys):  # label the settings that stand out
                    labels[-1].append((x, y, r["setting"]))
        d = next(r for r in rows if r["default"])
        ax.scatter([_plot_cpu(d, tex)], [d["per_texture"][tex]["rms_error_pct"]],
                   s=160, facecolors="none", edgecolors="k", label="defaults")
        ax.axvline(30.0, color="0.6", ls="--", lw=0.8)
        ax.axhline(1.0, color="0.6", ls=":", lw=0.8)
        ax.set_yscale("log")
        ax.set_title(tex)
        ax.set_xlabel("CPU ms per second of 3 kHz output (dashed: 3 % of a core; bars: min-max "
                      "of the repeats)", fontsize=8)
    axes[0][0].set_ylabel("RMS error, % of the ideal displacement's RMS (dotted: 1 %)")
    axes[0][-1].legend(fontsize=7)
    fig.suptitle("Render pipeline: accuracy against CPU cost, one knob changed at a time")
    fig.tight_layout()
    from hostd.plotting import place_labels

    for ax, lab in zip(axes[0], labels, strict=True):  # after the layout, without overlaps
        place_labels(ax, lab, fontsize=6)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_cpu(r: dict, tex: str) -> float:
    """x of a setting in the plot: the host's CPU, or for the device row the firmware's."""
    if r.get("fw_cpu_ms_per_s") is not None:
        return r["fw_cpu_ms_per_s"]
    return r["per_texture"][tex]["cpu_ms_per_s"]


def table(rows: list[dict]) -> str:
    lines = [f"{'knob':<18} {'setting':<26} {'default':<7} {'rms µm':>9} {'rms %':>8} "
             f"{'CPU ms/s':>9} {'min-max (runs)':>17} {'p99 µs':>8} {'fw tick p99 µs':>14}  worst"]
    notes = []
    for r in rows:
        fw = r.get("fw_tick_p99_us")
        fw_s = "" if fw is None else f"{fw:.2f}"
        if r.get("fw_cost_source") is not None:  # the device row: the firmware's cost
            cpu_s = "n/a" if r.get("fw_cpu_ms_per_s") is None else f"{r['fw_cpu_ms_per_s']:.1f}*"
            spread = "firmware"
            notes.append(f"* {r['knob']} = {r['setting']}: host CPU 0 (the host supervises); the "
                         f"firmware's cost: {r['fw_cost_source']}"
                         + (f"; {r['fw_insn_per_tick']:.0f} instructions per tick (mean), "
                            f"{r['fw_insn_per_tick_max']:.0f} slowest"
                            if r.get("fw_insn_per_tick") is not None else ""))
        else:
            cpu_s = f"{r['cpu_ms_per_s']:.2f}"
            spread = f"{r['cpu_min_ms_per_s']:.1f}-{r['cpu_max_ms_per_s']:.1f} ({r['repeats']})"
        lines.append(f"{r['knob']:<18} {r['setting']:<26} {'yes' if r['default'] else '':<7} "
                     f"{r['rms_error_um']:>9.4f} {r['rms_error_pct']:>8.3f} {cpu_s:>9} {spread:>17} "
                     f"{r['batch_p99_us']:>8.1f} {fw_s:>14}  {r['worst_texture']}")
    return "\n".join(lines + notes)
