"""Micro-benchmarks of the codec and of scoring.

Each figure is the median of repeated runs in this process, measured in CPU time
of the working thread (time.thread_time_ns, BLAS limited to that thread) to be robust to other
load on a shared machine.
"""

from __future__ import annotations

import numpy as np

from hostd.bench.common import cpu_median_s
from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.perception import indices, thresholds
from hostd.texture import synth


def bench_codec(step=lambda: None) -> list[dict]:
    curve = thresholds.default_curve()
    rows = []
    for kind in ("wood", "sandpaper"):
        prof = synth.make(kind, seed=1)
        geom = transform.Geometry(prof.n, prof.length_mm)
        for kw in (dict(method="quant", levels=14), dict(method="cut", b0_db=0.0, value_bits=16)):
            data = vtx.v1.encode_profile(prof.heights_um, geom, curve, **kw)
            enc = cpu_median_s(lambda kw=kw, p=prof, g=geom: vtx.v1.encode_profile(p.heights_um, g, curve,
                                                                                    **kw),
                               repeat=15, inner=20)
            dec = cpu_median_s(lambda data=data: vtx.decode(data), repeat=15, inner=50)
            recon = cpu_median_s(lambda data=data: vtx.decode(data).reconstruct(), repeat=15,
                                 inner=20)
            rows.append({"bench": "codec", "texture": kind, "method": kw["method"],
                         "n": prof.n, "bytes": len(data), "encode_ms": enc * 1e3,
                         "decode_coeffs_ms": dec * 1e3, "decode_profile_ms": recon * 1e3})
            step()
    return rows


def bench_scoring() -> list[dict]:
    rng = np.random.default_rng(0)
    b = thresholds.default_curve()(np.linspace(2.5, 400, 160))
    c = rng.normal(0, 1, 160)
    rows = []
    for m in (1000, 10000, 100000):
        variants = c + rng.normal(0, 0.1, (m, 160))
        t = cpu_median_s(lambda v=variants: indices.score(c, v, b), repeat=9)
        rows.append({"bench": "scoring", "variants": m, "n_keep": 160, "seconds": t,
                     "scores_per_s": m / t})
    return rows


def bench_load(lines: int = 2_000_000, step=lambda: None) -> list[dict]:
    """Loading a two-column CSV of `lines` rows (written to a temporary file): the profile
    loader's text reader against np.loadtxt on the same file (goal: within 1.5x), and a
    10 mm patch of it (the reader stops once x has passed the patch)."""
    import tempfile
    from pathlib import Path

    from hostd.texture.load import LoadOptions, load_profile, read_columns

    rng = np.random.default_rng(0)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "big.csv"
        np.savetxt(f, np.column_stack([np.arange(lines) * 0.5, rng.normal(0, 3, lines)]),
                   delimiter=",", fmt="%.6f", header="x_um,height_um")
        step()
        ref = cpu_median_s(lambda: np.loadtxt(f, delimiter=","), repeat=3)
        step()
        ours = cpu_median_s(lambda: read_columns(f), repeat=3)
        step()
        whole = cpu_median_s(lambda: load_profile(f, LoadOptions(length_mm=None)), repeat=3)
        step()
        patch = cpu_median_s(lambda: load_profile(f, LoadOptions(length_mm=10.0)), repeat=3)
        step()
        rows.append({"bench": "load", "lines": lines, "mib": f.stat().st_size / 2**20,
                     "np_loadtxt_s": ref, "read_columns_s": ours, "ratio": ours / ref,
                     "load_profile_whole_s": whole, "load_profile_10mm_s": patch})
    return rows
