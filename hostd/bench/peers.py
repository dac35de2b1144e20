"""Peer codecs for `hostd bench codec --peers DIR` (issue 14): the MPEG-I Haptics reference
software (ISO/IEC 23090-31 RM: wavelet + SPIHT) and VC-PWQ (perceptual wavelet quantization),
run as external programs and scored exactly like hostd's streams.

Their code is not part of hostd (VC-PWQ is CC BY-NC): they are built outside the repository
(docs/benchmarks.md, "Peer codecs", gives the commits and the build commands) and only run.

What every codec is scored on (the same for hostd v2 and the peers):
- the texture's N' coefficients C_k (hostd.codec.transform.analyze), and
- the signal a hand at the texture's reference speed feels: `peer.played_signal` at 8 kHz.
A peer is given the displacement felt while crossing the patch once (L / v seconds of that
signal, 8 kHz), scaled to a peak of 1 (a full-scale WAV: these codecs' perceptual models
assume full-scale signals). Its decoded signal is scaled back and reduced to the texture's
N' components by least squares (hostd.render.series.project, the same fit the recorder
uses); those coefficients C'_k are scored like a decoded hostd stream: Iobj against C
(ref sums exact), and ST-SIM/SPQI of played(C') against played(C) over 1 s.
In the peers' favour: the projection drops their error outside the N' components, and the
bytes are only the file their encoder writes (the scale factor and the patch geometry a
receiver would also need are not counted).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostd.errors import HostdError
from hostd.perception import indices, peer

FS_HZ = 8000  # vibromaf's rate; VC-PWQ supports 8000, 2800 and 2500 Hz
RUN_TIMEOUT_S = 60.0


class PeerError(HostdError):
    """A peer codec's executable is missing, failed, or wrote something unreadable."""


@dataclass(frozen=True)
class PeerCodec:
    """One external codec: `run(signal, workdir, knob)` -> (stream bytes, decoded signal)."""

    name: str
    knob: str  # what the knob means (for the table)
    knob_values: tuple[int, ...]
    executables: tuple[Path, ...]
    run: Callable[[np.ndarray, Path, int], tuple[int, np.ndarray]]


# ----------------------------------------------------------------------------- WAV in and out

def write_wav(path: Path, signal: np.ndarray, fs_hz: int = FS_HZ) -> None:
    """32-bit float mono WAV of a signal whose peak is <= 1."""
    import scipy.io.wavfile

    scipy.io.wavfile.write(path, fs_hz, np.asarray(signal, dtype=np.float32))


def read_wav(path: Path) -> np.ndarray:
    """The first channel of a WAV as float64 in -1..1 (integer PCM scaled by its full scale)."""
    import scipy.io.wavfile

    try:
        _, data = scipy.io.wavfile.read(path)
    except (OSError, ValueError) as e:
        raise PeerError(f"cannot read the peer's decoded WAV {path}: {e}") from None
    if data.ndim > 1:
        data = data[:, 0]
    if data.dtype == np.uint8:
        return (data.astype(np.float64) - 128.0) / 128.0
    if np.issubdtype(data.dtype, np.integer):
        return data.astype(np.float64) / float(-np.iinfo(data.dtype).min)
    return data.astype(np.float64)


def _run(cmd: list[str], cwd: Path) -> None:
    try:
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
    except FileNotFoundError:
        raise PeerError(f"peer executable not found: {cmd[0]}") from None
    except subprocess.TimeoutExpired:
        raise PeerError(f"{Path(cmd[0]).name} did not finish within {RUN_TIMEOUT_S:g} s") from None
    if r.returncode != 0:
        last = (r.stderr.strip() or r.stdout.strip()).splitlines()[-1:] or ["no output"]
        raise PeerError(f"{Path(cmd[0]).name} failed (exit {r.returncode}): {last[0]}")


# ----------------------------------------------------------------------------- the two peers

VCPWQ_ENV = "HOSTD_PEER_VCPWQ"
MPEG_ENCODER_ENV = "HOSTD_PEER_MPEG_ENCODER"
MPEG_SYNTH_ENV = "HOSTD_PEER_MPEG_SYNTHESIZER"
# where the build commands of docs/benchmarks.md put them, relative to --peers DIR
VCPWQ_REL = "VC-PWQ/build/source/testprogram/VC_PWQ"
MPEG_ENCODER_REL = "HapticReferenceSoftware/build/source/Encoder/Encoder"
MPEG_SYNTH_REL = "HapticReferenceSoftware/build/source/Synthesizer/Synthesizer"

VCPWQ_BUDGETS = (1, 2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 120)
VCPWQ_BLOCK = 512  # its default block length


def vcpwq(exe: Path) -> PeerCodec:
    """VC-PWQ's demo program (it codes every WAV of a folder): knob = bit budget per block."""

    def run(signal: np.ndarray, work: Path, budget: int) -> tuple[int, np.ndarray]:
        for sub in ("in", "enc", "dec"):
            shutil.rmtree(work / sub, ignore_errors=True)
            (work / sub).mkdir()
        write_wav(work / "in" / "sig.wav", signal)
        _run([str(exe), "-i", "in", "-c", "enc", "-o", "dec", "-b", str(budget),
              "-bl", str(VCPWQ_BLOCK), "-fs", str(FS_HZ)], work)
        enc = work / "enc" / f"sig_{budget}.binary"
        dec = work / "dec" / f"sig_{budget}.wav"
        if not enc.is_file() or not dec.is_file():
            raise PeerError(f"VC-PWQ wrote no {enc.name} / {dec.name} in {work}")
        return enc.stat().st_size, read_wav(dec)

    return PeerCodec("VC-PWQ", f"bit budget per {VCPWQ_BLOCK}-sample block", VCPWQ_BUDGETS,
                     (exe,), run)


MPEG_BITRATES_KBPS = (1, 2, 4, 6, 8, 12, 16, 20, 24, 32, 48, 64)


def mpeg_rm(encoder: Path, synthesizer: Path, options: tuple[str, ...] = ()) -> PeerCodec:
    """The MPEG-I Haptics reference software: Encoder (WAV -> binary .hmpg at a target bitrate,
    kb/s; `options` are extra encoder options) and Synthesizer (.hmpg -> WAV at 8 kHz)."""

    def run(signal: np.ndarray, work: Path, kbps: int) -> tuple[int, np.ndarray]:
        write_wav(work / "sig.wav", signal)
        for f in ("sig.hmpg", "dec.wav"):
            (work / f).unlink(missing_ok=True)
        _run([str(encoder), "-f", "sig.wav", "-o", "sig.hmpg", "--binary", "-kb", str(kbps),
              *options], work)
        _run([str(synthesizer), "-f", "sig.hmpg", "-o", "dec.wav", "--binary",
              "-fs", str(FS_HZ)], work)
        if not (work / "sig.hmpg").is_file() or not (work / "dec.wav").is_file():
            raise PeerError(f"the MPEG RM wrote no sig.hmpg / dec.wav in {work}")
        return (work / "sig.hmpg").stat().st_size, read_wav(work / "dec.wav")

    name = "MPEG-I RM" + (f" ({' '.join(options)})" if options else "")
    return PeerCodec(name, "target bitrate, kb/s", MPEG_BITRATES_KBPS, (encoder, synthesizer), run)


def mpeg_rm_variants(encoder: Path, synthesizer: Path) -> list[PeerCodec]:
    """Its default (a vectorial band below 72.5 Hz + a wavelet band), and one wavelet band over
    the whole spectrum (-cf 0), which needed fewer bytes on wood in a first trial."""
    return [mpeg_rm(encoder, synthesizer), mpeg_rm(encoder, synthesizer, ("-cf", "0"))]


def _exe(env: str, root: Path | None, rel: str) -> Path | None:
    if os.environ.get(env):
        return Path(os.environ[env])
    return None if root is None else root / rel


def find(root: Path | None) -> tuple[list[PeerCodec], list[str]]:
    """The peers that can run, and one note for each one that cannot (what is missing, and
    how to provide it). root: the --peers DIR (None: only the environment variables)."""
    found, notes = [], []
    cands = [
        ("VC-PWQ", [(VCPWQ_ENV, VCPWQ_REL)], lambda exe: [vcpwq(exe)]),
        ("MPEG-I RM", [(MPEG_ENCODER_ENV, MPEG_ENCODER_REL), (MPEG_SYNTH_ENV, MPEG_SYNTH_REL)],
         mpeg_rm_variants),
    ]
    for name, parts, make in cands:
        paths = [_exe(env, root, rel) for env, rel in parts]
        missing = [f"{env} or DIR/{rel}" if p is None else str(p)
                   for (env, rel), p in zip(parts, paths, strict=True)
                   if p is None or not (p.is_file() and os.access(p, os.X_OK))]
        if missing:
            notes.append(f"{name} not run: no executable at {', '.join(missing)} (build the peer's "
                         f"reference software, then pass --peers DIR or set "
                         f"{' / '.join(env for env, _ in parts)})")
        else:
            found += make(*paths)
    return found, notes


# ----------------------------------------------------------------------------- scoring

@dataclass(frozen=True)
class Texture:
    name: str
    coeffs_um: np.ndarray  # C_1..C_N'
    n: int
    length_mm: float
    speed_mm_s: float
    b_k: np.ndarray


def traverse_theta(t: Texture) -> np.ndarray:
    """Phases of the samples of one crossing of the patch at 8 kHz (t = 0 .. L/v)."""
    from hostd.render import series

    m = max(2, round(t.length_mm / t.speed_mm_s * FS_HZ))
    return series.phase_rad(np.arange(m) * (t.speed_mm_s / FS_HZ), t.n, t.length_mm)


def traverse_signal(t: Texture) -> np.ndarray:
    """The displacement (µm) felt while crossing the patch once, at 8 kHz."""
    from hostd.render import series

    return series.evaluate(t.coeffs_um, traverse_theta(t))


def coefficients_from_signal(t: Texture, signal_um: np.ndarray) -> np.ndarray:
    """C'_1..C'_N' of a decoded crossing: least squares on the texture's components."""
    from hostd.render import series

    th = traverse_theta(t)
    y = np.zeros(th.size)
    k = min(th.size, signal_um.size)
    y[:k] = signal_um[:k]  # a codec that returns fewer samples is scored on zeros after them
    return series.project(th, y, t.coeffs_um.size)[1:]


def score(t: Texture, decoded_um: np.ndarray) -> dict:
    """Iobj (against the exact reference sums), wSNR, ST-SIM and SPQI of decoded coefficients."""
    from hostd.perception import guard

    P, A = indices.weighted_sums(t.coeffs_um, t.b_k)
    Pp, Ap = indices.weighted_sums(decoded_um, t.b_k)
    ps = peer.peer_scores(t.coeffs_um, decoded_um, t.n, t.length_mm, t.speed_mm_s) or {}
    return {"Iobj": float(indices.scores_from_sums(P, A, Pp, Ap).Iobj),
            "wsnr_db": guard.weighted_snr_db(t.coeffs_um, decoded_um, t.b_k),
            "st_sim": ps.get("st_sim"), "spqi": ps.get("spqi")}


def run_peer(codec: PeerCodec, t: Texture, knob: int, work: Path) -> dict:
    """One peer encode + decode of the texture's crossing, scored."""
    sig = traverse_signal(t)
    peak = float(np.max(np.abs(sig)))
    scale = peak if peak > 0 else 1.0
    nbytes, dec = codec.run(sig / scale, work, knob)
    if not np.all(np.isfinite(dec)):
        raise PeerError(f"{codec.name} decoded NaN or Inf samples")
    c = coefficients_from_signal(t, dec * scale)
    return {"bytes": int(nbytes), **score(t, c)}


def sweep(codec: PeerCodec, t: Texture, spqi_min: float = 0.9) -> list[dict]:
    """The peer across its knob on one texture: the knob's grid, then every integer knob value
    between the largest one below spqi_min and the smallest one reaching it."""
    rows: dict[int, dict] = {}
    with tempfile.TemporaryDirectory(prefix="hostd-peer-") as d:
        def at(knob: int) -> None:
            if knob not in rows:
                rows[knob] = {"bench": "codec_peer", "texture": t.name, "codec": codec.name,
                              "knob": knob, **run_peer(codec, t, knob, Path(d))}

        for knob in codec.knob_values:
            at(knob)
        good = [k for k in codec.knob_values if (rows[k]["spqi"] or 0.0) >= spqi_min]
        if good:
            below = [k for k in codec.knob_values if k < good[0]]
            for knob in range((below[-1] + 1) if below else good[0], good[0]):
                at(knob)
    return [rows[k] for k in sorted(rows)]


def smallest(rows: list[dict], spqi_min: float = 0.9, iobj_max: float | None = None) -> dict | None:
    """The smallest row with SPQI >= spqi_min (and Iobj <= iobj_max when given)."""
    ok = [r for r in rows if r["spqi"] is not None and r["spqi"] >= spqi_min
          and (iobj_max is None or r["Iobj"] <= iobj_max)]
    return min(ok, key=lambda r: (r["bytes"], -r["spqi"])) if ok else None


