"""A short pass of the fuzzers of device bytes and of the profile readers: the libFuzzer
harnesses of the compiled parsers (tests/fuzz/run_fuzzers.sh, ASan + UBSan: _fastpump.c's
deframer and _fastlink.c's decoder, differential against plain references; _fastpump.c's
STATUS reader, its properties) and the atheris harness of the Python paths
(tests/fuzz/fuzz_device_link.py: protocol.py against _fastlink, built with ASan + UBSan by
tests/fuzz/sanitize_device_link.sh); the atheris harness of the profile readers
(tests/fuzz/fuzz_profiles.py: text, .npy, .mat, .wav under an RSS limit) and its kept inputs.
FUZZ_S seconds each; the long
runs and their counts are in docs/fuzzing.md. Missing clang or atheris fails under CI=true
(`./run test` installs both), and skips, saying so, elsewhere."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

FUZZ = Path(__file__).parent / "fuzz"
FUZZ_S = 10


def _missing(what: str) -> None:
    if os.environ.get("CI") == "true":
        pytest.fail(f"{what} is missing: ./run test installs it (apt-get install clang; pip install atheris)")
    pytest.skip(f"{what} is not installed (apt-get install clang; pip install atheris)")


def test_compiled_device_parsers_libfuzzer_short_pass(tmp_path):
    if shutil.which("clang") is None:
        _missing("clang")
    out = tmp_path / "not-yet"  # docs/fuzzing.md's FUZZ_OUT need not exist
    r = subprocess.run(["sh", str(FUZZ / "run_fuzzers.sh"), str(FUZZ_S)], capture_output=True, text=True,
                       env=dict(os.environ, FUZZ_OUT=str(out), PYTHON=sys.executable), timeout=600)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    counts = dict(re.findall(r"^(fuzz_\w+): (\d+) executions$", r.stdout, re.M))
    assert set(counts) == {"fuzz_fastpump_deframe", "fuzz_fastpump_status", "fuzz_fastlink_decode"}, r.stdout
    assert all(int(n) > 1000 for n in counts.values()), counts


def test_device_link_python_paths_atheris_short_pass(tmp_path):
    """The atheris harness against _fastlink.c built with ASan + UBSan (sanitize_device_link.sh)."""
    try:
        import atheris  # noqa: F401
    except ImportError:
        _missing("atheris")
    if shutil.which("clang") is None:
        _missing("clang")
    corpus = tmp_path / "corpus"
    corpus.mkdir()
    r = subprocess.run(["sh", str(FUZZ / "sanitize_device_link.sh"), f"-max_total_time={FUZZ_S}",
                        str(corpus)], capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env=dict(os.environ, FUZZ_OUT=str(tmp_path), PYTHON=sys.executable))
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    # the sanitizer build is the one fuzzed (the harness refuses the reference against itself)
    assert f"protocol.decode against {tmp_path}/_fastlink" in r.stderr, r.stderr[-2000:]
    done = re.search(r"Done (\d+) runs", r.stderr)
    assert done and int(done.group(1)) > 1000, r.stderr[-2000:]


# ----------------------------------------------------------------- the profile readers (.mat/.wav/.npy/text)


def test_profile_readers_seed_and_regression_inputs(tmp_path):
    """Every input kept in tests/fuzz/corpus/profiles, in-process (no atheris needed): the seeds
    load a finite profile, the regression inputs (declared sizes the bytes do not back, a zlib
    bomb, WAV headers that once escaped as ZeroDivisionError or struct.error) are refused in one
    line; and the folder holds what tests/fuzz/profile_inputs.py makes."""
    import numpy as np

    from hostd.errors import HostdError
    from hostd.texture.load import load_profile
    from tests.fuzz import profile_inputs as pin

    folder = FUZZ / "corpus" / "profiles"
    made = {**pin.seeds(), **pin.regressions()}
    assert {p.name for p in folder.iterdir()} == set(made)
    for p in sorted(folder.iterdir()):
        data = p.read_bytes()
        suffix, opts = pin.options(data[0])
        f = tmp_path / f"{p.stem}{suffix}"
        f.write_bytes(data[1:])
        if p.name.startswith("seed-"):
            prof = load_profile(f, opts)
            assert prof.n >= 2 and np.all(np.isfinite(prof.heights_um)), p.name
        else:
            with pytest.raises(HostdError) as e:
                load_profile(f, opts)
            assert len(str(e.value).strip().splitlines()) == 1, (p.name, str(e.value))


def _atheris_pass(tmp_path, harness: str, seconds: int) -> str:
    try:
        import atheris  # noqa: F401
    except ImportError:
        _missing("atheris")
    out = tmp_path / "fz"  # not made yet: run_atheris.sh makes it, as docs/fuzzing.md says
    r = subprocess.run(["sh", str(FUZZ / "run_atheris.sh"), harness, str(seconds)], capture_output=True,
                       text=True, timeout=600, env=dict(os.environ, FUZZ_OUT=str(out), PYTHON=sys.executable))
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    assert (out / f"{harness}.corpus").is_dir()
    return r.stderr


def test_profile_readers_atheris_short_pass(tmp_path):
    """fuzz_profiles.py for FUZZ_S seconds under libFuzzer's RSS limit (600 MB: the interpreter
    with numpy and scipy is some 120 MB of it), from the kept seeds."""
    err = _atheris_pass(tmp_path, "fuzz_profiles", FUZZ_S)
    done = re.search(r"Done (\d+) runs", err)
    assert done and int(done.group(1)) > 200, err[-2000:]


def test_stream_fuzzer_runs_as_documented(tmp_path):
    """docs/fuzzing.md's command for fuzz_stream.py on a fresh machine: no FUZZ_OUT, no corpus yet."""
    err = _atheris_pass(tmp_path, "fuzz_stream", 3)
    assert re.search(r"Done \d+ runs", err), err[-2000:]
