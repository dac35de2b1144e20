"""Codec v2 benchmark (issue 14): bytes at Iobj <= 0.05 with the waveform guard, v2 vs v1; times.

`hostd bench codec` prints these rows after the v1 micro-benchmarks:
- `codec_rate`: per texture, the stream `hostd encode --target-iobj 0.05` returns in v2 and in
  v1 (both with the default guard wSNR >= 25 dB), and what v1 returned before the guard
  (Iobj alone, the exhaustive search): bytes, Iobj, wSNR, SPQI (when vibromaf is installed),
  the number of encodes and the CPU time of the search.
- `codec_time`: CPU time at N = 20000 (median, in process) of v2 shaped encode (profile to
  bytes, DCT included), decode, and decode + reconstruction of the 20000 heights.
`hostd bench codec --tune-deadzone` measures the shaped quantizer's dead zone and
reconstruction offset (docs/stream-format.md, "Threshold-shaped quantizer").
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from hostd.bench.common import cpu_median_s
from hostd.codec import methods, ratecontrol, stream2, transform
from hostd.codec import stream as vtx
from hostd.perception import guard, indices, peer, thresholds
from hostd.texture import synth

TARGET = 0.05
# Real instrument profiles (shared/data/profiles), with the reference speed at which each holds
# a few components below 400 Hz (as in the tests).
REAL = (("dektak-1.csv", {"x_unit": "um", "y_unit": "um"}, 50.0),
        ("xy-1.txt", {"x_unit": "um", "y_unit": "um"}, 5.0),
        ("xy-4.txt", {"x_unit": "mm", "y_unit": "um"}, 50.0))


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
    return out


def _quality(y: np.ndarray, geom: transform.Geometry, data: bytes) -> dict:
    s = vtx.decode(data)
    c = transform.analyze(y, s.n_keep)
    ps = peer.peer_scores(c, s.coefficients, s.n, s.length_mm, s.speed_mm_s)
    return {"spqi": None if ps is None else round(ps["spqi"], 3)}


def rate_rows() -> list[dict]:
    curve = thresholds.default_curve()
    rows = []
    for name, y, geom in textures():
        row: dict = {"bench": "codec_rate", "texture": name, "n_keep": geom.n_keep}
        for label, fmt in (("v2", "v2"), ("v1", "v1")):
            r = ratecontrol.search(y, geom, curve, TARGET, fmt=fmt)
            row.update({f"{label}_bytes": r.best.nbytes, f"{label}_method": r.best.method,
                        f"{label}_Iobj": round(r.best.Iobj, 4),
                        f"{label}_wsnr_db": round(r.best.wsnr_db, 1),
                        f"{label}_spqi": _quality(y, geom, r.best.data)["spqi"],
                        f"{label}_encodes": r.encodes, f"{label}_search_ms": round(r.seconds * 1e3)})
        old = ratecontrol.smallest_within(y, geom, curve, TARGET)  # v1, Iobj alone, exhaustive
        b_k = curve(geom.frequencies_hz())
        c = transform.analyze(y, geom.n_keep)
        row.update({"v1_noguard_bytes": old.nbytes, "v1_noguard_Iobj": round(old.Iobj, 4),
                    "v1_noguard_wsnr_db": round(guard.weighted_snr_db(
                        c, vtx.decode(old.data).coefficients, b_k), 1),
                    "v1_noguard_spqi": _quality(y, geom, old.data)["spqi"],
                    "v2_over_v1": round(row["v2_bytes"] / row["v1_bytes"], 3)})
        rows.append(row)
    return rows


def time_rows() -> list[dict]:
    curve = thresholds.default_curve()
    p = synth.make("wood", seed=1)
    geom = transform.Geometry(p.n, p.length_mm)
    rows = []
    for label, enc in (
        ("v2 shaped g=-10", lambda: stream2.encode_profile(p.heights_um, geom, curve,
                                                           method="shaped", g_db=-10.0)),
        ("v1 quant L=14", lambda: vtx.encode_profile(p.heights_um, geom, curve, method="quant",
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


def guard_calibration_rows(step_db: float = 3.0) -> list[dict]:
    """Shaped streams of every benchmark texture over g (step_db apart, from 45 dB below to
    5 dB above its largest |C_k| / b_k): bytes, Iobj, wSNR and SPQI, to see which wSNR gives
    SPQI >= 0.9 (the guard's default)."""
    curve = thresholds.default_curve()
    rows = []
    for name, y, geom in textures():
        ig = stream2.int_geometry(geom)
        c = transform.analyze(y, ig.n_keep)
        b = curve(ig.frequencies_hz())
        top = 20.0 * math.log10(max(float(np.max(np.abs(c) / b)), 1e-300))
        g = max(methods.G_MIN_DB, math.floor((top - 45.0) * 4) / 4)
        while g <= top + 5.0:
            data = stream2.encode_coefficients(c, ig, curve, method="shaped", g_db=g)
            s = vtx.decode(data)
            Pp, Ap = indices.weighted_sums(s.coefficients, b)
            io = float(indices.scores_from_sums(s.ref_P, s.ref_A, Pp, Ap).Iobj)
            rows.append({"bench": "guard_calibration", "texture": name, "g_db": g,
                         "bytes": len(data), "Iobj": round(io, 4),
                         "wsnr_db": round(guard.weighted_snr_db(c, s.coefficients, b), 1),
                         "spqi": _quality(y, geom, data)["spqi"]})
            g += step_db
    return rows
