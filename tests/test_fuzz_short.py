"""A short pass of the fuzzers of device bytes (issue 29): the libFuzzer harnesses of the compiled
parsers (tests/fuzz/run_fuzzers.sh, ASan + UBSan: _fastpump.c's deframer and _fastlink.c's
decoder, differential against plain references; _fastpump.c's STATUS reader, its properties)
and the atheris harness of the Python paths
(tests/fuzz/fuzz_device_link.py: protocol.py against _fastlink, built with ASan + UBSan by
tests/fuzz/sanitize_device_link.sh). FUZZ_S seconds each; the long
runs and their counts are in development/fuzzing.md. Missing clang or atheris fails under CI=true
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
    r = subprocess.run(["sh", str(FUZZ / "run_fuzzers.sh"), str(FUZZ_S)], capture_output=True, text=True,
                       env=dict(os.environ, FUZZ_OUT=str(tmp_path), PYTHON=sys.executable), timeout=600)
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
