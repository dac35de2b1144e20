"""Codec v2 benchmark (issue 14): bytes at Iobj <= 0.05 with the waveform guard, v2 vs v1; times.

`hostd bench codec` prints these rows after the v1 micro-benchmarks:
- `codec_rate`: per texture, the stream `hostd encode --target-iobj 0.05` returns in v2 and in
  v1 (both with the default criteria: Iobj and SPQI >= 0.9 measured on the stream), the v2
  streams of the previous defaults (the proxy guard wSNR >= 25 dB and sSNR >= 27 dB; before
  that wSNR >= 25 dB alone), and what v1 returned before any guard (Iobj alone, the
  exhaustive search): bytes, Iobj, wSNR, sSNR, SPQI, the number of encodes and the CPU time
  of the search.
- `codec_time`: CPU time at N = 20000 (median, in process) of v2 shaped encode (profile to
  bytes, DCT included), decode, and decode + reconstruction of the 20000 heights.
`hostd bench codec --tune-deadzone` measures the shaped quantizer's dead zone and
reconstruction offset (docs/stream-format.md, "Threshold-shaped quantizer").
`hostd bench codec --guard-calibration` measures SPQI against wSNR and sSNR on 32 textures
(the guard's defaults, hostd/perception/guard.py).
`hostd bench codec --holdout` runs the defaults on the held-out textures (hostd/bench/holdout.py).
`hostd bench codec --peers DIR` adds the peer codecs (hostd/bench/peers.py) next to v2.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from hostd.bench.common import cpu_median_s
from hostd.codec import methods, ratecontrol, transform
from hostd.codec import stream as vtx
from hostd.codec.stream import v2 as stream2
from hostd.perception import guard, indices, peer, thresholds
from hostd.texture import synth

TARGET = 0.05
# rate control's previous defaults, for comparison: the proxy guard certified instead of SPQI
PROXY_GUARD = {"spqi_min": None, "guard_db": guard.DEFAULT_GUARD_DB, "ssnr_db": guard.DEFAULT_SSNR_DB}
WSNR_ONLY = {"spqi_min": None, "guard_db": guard.DEFAULT_GUARD_DB}  # the one before that
# Real instrument profiles (shared/data/profiles, units from its README; xy-1's and xy-4's
# are unknown, read as µm and mm), with the reference speed at which each holds a few
# components below 400 Hz (opdx-3 is 50 µm long: 2 mm/s).
REAL = (("dektak-1.csv", {"x_unit": "um", "y_unit": "um"}, 50.0),
        ("xy-1.txt", {"x_unit": "um", "y_unit": "um"}, 5.0),
        ("xy-4.txt", {"x_unit": "mm", "y_unit": "um"}, 50.0),
        ("opdx-3.txt", {"x_unit": "m", "y_unit": "m", "length_mm": None}, 2.0))


# the six textures the dead-zone table of docs/stream-format.md was measured on
DEADZONE_TEXTURES = ("wood:1", "sandpaper:1", "wood:5", "dektak-1.csv", "xy-1.txt", "xy-4.txt")


def _profiles_dir() -> Path:
    env = os.environ.get("HOSTD_PROFILES_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data" / "profiles"


def textures() -> list[tuple[str, np.ndarray, transform.Geometry]]:
    out = []
    for kind, seed in (("wood", 1), ("sandpaper", 1), ("wood", 5)):
        p = synth.make(kind, seed=seed)
        out.append((f"{kind}:{seed}", p.heights_um, transform.Geometry(p.n, p.length_mm)))
    from hostd.texture.load import LoadOptions, load_profile

    d = _profiles_dir()
    for name, opts, speed in REAL:
        if (d / name).exists():
            prof = load_profile(d / name, LoadOptions(**opts))
            out.append((name, prof.heights_um, transform.Geometry(prof.n, prof.length_mm,
                                                                   speed_mm_s=speed)))
    from hostd.texture.load import bundled_profile

    b = bundled_profile()  # dektak-1 as shipped: whole length, linear detrend, CLI defaults
    if b is not None:
        out.append(("bundled (dektak-1)", b.heights_um, transform.Geometry(b.n, b.length_mm)))
    return out


def calibration_textures() -> list[tuple[str, np.ndarray, transform.Geometry]]:
    """The guard's calibration set: wood and sandpaper seeds 0..5, and every real profile at
    several speeds, patch windows and detrendings (7 to 160 components)."""
    from hostd.texture.load import LoadOptions, load_profile

    out = []
    for kind in ("wood", "sandpaper"):
        for seed in range(6):
            p = synth.make(kind, seed=seed)
            out.append((f"{kind}:{seed}", p.heights_um, transform.Geometry(p.n, p.length_mm)))
    d = _profiles_dir()
    um = {"x_unit": "um", "y_unit": "um"}
    variants = [("dektak-1.csv", um, (25, 50, 100), ""),
                ("dektak-1.csv", {**um, "length_mm": None, "detrend": "linear"}, (50,), "[whole, linear]")]
    variants += [("dektak-1.csv", {**um, "length_mm": 0.5, "offset_mm": off}, (20, 50),
                  f"[0.5 mm at {off:g}]") for off in (0.0, 0.5, 1.0)]
    variants += [("xy-1.txt", um, (2, 5, 10), ""),
                 ("xy-4.txt", {"x_unit": "mm", "y_unit": "um"}, (25, 50, 100), ""),
                 ("xy-4.txt", {"x_unit": "mm", "y_unit": "um", "detrend": "linear"}, (50,), "[linear]"),
                 ("opdx-3.txt", {"x_unit": "m", "y_unit": "m", "length_mm": None}, (1, 2, 4), "")]
    for name, opts, speeds, tag in variants:
        if not (d / name).exists():
            continue
        p = load_profile(d / name, LoadOptions(**opts))
        for v in speeds:
            out.append((f"{name}{tag}@{v:g}", p.heights_um,
                        transform.Geometry(p.n, p.length_mm, speed_mm_s=float(v))))
    return out


def _quality(y: np.ndarray, geom: transform.Geometry, data: bytes) -> dict:
    s = vtx.decode(data)
    c = transform.analyze(y, s.n_keep)
    ps = peer.peer_scores(c, s.coefficients, s.n, s.length_mm, s.speed_mm_s)
    return {"spqi": None if ps is None else round(ps["spqi"], 3),
            "spqi_exact": None if ps is None else ps["spqi"]}


def rate_rows(step=lambda: None) -> list[dict]:
    """step(): called after each texture (a progress bar's update)."""
    curve = thresholds.default_curve()
    rows = []
    for name, y, geom in textures():
        row: dict = {"bench": "codec_rate", "texture": name, "n_keep": geom.n_keep}
        for label, fmt, extra in (("v2", "v2", {}), ("v1", "v1", {}),
                                  ("v2_proxy_guard", "v2", PROXY_GUARD),
                                  ("v2_wsnr_only", "v2", WSNR_ONLY)):
            r = ratecontrol.search(y, geom, curve, TARGET, fmt=fmt, **extra)
            row.update({f"{label}_bytes": r.best.nbytes, f"{label}_method": r.best.method,
                        f"{label}_Iobj": round(r.best.Iobj, 4),
                        f"{label}_wsnr_db": round(r.best.wsnr_db, 1),
                        f"{label}_ssnr_db": round(r.best.ssnr_db, 1),
                        f"{label}_spqi": _quality(y, geom, r.best.data)["spqi"],
                        f"{label}_encodes": r.encodes, f"{label}_search_ms": round(r.seconds * 1e3),
                        f"{label}_size_set_by": r.size_set_by})
        # v1's smallest stream meeting Iobj <= 0.05 AND SPQI >= 0.9 (every v1 candidate)
        v1c = sorted((k for k in ratecontrol.candidates(y, geom, curve) if k.Iobj <= TARGET),
                     key=lambda k: k.nbytes)
        best_v1 = None
        if peer.available():
            best_v1 = next((k for k in v1c if _quality(y, geom, k.data)["spqi_exact"] >= 0.9), None)
        # v2's smallest stream meeting it (shaped, quant and cut settings of the calibration grid)
        ig = stream2.int_geometry(geom)
        c2 = transform.analyze(y, ig.n_keep)
        b2 = curve(ig.frequencies_hz())
        v2c = []
        for st in _calibration_settings(c2, b2):
            data = stream2.encode_coefficients(c2, ig, curve, **st)
            s2 = vtx.decode(data)
            Pp, Ap = indices.weighted_sums(s2.coefficients, b2)
            if float(indices.scores_from_sums(s2.ref_P, s2.ref_A, Pp, Ap).Iobj) <= TARGET:
                v2c.append((len(data), st["method"], data))
        best_v2 = None
        if peer.available():
            best_v2 = next((k for k in sorted(v2c, key=lambda k: k[0])
                            if _quality(y, geom, k[2])["spqi_exact"] >= 0.9), None)
        row.update({"v2_min_spqi0.9_bytes": None if best_v2 is None else best_v2[0],
                    "v2_min_spqi0.9_method": None if best_v2 is None else best_v2[1]})
        row.update({"v1_min_spqi0.9_bytes": None if best_v1 is None else best_v1.nbytes,
                    "v1_min_spqi0.9_method": None if best_v1 is None else best_v1.method,
                    "v2_over_v1_min_spqi0.9": None if best_v1 is None
                    else round(row["v2_bytes"] / best_v1.nbytes, 3),
                    "v2min_over_v1min_spqi0.9": None if best_v1 is None or best_v2 is None
                    else round(best_v2[0] / best_v1.nbytes, 3)})
        old = ratecontrol.smallest_within(y, geom, curve, TARGET)  # v1, Iobj alone, exhaustive
        b_k = curve(geom.frequencies_hz())
        c = transform.analyze(y, geom.n_keep)
        row.update({"v1_noguard_bytes": old.nbytes, "v1_noguard_Iobj": round(old.Iobj, 4),
                    "v1_noguard_wsnr_db": round(guard.weighted_snr_db(
                        c, vtx.decode(old.data).coefficients, b_k), 1),
                    "v1_noguard_spqi": _quality(y, geom, old.data)["spqi"],
                    "v2_over_v1": round(row["v2_bytes"] / row["v1_bytes"], 3)})
        rows.append(row)
        step()
    return rows


def time_rows() -> list[dict]:
    curve = thresholds.default_curve()
    p = synth.make("wood", seed=1)
    geom = transform.Geometry(p.n, p.length_mm)
    rows = []
    for label, enc in (
        ("v2 shaped g=-10", lambda: stream2.encode_profile(p.heights_um, geom, curve,
                                                           method="shaped", g_db=-10.0)),
        ("v1 quant L=14", lambda: vtx.v1.encode_profile(p.heights_um, geom, curve, method="quant",
                                                     levels=14)),
    ):
        data = enc()
        rows.append({
            "bench": "codec_time", "stream": label, "n": p.n, "bytes": len(data),
            "encode_ms": cpu_median_s(enc, repeat=15, inner=10) * 1e3,
            "decode_ms": cpu_median_s(lambda d=data: vtx.decode(d), repeat=15, inner=10) * 1e3,
            "decode_reconstruct_ms": cpu_median_s(lambda d=data: vtx.decode(d).reconstruct(),
                                                  repeat=15, inner=10) * 1e3,
        })
    return rows


def tune_deadzone_rows(guard_db: float = guard.DEFAULT_GUARD_DB) -> list[dict]:
    """Summed bytes of the smallest shaped stream with Iobj <= 0.05 and wSNR >= guard_db over
    the benchmark textures, for each dead-zone rounding offset rho and reconstruction offset
    delta (g scanned in 0.5 dB steps from 60 dB below to 10 dB above the texture's largest
    |C_k| / b_k)."""
    curve = thresholds.default_curve()
    prepared = []
    for name, y, geom in textures():
        if name not in DEADZONE_TEXTURES:
            continue
        ig = stream2.int_geometry(geom)
        c = transform.analyze(y, ig.n_keep)
        b = curve(ig.frequencies_hz())
        prepared.append((name, ig, c, b))
    saved = methods.SHAPED_RHO, methods.SHAPED_DELTA
    rows = []
    try:
        for rho in (0.3, 0.4, 0.5, 0.6):
            for delta in (0.0, 0.1, 0.2):
                methods.SHAPED_RHO, methods.SHAPED_DELTA = rho, delta
                per = {}
                for name, ig, c, b in prepared:
                    best = None
                    top = 20.0 * math.log10(max(float(np.max(np.abs(c) / b)), 1e-300))
                    lo = max(math.floor((top - 60) * 2), int(methods.G_MIN_DB * 2))
                    for u in range(lo, min(math.ceil((top + 10) * 2), int(methods.G_MAX_DB * 2)) + 1):
                        data = stream2.encode_coefficients(c, ig, curve, method="shaped", g_db=u / 2)
                        s = vtx.decode(data)
                        Pp, Ap = indices.weighted_sums(s.coefficients, b)
                        io = float(indices.scores_from_sums(s.ref_P, s.ref_A, Pp, Ap).Iobj)
                        if io <= TARGET and guard.weighted_snr_db(c, s.coefficients, b) >= guard_db:
                            best = len(data) if best is None else min(best, len(data))
                    per[name] = best
                rows.append({"bench": "shaped_deadzone", "rho": rho, "delta": delta,
                             "total_bytes": sum(v for v in per.values() if v is not None),
                             **{f"bytes[{k}]": v for k, v in per.items()}})
    finally:
        methods.SHAPED_RHO, methods.SHAPED_DELTA = saved
    return rows


def _calibration_settings(c: np.ndarray, b: np.ndarray) -> list[dict]:
    """Shaped every 0.5 dB of g and cut every 0.5 dB of b0 (50 dB below to 5 dB above the
    texture's largest |C_k| / b_k), quant L = 2..39 and 40..256 in steps of 4."""
    top = 20.0 * math.log10(max(float(np.max(np.abs(c) / b)), 1e-300))
    sets: list[dict] = []
    g = max(methods.G_MIN_DB, math.floor((top - 50.0) * 4) / 4)
    while g <= min(top + 5.0, methods.G_MAX_DB):
        sets.append({"method": "shaped", "g_db": g})
        g += 0.5
    sets += [{"method": "quant", "levels": L} for L in [*range(2, 40), *range(40, 257, 4)]]
    b0 = math.floor(top) + 1.0
    while b0 >= top - 50.0:
        sets.append({"method": "cut", "b0_db": b0, "value_bits": 16})
        b0 -= 0.5
    return sets


def guard_calibration_rows() -> list[dict]:
    """SPQI against the guard's two SNRs (hostd.perception.guard) on the calibration textures.

    For each texture, every v2 stream of _calibration_settings with Iobj <= 0.05 is scored;
    one row per texture gives the largest wSNR and the largest sSNR at which a stream still had
    SPQI < 0.9 (a guard floor above it gives SPQI >= 0.9 on that texture), and what rate control
    returns with the default guard and with the previous default (wSNR >= 25 dB alone).
    The last row summarizes."""
    curve = thresholds.default_curve()
    rows = []
    for name, y, geom in calibration_textures():
        ig = stream2.int_geometry(geom)
        c = transform.analyze(y, ig.n_keep)
        f = ig.frequencies_hz()
        b = curve(f)
        bad_w, bad_s, probes = -math.inf, -math.inf, 0
        for s in _calibration_settings(c, b):
            data = stream2.encode_coefficients(c, ig, curve, **s)
            st = vtx.decode(data)
            Pp, Ap = indices.weighted_sums(st.coefficients, b)
            if float(indices.scores_from_sums(st.ref_P, st.ref_A, Pp, Ap).Iobj) > TARGET:
                continue
            probes += 1
            if _quality(y, geom, data)["spqi_exact"] < 0.9:
                v = guard.check(c, st.coefficients, b, f)
                bad_w, bad_s = max(bad_w, v.wsnr_db), max(bad_s, v.ssnr_db)
        row = {"bench": "guard_calibration", "texture": name, "n_keep": ig.n_keep,
               "probes": probes, "max_wsnr_db_spqi_below_0.9": round(bad_w, 1),
               "max_ssnr_db_spqi_below_0.9": round(bad_s, 1)}
        for label, extra in (("default", {}), ("proxy_guard", PROXY_GUARD), ("wsnr_only", WSNR_ONLY)):
            r = ratecontrol.search(y, geom, curve, TARGET, **extra)
            row.update({f"{label}_bytes": r.best.nbytes,
                        f"{label}_spqi": _quality(y, geom, r.best.data)["spqi"]})
        rows.append(row)
    rows.append({"bench": "guard_calibration_summary", "textures": len(rows),
                 "max_wsnr_db_spqi_below_0.9": max(r["max_wsnr_db_spqi_below_0.9"] for r in rows),
                 "max_ssnr_db_spqi_below_0.9": max(r["max_ssnr_db_spqi_below_0.9"] for r in rows),
                 "default_min_spqi": min(r["default_spqi"] for r in rows),
                 "default_bytes": sum(r["default_bytes"] for r in rows),
                 "proxy_guard_min_spqi": min(r["proxy_guard_spqi"] for r in rows),
                 "proxy_guard_bytes": sum(r["proxy_guard_bytes"] for r in rows),
                 "wsnr_only_min_spqi": min(r["wsnr_only_spqi"] for r in rows),
                 "wsnr_only_bytes": sum(r["wsnr_only_bytes"] for r in rows)})
    return rows + guard_target_rows() + guard_heldout_rows()


def guard_heldout_rows() -> list[dict]:
    """Textures not in the calibration set (other seeds, speeds, fmax up to 1000 Hz): the
    stream `--target-iobj 0.05` returns with the default guard and with wSNR >= 25 dB alone."""
    from hostd.texture.load import bundled_profile

    curve = thresholds.default_curve()
    cases = []
    for kind, seed in (("wood", 7), ("sandpaper", 8)):
        p = synth.make(kind, seed=seed)
        for v, fm in ((25, 400), (100, 400), (50, 800), (200, 1000)):
            cases.append((f"{kind}:{seed}@{v} fmax {fm}", p.heights_um,
                          transform.Geometry(p.n, p.length_mm, float(v), float(fm))))
    b = bundled_profile()
    if b is not None:
        for v, fm in ((25, 400), (12.5, 400), (50, 800), (100, 1000)):
            cases.append((f"bundled@{v:g} fmax {fm}", b.heights_um,
                          transform.Geometry(b.n, b.length_mm, float(v), float(fm))))
    rows = []
    for name, y, geom in cases:
        row: dict = {"bench": "guard_heldout", "texture": name}
        for label, extra in (("default", {}), ("proxy_guard", PROXY_GUARD), ("wsnr_only", WSNR_ONLY)):
            r = ratecontrol.search(y, geom, curve, TARGET, **extra)
            row.update({"n_keep": vtx.decode(r.best.data).n_keep, f"{label}_bytes": r.best.nbytes,
                        f"{label}_spqi": _quality(y, geom, r.best.data)["spqi"]})
        rows.append(row)
    return rows


def guard_target_rows(targets: tuple[float, ...] = (0.02, 0.05, 0.1, 0.2)) -> list[dict]:
    """For each target Iobj, the stream rate control returns with the default guard on every
    calibration texture: the lowest SPQI (and where), how many are below 0.9, total bytes."""
    curve = thresholds.default_curve()
    tex = calibration_textures()
    rows = []
    for target in targets:
        spqi, total = [], 0
        for name, y, geom in tex:
            r = ratecontrol.search(y, geom, curve, target)
            spqi.append((_quality(y, geom, r.best.data)["spqi_exact"], name))
            total += r.best.nbytes
        low = min(spqi)
        rows.append({"bench": "guard_target", "target_iobj": target, "textures": len(tex),
                     "min_spqi": round(low[0], 3), "min_spqi_texture": low[1],
                     "below_0.9": sum(q < 0.9 for q, _ in spqi), "total_bytes": total})
    return rows


def peer_rows(peers_dir: Path | None) -> list[dict]:
    """`hostd bench codec --peers DIR`: bytes needed for SPQI >= 0.9 (and for SPQI >= 0.9 with
    Iobj <= 0.05) by v2 and by each peer codec found (hostd/bench/peers.py), every codec scored
    by the same function (peers.score) on the same textures; plus every peer run (knob, bytes,
    Iobj, wSNR, ST-SIM, SPQI). A peer that is not built gives a `codec_peer_note` row."""
    from hostd.bench import peers

    if peers_dir is not None and not peers_dir.is_dir():
        raise peers.PeerError(f"--peers {peers_dir}: no such directory (it should hold the peer "
                              "builds: see hostd bench codec --help)")
    found, notes = peers.find(peers_dir)
    rows: list[dict] = [{"bench": "codec_peer_note", "note": n} for n in notes]
    if not found:
        return rows
    if not peer.available():
        raise peers.PeerError(peer.NOTE_MISSING)
    curve = thresholds.default_curve()
    for name, y, geom in textures():
        ig = stream2.int_geometry(geom)
        c = transform.analyze(y, ig.n_keep)
        b = curve(ig.frequencies_hz())
        t = peers.Texture(name, c, ig.n, ig.length_mm, ig.speed_mm_s, b)
        summary: dict = {"bench": "codec_peer_summary", "texture": name, "n_keep": ig.n_keep}
        r = ratecontrol.search(y, geom, curve, TARGET)
        sc = peers.score(t, vtx.decode(r.best.data).coefficients)
        summary.update({"v2_default_bytes": r.best.nbytes, "v2_default_spqi": round(sc["spqi"], 3)})
        v2 = []
        for s in _calibration_settings(c, b):
            if s["method"] == "shaped":
                data = stream2.encode_coefficients(c, ig, curve, **s)
                v2.append({"bytes": len(data), **peers.score(t, vtx.decode(data).coefficients)})
        per = [("v2 shaped", v2)] + [(codec.name, peers.sweep(codec, t)) for codec in found]
        for label, runs in per:
            if label != "v2 shaped":
                rows += runs
            best = peers.smallest(runs)
            both = peers.smallest(runs, iobj_max=TARGET)
            summary[f"{label}: bytes for SPQI>=0.9"] = best["bytes"] if best else None
            summary[f"{label}: bytes for SPQI>=0.9 and Iobj<=0.05"] = both["bytes"] if both else None
        rows.append(summary)
    return rows
