"""The WAV readers of the MPEG interchange and the peer codecs (hostd.corpus.peercodecs.read_wav,
hostd.texture.hjif.read_wav_full_scale, both on scipy.io.wavfile): a broken WAV is one line."""

from __future__ import annotations

import struct
import warnings

import pytest

from hostd.corpus.codecs import CodecFailure
from hostd.corpus.peercodecs import read_wav
from hostd.errors import ProfileError
from hostd.texture import hjif

# mutations of a 400-sample 16-bit WAV that made scipy raise something else than ValueError
MUTATED = {
    "UnboundLocalError": "524946464403000057415645666d74203c00000001000100401f0000803e0000020010"
                         "0020617461200300000000de20",
    "ZeroDivisionError": "524946465503005e57415645666d74201000000001009400401f0000803e0000020010"
                         "0064617461200300000000de20",
    "struct.error": (b"RIFF" + struct.pack("<I", 36) + b"WAVEfmt " + struct.pack("<I", 16)
                     + b"\x01\x00").hex(),
}


@pytest.mark.parametrize("name", sorted(MUTATED))
def test_a_broken_wav_is_one_line(tmp_path, name):
    f = tmp_path / "dec.wav"
    f.write_bytes(bytes.fromhex(MUTATED[name]) + b"\0" * 800)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(CodecFailure, match=r"cannot read the peer's decoded WAV .*dec.wav: ") as e:
            read_wav(f)
        assert "\n" not in str(e.value)
        with pytest.raises(ProfileError, match=r"cannot read the WAV .*dec.wav: ") as e:
            hjif.read_wav_full_scale(f)
        assert "\n" not in str(e.value)
