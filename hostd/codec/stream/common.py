"""What both stream versions share: the decoded Stream, the varints, the curve a stream names,
and the caller's limits (checked from the header before any allocation proportional to N or N')."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hostd.codec import transform
from hostd.errors import StreamError
from hostd.perception import thresholds as th


@dataclass(frozen=True)
class Limits:
    """A caller's caps (the daemon's library.max_n, max_n_keep; the display's travel). N and N'
    are checked from the header, before any array of their size is allocated (a 21-byte stream
    can promise N = 2^22); max_abs_um on the decoded values (a quant step of 1e300 decodes to
    finite coefficients no display can play and whose sums overflow)."""

    max_n: int | None = None
    max_n_keep: int | None = None
    max_abs_um: float | None = None

    def check_size(self, n: int, n_keep: int) -> None:
        if self.max_n is not None and n > self.max_n:
            raise StreamError(f"stream has N = {n} samples, more than this daemon plays "
                              f"({self.max_n}, library.max_n)")
        if self.max_n_keep is not None and n_keep > self.max_n_keep:
            raise StreamError(f"stream has N' = {n_keep} coefficients, more than this daemon plays "
                              f"({self.max_n_keep}, library.max_n_keep)")

    def check_values(self, coeffs: np.ndarray) -> None:
        if self.max_abs_um is None or coeffs.size == 0:
            return
        peak = float(np.max(np.abs(coeffs)))
        if not peak <= self.max_abs_um:
            raise StreamError(f"stream has a coefficient of {peak:.3g} µm, beyond {self.max_abs_um:g} µm "
                              "(100 times the display's travel, output.travel_um): it cannot be played "
                              "or scored; re-encode it from a profile in µm")


NO_LIMITS = Limits()


@dataclass(frozen=True)
class Stream:
    """A decoded stream: header fields and the decoded coefficients C'_1..C'_N'."""

    method: str
    coder: str
    n: int
    n_keep: int
    length_mm: float
    speed_mm_s: float
    fmax_hz: float
    threshold_id: bytes
    ref_P: float
    ref_A: float
    levels: int | None
    step_um: float | None
    b0_db: float | None
    value_bits: int | None
    curve: th.ThresholdCurve | None  # embedded curve, if any
    coefficients: np.ndarray
    nbytes: int
    payload_bytes: int
    version: int = 1  # the stream format version it was read from
    g_db: float | None = None  # shaped (v2): the knob, dB relative to the threshold
    guard_wsnr_db: float | None = None  # v2: the sender's wSNR (lower bound, 0.5 dB steps)

    @property
    def spacing_um(self) -> float:
        return self.length_mm * 1000.0 / self.n

    @property
    def frequencies_hz(self) -> np.ndarray:
        return transform.frequencies_hz(
            np.arange(1, self.n_keep + 1), self.length_mm, self.speed_mm_s
        )

    @property
    def ratio_coeffs(self) -> float:
        """Stream bytes over 16-bit raw coefficients (2 bytes x N')."""
        return self.nbytes / (2.0 * self.n_keep)

    @property
    def ratio_profile(self) -> float:
        """Stream bytes over the raw 16-bit profile (2 bytes x N)."""
        return self.nbytes / (2.0 * self.n)

    def reconstruct(self) -> np.ndarray:
        return transform.synthesize(self.coefficients, self.n)

    def summary(self) -> dict:
        out = {
            "version": self.version,
            "n": self.n,
            "length_mm": self.length_mm,
            "spacing_um": self.spacing_um,
            "speed_mm_s": self.speed_mm_s,
            "fmax_hz": self.fmax_hz,
            "n_keep": self.n_keep,
            "method": self.method,
            "coder": self.coder,
            "threshold_id": self.threshold_id.hex(),
            "curve_embedded": self.curve is not None,
            "bytes": self.nbytes,
            "payload_bytes": self.payload_bytes,
            "ratio_coeffs": self.ratio_coeffs,
            "ratio_profile": self.ratio_profile,
            "ref_P": self.ref_P,
            "ref_A": self.ref_A,
        }
        if self.guard_wsnr_db is not None:
            out["guard_wsnr_db"] = self.guard_wsnr_db
        if self.method == "shaped":
            out["g_db"] = self.g_db
            out["kept"] = int(np.count_nonzero(self.coefficients))
        elif self.method == "quant":
            out["levels"] = self.levels
            out["step_um"] = self.step_um
        else:
            out["b0_db"] = self.b0_db
            out["value_bits"] = self.value_bits
            out["kept"] = int(np.count_nonzero(self.coefficients))
        out["coefficients"] = self.coefficients.tolist()
        return out


def varint(u: int) -> bytes:
    """An unsigned LEB128 varint (7 bits a byte, low first); stream v1's q_min and the v2 header."""
    out = bytearray()
    while True:
        b = u & 0x7F
        u >>= 7
        if u:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def zigzag_varint(v: int) -> bytes:
    """The varint of v's zigzag code (2v for v >= 0, -2v - 1 below; |v| < 2^63)."""
    return varint(((v << 1) ^ (v >> 63)) & ((1 << 64) - 1))


def curve_for(stream: Stream, given: th.ThresholdCurve | None = None) -> th.ThresholdCurve:
    """The curve a stream was made with: the embedded one, the user's, or a shipped one by id."""
    if stream.curve is not None:
        return stream.curve
    if given is not None:
        if given.id_bytes != stream.threshold_id:
            raise StreamError(
                f"stream was made with threshold curve {stream.threshold_id.hex()}, "
                f"but {given.name} is {given.curve_id}: pass the curve it was encoded with"
            )
        return given
    found = th.shipped_curves().get(stream.threshold_id)
    if found is None:
        raise StreamError(
            f"threshold curve {stream.threshold_id.hex()} is not embedded and not shipped: "
            "pass it with --thresholds CSV"
        )
    return found
