"""Offline speed: scene simulation against effects and duration, the shipped scenes at
N' = 1600, and the rate-quality report at N' = 160.

Times are CPU seconds of the working thread (time.thread_time) with BLAS limited to that
thread, so they do not swing with other load on the machine; imports are warmed up first.
"""

from __future__ import annotations

import time
from dataclasses import replace

from hostd.bench.common import one_blas_thread
from hostd.paths import find
from hostd.sim import scene

SHIPPED = ("ideal", "paper-experiment", "usb-jitter", "clock-drift", "worst-case")
GOAL_SIM_1600_S = 5.0
GOAL_REPORT_160_S = 3.0


def _cpu(fn) -> float:
    t0 = time.thread_time()
    fn()
    return time.thread_time() - t0


def run(durations=(2.4, 9.6)) -> list[dict]:
    rows = []
    with one_blas_thread():
        scene.run(replace(scene.load(find("scenes", "ideal.toml")), duration_s=0.5))  # warm up
        for name in ("ideal", "paper-experiment", "worst-case"):
            base = scene.load(find("scenes", f"{name}.toml"))
            for dur in durations:
                sc = replace(base, duration_s=dur)
                cpu = _cpu(lambda sc=sc: scene.run(sc))
                rows.append({"bench": "sim", "scene": name, "effects": len(sc.effects), "duration_s": dur,
                             "cpu_s": cpu, "x_realtime": dur / cpu})
    return rows


def run_offline() -> list[dict]:
    """`hostd sim` of every shipped scene with a stream of N' = 1600 (f_max 4 kHz), and the
    rate-quality report of synthetic:wood:1 at N' = 160, against their goals."""
    import tempfile

    from hostd.codec import transform
    from hostd.perception import thresholds
    from hostd.report import rate_quality
    from hostd.texture import synth

    rows = []
    with one_blas_thread():
        for name in SHIPPED:
            base = scene.load(find("scenes", f"{name}.toml"))
            tex = dict(base.texture)
            if "stream" in tex:
                continue
            sc = replace(base, texture={**tex, "fmax_hz": 4000.0})
            cpu = _cpu(lambda sc=sc: scene.report(sc, progress=False))
            rows.append({"bench": "offline", "what": f"hostd sim {name}", "n_keep": 1600,
                         "runs": len(sc.effects) + 1 + (len(sc.effects) > 1),
                         "duration_s": sc.duration_s, "cpu_s": cpu, "goal_s": GOAL_SIM_1600_S,
                         "met": cpu < GOAL_SIM_1600_S})
        prof = synth.from_spec("synthetic:wood:1")
        geom = transform.Geometry(prof.n, prof.length_mm)
        curve = thresholds.default_curve()
        with tempfile.TemporaryDirectory() as d:
            rate_quality(prof.heights_um, geom, curve, d, "warm-up", progress=False)
            cpu = _cpu(lambda: rate_quality(prof.heights_um, geom, curve, d, "wood", progress=False))
        rows.append({"bench": "offline", "what": "hostd report rate-quality synthetic:wood:1",
                     "n_keep": geom.n_keep, "cpu_s": cpu, "goal_s": GOAL_REPORT_160_S,
                     "met": cpu < GOAL_REPORT_160_S})
    return rows
