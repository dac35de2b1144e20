"""Quality of a received stream: Ip, Ia, Iobj from the stream alone or against its original.

A receiver has only the stream: the reference sums P and A travel in its header (computed by
the sender from the uncompressed texture under the stream's own threshold curve), so it
scores exactly what the sender would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hostd.codec import transform
from hostd.codec.stream import Stream, curve_for
from hostd.errors import CodecError
from hostd.perception import indices
from hostd.perception.thresholds import ThresholdCurve


@dataclass(frozen=True)
class Scoring:
    """The curve and weights that score a stream (scoring_for)."""

    curve: ThresholdCurve | None  # None: the stream's own (embedded, or shipped by its id)
    a: float
    b: float
    calibration: str | None  # NAME@ID: the calibration's curve and weights score it; None: not
    note: str | None  # why the asked curve and weights were not applied (None: they were)


def scoring_for(stream: Stream, curve: ThresholdCurve | None = None, a: float = indices.DEFAULT_AB[0],
                b: float = indices.DEFAULT_AB[1], calibration: str | None = None,
                own_ab: tuple[float, float] = indices.DEFAULT_AB) -> Scoring:
    """The one rule for which curve and weights score a stream (the daemon's quality row, `hostd
    iobj`). The asked curve (a calibration's, labelled `calibration`, or a threshold CSV) with the
    weights (a, b), when the stream was made with that curve (its header names it or embeds it).
    A stream made with another curve cannot be scored with it (its reference sums are under its
    own): it is scored with its own curve and `own_ab`, the weights that go with that curve (the
    asked ones were fitted to indices under the asked curve), and `note` says so."""
    if curve is None or curve.id_bytes == stream.threshold_id:
        return Scoring(curve, a, b, calibration if curve is not None else None, None)
    what = f"calibration {calibration}'s curve" if calibration else f"{curve.name}"
    note = (f"the stream was made with threshold curve {stream.threshold_id.hex()}, not {what} "
            f"({curve.curve_id}): scored with its own curve and weights a={own_ab[0]:g}, b={own_ab[1]:g}")
    return Scoring(None, own_ab[0], own_ab[1], None, note)


def stream_thresholds(stream: Stream, curve: ThresholdCurve | None = None) -> np.ndarray:
    """b(f_k) for k = 1..N' at the stream's reference speed."""
    return curve_for(stream, curve)(stream.frequencies_hz)


def score_stream(
    stream: Stream,
    *,
    reference_um: np.ndarray | None = None,
    curve: ThresholdCurve | None = None,
    a: float = indices.DEFAULT_AB[0],
    b: float = indices.DEFAULT_AB[1],
) -> indices.Scores:
    """Score a decoded stream; against reference_um (N heights) if given, else its header."""
    b_k = stream_thresholds(stream, curve)
    comp = indices.scaled_sums(stream.coefficients, b_k)  # no overflow at any scale
    if reference_um is None:
        ref = indices.WeightedSums(np.float64(stream.ref_P), np.float64(stream.ref_A), 0)
    else:
        y = np.asarray(reference_um, dtype=np.float64)
        if y.size != stream.n:
            raise CodecError(
                f"the reference profile has {y.size} samples but the stream {stream.n}: "
                "load it with the same options (--length-mm, --spacing, units) as at encode"
            )
        ref = indices.scaled_sums(transform.analyze(y, stream.n_keep), b_k)
    return indices.scores_from_weighted(ref, comp, a, b)


def guard_report(stream: Stream, *, reference_um: np.ndarray | None = None,
                 curve: ThresholdCurve | None = None) -> dict:
    """The waveform guard of a stream: measured against the original when given, else the
    sender's value from a v2 header (a lower bound in 0.5 dB steps), else unavailable."""
    from hostd.perception import guard

    if reference_um is not None:
        b_k = stream_thresholds(stream, curve)
        c = transform.analyze(np.asarray(reference_um, dtype=np.float64), stream.n_keep)
        return {"wsnr_db": guard.weighted_snr_db(c, stream.coefficients, b_k),
                "ssnr_db": guard.spectral_snr_db(c, stream.coefficients, stream.frequencies_hz),
                "nmr_max_db": guard.max_nmr_db(c, stream.coefficients, b_k),
                "guard_source": "profile"}
    if stream.guard_wsnr_db is not None:
        return {"wsnr_db": stream.guard_wsnr_db, "guard_source": "stream_header"}
    return {"wsnr_db": None, "guard_source": "unavailable: a v1 stream does not record it; "
            "pass REFERENCE_PROFILE"}


def reference_mismatch(s, P: float, A: float, rel: float | None = None) -> str | None:
    """None when the reference's P and A match the stream header's (the stream's own original),
    else a sentence for the user. The tolerance is the header's precision: exact float64 in v1
    (1e-6 relative, for re-loading rounding), 17 significant bits in v2 (2^-16 relative)."""
    if rel is None:
        rel = 1e-6 if getattr(s, "version", 1) == 1 else 2.0 ** -16

    def close(x: float, y: float) -> bool:
        if not (math.isfinite(x) and math.isfinite(y)):
            return False  # a sum beyond float64 cannot be the header's (finite) one
        return abs(x - y) <= rel * max(abs(x), abs(y), 1e-300)

    if close(P, s.ref_P) and close(A, s.ref_A):
        return None
    return (f"the reference is not this stream's original: its P = {P:.6g}, A = {A:.6g}, the "
            f"stream header's P = {s.ref_P:.6g}, A = {s.ref_A:.6g}; check the file, seed and "
            "loading options (--length-mm, --offset-mm, units), or score with the header alone")
