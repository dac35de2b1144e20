"""Peer codecs for `hostd bench codec --peers DIR` (issue 14): the MPEG-I Haptics reference
software (ISO/IEC 23090-31 RM: the standard's codec, wavelet + SPIHT) and VC-PWQ (perceptual
wavelet quantization: a research codec under CC BY-NC, not the standard's), run as external
programs through the corpus codec protocol (hostd.corpus.peercodecs: the same objects
`hostd corpus` runs) and scored exactly like hostd's streams.

Their code is not part of hostd (VC-PWQ is CC BY-NC): they are built outside the repository
(DEVELOPMENT.md, "Peer codecs", and docs/interchange.md give the commits and the build
commands) and only run; each is used only when its programs are present.

What every codec is scored on (the same for hostd v2 and the peers):
- the texture's N' coefficients C_k (hostd.codec.transform.analyze), and
- the signal a hand at the texture's reference speed feels: `peer.played_signal` at 8 kHz.
A peer is given the displacement felt while crossing the patch once (L / v seconds of that
signal, 8 kHz), scaled to a peak of 1 (a full-scale WAV: these codecs' perceptual models
assume full-scale signals). Its decoded signal is scaled back and reduced to the texture's
N' components by least squares (hostd.render.series.project, the same fit the recorder
uses); those coefficients C'_k are scored like a decoded hostd stream: Iobj against C
(ref sums exact), and ST-SIM/SPQI of played(C') against played(C) over 1 s.
In the peers' favour: the projection drops their error outside the N' components. The bytes
are the file their encoder writes plus the 4-byte scale factor (the protocol counts the side
information a receiver needs; the patch geometry, needed by every codec, is not counted).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hostd.corpus import peercodecs
from hostd.corpus.peercodecs import (  # noqa: F401  (kept importable from here)
    FS_HZ,
    MPEG_BITRATES_KBPS,
    MPEG_ENCODER_ENV,
    MPEG_SYNTH_ENV,
    VCPWQ_BLOCK,
    VCPWQ_BUDGETS,
    VCPWQ_ENV,
    read_wav,
    write_wav,
)
from hostd.errors import HostdError
from hostd.perception import indices, peer


class PeerError(HostdError):
    """A peer codec's executable is missing, failed, or wrote something unreadable."""


@dataclass(frozen=True)
class PeerCodec:
    """One external codec of the corpus protocol, with the knob its table sweeps."""

    name: str
    knob: str  # what the knob means (for the table)
    knob_values: tuple[int, ...]
    codec: peercodecs._TimeSignalPeer  # the protocol object (hostd.corpus.codecs)
    knob_key: str  # the setting's keyword the knob sets

    def setting(self, knob: int) -> dict:
        return {self.knob_key: knob}


# where the build commands of DEVELOPMENT.md put them, relative to --peers DIR
VCPWQ_REL = "VC-PWQ/build/source/testprogram/VC_PWQ"
MPEG_ENCODER_REL = "HapticReferenceSoftware/build/source/Encoder/Encoder"
MPEG_SYNTH_REL = "HapticReferenceSoftware/build/source/Synthesizer/Synthesizer"


def _peer(codec: peercodecs._TimeSignalPeer, name: str) -> PeerCodec:
    key = next(iter(codec.settings[0]))
    return PeerCodec(name, codec.knob, tuple(s[key] for s in codec.settings), codec, key)


def vcpwq(exe: Path) -> PeerCodec:
    """VC-PWQ's demo program (a research codec, CC BY-NC): knob = bit budget per block."""
    return _peer(peercodecs.VcPwq(exe), "VC-PWQ (research, CC BY-NC)")


def mpeg_rm(encoder: Path, synthesizer: Path, options: tuple[str, ...] = ()) -> PeerCodec:
    """The MPEG-I Haptics reference software: Encoder (WAV -> binary .hmpg at a target bitrate,
    kb/s; `options`: () or ("-cf", "0")) and Synthesizer (.hmpg -> WAV at 8 kHz)."""
    cls = {(): peercodecs.MpegRm, ("-cf", "0"): peercodecs.MpegRmCf0}.get(tuple(options))
    if cls is None:
        raise PeerError(f"MPEG-I RM options {' '.join(options)!r}: only the default and -cf 0 are tabled")
    name = "MPEG-I RM" + (f" ({' '.join(options)})" if options else "")
    return _peer(cls(encoder, synthesizer), name)


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
    how to provide it). root: the --peers DIR (None: the environment variables, and for the
    reference software the cache its build.sh fills: hostd.texture.hjif.rm_dir)."""
    from hostd.texture import hjif

    found, notes = [], []
    rm = hjif.rm_dir()
    cands = [
        ("VC-PWQ (research, CC BY-NC)", [(VCPWQ_ENV, VCPWQ_REL, None)], lambda exe: [vcpwq(exe)]),
        ("MPEG-I RM", [(MPEG_ENCODER_ENV, MPEG_ENCODER_REL, rm and rm / "Encoder"),
                       (MPEG_SYNTH_ENV, MPEG_SYNTH_REL, rm and rm / "Synthesizer")], mpeg_rm_variants),
    ]
    for name, parts, make in cands:
        paths = []
        for env, rel, cached in parts:
            p = _exe(env, root, rel)
            if (p is None or not p.is_file()) and cached is not None:
                p = cached
            paths.append(p)
        missing = [f"{env} or DIR/{rel}" if p is None else str(p)
                   for (env, rel, _), p in zip(parts, paths, strict=True)
                   if p is None or not (p.is_file() and os.access(p, os.X_OK))]
        if missing:
            notes.append(f"{name} not run: no executable at {', '.join(missing)} (build the peer's "
                         f"reference software, then pass --peers DIR or set "
                         f"{' / '.join(env for env, _, _ in parts)})")
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


def run_peer(codec: PeerCodec, t: Texture, knob: int, work: Path | None = None) -> dict:
    """One peer encode + decode of the texture through the corpus protocol, scored. The heights
    it is given are the texture's N' components on its grid (so its own analysis finds C)."""
    from hostd.codec import transform
    from hostd.corpus.codecs import CodecFailure, run_codec

    heights = transform.synthesize(t.coeffs_um, t.n)
    geometry = {"speed_mm_s": t.speed_mm_s,
                "fmax_hz": t.coeffs_um.size * t.speed_mm_s / (2.0 * t.length_mm)}  # N' = C's size
    try:
        coded = run_codec(codec.codec, heights, t.length_mm * 1000.0 / t.n, codec.setting(knob), geometry)
    except CodecFailure as e:
        raise PeerError(str(e)) from None
    c = transform.analyze(coded.reconstruction_um, t.coeffs_um.size)
    return {"bytes": len(coded.data), **score(t, c)}


def sweep(codec: PeerCodec, t: Texture, spqi_min: float = 0.9) -> list[dict]:
    """The peer across its knob on one texture: the knob's grid, then every integer knob value
    between the largest one below spqi_min and the smallest one reaching it."""
    rows: dict[int, dict] = {}

    def at(knob: int) -> None:
        if knob not in rows:
            rows[knob] = {"bench": "codec_peer", "texture": t.name, "codec": codec.name,
                          "knob": knob, **run_peer(codec, t, knob)}

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


