"""Scenes: simulate only the effects a scene names, and score the quality delivered.

A scene (TOML, config/scenes/) names a texture (a stream, or a profile encoded on the fly),
a duration, a seed, the hand's motion and a table of effects. `run()` builds exactly the
effects asked for (hostd.sim.effects) and simulates:

- with no closed-loop effect, the host knows the hand's true position at every play instant:
  the band-limited series is evaluated for all samples at once (vectorized, no loop), then
  the output effects act on the commands. The command before the output effects depends
  only on the renderer's configuration, so the runs of one report that differ only by output
  effects (dac, actuator, finger_load) render it once (`Shared`);
- with encoder, transport, clock_drift or cpu_load, the host's real render pipeline runs
  batch by batch on what the host would see, when it would see it: motion estimate,
  prediction, re-locks and their crossfade, stalls and underruns. The hand does not feel the
  display, so the readings do not depend on what was rendered: each batch is planned with
  the pipeline's own code (Renderer.plan) and the planned heights are evaluated afterwards,
  one call of the pipeline's height evaluator per speed bucket (Renderer.heights_many_um),
  equal to rendering batch by batch to float rounding (tests/test_sim_speed.py).

Delivered quality: the displacement the finger received is fitted, by least squares, onto the
patch's cosine series at the hand's true positions (normal equations from nonuniform FFTs,
hostd.render.series.Projector; runs delivered at the same instants share its factored Gram
matrix) (the mirror-even series the codec uses), and
the fitted C'_k are scored with the same index as the codec (Ip, Ia, Iobj against the stream
header's reference). With an ideal chain this recovers the decoded coefficients, so the
delivered Iobj equals the codec-only Iobj.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hostd import paths, tomlfile
from hostd.errors import ConfigError, HostdError, ProfileError

SETTLE_S = 0.15  # soft start (50 ms) and filters settle before delivered samples count
FS = 3000.0
IDEAL_COUNT_UM = 1e-6  # an ideal encoder: 1 pm per count (the pipeline still takes counts)


@dataclass
class Scene:
    name: str
    duration_s: float
    seed: int
    texture: dict
    hand: dict
    effects: dict[str, dict] = field(default_factory=dict)
    path: str = ""
    description: str = ""


def load(path: str | Path) -> Scene:
    p = Path(path)
    doc = tomlfile.read(p, "scene", f"shipped ones are in {paths.scenes_dir()}")
    allowed = {"name", "description", "duration_s", "seed", "texture", "hand", "effects"}
    for k in doc:
        if k not in allowed:
            raise ConfigError(f"{p}: unknown field {k!r} (expected {', '.join(sorted(allowed))})")
    dur = doc.get("duration_s", 4.8)
    if isinstance(dur, bool) or not isinstance(dur, int | float) or not 0.3 <= dur <= 3600:
        raise ConfigError(f"{p}: duration_s must be a number within 0.3..3600 s, not {dur!r}")
    seed = doc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{p}: seed must be an integer >= 0, not {seed!r}")
    for sec in ("texture", "hand", "effects"):
        if not isinstance(doc.get(sec, {}), dict):
            raise ConfigError(f"{p}: {sec} must be a table [{sec}]")
    sc = Scene(name=str(doc.get("name", p.stem)), duration_s=float(dur), seed=seed,
               texture=doc.get("texture", {}), hand=doc.get("hand", {}), effects=doc.get("effects", {}),
               path=str(p), description=str(doc.get("description", "")))
    try:  # validate everything now: bad fields fail before any work
        _hand(sc)
        _stream(sc)
        from hostd.sim import effects as fx

        fx.build(sc.effects, sc.seed)
    except HostdError:  # (a ValueError too) already names what to change
        raise
    except (ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"{p}: {e}") from None
    return sc


def _hand(sc: Scene):
    from hostd.sim import hand

    h = dict(sc.hand)
    model = h.pop("model", "metronome")
    try:
        if model == "metronome":
            return hand.Metronome(**{k: float(v) if k.endswith("_mm") or k.endswith("_hz") else int(v)
                                     for k, v in h.items()})
        if model == "constant":
            return hand.Constant(**{k: float(v) for k, v in h.items()})
        if model == "recorded":
            f = Path(h.pop("file"))
            if h:
                raise ValueError(f"hand: unknown field {next(iter(h))!r}")
            return hand.Recorded.from_csv(f if f.is_absolute() else Path(sc.path).parent / f)
    except TypeError as e:
        raise ValueError(f"hand: {e}") from None
    raise ValueError(f"hand.model must be metronome, constant or recorded, not {model!r}")


def _stream(sc: Scene):
    from hostd.codec import stream as vtx
    from hostd.codec import transform
    from hostd.perception import thresholds
    from hostd.texture import synth

    t = dict(sc.texture)
    if "stream" in t:
        f = Path(t.pop("stream"))
        f = f if f.is_absolute() else Path(sc.path).parent / f
        if t:
            raise ValueError(f"texture: with stream, no other field (got {next(iter(t))!r})")
        return vtx.decode(f.read_bytes())
    profile = str(t.pop("profile", "synthetic:wood:1"))
    kw = {}
    method = t.pop("method", "quant")
    if method == "quant":
        kw = {"method": "quant", "levels": int(t.pop("levels", 14))}
    elif method == "cut":
        kw = {"method": "cut", "b0_db": float(t.pop("b0_db", 0.0)),
              "value_bits": int(t.pop("value_bits", 16))}
    else:
        raise ValueError(f"texture.method must be quant or cut, not {method!r}")
    fmax_hz = float(t.pop("fmax_hz", 400.0))
    if t:
        raise ValueError(f"texture: unknown field {next(iter(t))!r} (expected profile|stream, method, "
                         "levels, b0_db, value_bits, fmax_hz)")
    if not synth.is_spec(profile):
        raise ValueError("texture.profile: only synthetic:KIND[:SEED] here; encode real profiles with "
                         "hostd encode and name the .vtx as texture.stream")
    try:
        prof = synth.from_spec(profile)
    except ProfileError as e:
        raise ValueError(f"texture.profile: {e}") from None
    geom = transform.Geometry(prof.n, prof.length_mm, fmax_hz=fmax_hz)
    return vtx.decode(vtx.v1.encode_profile(prof.heights_um, geom, thresholds.default_curve(), **kw))


class Shared:
    """What the runs of one scene report share, computed once: the texture (stream), the hand,
    the open-loop command of each renderer configuration (an output effect - dac, actuator,
    finger_load - acts after the renderer, so the runs that differ only by such effects
    render once), and the least-squares projector of each set of delivery instants (its
    factored Gram matrix depends only on the phases; runs whose effects do not move the
    delivery instants reuse it)."""

    def __init__(self, sc: Scene, projector_bytes: int = 256 << 20) -> None:
        self.stream = _stream(sc)
        self.hand = _hand(sc)
        self.open_loop: dict[str, np.ndarray] = {}
        self._projectors: dict[bytes, object] = {}
        self._budget = projector_bytes

    def projector(self, theta: np.ndarray, n_keep: int):
        import hashlib

        from hostd.render import series

        key = hashlib.blake2b(theta.tobytes(), digest_size=16).digest() + n_keep.to_bytes(8, "little")
        pj = self._projectors.pop(key, None)
        if pj is None:
            pj = series.Projector(theta, n_keep)
        self._projectors[key] = pj  # most recently used last
        while sum(q.nbytes for q in self._projectors.values()) > self._budget and len(self._projectors) > 1:
            del self._projectors[next(iter(self._projectors))]
        return pj


def run(sc: Scene, only: list[str] | None = None, progress: bool = False, shared: Shared | None = None,
        vectorized: bool = True) -> dict:
    """Simulate the scene with the effects in `only` (default: all the scene names).

    Closed loop, the renderer is fed the encoder readings batch by batch, when the host would
    have them, and plans each batch (motion estimate, prediction, re-lock crossfade) with the
    real pipeline's code. The hand does not feel the display, so what the host reads does not
    depend on what it rendered: with `vectorized` the planned batches' heights are evaluated
    afterwards in one call per speed bucket, then equalized and limited in one pass
    (Renderer.heights_many_um, equal to rendering batch by batch to float rounding);
    vectorized=False renders every batch through Renderer.render_um, as the daemon does.
    `shared` (from report) reuses what runs of the same scene have in common.
    """
    from hostd.device import protocol as pr
    from hostd.perception import indices
    from hostd.quality import score_stream, stream_thresholds
    from hostd.render import RenderConfig, Renderer
    from hostd.render.equalizer import EqualizerConfig
    from hostd.sim import chain
    from hostd.sim import effects as fx

    names = list(sc.effects) if only is None else only
    es = fx.build({k: sc.effects[k] for k in names}, sc.seed)
    shared = shared or Shared(sc)
    hand = shared.hand
    s = shared.stream
    coeffs, n, length = s.coefficients, s.n, s.length_mm
    cfg = RenderConfig(equalizer=EqualizerConfig(enabled=es.actuator is not None))
    if es.actuator is not None:
        cfg = replace(cfg, actuator=es.actuator.model)  # look-ahead: the chain's delay (auto)
    else:
        cfg = replace(cfg, latency_s=0.0)  # an ideal actuator: displacement = command, no delay
    if es.encoder is not None:
        cfg = replace(cfg, um_per_count=es.encoder.p["resolution_um"])
    else:
        cfg = replace(cfg, um_per_count=IDEAL_COUNT_UM)
    r = Renderer(coeffs, n, length, cfg)
    ppm = es.clock_drift.p["ppm"] if es.clock_drift else 0.0
    scale = 1.0 + ppm * 1e-6  # device seconds per true second
    b = cfg.samples_per_batch
    n_batches = int(sc.duration_s * FS / b)
    n_samp = n_batches * b
    lead_s = (es.transport.p["latency_ms"] + es.transport.p["buffer_ms"]) * 1e-3 if es.transport else 0.0
    t_dev_play = np.arange(n_samp) / FS + lead_s  # device clock
    t_true_play = t_dev_play / scale
    underruns = 0
    if es.closed_loop:
        t_dev_status = np.arange(0.0, sc.duration_s + lead_s + 0.01, 1e-3)
        t_true_status = t_dev_status / scale
        x_status = hand.position_mm(t_true_status)
        counts = (es.encoder.counts(x_status) if es.encoder
                  else chain.quantize_counts(x_status, IDEAL_COUNT_UM))
        arrive = es.transport.arrivals(t_true_status) if es.transport else t_true_status.copy()
        order = np.argsort(arrive, kind="stable")  # jitter can reorder: the host takes them as they come
        arrive_sorted = arrive[order].tolist()
        t_dev_sorted = t_dev_status[order].tolist()
        counts_sorted = (counts[order] % (1 << 32)).tolist()
        stalls = es.cpu_load.stalls(n_batches, b / FS) if es.cpu_load else np.zeros(n_batches)
        t_host = (np.arange(n_batches) * b / FS) / scale + stalls  # when the host renders batch j
        out = np.empty(n_samp)
        plans = []
        m = 0
        n_arrive = len(arrive_sorted)
        last_t = -1.0
        r.start()
        from hostd.tty import progress_bar

        on_encoder, plan, render_um = r.on_encoder, r.plan, r.render_um
        for j, th in enumerate(progress_bar(progress, iterable=t_host.tolist(), unit="ms", leave=False,
                                            desc=f"{sc.name} {'+'.join(names) or 'ideal'}",
                                            mininterval=0.5)):
            while m < n_arrive and arrive_sorted[m] <= th + 1e-12:
                if t_dev_sorted[m] > last_t:  # a report older than one already seen adds nothing
                    on_encoder(t_dev_sorted[m], counts_sorted[m])
                    last_t = t_dev_sorted[m]
                m += 1
            if vectorized:
                plans.append(plan(t_dev_play[j * b : (j + 1) * b]))
            else:
                out[j * b : (j + 1) * b] = render_um(t_dev_play[j * b : (j + 1) * b])
        if vectorized:
            out = r.finish_um(r.heights_many_um(plans))
        if es.dac is not None:
            out = r.out.to_codes(out) * r.out.cfg.um_per_code
        # samples whose play instant passed before they could arrive: the device underran
        arrival_s = t_host + (es.transport.p["latency_ms"] * 1e-3 if es.transport else 0.0)
        late = (t_true_play < np.repeat(arrival_s, b) - 1e-12).reshape(n_batches, b)
        late_batch = late.any(axis=1)
        underruns = int(np.count_nonzero(late_batch & ~np.concatenate([[False], late_batch[:-1]])))
        step = r.out.limit_um / pr.P["ramp_ticks"]
        for j in np.flatnonzero(late_batch).tolist():  # the device ramps toward zero (50 ms)
            prev = out[j * b - 1] if j > 0 else 0.0
            for i in np.flatnonzero(late[j]).tolist():
                prev = prev - step if prev > step else prev + step if prev < -step else 0.0
                out[j * b + i] = prev
        command = out
    else:
        # open loop: the host knows the hand's true position; output effects act afterwards,
        # so the command (before the DAC) depends only on the renderer's configuration
        key = repr(sorted(sc.effects["actuator"].items())) if es.actuator is not None else ""
        command = shared.open_loop.get(key)
        if command is None:
            h = chain.reference(coeffs, n, length, hand, t_true_play + r.latency_s, r)
            r.start()
            command = shared.open_loop[key] = r.finish_um(h)
        if es.dac is not None:
            command = r.out.to_codes(command) * r.out.cfg.um_per_code
    delivered = command
    delay_s = 0.0
    if es.actuator is not None:
        delivered = chain.actuate(delivered, es.actuator.model, FS)
        delay_s = es.actuator.model.delay_s
    if es.finger_load is not None:
        delivered = es.finger_load.apply(delivered, FS)
    t_deliver = t_true_play + delay_s
    keep = t_deliver >= SETTLE_S + lead_s
    x = hand.position_mm(t_deliver[keep])
    y = delivered[keep]
    from hostd.render import series

    theta = series.phase_rad(x, n, length)
    fit = shared.projector(theta, s.n_keep).fit(y)
    intended = series.evaluate(coeffs, theta)  # the codec's texture at the true positions
    b_k = stream_thresholds(s)
    pp, ap = indices.weighted_sums(fit[1:], b_k)
    sc_del = indices.scores_from_sums(s.ref_P, s.ref_A, pp, ap)
    codec = score_stream(s)
    chain_ms = (lead_s + (r.latency_s if es.actuator is not None else 0.0)) * 1e3
    return {"effects": names, "closed_loop": es.closed_loop, "Ip": float(sc_del.Ip), "Ia": float(sc_del.Ia),
            "Iobj": float(sc_del.Iobj), "codec_iobj": float(codec.Iobj),
            "rms_error_um": float(np.sqrt(np.mean((y - intended) ** 2))),
            "rms_texture_um": float(np.sqrt(np.mean(intended**2))),
            "underruns": underruns, "latency_ms": chain_ms,
            "_trace": {"t": t_deliver[keep], "delivered": y, "intended": intended,
                       "x_mm": x, "speed_mm_s": hand.velocity_mm_s(t_deliver[keep]),
                       "fit": fit, "b_k": b_k, "codec": s.coefficients, "fs": FS,
                       "f_k_hz": np.asarray(s.frequencies_hz, dtype=np.float64), "n": n,
                       "length_mm": length, "band": r.height.band}}


def report(sc: Scene, progress: bool = True) -> dict:
    """The scene with no effect, each effect alone, then all of them (sharing what the runs
    have in common: Shared)."""
    shared = Shared(sc)
    runs = [run(sc, [], progress, shared)]
    if sc.effects:
        for name in sc.effects:
            runs.append(run(sc, [name], progress, shared))
        if len(sc.effects) > 1:
            runs.append(run(sc, list(sc.effects), progress, shared))
    base = runs[0]["_trace"]["fit"][1:]
    for rr in runs:  # what each run changed in the delivered spectrum, against no effects
        rr["spectrum_change_um"] = float(np.sqrt(np.mean((rr["_trace"]["fit"][1:] - base) ** 2)))
    codec = runs[0]["codec_iobj"]
    out = {"scene": sc.name, "description": sc.description, "duration_s": sc.duration_s, "seed": sc.seed,
           "codec_iobj": codec, "runs": runs}
    return out


def strip(result: dict) -> dict:
    """JSON-ready: without the traces."""
    r = dict(result)
    r["runs"] = [{k: v for k, v in run.items() if not k.startswith("_")} for run in result["runs"]]
    return r


def band_limited(tr: dict, sl: slice) -> np.ndarray:
    """The ideal display over trace samples sl: the codec's series with the band gains of the
    hand's true speed at each sample (what a perfect chain delivers)."""
    from hostd.sim import chain

    return chain.ideal(tr["codec"], tr["n"], tr["length_mm"], tr["x_mm"][sl], tr["speed_mm_s"][sl],
                       tr["band"])


def threshold_crossings(f_hz: np.ndarray, err: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Frequencies (Hz) where |error| crosses the detection threshold (linear interpolation
    of err - b between neighbouring components)."""
    d = err - b
    i = np.flatnonzero(np.sign(d[:-1]) * np.sign(d[1:]) < 0)
    return f_hz[i] + (f_hz[i + 1] - f_hz[i]) * d[i] / (d[i] - d[i + 1])


def plot(result: dict, out_dir: str | Path) -> list[Path]:
    """Two figures per scene.

    <scene>-stroke.png: over the first 0.8 s, the band-limited intended displacement (the
    ideal display: the codec's texture with the band gains of the hand's true speed), the
    delivered displacement with no effect and with the scene's effects, and below them the
    hand's speed. <scene>-error-spectrum.png: per component, |delivered - codec| amplitude
    against f_k in Hz (at the stream's reference speed) for the no-effect run and the run with
    every effect, the detection threshold b(f_k), and where the error crosses it.
    """
    from hostd.extras import need

    matplotlib = need("matplotlib", "plot", "hostd sim --plot")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def save(fig, path: Path) -> Path:
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path

    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    base, last = result["runs"][0], result["runs"][-1]
    tr, tb = last["_trace"], base["_trace"]
    label = ("+".join(last["effects"]) if len(last["effects"]) <= 2
             else f"all {len(last['effects'])} effects") or "no effect"
    n_show = min(tr["t"].size, tb["t"].size, int(0.8 * tr["fs"]))  # one metronome stroke
    sl = slice(0, n_show)
    fig, (ax, axv) = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True,
                                  gridspec_kw={"height_ratios": [3, 1]})
    ax.plot(tb["t"][sl], tb["delivered"][sl], lw=1.8, color="C0", alpha=0.6, label="delivered, no effect")
    if last is not base:
        ax.plot(tr["t"][sl], tr["delivered"][sl], lw=0.8, color="C3", label=f"delivered, {label}")
    ax.plot(tb["t"][sl], band_limited(tb, sl), lw=0.7, color="k", ls="--",
            label="intended: band-limited for the hand's speed (ideal display)")
    ax.set_ylabel("displacement, µm")
    ax.legend(fontsize=7, loc="lower left", ncols=3, bbox_to_anchor=(0, 1.0), frameon=False)
    fig.suptitle(f"{result['scene']}: intended vs delivered over a stroke", fontsize=10)
    ax.grid(True, alpha=0.3)
    axv.plot(tb["t"][sl], tb["speed_mm_s"][sl], color="k", lw=1)
    axv.set_ylabel("hand speed\nmm/s", fontsize=8)
    axv.set_xlabel("time, s")
    axv.grid(True, alpha=0.3)
    p1 = save(fig, d / f"{result['scene']}-stroke.png")

    fig, ax = plt.subplots(figsize=(8, 4.5))
    f = tr["f_k_hz"]
    b = tr["b_k"]
    err0 = np.abs(tb["fit"][1:] - tb["codec"])
    err = np.abs(tr["fit"][1:] - tr["codec"])
    ax.semilogy(f, err0, lw=0.8, color="C0", label="|delivered − codec|, no effect")
    if last is not base:
        ax.semilogy(f, err, lw=0.8, color="C3", label=f"|delivered − codec|, {label}")
    ax.semilogy(f, b, lw=1.6, color="k", label="detection threshold b(f)")
    cross = threshold_crossings(f, err, b)
    for i, fc in enumerate(cross):
        ax.axvline(fc, color="C3", ls=":", lw=0.9, label="error crosses the threshold" if i == 0 else None)
    above = err > b
    if above.any():
        ax.plot(f[above], err[above], "o", ms=2.5, color="C3", label="components above the threshold")
    top = float(max(err.max(), err0.max(), b.max())) * 2
    bottom = max(float(b.min()) * 1e-3, top * 1e-6)  # from 3 decades below the threshold
    ax.set_ylim(bottom, top)
    ax.set_xlabel("frequency f_k = k v_ref / 2L, Hz (at the stream's reference speed)")
    ax.set_ylabel("amplitude, µm")
    ax.legend(fontsize=7, loc="lower left")
    ax.grid(True, which="both", alpha=0.25)
    ax.set_title(f"{result['scene']}: spectrum of the delivered error against the threshold"
                 f" ({cross.size} crossing{'s' if cross.size != 1 else ''})", fontsize=10)
    return [p1, save(fig, d / f"{result['scene']}-error-spectrum.png")]
