"""Regenerate the golden .vtx vectors: python tests/vectors/make_stream_vectors.py

Each vector is NAME.vtx plus NAME.json with the header fields and the decoded coefficients
(JSON numbers written with Python's repr, which round-trips float64 exactly). A decoder in
any language must turn NAME.vtx into exactly NAME.json's values.
"""

import json
from pathlib import Path

import numpy as np

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.perception import thresholds

HERE = Path(__file__).resolve().parent

CASES = {
    "quant_l14_deflate": dict(method="quant", levels=14, coder="deflate"),
    "quant_l4_none": dict(method="quant", levels=4, coder="none"),
    "cut_b0m4_exact_none": dict(method="cut", b0_db=-4.0, value_bits=0, coder="none"),
    "cut_b0p0_16bit_deflate": dict(method="cut", b0_db=0.0, value_bits=16, coder="deflate"),
    "cut_all_cut_none": dict(method="cut", b0_db=60.0, value_bits=0, coder="none"),
    "quant_embedded_curve_none": dict(method="quant", levels=6, coder="none", embed_curve=True),
}


def profile() -> np.ndarray:
    """A small deterministic profile: 2000 samples over 2 mm (N' = 32 at 50 mm/s, 400 Hz)."""
    n = 2000
    x = np.arange(n) / n
    return (3.0 * np.cos(np.pi * 3 * (x + 0.5 / n)) + 0.5 * np.sin(2 * np.pi * 11 * x)
            + 0.05 * np.cos(np.pi * 29 * x) + 0.2 * np.sin(2 * np.pi * 2.3 * x) ** 3)


def main() -> None:
    y = profile()
    geom = transform.Geometry(n=y.size, length_mm=2.0)
    curve = thresholds.default_curve()
    for name, kw in CASES.items():
        data = vtx.encode_profile(y, geom, curve, **kw)
        s = vtx.decode(data)
        info = s.summary()
        info["encode"] = kw
        (HERE / f"{name}.vtx").write_bytes(data)
        (HERE / f"{name}.json").write_text(json.dumps(info, indent=1) + "\n")
        print(name, len(data))


if __name__ == "__main__":
    main()
