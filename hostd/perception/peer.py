"""Peer metrics SPQI and ST-SIM (Hassen/Steinbach; Noll et al., TUM) on the played signal.

Both are computed on the displacement signals that a hand at the reference speed would feel:
the band-limited series of the reference and of the compressed coefficients, played for
`duration_s` over the patch's mirror-even extension, sampled at vibromaf's 8 kHz. Their
perceptual model was built for vibrotactile acceleration signals, so read them as a
side-by-side reference, not as a calibrated predictor for displacement textures.
SPQI is hostd's own implementation (hostd.perception.spqi, tested equal to vibromaf's), so it
is always computed; ST-SIM comes from the optional `vibromaf` (`pip install 'hostd[peer]'`):
without it, `available()` is False, `peer_scores` has no 'st_sim' and callers print a note.
"""

from __future__ import annotations

import warnings
from functools import lru_cache

import numpy as np

from hostd.perception import spqi as spqi_mod

FS_HZ = 8000.0


def __getattr__(name: str):
    if name == "NOTE_MISSING":  # names the command that installs the extra from what the user has
        from hostd.extras import pip_install

        return f"ST-SIM not computed: install the extra with {pip_install('peer')}"
    raise AttributeError(name)


def available() -> bool:
    """Whether vibromaf (ST-SIM) is installed; SPQI needs nothing extra."""
    try:
        import vibromaf.metrics.spqi
        import vibromaf.metrics.stsim  # noqa: F401
    except Exception:
        return False
    return True


def played_signal(coeffs_um: np.ndarray, n: int, length_mm: float, speed_mm_s: float,
                  duration_s: float = 1.0, fs_hz: float = FS_HZ) -> np.ndarray:
    """Height under a finger moving at constant speed v from x = 0, sampled at fs:
    h(t_m) = sum_k C_k cos(k theta(v t_m)), theta as in hostd.render.series (one chirp-z
    transform, FFT-based: no samples x N' cosine matrix)."""
    from hostd.render.stroke import at_constant_speed

    return at_constant_speed(coeffs_um, n, length_mm, speed_mm_s, fs_hz, round(duration_s * fs_hz),
                             band_limited=False)


@lru_cache(maxsize=8)
def _reference_signal(key: bytes, n: int, length_mm: float, speed_mm_s: float,
                      duration_s: float) -> np.ndarray:
    sig = played_signal(np.frombuffer(key, dtype=np.float64), n, length_mm, speed_mm_s, duration_s)
    sig.flags.writeable = False
    return sig


ST_SIM_ETA = 2.0 / 3.0  # vibromaf's st_sim() default: weight of the temporal similarity


@lru_cache(maxsize=8)
def _reference_st_sim(key: bytes, n: int, length_mm: float, speed_mm_s: float,
                      duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference's side of ST-SIM (its spectral support and normalized blocks, by
    vibromaf's own building blocks): the same for every variant of one original."""
    from vibromaf.metrics.stsim import STSIM
    from vibromaf.signal.spectrum import compute_spectral_support

    ref = _reference_signal(key, n, length_mm, speed_mm_s, duration_s)
    psb = STSIM.perceptual_spectrum_builder
    return (compute_spectral_support(psb.compute_perceptual_spectrum(ref)),
            psb.block_builder.divide_and_normalize(ref))


def _st_sim(dist: np.ndarray, ref: np.ndarray, ref_support: np.ndarray, ref_blocks: np.ndarray) -> float:
    """vibromaf's STSIM(eta).calculate(dist, ref), with the reference's side given."""
    from vibromaf.metrics.stsim import STSIM
    from vibromaf.signal.spectrum import compute_spectral_support
    from vibromaf.signal.transform import preprocess_input_signal

    dist = preprocess_input_signal(dist, ref)
    if np.array_equal(dist, ref):
        return 1.0
    psb = STSIM.perceptual_spectrum_builder
    spectral = STSIM.compute_sim(ref_support, compute_spectral_support(psb.compute_perceptual_spectrum(dist)))
    temporal = STSIM.compute_sim(ref_blocks, psb.block_builder.divide_and_normalize(dist))
    return pow(temporal, ST_SIM_ETA) * pow(spectral, 1 - ST_SIM_ETA)


@lru_cache(maxsize=8)
def _reference_spqi(key: bytes, n: int, length_mm: float, speed_mm_s: float,
                    duration_s: float) -> spqi_mod.Reference:
    """The reference's half of SPQI (its block spectra), once per original."""
    return spqi_mod.Reference(_reference_signal(key, n, length_mm, speed_mm_s, duration_s))


def played_spqi(ref_coeffs_um: np.ndarray, coeffs_um: np.ndarray, n: int, length_mm: float,
                speed_mm_s: float, duration_s: float = 1.0) -> float:
    """SPQI of the signal played from `coeffs_um` against the one played from the reference's
    coefficients (both at speed_mm_s for duration_s, 8 kHz), exactly as `hostd iobj REF
    STREAM` reports it; the reference's half is cached."""
    key = np.ascontiguousarray(ref_coeffs_um, dtype=np.float64).tobytes()
    ref = _reference_spqi(key, int(n), float(length_mm), float(speed_mm_s), float(duration_s))
    return ref.score(played_signal(coeffs_um, n, length_mm, speed_mm_s, duration_s))


def peer_scores(ref_coeffs_um: np.ndarray, coeffs_um: np.ndarray, n: int, length_mm: float,
                speed_mm_s: float, duration_s: float = 1.0) -> dict:
    """{'spqi': .., 'st_sim': ..} (1 = identical); 'st_sim' only when vibromaf is installed
    (None, with 'st_sim_note', where vibromaf's formula gives a complex number).
    The reference's played signal and its sides of SPQI and ST-SIM are cached (a sweep scores
    many variants of one original); both equal vibromaf's (tests/test_peer.py, test_spqi.py)."""
    key = np.ascontiguousarray(ref_coeffs_um, dtype=np.float64).tobytes()
    args = (key, int(n), float(length_mm), float(speed_mm_s), float(duration_s))
    dist = played_signal(coeffs_um, n, length_mm, speed_mm_s, duration_s)
    out = {"spqi": _reference_spqi(*args).score(dist)}
    if available():
        ref = _reference_signal(*args)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            st = _st_sim(dist, ref, *_reference_st_sim(*args))
        # vibromaf raises a negative similarity (anti-correlated blocks) to a fractional power:
        # a complex number, which is no score
        if isinstance(st, complex):
            out["st_sim"] = None
            out["st_sim_note"] = "ST-SIM undefined: a negative similarity (anti-correlated signals)"
        else:
            out["st_sim"] = float(st)
    return out
