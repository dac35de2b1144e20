"""The two implementations of the stream-v2 index coder (docs/stream-format.md, "Entropy coder
(exact)"): the compiled hostd/codec/_rangecoder.c and the pure-Python reference in
hostd/codec/rangecoder.py. Same bytes, same indices, same errors; the suite runs with either."""

import json
import os
import shutil
import subprocess
import sys
import sysconfig

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostd.codec import rangecoder
from hostd.codec.stream import v2 as stream2
from hostd.errors import StreamError
from tests import test_stream_v2 as v2
from tests.conftest import ROOT, VECTORS

HAVE_C = rangecoder._C is not None
needs_c = pytest.mark.skipif(not HAVE_C, reason="the compiled coder hostd.codec._rangecoder is not "
                             "built (no C compiler, or HOSTD_PURE_PYTHON=1): only the reference runs")
IMPLS = {"python": (rangecoder.encode_indices_py, rangecoder.decode_indices_py),
         "c": (rangecoder.encode_indices_c, rangecoder.decode_indices_c)}


@pytest.fixture(params=sorted(IMPLS))
def coder(request, monkeypatch):
    """Every codec call of the test goes through one implementation."""
    if request.param == "c" and not HAVE_C:
        pytest.skip("the compiled coder is not built")
    enc, dec = IMPLS[request.param]
    monkeypatch.setattr(rangecoder, "encode_indices", enc)
    monkeypatch.setattr(rangecoder, "decode_indices", dec)
    return request.param


def _outcome(dec, data: bytes, n_keep: int):
    try:
        return ("ok", dec(data, n_keep).tolist())
    except StreamError as exc:
        return ("error", str(exc))


def _payload(data: bytes) -> tuple[bytes, int]:
    s = stream2.decode(data)
    body = data[: len(data) - (2 if len(data) < stream2.CRC16_LIMIT else 4)]
    return body[len(body) - s.payload_bytes :], s.n_keep


def test_the_compiled_coder_is_built_where_a_c_compiler_is():
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if os.environ.get("HOSTD_PURE_PYTHON") or not shutil.which(cc):
        pytest.skip("pure Python asked for, or no C compiler: the fallback is the expected coder")
    assert HAVE_C and rangecoder.IMPLEMENTATION == "c", (
        "hostd.codec._rangecoder is not built although a C compiler exists: re-run "
        "`pip install -e .` (./run does on a change of setup.py or the C source)")


@pytest.mark.parametrize("name", v2.V2_NAMES)
def test_golden_vectors_decode_and_reencode_with_either_coder(name, coder):
    v2.test_v2_vectors_decode_to_their_values_and_are_reproduced(name)


@needs_c
@pytest.mark.parametrize("name", v2.V2_NAMES)
def test_both_coders_agree_on_every_golden_payload(name):
    payload, n_keep = _payload((VECTORS / f"{name}.vtx").read_bytes())
    q = rangecoder.decode_indices_py(payload, n_keep)
    assert np.array_equal(rangecoder.decode_indices_c(payload, n_keep), q)
    assert rangecoder.encode_indices_c(q) == rangecoder.encode_indices_py(q) == payload


_small = st.integers(min_value=-3, max_value=3)
_any = st.integers(min_value=-(2**40) + 1, max_value=2**40 - 1)
_indices = st.lists(st.one_of(_small, _small, _small, _any), min_size=0, max_size=400)


@needs_c
@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(vals=_indices, zeros=st.integers(min_value=0, max_value=50), dtype=st.sampled_from(["<i8", "<i4"]))
def test_both_coders_give_the_same_bytes_and_round_trip(vals, zeros, dtype):
    if dtype == "<i4":
        vals = [max(-(2**31), min(2**31 - 1, v)) for v in vals]
    q = np.array(vals + [0] * zeros, dtype=dtype)
    data = rangecoder.encode_indices_py(q)
    assert rangecoder.encode_indices_c(q) == data
    for dec in (rangecoder.decode_indices_py, rangecoder.decode_indices_c):
        got = dec(data, q.size)
        assert got.dtype == np.int64 and np.array_equal(got, q)


@needs_c
@settings(max_examples=600, deadline=None)
@given(data=st.binary(max_size=80), n_keep=st.integers(min_value=-2, max_value=300))
def test_both_coders_treat_garbage_alike(data, n_keep):
    assert _outcome(rangecoder.decode_indices_c, data, n_keep) == \
        _outcome(rangecoder.decode_indices_py, data, n_keep)


@needs_c
@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(vals=_indices.filter(bool), cut=st.integers(min_value=0), flip=st.integers(min_value=0),
       bit=st.integers(min_value=0, max_value=7), tail=st.binary(max_size=8),
       n_keep_delta=st.integers(min_value=-3, max_value=3))
def test_both_coders_treat_damaged_payloads_alike(vals, cut, flip, bit, tail, n_keep_delta):
    """Truncated, bit-flipped and extended payloads of real index streams, with a right or
    wrong N': identical indices or identical StreamError messages."""
    q = np.array(vals, dtype=np.int64)
    good = rangecoder.encode_indices_py(q)
    n_keep = max(0, q.size + n_keep_delta)
    flipped = bytearray(good or b"\0")
    flipped[flip % len(flipped)] ^= 1 << bit
    for data in (good[: cut % (len(good) + 1)], bytes(flipped), good + tail):
        assert _outcome(rangecoder.decode_indices_c, data, n_keep) == \
            _outcome(rangecoder.decode_indices_py, data, n_keep)


def _crafted(n_sig: int, magnitude_minus_2: int | None = None) -> bytes:
    """An index stream built from decisions (the reference encoder's own coder), able to say
    what the encoder never writes: n_sig = `n_sig`, then one component q_1 = +(v + 2)."""
    p_sig, p_mag, p_gt1 = [rangecoder.PROB_INIT] * 16, [rangecoder.PROB_INIT] * 16, \
        [rangecoder.PROB_INIT] * rangecoder.N_CTX
    ops: list = []
    rangecoder._eg(ops, p_sig, n_sig)
    if magnitude_minus_2 is not None:
        ops += [(None, 0, 0), (p_gt1, 0, 1)]
        rangecoder._eg(ops, p_mag, magnitude_minus_2)
    return rangecoder._code(ops)


@pytest.mark.parametrize(("data", "n_keep", "message"), [
    (_crafted(2**41), 10, "entropy-coded number too long"),
    (_crafted(2**41 - 2), 10, "claims 2199023255550 significant components, N' = 10"),
    (_crafted(11), 10, "claims 11 significant components, N' = 10"),
    (_crafted(1), -1, "claims 1 significant components, N' = -1"),
    (_crafted(1, 2**40 - 1), 5, "entropy-coded index out of range"),
    (b"\xff" * 12, 160, "entropy-coded number too long"),
])
def test_each_malformation_gets_its_one_line_error(coder, data, n_keep, message):
    with pytest.raises(StreamError, match=message) as e:
        rangecoder.decode_indices(data, n_keep)
    assert "\n" not in str(e.value)


def test_the_largest_index_decodes_and_one_more_is_refused(coder):
    top = rangecoder.MAX_ABS_INDEX
    assert rangecoder.decode_indices(_crafted(1, top - 2), 1).tolist() == [top]
    q = np.array([0, -top, top, 0], dtype=np.int64)
    assert np.array_equal(rangecoder.decode_indices(rangecoder.encode_indices(q), 4), q)
    for bad in ([top + 1], [-top - 1], [np.iinfo(np.int64).min], np.array([2**63], dtype=np.uint64)):
        with pytest.raises(ValueError, match="beyond 2"):
            rangecoder.encode_indices(np.asarray(bad))


def test_empty_and_all_zero_indices(coder):
    for q in (np.zeros(0, dtype=np.int64), np.zeros(7, dtype=np.int64)):
        data = rangecoder.encode_indices(q)
        assert data == b""  # n_sig = 0: a single decision, then the tail is all zeros
        assert np.array_equal(rangecoder.decode_indices(data, q.size), q)


def test_pure_python_can_be_forced_and_reads_the_same_streams():
    """HOSTD_PURE_PYTHON=1 selects the reference at import (a machine without a C compiler
    gets it anyway); decoding a vector there gives what this process decodes."""
    name = "v2_shaped_gm9"
    code = ("import sys; from hostd.codec import rangecoder, stream; "
            "s = stream.decode(open(sys.argv[1], 'rb').read()); "
            "print(rangecoder.IMPLEMENTATION, s.coefficients.tobytes().hex())")
    env = {**os.environ, "HOSTD_PURE_PYTHON": "1"}
    r = subprocess.run([sys.executable, "-c", code, str(VECTORS / f"{name}.vtx")], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    impl, coeffs = r.stdout.split()
    assert impl == "python"
    from hostd.codec import stream as vtx

    assert coeffs == vtx.decode((VECTORS / f"{name}.vtx").read_bytes()).coefficients.tobytes().hex()


def test_doctor_says_which_coder_is_active(capsys):
    from hostd.cli import main

    main(["doctor", "--json"])
    doc = json.loads(capsys.readouterr().out)
    (check,) = [c for c in doc["checks"] if c["section"] == "codec"]
    assert ("compiled" in check["message"]) == HAVE_C and check["status"] in ("ok", "note")
