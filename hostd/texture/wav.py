"""WAV files: the one reader of WAV samples (scipy.io.wavfile, after a check of the file's chunks).

`read_samples` gives a WAV's samples as float64 (n, channels): integer PCM scaled by its full
scale to -1..1 (8-bit, unsigned: (x - 128) / 128; 16/24/32/64-bit: x / 2^(bits-1)), IEEE float
as stored. Before scipy reads anything, the RIFF chunks are walked and checked against the file:
a chunk that claims more bytes than the file has, a `fmt ` chunk that is not 16 to 1024 bytes,
zero channels, a block alignment that does not fit the channels, or more samples than a profile
file may hold (hostd.texture.load.MAX_VALUES) is refused in one line, so
scipy never sizes a buffer from a number the file made up. The data chunk is read by scipy with
np.fromfile, which reads no more than the file holds.

`read_wav` is the format registry's reader (hostd.texture.formats): a recording's samples
become a profile of heights, with the spacing the user gives (--spacing, in --x-unit), one
channel chosen with --columns CHANNEL when there are several. The heights are in --y-unit per
full scale (an integer recording scaled to -1..1, as above).
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np

from hostd.errors import ProfileError
from hostd.texture.formats import Columns, LoadOptions

FMT_MAX_BYTES = 1024  # a fmt chunk is 16, 18 or 40 bytes: anything beyond 1 kB is not a WAV's
MAX_CHANNELS = 1024
CONVERT = ("convert it to 32-bit float PCM first: `ffmpeg -i IN -c:a pcm_f32le OUT.wav` or "
           "`sox IN -e floating-point -b 32 OUT.wav`")


class WavError(ProfileError):
    """A WAV file that cannot be read (one line, naming the file)."""


def _check_chunks(fh, name: str, size: int, max_values: int) -> None:
    """Walk the RIFF chunks; refuse one whose declared size the file cannot hold."""
    head = fh.read(12)
    if len(head) < 12 or head[:4] not in (b"RIFF", b"RIFX", b"RF64") or head[8:12] != b"WAVE":
        raise WavError(f"{name} is not a WAV file (no RIFF/WAVE header): {CONVERT}")
    big = head[:4] == b"RIFX"
    pos, seen_fmt, align, channels = 12, False, 1, 1
    while pos + 8 <= size:
        fh.seek(pos)
        cid, n = struct.unpack(f"{'>' if big else '<'}4sI", fh.read(8))
        left = size - pos - 8
        if cid == b"fmt ":
            if not 16 <= n <= min(FMT_MAX_BYTES, left):
                raise WavError(f"{name}: its fmt chunk declares {n} bytes (a WAV's is 16 to 40, and "
                               f"{left} are left in the file): the file is damaged; {CONVERT}")
            _tag, channels, rate, _bps, align, bits = struct.unpack(
                f"{'>' if big else '<'}HHIIHH", fh.read(16))
            if not 1 <= channels <= MAX_CHANNELS or align < channels or align % channels:
                raise WavError(f"{name}: its fmt chunk says {channels} channel(s) with {align}-byte "
                               f"frames, which does not fit: the file is damaged; {CONVERT}")
            if rate == 0 or bits == 0:
                raise WavError(f"{name}: its fmt chunk says {rate} Hz, {bits} bits: the file is damaged")
            seen_fmt = True
        elif cid == b"data":
            if not seen_fmt:
                raise WavError(f"{name}: the samples come before the fmt chunk: the file is damaged")
            samples = min(n, left) // (align // channels)
            if samples > max_values:
                raise WavError(f"{name} holds {samples:,} samples, more than the {max_values:,} a "
                               "profile file may: cut the recording first")
            return  # scipy reads the samples; np.fromfile stops at the end of the file
        elif n > left:
            raise WavError(f"{name}: a {cid!r} chunk declares {n} bytes but {left} are left in the "
                           f"file: the file is truncated or damaged")
        pos += 8 + n + (n & 1)
    raise WavError(f"{name}: no {'data' if seen_fmt else 'fmt'} chunk: not a complete WAV file")


def read_samples(path: str | Path) -> tuple[int, np.ndarray]:
    """(rate_hz, samples float64 (n, channels)) of a WAV file, integer PCM scaled to -1..1.

    Every failure is a WavError (ProfileError) of one line; a missing file is ProfileNotFound,
    a FIFO or device is refused without waiting on it."""
    import scipy.io.wavfile

    from hostd.texture.formats import open_profile
    from hostd.texture.load import MAX_VALUES

    p = Path(path)
    with open_profile(p, WavError) as fh:
        size = fh.seek(0, 2)
        fh.seek(0)
        try:
            _check_chunks(fh, str(p), size, MAX_VALUES)
        except struct.error:
            raise WavError(f"{p}: a chunk header is cut short: the file is truncated") from None
        fh.seek(0)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", scipy.io.wavfile.WavFileWarning)
                rate, data = scipy.io.wavfile.read(fh)
        except MemoryError:
            raise WavError(f"{p}: too large to read into memory") from None
        except Exception as exc:  # ValueError (unknown encoding, bit depth), struct.error, ...
            raise WavError(f"cannot read {p} as a WAV file ({exc}): {CONVERT}") from None
    data = np.asarray(data)
    if data.ndim == 1:
        data = data.reshape(-1, 1)
    if data.dtype == np.uint8:
        out = (data.astype(np.float64) - 128.0) / 128.0
    elif np.issubdtype(data.dtype, np.integer):
        out = data.astype(np.float64) / float(-np.iinfo(data.dtype).min)
    elif np.issubdtype(data.dtype, np.floating):
        out = data.astype(np.float64)
    else:
        raise WavError(f"{p}: samples of type {data.dtype}: {CONVERT}")
    return int(rate), out


def read_wav(p: Path, opts: LoadOptions) -> Columns:
    """The WAV reader of the format registry: one channel's samples as heights."""
    rate, data = read_samples(p)
    n, channels = data.shape
    if n < 2:
        raise ProfileError(f"{p}: the WAV holds {n} sample(s); a profile needs at least 2")
    cols = opts.columns
    if cols is not None and len(cols) != 1:
        raise ProfileError(f"{p}: a WAV file has no x column: choose a channel with --columns "
                           f"CHANNEL (1 to {channels})")
    if cols is None and channels > 1:
        raise ProfileError(f"{p} holds {channels} channels: choose one with --columns CHANNEL "
                           f"(1 to {channels})")
    ch = 0 if cols is None else cols[0]
    if ch >= channels:
        raise ProfileError(f"{p}: --columns {ch + 1} asks for a channel it does not have (it has "
                           f"{channels})")
    if opts.spacing is None:
        raise ProfileError(
            f"{p} is a recording at {rate} Hz: give the distance between its samples with --spacing "
            f"(in --x-unit; a stroke at v mm/s has v/{rate} mm, e.g. --spacing {50 / rate:.4g} "
            "--x-unit mm at 50 mm/s)")
    which = f", channel {ch + 1} of {channels}" if channels > 1 else ""
    note = (f"read a WAV recording ({rate} Hz{which}): heights in --y-unit per full scale "
            "(integer samples scaled to -1..1)")
    return Columns(np.ascontiguousarray(data[:, ch]).reshape(-1, 1), note=note)
