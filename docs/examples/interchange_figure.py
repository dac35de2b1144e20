"""docs/figures/interchange-rm.png: what the MPEG-I Haptics reference Synthesizer plays of a file
hostd exports, beside hostd's own samples. Needs the reference software (its build.sh; hostd finds
it in ~/.cache/mpeg-haptics-rm/bin or $HOSTD_MPEG_RM). docs/interchange.md shows the figure.

    PYTHONPATH=. python docs/examples/interchange_figure.py docs/figures/interchange-rm.png
"""

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from hostd.cli import main as hostd
from hostd.texture import hjif

RATE_HZ = 48000  # the Synthesizer's highest rate


def main(png: Path) -> None:
    rm = hjif.rm_dir()
    if rm is None:
        sys.exit(f"the reference software is not installed: {hjif.RM_HOW}")
    with tempfile.TemporaryDirectory() as t:
        f = Path(t) / "wood.hjif"
        assert hostd(["export", "synthetic:wood:3", "--length-mm", "4", "-o", str(f)]) == 0
        subprocess.run([str(rm / "Synthesizer"), "-f", f.name, "-o", "wood.wav", "-fs", str(RATE_HZ)],
                       cwd=t, check=True, capture_output=True)
        _, wav = hjif.read_wav_full_scale(Path(t) / "wood.wav")
        doc = json.loads(f.read_bytes())
        tex, tim = hjif.read_channel(f, "0"), hjif.read_channel(f, "1")
    ts = doc["timescale"]
    fig, (a, b) = plt.subplots(2, 1, figsize=(8, 6))
    # over space: the RM takes a position for a tick of 1/timescale s, and hostd's ticks are
    # v / timescale long, so the WAV's time x v is the position along the stroke
    x_um = np.arange(tex.samples.size) * tex.step_m * 1e6
    t_wav = np.arange(wav.shape[0]) / RATE_HZ
    speed_mm_s = tim.speed_mm_s
    a.plot(t_wav * speed_mm_s * 1e3, wav[:, 0] * tex.full_scale_um, lw=2.5, color="0.75",
           label=f"reference Synthesizer at {RATE_HZ // 1000} kHz (its time x {speed_mm_s:g} mm/s)")
    a.plot(x_um, tex.samples * tex.full_scale_um, lw=0.8, color="C0",
           label="hostd's texture (as read back: the series on its 0.5-µm grid)")
    a.set_xlim(0, x_um[-1] + 100)
    a.set_xlabel("position, µm (the whole 4-mm patch)")
    a.set_ylabel("height, µm")
    a.set_title(f"'Vibrotactile Texture' (over space): played at {speed_mm_s:g} mm/s, "
                f"a position every {speed_mm_s * 1e3 / ts:.4g} µm")
    a.legend(fontsize=8, loc="lower right")
    t_ms = np.arange(tim.samples.size) / tim.rate_hz * 1e3
    b.plot(t_wav * 1e3, wav[:, 1] * tim.full_scale_um, lw=2.5, color="0.75",
           label=f"reference Synthesizer at {RATE_HZ // 1000} kHz")
    b.plot(t_ms, tim.samples * tim.full_scale_um, ".", ms=3, color="C1",
           label=f"hostd's rendering at {tim.speed_mm_s:g} mm/s, {tim.rate_hz:g} Hz")
    b.set_xlim(0, 20)
    b.set_xlabel("time, ms (the first 20 ms of 80)")
    b.set_ylabel("displacement, µm")
    b.set_title("'Vibrotactile' (as played at 50 mm/s)")
    b.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(png, dpi=90)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
