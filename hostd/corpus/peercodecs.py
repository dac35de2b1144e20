"""Two peer codecs through the corpus protocol (hostd.corpus.codecs), each used only when its
program is present:

- `MpegRm`: the standard's codec, the MPEG-I Haptics reference software (ISO/IEC 23090-31 RM,
  BSD; MPEGGroup/HapticReferenceSoftware): Encoder (WAV -> .hmpg at a target bitrate, kb/s;
  wavelet + SPIHT, a Curve band below 72.5 Hz by default) and Synthesizer (.hmpg -> WAV).
  Found at $HOSTD_PEER_MPEG_ENCODER / $HOSTD_PEER_MPEG_SYNTHESIZER, else where the reference
  software's build.sh caches it (hostd.texture.hjif.rm_dir: $HOSTD_MPEG_RM,
  ~/.cache/mpeg-haptics-rm/bin).
- `VcPwq`: VC-PWQ (perceptual wavelet quantization), a research codec (CC BY-NC licence, not
  the standard's and not part of hostd): its demo program at $HOSTD_PEER_VCPWQ.

Both code time signals, so each is given what a hand at the reference speed v feels crossing
the patch once: the patch's N' components C_k (k v / 2L <= fmax) evaluated at 8 kHz for L / v
seconds (hostd.render.series), scaled to a peak of 1 (a full-scale WAV: their perceptual models
assume full-scale signals). The decoded signal is scaled back and reduced to the N' components
by least squares (series.project, the recorder's fit); the heights returned are those
components' series on the patch's grid (transform.synthesize), so the corpus scores them like
any codec. The bytes are the file the encoder writes plus the 4-byte float32 scale factor a
receiver needs (the patch geometry is not counted; a receiver of any codec needs it).

Names for `hostd corpus --codec`: mpeg-rm, mpeg-rm-cf0 (one wavelet band over the whole
spectrum, -cf 0), vc-pwq (hostd.corpus.codecs.PEERS), or in full hostd.corpus.peercodecs:MpegRm,
:MpegRmCf0, :VcPwq. `ABOUT` says what each is (its licence); the corpus report prints it beside
the tables wherever the codec appears.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import struct
import subprocess
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from hostd.corpus.codecs import CodecFailure, Unavailable

FS_HZ = 8000  # vibromaf's rate; VC-PWQ supports 8000, 2800 and 2500 Hz
RUN_TIMEOUT_S = 60.0
SCALE = struct.Struct("<f")  # the side information: the signal's peak, µm

VCPWQ_ENV = "HOSTD_PEER_VCPWQ"
MPEG_ENCODER_ENV = "HOSTD_PEER_MPEG_ENCODER"
MPEG_SYNTH_ENV = "HOSTD_PEER_MPEG_SYNTHESIZER"
VCPWQ_BUDGETS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 120)
VCPWQ_BLOCK = 512  # its default block length
MPEG_BITRATES_KBPS = (1, 2, 4, 6, 8, 12, 16, 20, 24, 32, 48, 64)


# ----------------------------------------------------------------------------- the signal a hand feels

def crossing(heights_um: np.ndarray, spacing_um: float, speed_mm_s: float, fmax_hz: float):
    """(theta, signal µm, N') of one crossing of the patch at 8 kHz: the N' components of the
    heights evaluated at the phases x = v t, t = 0 .. L / v."""
    from hostd.codec import transform
    from hostd.render import series
    from hostd.render.stroke import at_constant_speed, crossing_count

    y = np.asarray(heights_um, dtype=np.float64)
    n = y.size
    length_mm = n * spacing_um / 1000.0
    n_keep = max(1, min(n - 1, transform.n_keep_for(length_mm, speed_mm_s, fmax_hz)))
    c = transform.analyze(y, n_keep)
    m = crossing_count(length_mm, speed_mm_s, FS_HZ)
    theta = series.phase_rad(np.arange(m) * (speed_mm_s / FS_HZ), n, length_mm)
    return theta, at_constant_speed(c, n, length_mm, speed_mm_s, FS_HZ, m, band_limited=False), n_keep


def heights_from_signal(theta: np.ndarray, signal_um: np.ndarray, n_keep: int, n: int) -> np.ndarray:
    """The patch's heights from a decoded crossing: least squares on the N' components, then
    their series on the grid (a codec that returns fewer samples is scored on zeros after them)."""
    from hostd.codec import transform
    from hostd.render import series

    y = np.zeros(theta.size)
    k = min(theta.size, signal_um.size)
    y[:k] = signal_um[:k]
    return transform.synthesize(series.project(theta, y, n_keep)[1:], n)


def write_wav(path: Path, signal: np.ndarray, fs_hz: int = FS_HZ) -> None:
    """32-bit float mono WAV of a signal whose peak is <= 1."""
    import scipy.io.wavfile

    scipy.io.wavfile.write(path, fs_hz, np.asarray(signal, dtype=np.float32))


def read_wav(path: Path) -> np.ndarray:
    """The first channel of a WAV as float64 in -1..1 (integer PCM scaled by its full scale)."""
    import scipy.io.wavfile

    try:
        _, data = scipy.io.wavfile.read(path)
    except Exception as e:  # a broken header raises ZeroDivisionError, struct.error, UnboundLocalError...
        why = " ".join(f"{type(e).__name__}: {e}".split())[:200]
        raise CodecFailure(f"cannot read the peer's decoded WAV {path}: {why}", "bad_output") from None
    data = np.asarray(data)
    if data.ndim > 1:
        data = data[:, 0]
    if data.dtype == np.uint8:
        return (data.astype(np.float64) - 128.0) / 128.0
    if np.issubdtype(data.dtype, np.integer):
        return data.astype(np.float64) / float(-np.iinfo(data.dtype).min)
    return data.astype(np.float64)


def run(cmd: list[str], cwd: Path) -> None:
    """One run of a peer program; failures are one line (CodecFailure, a HostdError)."""
    try:
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S,
                           errors="replace")
    except FileNotFoundError:
        raise Unavailable(f"peer executable not found: {cmd[0]}") from None
    except subprocess.TimeoutExpired:
        raise CodecFailure(f"{Path(cmd[0]).name} did not finish within {RUN_TIMEOUT_S:g} s") from None
    if r.returncode != 0:
        last = (r.stderr.strip() or r.stdout.strip()).splitlines()[-1:] or ["no output"]
        raise CodecFailure(f"{Path(cmd[0]).name} failed (exit {r.returncode}): {last[0]}")


@lru_cache(maxsize=16)
def _digest(paths: tuple[str, ...]) -> str:
    h = hashlib.sha256()
    for p in paths:
        try:
            h.update(Path(p).read_bytes())
        except OSError:
            h.update(p.encode())
    return h.hexdigest()[:12]


def _executable(p: Path | None) -> bool:
    return p is not None and p.is_file() and os.access(p, os.X_OK)


class _TimeSignalPeer:
    """What both peers share: the crossing in, the program run in a temporary directory, the
    heights out; `_code(signal, work, **setting)` -> (bytes of its file, decoded signal)."""

    name = ""
    about = ""  # what it is, its licence: printed beside the corpus report's tables
    knob = ""
    settings: tuple[dict, ...] = ()

    def _paths(self) -> tuple[Path | None, ...]:
        raise NotImplementedError

    def _how(self) -> str:
        raise NotImplementedError

    @property
    def version(self) -> str:  # the programs' bytes: a rebuild is evaluated afresh
        paths = self._paths()
        return _digest(tuple(str(p) for p in paths)) if all(_executable(p) for p in paths) else "missing"

    def available(self) -> str | None:
        paths = self._paths()
        missing = [str(p) if p is not None else "(not found)" for p in paths if not _executable(p)]
        if missing:
            return f"{self.name}: binary missing: {', '.join(missing)}; {self._how()}"
        return None

    def encode_decode(self, heights_um: np.ndarray, spacing_um: float, *, speed_mm_s: float,
                      fmax_hz: float, **setting: Any) -> tuple[bytes, np.ndarray]:
        why = self.available()
        if why:
            raise Unavailable(why)
        theta, sig, n_keep = crossing(heights_um, spacing_um, speed_mm_s, fmax_hz)
        peak = float(np.max(np.abs(sig)))
        scale = float(np.float32(peak if peak > 0 else 1.0))
        with tempfile.TemporaryDirectory(prefix=f"hostd-{self.name}-") as d:
            data, dec = self._code(sig / scale, Path(d), **setting)
        if not np.all(np.isfinite(dec)):
            raise CodecFailure(f"{self.name} decoded NaN or Inf samples", "nonfinite")
        return SCALE.pack(scale) + data, heights_from_signal(theta, dec * scale, n_keep, heights_um.size)

    # the protocol's two calls, for drivers that want them separately: the program is one-shot
    def encode(self, heights_um: np.ndarray, spacing_um: float, **kw: Any) -> bytes:
        return self.encode_decode(heights_um, spacing_um, **kw)[0]

    def decode(self, data: bytes, n: int, spacing_um: float, **_: Any) -> np.ndarray:
        raise CodecFailure(f"{self.name} decodes only in one go with its encoder (encode_decode)")

    def _code(self, signal: np.ndarray, work: Path, **setting: Any) -> tuple[bytes, np.ndarray]:
        raise NotImplementedError


class MpegRm(_TimeSignalPeer):
    """The MPEG-I Haptics reference software (the standard's codec): knob = target bitrate, kb/s."""

    name = "mpeg-rm"
    about = ("the MPEG-I Haptics reference software (ISO/IEC 23090-31 RM, BSD): the standard's codec, "
             "WAV -> Encoder -> .hmpg -> Synthesizer")
    knob = "target bitrate, kb/s"
    settings = tuple({"kbps": k} for k in MPEG_BITRATES_KBPS)
    options: tuple[str, ...] = ()

    def __init__(self, encoder: Path | None = None, synthesizer: Path | None = None) -> None:
        self.encoder, self.synthesizer = encoder, synthesizer

    def _paths(self) -> tuple[Path | None, ...]:
        from hostd.texture import hjif

        rm = None if (self.encoder and self.synthesizer) else hjif.rm_dir()
        enc = self.encoder or (Path(os.environ[MPEG_ENCODER_ENV]) if os.environ.get(MPEG_ENCODER_ENV)
                               else rm / "Encoder" if rm else None)
        syn = self.synthesizer or (Path(os.environ[MPEG_SYNTH_ENV]) if os.environ.get(MPEG_SYNTH_ENV)
                                   else rm / "Synthesizer" if rm else None)
        return enc, syn

    def _how(self) -> str:
        return (f"set {MPEG_ENCODER_ENV} / {MPEG_SYNTH_ENV}, or build the reference software "
                "(its build.sh caches it in ~/.cache/mpeg-haptics-rm/bin)")

    def _code(self, signal: np.ndarray, work: Path, *, kbps: int, **_: Any) -> tuple[bytes, np.ndarray]:
        enc, syn = self._paths()
        write_wav(work / "sig.wav", signal)
        run([str(enc), "-f", "sig.wav", "-o", "sig.hmpg", "--binary", "-kb", str(int(kbps)), *self.options],
            work)
        run([str(syn), "-f", "sig.hmpg", "-o", "dec.wav", "--binary", "-fs", str(FS_HZ)], work)
        if not (work / "sig.hmpg").is_file() or not (work / "dec.wav").is_file():
            raise CodecFailure(f"the MPEG RM wrote no sig.hmpg / dec.wav in {work}", "bad_output")
        return (work / "sig.hmpg").read_bytes(), read_wav(work / "dec.wav")


class MpegRmCf0(MpegRm):
    """The reference software with one wavelet band over the whole spectrum (-cf 0)."""

    name = "mpeg-rm-cf0"
    about = "the MPEG-I Haptics reference software with one wavelet band over the whole spectrum (-cf 0)"
    options = ("-cf", "0")


class VcPwq(_TimeSignalPeer):
    """VC-PWQ's demo program (it codes every WAV of a folder): knob = bit budget per block.
    A research codec under CC BY-NC, not the standard's; hostd only runs a copy built outside."""

    name = "vc-pwq"
    about = ("VC-PWQ: a research codec (CC BY-NC licence), not the standard's and not part of hostd; "
             "only a copy built outside is run")
    knob = f"bit budget per {VCPWQ_BLOCK}-sample block"
    settings = tuple({"budget": b} for b in VCPWQ_BUDGETS)

    def __init__(self, exe: Path | None = None) -> None:
        self.exe = exe

    def _paths(self) -> tuple[Path | None, ...]:
        if self.exe is not None:
            return (self.exe,)
        env = os.environ.get(VCPWQ_ENV)
        return (Path(env) if env else None,)

    def _how(self) -> str:
        return f"set {VCPWQ_ENV} to the VC_PWQ program built from its sources (cmake)"

    def _code(self, signal: np.ndarray, work: Path, *, budget: int, **_: Any) -> tuple[bytes, np.ndarray]:
        (exe,) = self._paths()
        for sub in ("in", "enc", "dec"):
            shutil.rmtree(work / sub, ignore_errors=True)
            (work / sub).mkdir()
        write_wav(work / "in" / "sig.wav", signal)
        run([str(exe), "-i", "in", "-c", "enc", "-o", "dec", "-b", str(int(budget)),
             "-bl", str(VCPWQ_BLOCK), "-fs", str(FS_HZ)], work)
        enc = work / "enc" / f"sig_{int(budget)}.binary"
        dec = work / "dec" / f"sig_{int(budget)}.wav"
        if not enc.is_file() or not dec.is_file():
            raise CodecFailure(f"VC-PWQ wrote no {enc.name} / {dec.name} in {work}", "bad_output")
        return enc.read_bytes(), read_wav(dec)


# what each peer is, by the name its rows carry (the corpus report prints it where the codec appears)
ABOUT = {c.name: c.about for c in (MpegRm, MpegRmCf0, VcPwq)}
