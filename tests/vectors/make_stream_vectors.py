"""Regenerate the golden .vtx vectors: python -m tests.vectors.make_stream_vectors

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


PROFILE_FILE = HERE / "profile_2000.f64"


def formula_profile() -> np.ndarray:
    """How profile_2000.f64 was made (2000 samples over 2 mm, N' = 32 at 50 mm/s, 400 Hz).

    Kept as documentation only: numpy's sin/cos have CPU-specific SIMD kernels, so the vectors
    are made from the stored float64 file, which is the same input on every machine.
    """
    n = 2000
    x = np.arange(n) / n
    return (3.0 * np.cos(np.pi * 3 * (x + 0.5 / n)) + 0.5 * np.sin(2 * np.pi * 11 * x)
            + 0.05 * np.cos(np.pi * 29 * x) + 0.2 * np.sin(2 * np.pi * 2.3 * x) ** 3)


def profile() -> np.ndarray:
    """The vectors' input profile: 2000 little-endian float64 heights (µm) from PROFILE_FILE."""
    return np.frombuffer(PROFILE_FILE.read_bytes(), dtype="<f8").astype(np.float64)


# Version 2 (hostd/codec/stream/v2.py). "paper" vectors use the paper's geometry (N = 20000, 0.5 µm, 50 mm/s,
# 400 Hz: no geometry bytes) with C_1..C_160 taken from the stored profile's amplitudes.
CASES_V2 = {
    "v2_shaped_gm9": dict(method="shaped", g_db=-9.0),
    "v2_shaped_gp3": dict(method="shaped", g_db=3.0),
    "v2_shaped_all_zero": dict(method="shaped", g_db=40.0),
    "v2_shaped_embedded_curve": dict(method="shaped", g_db=-6.0, embed_curve=True),
    "v2_quant_l14": dict(method="quant", levels=14),
    "v2_cut_b0p0_16bit": dict(method="cut", b0_db=0.0, value_bits=16),
    "v2_paper_shaped_gm6": dict(method="shaped", g_db=-6.0, paper=True),
    "v2_paper_quant_l8": dict(method="quant", levels=8, paper=True),
    # explicit geometry with a reference speed other than the paper's: v_ref and f_max stored
    "v2_shaped_gm9_v25": dict(method="shaped", g_db=-9.0, speed_mm_s=25.0),
    "v2_shaped_gm9_f300": dict(method="shaped", g_db=-9.0, fmax_hz=300.0),
}


def build_v2(name: str) -> bytes:
    from hostd.codec.stream import v2 as stream2

    kw = dict(CASES_V2[name])
    y = profile()
    curve = thresholds.default_curve()
    if kw.pop("paper", False):
        c = transform.amplitudes(y)[1:161] * 3.0
        return stream2.encode_coefficients(c, stream2.PAPER_GEOMETRY, curve, **kw)
    geom = transform.Geometry(n=y.size, length_mm=2.0, speed_mm_s=kw.pop("speed_mm_s", 50.0),
                              fmax_hz=kw.pop("fmax_hz", 400.0))
    return stream2.encode_profile(y, geom, curve, **kw)


def build() -> dict[str, bytes]:
    """Every vector's stream bytes, made from profile(): what the files must hold."""
    y = profile()
    geom = transform.Geometry(n=y.size, length_mm=2.0)
    curve = thresholds.default_curve()
    out = {name: vtx.v1.encode_profile(y, geom, curve, **kw) for name, kw in CASES.items()}
    out.update({name: build_v2(name) for name in CASES_V2})
    return out


def main() -> None:
    if not PROFILE_FILE.exists():
        PROFILE_FILE.write_bytes(formula_profile().astype("<f8").tobytes())
    for name, data in build().items():
        s = vtx.decode(data)
        info = s.summary()
        info["encode"] = CASES.get(name) or CASES_V2[name]
        (HERE / f"{name}.vtx").write_bytes(data)
        (HERE / f"{name}.json").write_text(json.dumps(info, indent=1) + "\n")
        print(name, len(data))


if __name__ == "__main__":
    main()
