"""Coverage-guided fuzzing of the profile readers (text, .npy, .mat, .wav) with atheris, in bounded
memory.

    tests/fuzz/run_atheris.sh fuzz_profiles 60          # seeds copied to $FUZZ_OUT, RSS limit 600 MB

An input is one byte choosing the file's suffix (tests/fuzz/profile_inputs.py: SUFFIXES) and the
file's bytes, written to a temporary file and given to hostd.texture.load.load_profile as a
command would. Every input must load a finite profile or raise HostdError (the one-line error);
any other exception, a hang, or a peak RSS over libFuzzer's -rss_limit_mb (run_atheris.sh sets
600: the interpreter with numpy and scipy takes some 120 MB) is a finding. Seeds and regression
inputs: tests/fuzz/corpus/profiles (written by profile_inputs.py). Not collected by pytest
(tests/test_fuzz_short.py runs it, and its corpus in-process without atheris).
"""

import os
import sys
import tempfile
from pathlib import Path

import atheris

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

with atheris.instrument_imports(include=["hostd.texture"]):
    from hostd.errors import HostdError
    from hostd.texture.load import load_profile

import numpy as np

from tests.fuzz.profile_inputs import options

_DIR = Path(tempfile.mkdtemp(prefix="fuzz_profiles."))


def one_input(data: bytes) -> None:
    if not data:
        return
    suffix, opts = options(data[0])
    path = _DIR / f"p{suffix}"
    path.write_bytes(data[1:])
    try:
        prof = load_profile(path, opts)
    except HostdError as exc:
        assert "\n" not in str(exc).strip(), str(exc)
        return
    assert prof.n >= 2 and np.all(np.isfinite(prof.heights_um)), prof


def main() -> None:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
