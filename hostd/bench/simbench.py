"""How simulation time grows with the number of effects and with scene duration."""

from __future__ import annotations

import time
from dataclasses import replace

from hostd.paths import find
from hostd.sim import scene


def run(durations=(2.4, 9.6)) -> list[dict]:
    rows = []
    for name in ("ideal", "paper-experiment", "worst-case"):
        base = scene.load(find("scenes", f"{name}.toml"))
        for dur in durations:
            sc = replace(base, duration_s=dur)
            t0 = time.perf_counter()
            scene.run(sc)
            wall = time.perf_counter() - t0
            rows.append({"bench": "sim", "scene": name, "effects": len(sc.effects), "duration_s": dur,
                         "wall_s": wall, "x_realtime": dur / wall})
    return rows
