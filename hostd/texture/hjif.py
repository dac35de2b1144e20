"""MPEG-I Haptics (ISO/IEC 23090-31) interchange: `.hjif` (its JSON format) in and out, `.hmpg`
(its binary stream) in through the reference Decoder.

The standard's model is experience -> perceptions -> channels -> bands -> effects -> keyframes.
Its JSON schema is not public; what the reference software (MPEGGroup/HapticReferenceSoftware,
`source/IOHaptics/src/IOJson.cpp`) reads and plays is the judge, and the tests check hostd's
files with it (docs/interchange.md).

What hostd writes (`export`, `hostd export X -o Y.hjif`): one experience (version 2023, profile
Main, level 1, no avatars) with two perceptions, each of one channel holding one cubic Curve band
of one effect whose keyframes are the samples (a keyframe per sample, so the reference
Synthesizer's cubic interpolation passes through every sample and plays them exactly), then a 0
one step later and a last 0 at a common end (the RM never plays an effect's last keyframe: its
sample must lie past the WAV; RM_RATES_HZ). Every position stays within RM_MAX_POSITION (the
RM's 32-bit position x rate at 48 kHz), or the export is refused in one line:
- perception 0, "Vibrotactile Texture": the texture over space as hostd models it (its series
  C'_1..C'_K) along one stroke from x = 0 at the stated speed v, a keyframe per tick: the
  timescale is the largest multiple of rate_hz <= 48000 (timescale_for), a tick v / timescale
  long, so the reference Synthesizer, which takes positions for ticks, plays it at v. The tick
  is seldom a power of ten (unit_exponent: the nearest, tick_unit_exponent); the description
  states it and the series' geometry (`speed_mm_s= tick_um= terms= samples= spacing_um=`), and
  hostd's reader fits the terms back onto the N samples (_series_from_stroke).
- perception 1, "Vibrotactile": the texture as a hand at v feels it (one crossing of the patch,
  hostd's own rendering `hostd render` at that speed), in time: one keyframe per sample at
  `rate_hz`, timescale / rate_hz ticks apart.
With `compact`, each perception is one VectorialWave band instead, a sine effect per non-zero
term (vectorial_band), where the terms' frequencies at v are whole numbers of Hz.
Amplitudes are normalized: keyframe amplitude = height / full scale, |amplitude| <= 1, the
channel gain 1 and `perception_unit_exponent` 0, so the reference Synthesizer's WAV (full scale
= 1.0) holds the samples. The full scale in µm is written in each perception's description
(`full_scale_um=...`), and hostd's provenance (codec, setting, Iobj, geometry, source) as JSON in
the experience's description: the standard has no field for a physical displacement scale that
its Synthesizer honours, nor for a codec's provenance.

What hostd reads (`read`, the `.hjif` entry of hostd.texture.formats; `.hmpg` after the reference
Decoder): one channel of one perception, chosen with LoadOptions.member "PERCEPTION[/CHANNEL]"
(an index, or id=N). Its bands are evaluated as the reference Synthesizer evaluates them:
Curve bands (linear, cubic), WaveletWave bands (hostd.texture.hjif_wavelet, a port of the RM's
decoder) and VectorialWave and Transient bands (hostd.texture.hjif_vectorial, a port of its
evaluation) by hostd; in time-domain perceptions, Akima, Bezier and B-spline curves (and effects
the ports do not cover) through the reference Synthesizer, only when the user opts in (rm_opted_in:
$HOSTD_RUN_MPEG_RM=1) and then sandboxed (hjif_sandbox; an .hmpg likewise through the Decoder);
a one-line error saying how otherwise; the channel
is clipped to -1..1 and scaled by gain x 10^perception_unit_exponent. Spatial perceptions keep
their spacing (unit_exponent); a time-domain one needs a spacing (v / fs): the file's own when
hostd wrote it, else --spacing.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hostd.errors import ProfileError

if TYPE_CHECKING:
    from hostd.texture.formats import Columns
    from hostd.texture.load import LoadOptions

MAX_HJIF_BYTES = 64 << 20  # a larger file is refused before it is parsed (~1 M keyframes)
# samples of one evaluated channel: the loader's limit for a patch (hostd.codec.transform), 32 MB
# as float64. A file's declared sizes (positions, sample_count, blocks) are checked against it
# before anything is allocated, and a channel is evaluated into one buffer in chunks, so a crafted
# file of a few kB takes at most a few times the samples it yields (tests/test_hjif.py measures it)
MAX_SAMPLES = 1 << 22
CHUNK = 1 << 16  # samples evaluated at a time
MAX_KEYFRAMES = 2_000_000
MAX_AMPLITUDE = 1e3  # keyframe amplitudes are -1..1; the RM clips the channel's sum to that
MAX_GAIN = 1e6
DEFAULT_RATE_HZ = 8000  # the reference Synthesizer's default output rate
MAX_TIMESCALE = 48000  # the Main profile's limit (IOJson.cpp)
# The reference Synthesizer (2de9ff1, Band::EvaluationBand) maps a Curve keyframe to an output
# sample as relative_position x rate / timescale with a 32-bit int product divided as unsigned:
# past 2^32 the product wraps and the rest of the effect plays as zeros or garbage. At its
# highest rate, 48 kHz, the last position must stay at or below this; its effect positions other
# than 0 are misplaced too (position x rate x timescale), so a Curve band is one effect at 0.
# hostd's files keep every keyframe position within it (tests/test_hjif_rm.py plays them at 8 and
# 48 kHz), or are refused in one line.
RM_MAX_RATE_HZ = 48000
RM_MAX_POSITION = (2**32 - 1) // RM_MAX_RATE_HZ  # 89478
# The Synthesizer never plays a Curve effect's last keyframe (cubicInterpolation2 stops one short)
# and writes whatever lies past its buffer at that keyframe's sample. hostd's effects therefore end
# with a keyframe of 0 one step after the signal and a last one, also 0, at the end of the WAV:
# a common position that is a whole number of samples at each of these rates (the usual ones), so
# that its sample is the first one past the WAV's end
RM_RATES_HZ = (8000, 16000, 22050, 24000, 32000, 44100, 48000)


def rm_end_position(last: int, timescale: int) -> int:
    """The first position after `last` that is a whole number of samples at every RM_RATES_HZ."""
    m = math.lcm(*(timescale // math.gcd(timescale, f) for f in RM_RATES_HZ))
    return (last // m + 1) * m
# The body part mask's bits as the reference software defines them (Tools/include/OHMData.h,
# OHMData::Body, the OHM format's body table): RIGHT_HAND_FINGERS 0x00100000, LEFT_HAND_FINGERS
# 0x00200000. hostd's display is under a fingertip of either hand (body_part_target "Index")
BODY_PART_MASK = 0x00100000 | 0x00200000
# terms of the series in a spatial perception hostd reads back by a least-squares fit of the stroke
# (hostd.render.series.Projector: a (K+1)^2 Gram matrix, 33 MB and ~1 s at this K); 93 mm of texture
# at 400 Hz and 50 mm/s is 1,490
MAX_TERMS = 2048
MAX_DESCRIPTION_BYTES = 255  # .hmpg stores a description's length in 8 bits
VERSION = "2023"
TEXTURE = "Vibrotactile Texture"
TIME = "Vibrotactile"
SPATIAL_MODALITIES = {"Vibrotactile Texture", "Texture"}  # the RM's names (Perception.h)
# "Other": what the reference Encoder writes for a WAV input; read as a time-domain signal
TEMPORAL_MODALITIES = {"Vibrotactile", "Vibration", "Other"}
SPACING_UM_RANGE = (1e-4, 1e4)  # 0.1 nm .. 1 cm between samples: outside, the unit is absurd
NATIVE_CURVES = {"Linear", "Cubic", "Unknown"}  # "Unknown": the RM's default case, cubic
RM_ENV = "HOSTD_MPEG_RM"  # a directory with the reference software's Encoder, Decoder, Synthesizer
RM_TOOLS = ("Encoder", "Decoder", "Synthesizer")
RM_TIMEOUT_S = 30.0  # a valid 4-MiB .hmpg decodes in a few seconds
# What a reference tool may use: a legitimate .hmpg of 10 s of noise at 64 kb/s decodes in 6 MB,
# but 2 kB of random bytes made the Decoder at 2de9ff1 take 1 GB and 22 s. A tool past these
# fails (std::bad_alloc, SIGXCPU) and hostd says so in one line.
RM_MEMORY_BYTES = 1 << 30  # address space
RM_CPU_S = int(RM_TIMEOUT_S)
RM_FILE_BYTES = 256 << 20  # the largest file a tool may write (its WAV or .hjif)
MAX_HMPG_BYTES = 4 << 20  # refused before the Decoder runs (its .hjif is ~20x larger)
# The reference tools are third-party native parsers, not robust against hostile input (seeded
# mutations of a band's numbers crash the Synthesizer): hostd runs one on a file's content only
# when the user opts in with this setting (1), and then in a sandbox (hostd/texture/hjif_sandbox.py)
RM_OPT_IN_ENV = "HOSTD_RUN_MPEG_RM"
MAX_ERROR_CHARS = 300  # a quoted part of a one-line error (a tool's last line, a JSON error)
_FULL_SCALE = re.compile(r"full_scale_um=([0-9.eE+-]+)")
_SPEED = re.compile(r"speed_mm_s=([0-9.eE+-]+)")
_SPACING = re.compile(r"spacing_um=([0-9.eE+-]+)")
_SAMPLES = re.compile(r"samples=([0-9]+)")
_TICK = re.compile(r"tick_um=([0-9.eE+-]+)")
_TERMS = re.compile(r"terms=([0-9]+)")


# ============================================================================ the reference software

def rm_dir() -> Path | None:
    """The directory holding the reference Encoder, Decoder and Synthesizer: $HOSTD_MPEG_RM, else
    where the reference software's build.sh caches them (~/.cache/mpeg-haptics-rm/bin), else the
    directory of a `Synthesizer` on PATH. None when none of these holds all three."""
    cands: list[Path] = []
    if os.environ.get(RM_ENV):
        cands.append(Path(os.environ[RM_ENV]))
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    cands.append(cache / "mpeg-haptics-rm" / "bin")
    on_path = shutil.which("Synthesizer")
    if on_path:
        cands.append(Path(on_path).resolve().parent)
    for d in cands:
        if all((d / t).is_file() and os.access(d / t, os.X_OK) for t in RM_TOOLS):
            return d
    return None


RM_HOW = (f"build the MPEG-I Haptics reference software (its build.sh "
          f"caches it in ~/.cache/mpeg-haptics-rm/bin) or set {RM_ENV} to the "
          f"directory holding Encoder, Decoder and Synthesizer")


def rm_tool(name: str) -> Path:
    d = rm_dir()
    if d is None:
        raise ProfileError(f"the reference {name} is not installed: {RM_HOW}")
    return d / name


def rm_opted_in() -> bool:
    """Whether the user allows hostd to run the reference software on a file's content
    ($HOSTD_RUN_MPEG_RM=1)."""
    return os.environ.get(RM_OPT_IN_ENV, "").strip().lower() in ("1", "yes", "true", "on")


def rm_refusal(path: Path, what: str) -> ProfileError:
    """The one-line refusal to run the reference software on `path` without the opt-in."""
    return ProfileError(f"{path}: {what} only the reference software evaluates, a third-party program "
                        f"hostd runs on a file's content only when asked: set {RM_OPT_IN_ENV}=1 to run it "
                        "(sandboxed: no network, a private folder, a read-only copy of the input, "
                        f"{RM_MEMORY_BYTES >> 20} MiB, {RM_CPU_S} s of CPU)")


def _short(text: str, limit: int = MAX_ERROR_CHARS) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 15] + f" ... ({len(text)} chars)"


_SIGNALS = {9: "SIGKILL", 11: "SIGSEGV", 6: "SIGABRT", 24: "SIGXCPU", 25: "SIGXFSZ", 7: "SIGBUS", 8: "SIGFPE"}


def run_rm(name: str, *args: str, cwd: Path, source: Path | None = None,
           read_only: Path | None = None) -> str:
    """Run one reference tool in the folder `cwd` (private: made by the caller, holding only the
    tool's input, `read_only`) under hjif_sandbox: its stdout. A failure is one line naming the
    tool and `source`, the user's file the tool works on."""
    import sys

    exe = rm_tool(name)
    launcher = Path(__file__).with_name("hjif_sandbox.py")
    cmd = [sys.executable, "-I", str(launcher), str(RM_MEMORY_BYTES), str(RM_CPU_S), str(RM_FILE_BYTES),
           str(read_only) if read_only is not None else "-", str(exe), *args]
    env = {"PATH": "/usr/bin:/bin", "LANG": "C.UTF-8", "TMPDIR": str(cwd), "HOME": str(cwd)}
    who = f"{source}: " if source is not None else ""
    try:
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=RM_TIMEOUT_S,
                           errors="replace", env=env, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise ProfileError(f"{who}the reference {name} did not finish within {RM_TIMEOUT_S:g} s") from None
    if r.returncode != 0:
        lines = [x for x in (r.stderr.strip() or r.stdout.strip()).splitlines() if x.strip()]
        own = [x for x in lines if not x.startswith("sandbox:")]
        last = (own or lines or ["no output"])[-1]
        sig = _SIGNALS.get(-r.returncode, f"signal {-r.returncode}") if r.returncode < 0 else None
        status = f"killed by {sig}" if sig else f"exit {r.returncode}"
        raise ProfileError(f"{who}the reference {name} failed ({status}): {_short(last)}")
    return r.stdout


def _private_copy(src: Path, folder: Path, name: str, limit: int) -> Path:
    """A read-only copy of the user's file in the tool's private folder (at most `limit` bytes)."""
    try:
        with src.open("rb") as fh:
            data = fh.read(limit + 1)
    except OSError as e:
        raise ProfileError(f"cannot read {src}: {e.strerror or e}") from None
    if len(data) > limit:
        raise ProfileError(f"{src}: more than {limit} bytes; refused")
    dst = folder / name
    dst.write_bytes(data)
    dst.chmod(0o444)
    return dst


def read_wav_full_scale(path: Path, shown: Path | None = None) -> tuple[int, np.ndarray]:
    """(rate, samples (frames, channels)) of a PCM WAV as the reference tools write it, in units
    of full scale (int16 / 32768). Any failure of the reader is one line naming `shown` (or path)."""
    import scipy.io.wavfile

    try:
        rate, data = scipy.io.wavfile.read(path)
    except Exception as e:  # scipy's WAV reader raises more than ValueError on a broken header
        why = _short(f"{type(e).__name__}: {e}")
        raise ProfileError(f"cannot read the WAV {shown or path}: {why}") from None
    data = np.asarray(data)
    if data.ndim == 1:
        data = data.reshape(-1, 1)
    if np.issubdtype(data.dtype, np.integer):
        return int(rate), data.astype(np.float64) / float(-np.iinfo(data.dtype).min)
    return int(rate), data.astype(np.float64)


# ============================================================================ writing

@dataclasses.dataclass(frozen=True)
class Export:
    """What one .hjif of hostd holds (amplitudes in µm; the writer normalizes them)."""

    heights_um: np.ndarray  # the texture over space, uniform spacing
    spacing_um: float
    # hostd's representation of it: the series C'_1..C'_K of the N-sample patch (hostd.codec.transform);
    # the spatial perception is this series along one stroke at speed_mm_s, a keyframe per tick
    coeffs_um: np.ndarray
    n: int
    length_mm: float
    played_um: np.ndarray  # the texture in time at speed_mm_s, rate_hz
    speed_mm_s: float
    rate_hz: int
    provenance: dict
    full_scale_um: float | None = None  # None: the peak of both signals
    # which perceptions: "both", "texture" (over space) or "time" (as played). The reference
    # software at 2de9ff1 writes an .hmpg of a spatial perception its own Decoder cannot read
    # (it aborts: map::at), so an .hmpg for that software is made from "time"
    perceptions: str = "both"
    # each perception as one VectorialWave band, a sinusoid effect per non-zero term (vectorial_band)
    compact: bool = False


def timescale_for(rate_hz: int, spatial: bool) -> int:
    """The experience's timescale (ticks per second): with a spatial perception the largest
    multiple of rate_hz within the Main profile's MAX_TIMESCALE (48000 at 8, 16, 24 or 48 kHz,
    44100 at 22.05 or 44.1 kHz), so that a tick is one output sample at the RM's highest rate;
    without one, rate_hz (a time-domain perception alone then plays longest: RM_MAX_POSITION)."""
    return int(rate_hz) * (MAX_TIMESCALE // int(rate_hz)) if spatial else int(rate_hz)


def tick_unit_exponent(tick_um: float) -> int:
    """The power of ten nearest (in log) to the spatial tick: the perception's unit_exponent. The
    standard's unit is a power of ten; a stroke speed over a timescale of <= 48000 is seldom one
    (50 mm/s / 48000 = 1.0417 µm), so the exact tick is stated in the description (`tick_um=`)."""
    return round(math.log10(tick_um * 1e-6))


def vectorial_band(coeffs: np.ndarray, n: int, length_mm: float, speed_mm_s: float, end: int) -> dict:
    """One VectorialWave band of the series sum_k c_k cos(k theta(v t)) along a stroke from x = 0
    (c_k normalized to full scale): an effect at 0 per non-zero term, a sine of the term's
    frequency f_k = k v / 2L and amplitude |c_k| with the effect's phase k pi / 2N + pi/2 (+ pi when
    c_k < 0), and one keyframe, at `end` ticks (the RM's Synthesizer holds the first amplitude and
    frequency keyframe from 0, and its phase bookkeeping, which takes ticks for milliseconds, adds
    nothing before the first keyframe). The RM reads frequency_modulation as an integer number of
    Hz: every f_k must be one, else a one-line refusal saying why and which speeds allow it."""
    c = np.asarray(coeffs, dtype=np.float64)
    k = np.flatnonzero(c) + 1
    step_hz = speed_mm_s / (2 * length_mm)
    f = k * step_hz
    if k.size == 0:
        raise ProfileError("--compact: the texture has no non-zero component to write")
    off = np.abs(f - np.round(f))
    if np.any(off > 1e-9 * np.maximum(f, 1.0)):
        bad = int(k[np.argmax(off)])
        raise ProfileError(f"--compact: at {speed_mm_s:g} mm/s over {length_mm:.6g} mm the texture's "
                           f"components lie at k x {step_hz:.6g} Hz (k = {bad}: {bad * step_hz:.6g} Hz), and "
                           "the standard's vectorial effects take a whole number of Hz (frequency_modulation "
                           "is an integer), so they would drift out of phase: export at a --speed-mm-s that "
                           f"is a multiple of {2 * length_mm:.6g} mm/s (2 x the patch length x 1 Hz), or "
                           "without --compact")
    phase = (k * np.pi / (2 * n) + np.pi / 2 + np.where(c[k - 1] < 0, np.pi, 0.0)) % (2 * np.pi)
    def f32(x: float) -> float:  # what the RM reads (float32), in its shortest decimal form
        return float(str(np.float32(x)))

    effects = [{"effect_type": "Basis", "position": 0, "phase": f32(ph), "base_signal": "Sine",
                "keyframes": [{"relative_position": int(end), "amplitude_modulation": f32(abs(a)),
                               "frequency_modulation": round(fk)}]}
               for ph, a, fk in zip(phase.tolist(), c[k - 1].tolist(), f.tolist(), strict=True)]
    return {"band_type": "VectorialWave", "lower_frequency_limit": 0,
            "upper_frequency_limit": round(float(f.max())), "effects": effects}


def _curve_channel(desc: str, positions: np.ndarray, amps: np.ndarray, upper_hz: int,
                   extra: dict | None = None) -> dict:
    kfs = [{"relative_position": int(p), "amplitude_modulation": float(a)}
           for p, a in zip(positions.tolist(), amps.tolist(), strict=True)]
    ch = {"id": 0, "description": desc, "gain": 1.0, "mixing_coefficient": 1.0,
          "body_part_mask": BODY_PART_MASK, **(extra or {}),
          "bands": [{"band_type": "Curve", "curve_type": "Cubic", "lower_frequency_limit": 0,
                     "upper_frequency_limit": int(upper_hz),
                     "effects": [{"effect_type": "Basis", "position": 0, "keyframes": kfs}]}]}
    return ch


def build(ex: Export, date: str | None = None) -> dict:
    """The .hjif document (a dict ready for json) of an Export."""
    h = np.asarray(ex.heights_um, dtype=np.float64)
    p = np.asarray(ex.played_um, dtype=np.float64)
    if h.ndim != 1 or h.size < 3 or p.ndim != 1 or p.size < 3:
        raise ProfileError("an .hjif export needs at least 3 samples over space and in time")
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(p))):
        raise ProfileError("an .hjif export cannot hold NaN or Inf heights")
    if ex.perceptions not in ("both", "texture", "time"):
        raise ProfileError(f"perceptions must be both, texture or time, got {ex.perceptions!r}")
    if not (1 <= ex.rate_hz <= MAX_TIMESCALE) or int(ex.rate_hz) != ex.rate_hz:
        raise ProfileError(f"--rate-hz must be a whole number of Hz in 1..{MAX_TIMESCALE} (the Main "
                           f"profile's timescale), got {ex.rate_hz}")
    want_tex, want_time = ex.perceptions in ("both", "texture"), ex.perceptions in ("both", "time")
    rate = int(ex.rate_hz)
    ts = timescale_for(rate, want_tex)
    m = rm_end_position(0, ts)
    limit = (RM_MAX_POSITION // m) * m - 1  # the last 0 keyframe; the end is then <= RM_MAX_POSITION
    step_t = ts // rate  # ticks per sample of the time-domain perception
    stroke = recon = None
    if want_tex:
        from hostd.codec import transform
        from hostd.render.stroke import at_constant_speed, crossing_count

        tick_um = ex.speed_mm_s * 1e3 / ts
        count = crossing_count(ex.length_mm, ex.speed_mm_s, ts, minimum=3)
        if count + 1 > limit:
            raise ProfileError(f"one stroke over the {ex.length_mm:.4g}-mm patch at {ex.speed_mm_s:g} mm/s "
                               f"is {count} positions of 1/{ts} s, more than the reference player plays "
                               f"({limit}: it computes position x rate in 32 bits, up to 48 kHz): export "
                               f"at most {limit * tick_um / 1000:.4g} mm (--length-mm), raise --speed-mm-s, "
                               "or only the texture as played (--perceptions time)")
        k = np.asarray(ex.coeffs_um, dtype=np.float64).size
        top_hz = k * ex.speed_mm_s / (2 * ex.length_mm)  # the series' highest component at this speed
        if not 1 <= k <= MAX_TERMS or top_hz >= ts / 2 or k + 2 > count:
            raise ProfileError(f"the texture's {k} components reach {top_hz:.4g} Hz at {ex.speed_mm_s:g} "
                               f"mm/s: the spatial perception holds at most {MAX_TERMS} below {ts / 2:g} Hz "
                               "(half its timescale): lower --speed-mm-s or --fmax-hz, or export a shorter "
                               "patch (--length-mm)")
        stroke = at_constant_speed(ex.coeffs_um, ex.n, ex.length_mm, ex.speed_mm_s, ts, count,
                                   band_limited=False)
        recon = transform.synthesize(ex.coeffs_um, ex.n)  # what hostd's reader makes of it
    if want_time and p.size * step_t > limit:
        raise ProfileError(f"the texture as played is {p.size} samples at {ex.rate_hz} Hz "
                           f"({p.size / ex.rate_hz:.3g} s), more than the reference player plays ("
                           f"{limit // step_t} samples: it computes position x rate in 32 bits, up to "
                           "48 kHz): lower --rate-hz, raise --speed-mm-s or export a shorter patch "
                           "(--length-mm)")
    written = [a for a, on in ((stroke, want_tex), (recon, want_tex), (p, want_time)) if on]
    peak = max(float(np.max(np.abs(a))) for a in written)
    fs_um = ex.full_scale_um if ex.full_scale_um is not None else (peak if peak > 0 else 1.0)
    if not (math.isfinite(fs_um) and fs_um > 0):
        raise ProfileError(f"full scale must be a finite number > 0 µm, got {fs_um}")
    clipped = sum(int(np.count_nonzero(np.abs(a) > fs_um)) for a in written)
    if clipped:
        raise ProfileError(f"{clipped} samples exceed the full scale {fs_um:g} µm (peak {peak:.4g} µm): "
                           "raise --full-scale-um")
    scale = f"full_scale_um={fs_um!r}"
    # the displacement of amplitude 1.0, in metres; body_part_mask: the index finger (BODY_PART_MASK)
    device = {"id": 0, "name": "hostd vibrotactile texture display", "body_part_mask": BODY_PART_MASK,
              "maximum_displacement": fs_um * 1e-6}
    target = {"reference_device_id": 0, "body_part_target": ["Index"]}
    tex = tim = None
    if want_tex:
        e = tick_unit_exponent(tick_um)
        # the spatial band's frequency limit: the series' highest component, cycles per metre
        upper_tex = max(1, min(2**31 - 1, math.ceil(k / (2 * ex.length_mm * 1e-3))))
        tex = {"id": 0, "avatar_id": 0,
               "description": (f"hostd texture over space: one stroke at speed_mm_s={ex.speed_mm_s!r}, a "
                               f"position per tick_um={tick_um!r} (1/{ts} s), of the series of terms={k} of "
                               f"samples={ex.n} spacing_um={ex.spacing_um!r}; {scale}"),
               "perception_modality": TEXTURE, "unit_exponent": e, "perception_unit_exponent": 0,
               "reference_devices": [device], "effect_library": [],
               "channels": [_curve_channel("height profile along the stroke (normalized to full scale)",
                                           np.arange(count, dtype=np.int64), stroke / fs_um, upper_tex,
                                           target)]}
    if want_time:
        tim = {"id": 1, "avatar_id": 0,
               "description": (f"hostd texture as played at speed_mm_s={ex.speed_mm_s!r}: one crossing of "
                               f"the patch, {p.size} samples at {ex.rate_hz} Hz; {scale}"),
               "perception_modality": TIME, "perception_unit_exponent": 0,
               "reference_devices": [{**device, "maximum_frequency": ex.rate_hz / 2}], "effect_library": [],
               "channels": [_curve_channel("displacement at the fingertip (normalized to full scale)",
                                           np.arange(p.size, dtype=np.int64) * step_t, p / fs_um,
                                           ex.rate_hz // 2,
                                           {"frequency_sampling": rate, "sample_count": int(p.size),
                                            **target})]}
    if ex.compact:
        from hostd.render.stroke import with_band_gains

        if tex is not None:
            tex["channels"][0]["bands"] = [vectorial_band(np.asarray(ex.coeffs_um) / fs_um, ex.n,
                                                          ex.length_mm, ex.speed_mm_s, count - 1)]
        if tim is not None:
            gained = with_band_gains(ex.coeffs_um, ex.length_mm, ex.speed_mm_s, rate) / fs_um
            tim["channels"][0]["bands"] = [vectorial_band(gained, ex.n, ex.length_mm, ex.speed_mm_s,
                                                          (p.size - 1) * step_t)]
    chosen = [q for q in (tex, tim) if q is not None]
    # each Curve effect ends with 0 one step after its signal and 0 at a common end (RM_RATES_HZ)
    curves = [q for q in chosen if q["channels"][0]["bands"][0]["band_type"] == "Curve"]
    ends = []
    for q in curves:
        kfs = q["channels"][0]["bands"][0]["effects"][0]["keyframes"]
        step = kfs[-1]["relative_position"] - kfs[-2]["relative_position"]
        kfs.append({"relative_position": kfs[-1]["relative_position"] + step, "amplitude_modulation": 0.0})
        ends.append(kfs[-1]["relative_position"])
    end = rm_end_position(max(ends, default=0), ts)
    for q in curves:
        q["channels"][0]["bands"][0]["effects"][0]["keyframes"].append(
            {"relative_position": end, "amplitude_modulation": 0.0})
    for q in chosen:
        if len(q["description"].encode()) > MAX_DESCRIPTION_BYTES:
            raise ProfileError(f"description of perception {q['id']} is longer than "
                               f"{MAX_DESCRIPTION_BYTES} bytes")
    return {"version": VERSION, "profile": "Main", "level": 1,
            "date": date or _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d"),
            "description": provenance_text(ex.provenance),
            "timescale": ts, "avatars": [],
            "perceptions": chosen,
            "syncs": []}


def provenance_text(prov: dict) -> str:
    """hostd's provenance as compact JSON {"hostd": {...}} within MAX_DESCRIPTION_BYTES (the
    binary .hmpg stores a description's length in 8 bits: the reference Decoder fails on longer
    ones): a long source name is shortened, then the keys last in `prov` are dropped."""
    items = dict(prov)
    while True:
        text = json.dumps({"hostd": items}, separators=(",", ":"), allow_nan=False)
        if len(text.encode()) <= MAX_DESCRIPTION_BYTES:
            return text
        src = items.get("source")
        if isinstance(src, str) and len(src) > 24:
            items["source"] = src[:10] + "..." + src[-11:]
        elif items:
            items.pop(next(reversed(items)))
        else:
            return "hostd"


def dumps(doc: dict) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()


# ============================================================================ reading

class _Doc:
    """Typed access to the JSON with errors that name the file and the field."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def err(self, field: str, what: str) -> ProfileError:
        return ProfileError(f"{self.path}: {field}: {what}")

    def get(self, obj: dict, key: str, where: str, kind: str, default: Any = ...) -> Any:
        field = f"{where}.{key}" if where else key
        if key not in obj:
            if default is not ...:
                return default
            raise self.err(field, "missing")
        v = obj[key]
        ok = {"int": isinstance(v, int) and not isinstance(v, bool),
              "num": isinstance(v, int | float) and not isinstance(v, bool),
              "str": isinstance(v, str), "list": isinstance(v, list),
              "obj": isinstance(v, dict)}[kind]
        if not ok:
            names = {"int": "an integer", "num": "a number", "str": "a string", "list": "an array",
                     "obj": "an object"}
            raise self.err(field, f"must be {names[kind]}, got {type(v).__name__} {str(v)[:40]}")
        if kind == "num" and not math.isfinite(v):
            raise self.err(field, "must be finite")
        if kind == "int" and not -(2**31) <= v < 2**32:  # the RM reads 32-bit integers
            raise self.err(field, f"{v} is outside the 32-bit range the format uses")
        return v


def _reject_constant(name: str):
    raise ValueError(f"{name} is not JSON")


def load_json(path: Path, shown: Path | None = None) -> dict:
    """The parsed document; a file larger than MAX_HJIF_BYTES is refused before parsing. Errors
    name `shown` (the user's file) when given, else `path`."""
    real, path = path, shown if shown is not None else path
    try:
        size = real.stat().st_size
    except FileNotFoundError:
        raise ProfileError(f"no such .hjif file: {path}") from None
    except OSError as e:
        raise ProfileError(f"cannot read {path}: {e.strerror or e}") from None
    if size > MAX_HJIF_BYTES:
        raise ProfileError(f"{path}: {size} bytes, more than the {MAX_HJIF_BYTES >> 20} MiB an .hjif may "
                           "have here (hostd.texture.hjif.MAX_HJIF_BYTES); split the file")
    try:
        with real.open("rb") as fh:
            raw = fh.read(MAX_HJIF_BYTES + 1)
    except OSError as e:
        raise ProfileError(f"cannot read {path}: {e.strerror or e}") from None
    if len(raw) > MAX_HJIF_BYTES:
        raise ProfileError(f"{path}: more than {MAX_HJIF_BYTES >> 20} MiB; refused")
    try:
        doc = json.loads(raw, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as e:
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ProfileError(f"{path}: not valid JSON ({_short(msg)})") from None
    if not isinstance(doc, dict):
        raise ProfileError(f"{path}: not an .hjif (the top level must be a JSON object)")
    return doc


@dataclasses.dataclass(frozen=True)
class Channel:
    """One evaluated channel: samples as the reference Synthesizer plays them (full scale 1,
    times gain x 10^perception_unit_exponent), on a uniform grid."""

    samples: np.ndarray
    spatial: bool
    step_m: float | None  # spatial: grid spacing in metres
    rate_hz: float | None  # temporal: samples per second
    perception: int
    channel: int
    modality: str
    full_scale_um: float | None  # hostd's files: amplitude 1.0 in µm
    speed_mm_s: float | None  # hostd's time-domain perception: its stroke speed
    note: str = ""


def _label(d: _Doc, p: dict, i: int) -> str:
    chans = p.get("channels")
    return (f"{i} (id={str(p.get('id'))[:20]}, {str(p.get('perception_modality'))[:40]!r}, "
            f"{len(chans) if isinstance(chans, list) else 0} channel(s))")


def _stated(pattern: re.Pattern, text: str, upper: float) -> float | None:
    """A `key=value` hostd wrote in a description: a number in (0, upper], else None."""
    m = pattern.search(text)
    try:
        v = float(m.group(1)) if m else math.nan
    except ValueError:
        return None
    return v if 0 < v <= upper else None


MAX_CHOICES = 8  # choices listed in a message (a file may hold 50,000 perceptions)


def _choices(labels: list[str]) -> str:
    """The first MAX_CHOICES labels, and how many more: a one-line message stays short."""
    more = len(labels) - MAX_CHOICES
    return "; ".join(labels[:MAX_CHOICES]) + (f"; ... and {more} more" if more > 0 else "")


def _pick(items: list, spec: str | None, what: str, d: _Doc, labels: list[str]) -> int:
    choices = _choices(labels)
    m = re.fullmatch(r"\s*(?:(id)\s*=\s*)?(-?\d+)\s*", spec or "")
    if not m:
        raise d.err("member", f"{what} {spec!r}: give an index or id=N (choices: {choices})")
    n = int(m.group(2))
    if m.group(1):
        hits = [i for i, it in enumerate(items) if isinstance(it, dict) and it.get("id") == n]
        if len(hits) != 1:
            raise d.err("member", f"no single {what} with id {n} (choices: {choices})")
        return hits[0]
    if not 0 <= n < len(items):
        raise d.err("member", f"{what} index {n} out of range (choices: {choices})")
    return n


def select(doc: dict, path: Path, member: str | None) -> tuple[int, int, str]:
    """(perception index, channel index, note) chosen by member "PERCEPTION[/CHANNEL]"."""
    d = _Doc(path)
    perceptions = d.get(doc, "perceptions", "", "list")
    if not perceptions:
        raise d.err("perceptions", "empty: the file holds no perception")
    for i, p in enumerate(perceptions):
        if not isinstance(p, dict):
            raise d.err(f"perceptions[{i}]", "must be an object")
    labels = [_label(d, p, i) for i, p in enumerate(perceptions[: MAX_CHOICES + 1])]
    labels += [""] * (len(perceptions) - len(labels))  # counted, not listed
    note = ""
    pspec, _, cspec = (member or "").partition("/")
    if member:
        pi = _pick(perceptions, pspec, "perception", d, labels)
    elif len(perceptions) == 1:
        pi = 0
    else:
        spatial = [i for i, p in enumerate(perceptions)
                   if isinstance(p.get("perception_modality"), str)
                   and p["perception_modality"] in SPATIAL_MODALITIES]
        if len(spatial) != 1:
            raise ProfileError(f"{path}: {len(perceptions)} perceptions, choose one with --member "
                               f"PERCEPTION[/CHANNEL] (index or id=N): {_choices(labels)}")
        pi = spatial[0]
        note = (f"took perception {labels[pi] or _label(d, perceptions[pi], pi)}, the texture over space; "
                f"--member chooses another of: {_choices(labels)}")
    where = f"perceptions[{pi}]"
    chans = d.get(perceptions[pi], "channels", where, "list")
    if not chans:
        raise d.err(f"{where}.channels", "empty: the perception has no channel")
    clabels = [f"{j} (id={str(c.get('id'))[:20] if isinstance(c, dict) else '?'})"
               for j, c in enumerate(chans[: MAX_CHOICES + 1])]
    clabels += [""] * (len(chans) - len(clabels))
    if cspec:
        ci = _pick(chans, cspec, "channel", d, clabels)
    elif len(chans) == 1:
        ci = 0
    else:
        raise ProfileError(f"{path}: perception {pi} has {len(chans)} channels, choose one with --member "
                           f"{pi}/CHANNEL: {_choices(clabels)}")
    return pi, ci, note


def _hermite(idx: np.ndarray, amps: np.ndarray, curve: str, out: np.ndarray, start: int) -> None:
    """Add samples 0..idx[-1] of a curve through (idx, amps), idx non-decreasing from 0, to
    out[start:] (as far as out reaches), as the RM's linearInterpolation2 / cubicInterpolation2
    (cubic: zero slope at every keyframe); CHUNK samples at a time."""
    last = int(idx[-1])
    stop = min(out.size, start + last + 1)
    if stop <= start:
        return
    if last == 0:
        out[start] += amps[0]
        return
    linear = curve == "Linear" or idx.size == 2
    for c0 in range(0, stop - start, CHUNK):
        t = np.arange(c0, min(c0 + CHUNK, stop - start), dtype=np.float64)
        j1 = np.clip(np.searchsorted(idx, t, side="left"), 1, idx.size - 1)
        t0, t1 = idx[j1 - 1].astype(np.float64), idx[j1].astype(np.float64)
        f0, f1 = amps[j1 - 1], amps[j1]
        h = np.where(t1 > t0, t1 - t0, 1.0)
        if linear:
            y = (f0 * (t1 - t) + f1 * (t - t0)) / h
        else:
            y = f0 + (f1 - f0) * (3 * h + 2 * (t0 - t)) * (t - t0) ** 2 / h**3
        if c0 == 0:
            y[0] = amps[0]
        out[start + c0 : start + c0 + y.size] += y


def _effects(d: _Doc, band: dict, where: str) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(position, relative positions, amplitudes) of each effect of a Curve band, checked."""
    out = []
    for k, e in enumerate(d.get(band, "effects", where, "list")):
        ew = f"{where}.effects[{k}]"
        if not isinstance(e, dict):
            raise d.err(ew, "must be an object")
        etype = d.get(e, "effect_type", ew, "str")
        if etype != "Basis":
            raise d.err(f"{ew}.effect_type", f"{etype!r}: only Basis effects are read in Curve bands "
                        "(linearize the file with the reference Encoder -l)")
        pos = d.get(e, "position", ew, "int")
        kfs = d.get(e, "keyframes", ew, "list")
        if len(kfs) > MAX_KEYFRAMES:
            raise d.err(f"{ew}.keyframes", f"{len(kfs)} keyframes, more than {MAX_KEYFRAMES}")
        if not kfs:
            continue
        rel = np.empty(len(kfs), dtype=np.int64)
        amp = np.empty(len(kfs), dtype=np.float64)
        for m, kf in enumerate(kfs):
            kw = f"{ew}.keyframes[{m}]"
            if not isinstance(kf, dict):
                raise d.err(kw, "must be an object")
            rel[m] = d.get(kf, "relative_position", kw, "int")
            amp[m] = d.get(kf, "amplitude_modulation", kw, "num")
            if not abs(amp[m]) <= MAX_AMPLITUDE:
                raise d.err(f"{kw}.amplitude_modulation", f"{amp[m]:g} is absurd (the format's amplitudes "
                            f"are -1..1; at most {MAX_AMPLITUDE:g} is read, then clipped)")
        bad = np.flatnonzero(np.diff(rel) < 0)
        if bad.size:
            m = int(bad[0]) + 1
            raise d.err(f"{ew}.keyframes[{m}].relative_position",
                        f"{int(rel[m])} comes before {int(rel[m - 1])}: keyframes out of order")
        if rel[0] < 0 or pos < 0:
            raise d.err(f"{ew}.keyframes[0].relative_position", "negative positions are not played")
        out.append((pos, rel, amp))
    return out


def _curve_span(d: _Doc, band: dict, where: str, to_idx) -> int:
    """The samples a Curve band reaches (its last effect's end), checked against MAX_SAMPLES
    before anything is evaluated."""
    end = 0
    for pos, rel, _ in _effects(d, band, where):
        e = int(to_idx(pos + rel[0])) + int(to_idx(rel[-1]) - to_idx(rel[0])) + 1
        if e > MAX_SAMPLES:
            raise d.err(where, f"spans {e} samples, more than {MAX_SAMPLES} (hostd.texture.hjif.MAX_SAMPLES)")
        end = max(end, e)
    return end


def _render_curve(d: _Doc, band: dict, where: str, to_idx, out: np.ndarray) -> None:
    """Add a Curve band's samples to `out` (its size: the channel's)."""
    curve = band.get("curve_type", "Cubic")
    for pos, rel, amp in _effects(d, band, where):
        start = int(to_idx(pos + rel[0]))
        idx = to_idx(rel) - to_idx(rel[0])
        _hermite(idx, amp, curve, out, start)


def _kinds(bands: list[dict]) -> str:
    return ", ".join(sorted({str(b.get("band_type"))[:20] + (f" ({str(b.get('curve_type'))[:20]})"
                                                          if b.get("band_type") == "Curve" else "")
                             for b in bands}))


def _render_by_rm(doc: dict, perception: dict, channel: dict, bands: list[dict], rate: int,
                  count: int, path: Path) -> np.ndarray:
    """Bands hostd does not evaluate itself, played by the reference Synthesizer (int16 WAV), when
    the user opted in (rm_opted_in), sandboxed."""
    if not rm_opted_in():
        raise rm_refusal(path, f"its {_kinds(bands)} band(s) are what")
    ch = {**channel, "gain": 1.0, "bands": bands, "sample_count": int(count), "frequency_sampling": int(rate)}
    p = {**perception, "perception_unit_exponent": 0, "channels": [ch], "effect_library": []}
    one = {**doc, "perceptions": [p], "avatars": [], "syncs": []}
    with tempfile.TemporaryDirectory(prefix="hostd-rm-") as tmp:
        src, wav = Path(tmp) / "bands.hjif", Path(tmp) / "bands.wav"
        src.write_bytes(dumps(one))
        src.chmod(0o444)
        run_rm("Synthesizer", "-f", src.name, "-o", wav.name, "-fs", str(rate), cwd=Path(tmp), source=path,
               read_only=src)
        if not wav.is_file():
            raise ProfileError(f"{path}: the reference Synthesizer wrote no WAV")
        _, x = read_wav_full_scale(wav, shown=path)
    y = np.zeros(count)
    k = min(count, x.shape[0])
    y[:k] = x[:k, 0]
    return y


def _band_ticks(d: _Doc, band: dict, where: str, timescale: int) -> float:
    """A band's length in ticks as the reference Synthesizer takes it (Band::getBandTimeLength):
    its last effect's position plus that effect's last keyframe (+ 22 ms for a Transient band)."""
    effects = d.get(band, "effects", where, "list")
    if not effects:
        return 0.0
    last = effects[-1]
    lw = f"{where}.effects[{len(effects) - 1}]"
    if not isinstance(last, dict):
        raise d.err(lw, "must be an object")
    pos = d.get(last, "position", lw, "int", 0)
    kfs = d.get(last, "keyframes", lw, "list", [])
    rels = [k["relative_position"] for k in kfs if isinstance(k, dict) and "relative_position" in k]
    rel = d.get({"rp": rels[-1]}, "rp", f"{lw}.keyframes[-1].relative_position", "int") if rels else 0
    if band.get("band_type") == "WaveletWave" or not kfs:
        return float(pos)
    extra = 22.0 * timescale / 1000.0 if band.get("band_type") == "Transient" else 0.0
    return float(pos + rel) + extra


def _series_from_stroke(d: _Doc, where: str, y: np.ndarray, tick_um: float, spacing_um: float, n: int,
                        k: int) -> np.ndarray:
    """hostd's N samples of a texture from the spatial perception it wrote: the stroke y_j at
    x = j tick_um holds the series sum_k C'_k cos(k theta(x)) of the N-sample patch (k <= K, below
    the ticks' Nyquist: build checks it), so a least-squares fit of C'_0..C'_K at the stroke's
    phases gives the coefficients back (to rounding) and the DCT-III the N samples."""
    from hostd.codec import transform
    from hostd.render import series

    if not (2 <= n <= MAX_SAMPLES and 1 <= k <= MAX_TERMS and k + 2 <= y.size and k < n):
        raise d.err(f"{where}.bands[0]", f"{y.size} positions holding {k} terms of {n} samples: hostd's "
                    f"layout needs 1 <= terms <= min({MAX_TERMS}, positions - 2, samples - 1)")
    length_mm = n * spacing_um * 1e-3
    theta = series.phase_rad(np.arange(y.size) * (tick_um * 1e-3), n, length_mm)
    c = series.Projector(theta, k).fit(y)
    return transform.synthesize(c[1:], n) + c[0]


def evaluate(doc: dict, path: Path, pi: int, ci: int) -> Channel:
    """The samples of channel ci of perception pi, as the reference Synthesizer plays them."""
    d = _Doc(path)
    for key, kind in (("version", "str"), ("profile", "str"), ("level", "int"), ("date", "str"),
                      ("description", "str"), ("avatars", "list"), ("syncs", "list")):
        d.get(doc, key, "", kind)
    timescale = d.get(doc, "timescale", "", "int")
    if not 1 <= timescale <= 10**6:
        raise d.err("timescale", f"{timescale} ticks per second is absurd (1..1000000)")
    pw = f"perceptions[{pi}]"
    p = doc["perceptions"][pi]
    modality = d.get(p, "perception_modality", pw, "str")
    d.get(p, "id", pw, "int")
    d.get(p, "description", pw, "str")
    if modality in SPATIAL_MODALITIES:
        spatial = True
    elif modality in TEMPORAL_MODALITIES:
        spatial = False
    else:
        raise d.err(f"{pw}.perception_modality", f"{modality!r} is not a vibrotactile signal (hostd reads "
                    f"{', '.join(sorted(SPATIAL_MODALITIES | TEMPORAL_MODALITIES))}); choose another "
                    "perception with --member")
    ue = d.get(p, "unit_exponent", pw, "int", -3)
    pue = d.get(p, "perception_unit_exponent", pw, "int", 0)
    if not -12 <= ue <= 3:
        raise d.err(f"{pw}.unit_exponent", f"{ue}: positions in 1e{ue} m are absurd (-12..3)")
    if not -12 <= pue <= 12:
        raise d.err(f"{pw}.perception_unit_exponent", f"{pue} is absurd (-12..12)")
    cw = f"{pw}.channels[{ci}]"
    c = p["channels"][ci]
    if not isinstance(c, dict):
        raise d.err(cw, "must be an object")
    gain = d.get(c, "gain", cw, "num")
    bands = d.get(c, "bands", cw, "list")
    if not bands:
        raise d.err(f"{cw}.bands", "empty: the channel holds no band")
    fs_ch = d.get(c, "frequency_sampling", cw, "int", None)
    n_ch = d.get(c, "sample_count", cw, "int", None)
    for b, band in enumerate(bands):
        if not isinstance(band, dict):
            raise d.err(f"{cw}.bands[{b}]", "must be an object")
        d.get(band, "band_type", f"{cw}.bands[{b}]", "str")
        d.get(band, "curve_type", f"{cw}.bands[{b}]", "str", None)
    if not abs(gain) <= MAX_GAIN:
        raise d.err(f"{cw}.gain", f"{gain:g} is absurd (|gain| <= {MAX_GAIN:g})")

    desc = p["description"]
    full_scale = _stated(_FULL_SCALE, desc, 1e6)  # up to 1 m
    speed = _stated(_SPEED, desc, 1e6)

    def is_native(b: dict) -> bool:
        return b.get("band_type") == "Curve" and b.get("curve_type", "Cubic") in NATIVE_CURVES

    native = [b for b in bands if is_native(b)]
    other = [b for b in bands if not is_native(b) and (spatial or b["band_type"] != "WaveletWave")]
    note = ""
    stated_spacing = _stated(_SPACING, desc, SPACING_UM_RANGE[1])
    stated_n = _stated(_SAMPLES, desc, MAX_SAMPLES)
    stated_tick = _stated(_TICK, desc, SPACING_UM_RANGE[1])
    stated_k = _stated(_TERMS, desc, MAX_SAMPLES)
    own = None
    mine = spatial and None not in (stated_spacing, stated_n, stated_tick, stated_k) and len(bands) == 1
    if mine and bands[0].get("band_type") == "VectorialWave":
        # hostd's compact layout (vectorial_band): sinusoids along the stroke, a tick per sample
        from hostd.texture import hjif_vectorial

        if hjif_vectorial.covers(bands[0]):
            ends = [e["position"] + e["keyframes"][-1]["relative_position"] for e in bands[0]["effects"]
                    if e["keyframes"]]
            count = max(ends, default=0) + 1
            if not 3 <= count <= MAX_SAMPLES:
                raise d.err(f"{cw}.bands[0]", f"a stroke of {count} positions: absurd (3..{MAX_SAMPLES})")
            y = hjif_vectorial.render_band(bands[0], timescale, timescale, count, f"{cw}.bands[0]", path)
            own = _series_from_stroke(d, cw, np.clip(y, -1.0, 1.0), stated_tick, stated_spacing,
                                      int(stated_n), int(stated_k))
    elif mine and is_native(bands[0]):
        # hostd's own layout (build): one effect at 0, a keyframe per tick along one stroke, then a
        # 0 one tick later and a 0 at the file's common end; anything else is read as a foreign file
        effs = _effects(d, bands[0], f"{cw}.bands[0]")
        if len(effs) == 1 and effs[0][0] == 0 and effs[0][1].size >= 5:
            rel, amp = effs[0][1], effs[0][2]
            m = rel.size - 2
            if np.array_equal(rel[:m], np.arange(m)) and not np.any(amp[m:]):
                own = _series_from_stroke(d, cw, amp[:m], stated_tick, stated_spacing, int(stated_n),
                                          int(stated_k))
    elif (spatial and stated_tick is None and None not in (stated_spacing, stated_n) and len(bands) == 1
          and is_native(bands[0])):
        # the layout hostd wrote before the stroke (files from earlier releases): one effect, a
        # keyframe per sample within half a unit of i x the stated spacing, then a 0 after them and
        # a 0 at the file's common end
        effs = _effects(d, bands[0], f"{cw}.bands[0]")
        n_own = int(stated_n)
        if len(effs) == 1 and effs[0][0] == 0 and effs[0][1].size in (n_own, n_own + 2) and n_own >= 2:
            i = np.arange(n_own, dtype=np.float64)
            unit_um = 10.0 ** (ue + 6)
            off = np.abs(effs[0][1][:n_own] * unit_um - i * stated_spacing)
            near = np.all(off <= 0.5 * unit_um + 1e-9 * stated_spacing * (i + 1))
            if near and not np.any(effs[0][2][n_own:]):
                own = effs[0][2][:n_own]
    if own is not None:
        y = np.clip(own, -1.0, 1.0)
        step_m, rate = stated_spacing * 1e-6, None
    elif spatial:
        # a grid on every keyframe position: their greatest common step
        pos_all = []
        for band in native:
            for pos, rel, _ in _effects(d, band, f"{cw}.bands[{bands.index(band)}]"):
                pos_all.append(pos + rel)
        allpos = np.unique(np.concatenate(pos_all)) if pos_all else np.zeros(0, np.int64)
        if allpos.size < 2:
            raise d.err(f"{cw}.bands", "fewer than 2 keyframes: no profile")
        step = int(np.gcd.reduce(np.diff(allpos)))
        step_m = step * 10.0**ue
        if not SPACING_UM_RANGE[0] <= step_m * 1e6 <= SPACING_UM_RANGE[1]:
            raise d.err(f"{pw}.unit_exponent", f"keyframes every {step} x 1e{ue} m = {step_m * 1e6:g} µm: "
                        "an absurd spacing for a texture")
        if other:
            raise d.err(f"{cw}.bands", "a spatial perception with "
                        f"{sorted({b.get('band_type') for b in other})} bands: hostd reads Curve bands "
                        "(Linear, Cubic) of textures")

        def to_idx(x):
            return np.asarray(x, dtype=np.int64) // step

        count = max(_curve_span(d, band, f"{cw}.bands[{bands.index(band)}]", to_idx) for band in native)
        y = np.zeros(count)
        for band in native:
            _render_curve(d, band, f"{cw}.bands[{bands.index(band)}]", to_idx, y)
            np.clip(y, -1.0, 1.0, out=y)  # as the RM: the channel is clipped after each band
        rate = None
    else:
        # the channel's own rate; else the timescale's, at least the Synthesizer's default 8 kHz (an
        # AHAP or IVS input gives the RM's Encoder a timescale of 1000 ticks per second)
        rate = fs_ch if fs_ch is not None else max(timescale, DEFAULT_RATE_HZ)
        if not 1 <= rate <= 10**6:
            raise d.err(f"{cw}.frequency_sampling", f"{rate} Hz is absurd (1..1000000)")
        if n_ch is not None and not 0 < n_ch <= MAX_SAMPLES:
            raise d.err(f"{cw}.sample_count", f"{n_ch} samples: absurd (1..{MAX_SAMPLES})")

        def to_idx(x):
            return np.asarray(x, dtype=np.int64) * rate // timescale  # the RM's integer division

        if n_ch is not None:
            count = n_ch
        else:  # as the Synthesizer: its length in ticks (Helper::getTimeLength), at the rate
            spans = [_curve_span(d, band, f"{cw}.bands[{b}]", to_idx) for b, band in enumerate(bands)
                     if is_native(band)]
            ticks = [_band_ticks(d, band, f"{cw}.bands[{b}]", timescale) for b, band in enumerate(bands)
                     if not is_native(band)]
            count = max(spans + [round(rate * t / timescale) for t in ticks], default=0)
            if count > MAX_SAMPLES:
                raise d.err(f"{cw}.bands", f"last {count} samples at {rate} Hz, more than {MAX_SAMPLES} "
                            "(hostd.texture.hjif.MAX_SAMPLES)")
        from hostd.texture import hjif_vectorial

        by_rm = [b for b in bands if not is_native(b) and b["band_type"] != "WaveletWave"
                 and not hjif_vectorial.covers(b)]
        if by_rm and not rm_opted_in():
            raise rm_refusal(path, f"its {_kinds(by_rm)} band(s) are what")
        y = np.zeros(count)
        for b, band in enumerate(bands):
            if is_native(band):
                _render_curve(d, band, f"{cw}.bands[{b}]", to_idx, y)
            elif band["band_type"] == "WaveletWave":
                from hostd.texture import hjif_wavelet

                y += hjif_wavelet.render_band(band, timescale, int(rate), count, f"{cw}.bands[{b}]", path)
            elif hjif_vectorial.covers(band):
                y += hjif_vectorial.render_band(band, timescale, int(rate), count, f"{cw}.bands[{b}]", path)
            else:
                y += _render_by_rm(doc, p, c, [band], int(rate), count, path)
            np.clip(y, -1.0, 1.0, out=y)  # as the RM: the channel is clipped after each band
        if by_rm:
            note = (f"{len(by_rm)} {sorted({b.get('band_type') for b in by_rm})} band(s) played by the "
                    "reference Synthesizer (16-bit)")
        step_m = None
    if y.size < 2:
        raise d.err(f"{cw}.bands", "fewer than 2 samples: no profile")
    if not np.all(np.isfinite(y)):
        raise d.err(f"{cw}.bands", "evaluate to NaN or Inf (a keyframe's numbers are absurd)")
    y = np.clip(y, -1.0, 1.0) * gain * 10.0**pue
    return Channel(samples=y, spatial=spatial, step_m=step_m, rate_hz=None if spatial else float(rate),
                   perception=pi, channel=ci, modality=modality, full_scale_um=full_scale,
                   speed_mm_s=speed, note=note)


def rm_playback(doc: dict, rate_hz: int) -> np.ndarray:
    """(samples, perceptions) of what the reference Synthesizer (2de9ff1) plays of a file hostd
    wrote (one channel of one Curve effect at 0 per perception) at `rate_hz`, full scale 1: its
    length is the longest perception's (Helper::getTimeLength: sample_count / frequency_sampling,
    else the last keyframe's position), each keyframe at sample position x rate // timescale
    (exact here: hostd keeps position x rate within 32 bits), cubic between keyframes. For
    tests and docs that compare hostd's intent with the Synthesizer's WAV."""
    d = _Doc(Path("<doc>"))
    ts = int(doc["timescale"])
    lengths, curves = [], []
    for p in doc["perceptions"]:
        c = p["channels"][0]
        (band,) = c["bands"]
        (eff,) = _effects(d, band, "band")
        pos, rel, amp = eff
        if "sample_count" in c and "frequency_sampling" in c:
            lengths.append(ts * c["sample_count"] / c["frequency_sampling"])
        else:
            lengths.append(float(pos + rel[-1]))
        curves.append((rel * rate_hz // ts, amp, band.get("curve_type", "Cubic"), float(c["gain"])))
    n = round(rate_hz * max(lengths) / ts)
    out = np.zeros((n, len(curves)))
    for j, (idx, amp, curve, gain) in enumerate(curves):
        col = np.zeros(n)
        # the last keyframe is not played: its sample must lie past the WAV (build makes it so)
        assert idx[-1] >= n, (idx[-1], n)
        _hermite(idx[:-1] - idx[0], amp[:-1], curve, col, int(idx[0]))
        if idx.size > 2 and idx[1] == idx[0]:
            col[idx[0]] = 0.0  # the RM's first segment of length 0: 0/0, written as 0
        out[:, j] = np.clip(col, -1.0, 1.0) * gain
    return out


def read_channel(path: Path, member: str | None = None) -> Channel:
    """Load, select and evaluate one channel of an .hjif (or .hmpg through the reference Decoder,
    when the user opted in: rm_opted_in)."""
    path = Path(path)
    if path.suffix.lower() == ".hmpg":
        if not path.is_file():
            raise ProfileError(f"no such .hmpg file: {path}")
        size = path.stat().st_size
        if size > MAX_HMPG_BYTES:
            raise ProfileError(f"{path}: {size} bytes, more than the {MAX_HMPG_BYTES >> 20} MiB an .hmpg "
                               "may have (hostd.texture.hjif.MAX_HMPG_BYTES): refused before decoding")
        if rm_dir() is None:
            raise ProfileError(f"{path}: an .hmpg is read through the reference Decoder, which is not "
                               f"installed: {RM_HOW}")
        if not rm_opted_in():
            raise rm_refusal(path, "an .hmpg is a binary stream")
        with tempfile.TemporaryDirectory(prefix="hostd-rm-") as tmp:
            copy = _private_copy(path, Path(tmp), "input.hmpg", MAX_HMPG_BYTES)
            try:
                run_rm("Decoder", "-f", copy.name, "-o", "decoded.hjif", cwd=Path(tmp), source=path,
                       read_only=copy)
            except ProfileError as e:
                raise ProfileError(f"{e} (not a valid .hmpg? the Decoder may use {RM_MEMORY_BYTES >> 20} MiB "
                                   f"and {RM_CPU_S} s of CPU; a valid one needs far less)") from None
            out = Path(tmp) / "decoded.hjif"
            if not out.is_file():
                raise ProfileError(f"{path}: the reference Decoder wrote no .hjif")
            doc = load_json(out, shown=path)
        pi, ci, note = select(doc, path, member)
        ch = evaluate(doc, path, pi, ci)
        return dataclasses.replace(ch, note="; ".join(x for x in (note, ch.note, "decoded by the "
                                                                "reference Decoder") if x))
    doc = load_json(path)
    pi, ci, note = select(doc, path, member)
    ch = evaluate(doc, path, pi, ci)
    return dataclasses.replace(ch, note="; ".join(x for x in (note, ch.note) if x))


def read(path: Path, opts: LoadOptions) -> Columns:
    """The reader of hostd.texture.formats for .hjif and .hmpg: one channel as heights (n, 1) with
    the spacing the file states (spatial perceptions) or v/fs (time-domain ones)."""
    from hostd.texture.formats import Columns

    ch = read_channel(path, opts.member)
    y = ch.samples
    y_unit = None
    notes = [ch.note] if ch.note else []
    if ch.full_scale_um is not None:
        y, y_unit = y * ch.full_scale_um, "um"
    elif opts.full_scale_um is not None:
        y, y_unit = y * opts.full_scale_um, "um"
        notes.append(f"amplitude 1.0 read as {opts.full_scale_um:g} µm (--full-scale-um)")
    else:
        notes.append("amplitude 1.0 read as 1 " + (opts.y_unit or "um") + " (the file states no scale; "
                     "--full-scale-um sets it)")
    if ch.spatial:
        return Columns(y.reshape(-1, 1), x_unit="um", y_unit=y_unit, spacing=ch.step_m * 1e6,
                       note="; ".join(notes))
    if ch.speed_mm_s is not None:
        spacing_um = ch.speed_mm_s * 1e3 / ch.rate_hz
        notes.append(f"time-domain perception at {ch.speed_mm_s:g} mm/s: {spacing_um:g} µm per sample")
        return Columns(y.reshape(-1, 1), x_unit="um", y_unit=y_unit, spacing=spacing_um,
                       note="; ".join(notes))
    if opts.spacing is None:
        raise ProfileError(f"{path}: perception {ch.perception} ({ch.modality!r}) is a signal in time "
                           f"({ch.rate_hz:g} Hz): give its spacing over space with --spacing (speed / "
                           f"rate, e.g. {50e3 / ch.rate_hz:g} um at 50 mm/s)")
    return Columns(y.reshape(-1, 1), y_unit=y_unit, note="; ".join(notes))
