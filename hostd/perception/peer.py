"""Peer metrics ST-SIM and SPQI (Hassen/Steinbach; Noll et al., TUM) via the optional `vibromaf`.

Both are computed on the displacement signals that a hand at the reference speed would feel:
the band-limited series of the reference and of the compressed coefficients, played for
`duration_s` over the patch's mirror-even extension, sampled at vibromaf's 8 kHz. Their
perceptual model was built for vibrotactile acceleration signals, so read them as a
side-by-side reference, not as a calibrated predictor for displacement textures.
Install with `pip install 'hostd[peer]'`; without it, `available()` is False and callers
print a note instead of failing.
"""

from __future__ import annotations

import warnings

import numpy as np

FS_HZ = 8000.0
NOTE_MISSING = "peer metrics (ST-SIM, SPQI) not computed: install the extra with pip install 'hostd[peer]'"


def available() -> bool:
    try:
        import vibromaf.metrics.spqi
        import vibromaf.metrics.stsim  # noqa: F401
    except Exception:
        return False
    return True


def played_signal(coeffs_um: np.ndarray, n: int, length_mm: float, speed_mm_s: float,
                  duration_s: float = 1.0, fs_hz: float = FS_HZ) -> np.ndarray:
    """Height under a finger moving at constant speed: sum_k C_k cos(pi k (2 x/dx + 1) / (2N))."""
    c = np.asarray(coeffs_um, dtype=np.float64)
    dx_mm = length_mm / n
    t = np.arange(round(duration_s * fs_hz)) / fs_hz
    u = (2.0 * (speed_mm_s * t) / dx_mm + 1.0) * (np.pi / (2.0 * n))  # phase per unit k
    k = np.arange(1, c.size + 1, dtype=np.float64)
    return np.cos(np.outer(u, k)) @ c


def peer_scores(ref_coeffs_um: np.ndarray, coeffs_um: np.ndarray, n: int, length_mm: float,
                speed_mm_s: float, duration_s: float = 1.0) -> dict[str, float] | None:
    """{'st_sim': .., 'spqi': ..} (1 = identical), or None when vibromaf is not installed."""
    if not available():
        return None
    from vibromaf.metrics.spqi import spqi
    from vibromaf.metrics.stsim import st_sim

    ref = played_signal(ref_coeffs_um, n, length_mm, speed_mm_s, duration_s)
    dist = played_signal(coeffs_um, n, length_mm, speed_mm_s, duration_s)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return {"st_sim": float(st_sim(dist, ref)), "spqi": float(spqi(dist, ref))}
