"""The standard's codec against hostd v2 net of the .hmpg container: for clips of several lengths,
the BD-rate of `mpeg-rm` against hostd-v2/shaped as `hostd corpus report` gives it (gross), and
with each `.hmpg` counted without what a silent clip of the same length and bitrate costs (net:
the container, headers and metadata, not the signal). Needs the reference software (its build.sh;
hostd finds it in ~/.cache/mpeg-haptics-rm/bin). docs/interchange.md quotes its output.

    PYTHONPATH=. python docs/examples/mpeg_container_cost.py /tmp/mpeg-cost
"""

import json
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

from hostd.cli import main as hostd
from hostd.corpus import peercodecs, report
from hostd.corpus.store import Store
from hostd.texture import hjif

# (patch length mm, reference speed mm/s): 0.05, 0.1, 0.2 s at 50 mm/s, and 1 s (the synthetic
# textures are 10 mm long: a longer clip is the same patch at 10 mm/s)
CLIPS = ((2.5, 50.0), (5.0, 50.0), (10.0, 50.0), (10.0, 10.0))
TEXTURES = ["synthetic:wood:1-3", "synthetic:sandpaper:1-3"]


def silent_bytes(work: Path, seconds: float) -> dict[int, int]:
    """kb/s -> bytes of the .hmpg of a silent clip (+ the 4-byte scale a receiver needs)."""
    rm = hjif.rm_dir()
    peercodecs.write_wav(work / "silence.wav", np.zeros(round(seconds * peercodecs.FS_HZ)))
    out = {}
    for kbps in peercodecs.MPEG_BITRATES_KBPS:
        subprocess.run([str(rm / "Encoder"), "-f", "silence.wav", "-o", "silence.hmpg", "--binary", "-kb",
                        str(kbps)], cwd=work, check=True, capture_output=True)
        out[kbps] = (work / "silence.hmpg").stat().st_size + peercodecs.SCALE.size
    return out


def summary(rows: list[dict]) -> dict:
    table = report.bd_table(rows, "hostd-v2/shaped", "iobj_db")
    vals = [r.bd_rate_pct for r in table if r.curve == "mpeg-rm" and np.isfinite(r.bd_rate_pct)]
    return {"median": statistics.median(vals), "mean": statistics.fmean(vals),
            "wins": sum(v < 0 for v in vals), "n": len(vals),
            "warnings": sum(1 for r in table if r.curve == "mpeg-rm" and r.note)}


def main(work: Path) -> None:
    if hjif.rm_dir() is None:
        sys.exit(f"the reference software is not installed: {hjif.RM_HOW}")
    work.mkdir(parents=True, exist_ok=True)
    print("| clip | silent .hmpg + scale, B | hostd-v2 streams, B | mpeg-rm BD-rate gross: median (mean) "
          "| net of the container: median (mean) | textures hostd wins, gross / net | CPU a clip, "
          "median: hostd-v2 / mpeg-rm |")
    print("|---|---|---|---|---|---|---|")
    for length, speed in CLIPS:
        db = work / f"c{length:g}-{speed:g}.sqlite"
        db.unlink(missing_ok=True)
        assert hostd(["corpus", "run", *TEXTURES, "--codec", "hostd-v2", "--codec", "mpeg-rm",
                      "--length-mm", f"{length:g}", "--speed", f"{speed:g}", "--no-spqi", "--no-progress",
                      "-o", str(db)]) == 0
        st = Store(db)
        try:
            rows = [r for r in st.rows() if r["error"] is None]
        finally:
            st.close()
        seconds = length / speed
        empty = silent_bytes(work, seconds)
        net = [{**r, "bytes": max(1, r["bytes"] - empty[json.loads(r["setting"])["kbps"]])}
               if r["curve"] == "mpeg-rm" else r for r in rows]
        g, n = summary(rows), summary(net)
        own = [r["bytes"] for r in rows if r["curve"] == "hostd-v2/shaped"]
        cpu = {c: statistics.median(r["encode_cpu_s"] + (r["decode_cpu_s"] or 0.0) for r in rows
                                    if r["curve"] == c) for c in ("hostd-v2/shaped", "mpeg-rm")}
        print(f"| {length:g} mm at {speed:g} mm/s, {seconds:g} s | "
              f"{min(empty.values())}-{max(empty.values())} | "
              f"{min(own)}-{max(own)} | {g['median']:+.0f} % ({g['mean']:+.0f} %) | "
              f"{n['median']:+.0f} % ({n['mean']:+.0f} %) | {g['n'] - g['wins']} / {n['n'] - n['wins']} of "
              f"{g['n']} (low-overlap warnings: {g['warnings']} / {n['warnings']}) | "
              f"{cpu['hostd-v2/shaped'] * 1e3:.1f} / {cpu['mpeg-rm'] * 1e3:.0f} ms |")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
