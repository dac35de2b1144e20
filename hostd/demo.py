"""The demo on the embedded default: what the README's first command runs."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.perception import thresholds
from hostd.quality import score_stream
from hostd.texture import synth

DEMO_SETTINGS = (
    {"method": "quant", "levels": 14},
    {"method": "quant", "levels": 8},
    {"method": "quant", "levels": 4},
    {"method": "cut", "b0_db": -4.0, "value_bits": 16},
    {"method": "cut", "b0_db": 4.0, "value_bits": 16},
)


def codec_demo(out_dir: str | None = None) -> int:
    """Encode synthetic wood and sandpaper at several levels; print bytes and quality."""
    out = Path(out_dir) if out_dir else Path(tempfile.mkdtemp(prefix="hostd-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    curve = thresholds.default_curve()
    print(f"{'texture':<10} {'setting':<22} {'bytes':>6} {'%coeffs':>8} {'Ip':>7} {'Ia':>7} "
          f"{'Iobj':>7}")
    for kind in ("wood", "sandpaper"):
        prof = synth.make(kind, seed=1)
        geom = transform.Geometry(prof.n, prof.length_mm)
        for s in DEMO_SETTINGS:
            data = vtx.encode_profile(prof.heights_um, geom, curve, **s)
            tag = (f"quant L={s['levels']}" if s["method"] == "quant"
                   else f"cut b0={s['b0_db']:+.0f}dB 16-bit")
            name = f"{kind}-{tag.replace(' ', '_').replace('=', '')}.vtx"
            (out / name).write_bytes(data)
            st = vtx.decode(data)
            sc = score_stream(st)
            print(f"{kind:<10} {tag:<22} {st.nbytes:>6} {100 * st.ratio_coeffs:>7.1f}% "
                  f"{float(sc.Ip):>7.4f} {float(sc.Ia):>7.4f} {float(sc.Iobj):>7.4f}")
    print(f"streams written to {out}")
    return 0
