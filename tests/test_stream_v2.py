"""Stream v2: threshold-shaped quantizer, range coder, compact header; golden vectors; robustness."""

import binascii
import json
import math
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostd.codec import rangecoder, transform
from hostd.codec import stream as vtx
from hostd.codec.stream import v2 as stream2
from hostd.errors import CodecError, StreamError
from hostd.perception import guard, indices, thresholds
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile
from tests.conftest import REAL, REAL_SPEED, VECTORS, real_profile_path

CURVE = thresholds.default_curve()
V2_NAMES = sorted(p.stem for p in VECTORS.glob("v2_*.vtx"))


def _wood():
    p = synth.wood(seed=5)
    return p.heights_um, transform.Geometry(p.n, p.length_mm)


def _direct_shaped(c, b, g_db):
    """q_k = sign(C) floor(|C| / (G b) + 1/2), C'_k = q_k G b, element by element."""
    G = 10.0 ** (g_db / 20.0)
    out = []
    for ck, bk in zip(c.tolist(), b.tolist(), strict=True):
        q = math.floor(abs(ck) / (G * bk) + 0.5)
        out.append(math.copysign(q * G * bk, ck) if q else 0.0)
    return np.array(out)


@pytest.mark.parametrize("g_db", [-30.0, -9.0, 0.0, 6.25, 20.0])
def test_shaped_decodes_to_the_direct_formula(g_db):
    y, geom = _wood()
    s = vtx.decode(stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=g_db))
    c = transform.analyze(y, geom.n_keep)
    b = CURVE(geom.frequencies_hz())
    want = _direct_shaped(c, b, g_db)
    assert s.version == 2 and s.method == "shaped" and s.g_db == g_db and s.n_keep == 160
    assert np.max(np.abs(s.coefficients - want)) <= 1e-12 * np.max(np.abs(c))
    # every error is at most half a step: the error is shaped along the threshold curve
    step = 10.0 ** (g_db / 20.0) * b
    assert np.all(np.abs(c - s.coefficients) <= 0.5 * step * (1 + 1e-12))


@pytest.mark.parametrize("kw", [dict(method="quant", levels=14), dict(method="quant", levels=3000),
                                dict(method="cut", b0_db=-4.0, value_bits=16),
                                dict(method="cut", b0_db=2.5, value_bits=8)])
def test_the_papers_methods_in_v2_decode_like_v1(kw):
    y, geom = _wood()
    s2 = vtx.decode(stream2.encode_profile(y, geom, CURVE, **kw))
    s1 = vtx.decode(vtx.v1.encode_profile(y, geom, CURVE, **kw))
    assert s2.version == 2 and s1.version == 1
    assert np.array_equal(s2.coefficients, s1.coefficients)
    assert s2.nbytes < s1.nbytes


def test_reference_sums_are_kept_to_17_significant_bits():
    y, geom = _wood()
    s = vtx.decode(stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=0.0))
    P, A = indices.weighted_sums(transform.analyze(y, geom.n_keep), CURVE(geom.frequencies_hz()))
    assert abs(s.ref_P - P) <= P * 2.0**-17 and abs(s.ref_A - A) <= A * 2.0**-17
    for x in (0.0, 1e-300, 5e-324, 3.0, 1e300, 2.0**126 * 1.9999999, 2.0**-127):
        r = stream2.rounded_ref(x)
        assert abs(r - x) <= x * 2.0**-17


def test_common_case_overhead_is_at_most_16_bytes():
    y, geom = _wood()
    data = stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=-9.0)
    s = vtx.decode(data)
    assert s.nbytes - s.payload_bytes <= 16
    assert len(stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=60.0)) <= 16


def test_guard_byte_is_a_lower_bound_of_the_real_wsnr():
    y, geom = _wood()
    c = transform.analyze(y, geom.n_keep)
    b = CURVE(geom.frequencies_hz())
    for g in (-20.0, -9.0, 0.0, 10.0):
        s = vtx.decode(stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=g))
        w = guard.weighted_snr_db(c, s.coefficients, b)
        assert s.guard_wsnr_db <= w < s.guard_wsnr_db + 0.5 or s.guard_wsnr_db == 127.5


@pytest.mark.parametrize("name", list(REAL))
def test_real_profiles_round_trip_in_v2(name):
    prof = load_profile(real_profile_path(name), LoadOptions(**REAL[name]))
    geom = transform.Geometry(prof.n, prof.length_mm, speed_mm_s=REAL_SPEED[name])
    ig = stream2.int_geometry(geom)
    c = transform.analyze(prof.heights_um, ig.n_keep)
    s = vtx.decode(stream2.encode_coefficients(c, ig, CURVE, method="shaped", g_db=-12.0))
    want = _direct_shaped(c, CURVE(ig.frequencies_hz()), -12.0)
    assert np.max(np.abs(s.coefficients - want)) <= 1e-12 * max(np.max(np.abs(c)), 1e-300)
    # the spacing is kept to 1 pm: L is off by at most N · 0.5 pm
    assert abs(s.length_mm - geom.length_mm) <= geom.n * 0.5e-9 * (1 + 1e-9)


@pytest.mark.parametrize("case", ["silent", "below", "single", "huge", "tiny"])
def test_hard_cases(case):
    geom = transform.Geometry(20000, 10.0)
    b = CURVE(geom.frequencies_hz())
    c = {"silent": np.zeros(160), "below": 0.3 * b * np.cos(np.arange(160)),
         "single": np.where(np.arange(160) == 57, 2.5, 0.0),
         "huge": 1e6 * np.sin(np.arange(160.0)), "tiny": 1e-30 * np.sin(np.arange(160.0))}[case]
    for g in (-20.0, 0.0):
        data = stream2.encode_coefficients(c, geom, CURVE, method="shaped", g_db=g)
        s = vtx.decode(data)
        assert np.all(np.isfinite(s.coefficients))
        assert np.max(np.abs(s.coefficients - _direct_shaped(c, b, g))) <= 1e-12 * max(
            np.max(np.abs(c)), 1e-300)
    if case in ("silent", "below", "tiny"):
        assert not s.coefficients.any() and s.payload_bytes == 0
    if case == "single":
        assert np.count_nonzero(s.coefficients) == 1


@pytest.mark.parametrize("n_keep", [1, 4096])
def test_extreme_component_counts(n_keep, rng):
    # N' = floor(2 L fmax / v): choose fmax so that exactly n_keep components fit.
    geom = transform.Geometry(20000, 10.0, 50.0, fmax_hz=n_keep * 2.5)
    assert stream2.int_geometry(geom).n_keep == n_keep
    c = rng.normal(0, 1, n_keep)
    data = stream2.encode_coefficients(c, geom, CURVE, method="shaped", g_db=-40.0)
    s = vtx.decode(data)
    assert s.n_keep == n_keep
    b = CURVE(geom.frequencies_hz())
    assert np.max(np.abs(s.coefficients - _direct_shaped(c, b, -40.0))) <= 1e-12 * np.max(np.abs(c))
    crc_len = 2 if len(data) < stream2.CRC16_LIMIT else 4
    assert (crc_len == 4) == (n_keep == 4096)  # the big one is over 4 KiB and gets a CRC-32


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(vals=st.lists(st.integers(min_value=-(2**40) + 1, max_value=2**40 - 1), min_size=1,
                     max_size=300),
       zeros=st.integers(min_value=0, max_value=100))
def test_range_coder_round_trips_any_indices(vals, zeros):
    q = np.array(vals + [0] * zeros, dtype=np.int64)
    assert np.array_equal(rangecoder.decode_indices(rangecoder.encode_indices(q), q.size), q)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(min_value=0, max_value=2**32 - 1),
       g=st.integers(min_value=-160, max_value=80))
def test_random_spectra_round_trip(seed, g):
    r = np.random.default_rng(seed)
    geom = transform.Geometry(20000, 10.0)
    c = r.normal(0, 1, 160) * 10.0 ** r.uniform(-3, 2, 160)
    s = vtx.decode(stream2.encode_coefficients(c, geom, CURVE, method="shaped", g_db=g / 4))
    b = CURVE(geom.frequencies_hz())
    assert np.max(np.abs(s.coefficients - _direct_shaped(c, b, g / 4))) <= 1e-12 * np.max(np.abs(c))


def test_encoder_refuses_what_v2_cannot_store():
    y, geom = _wood()
    with pytest.raises(CodecError, match=r"multiple of 0\.25"):
        stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=0.1)
    with pytest.raises(CodecError, match="--g-db"):
        stream2.encode_profile(y, geom, CURVE, method="shaped")
    with pytest.raises(CodecError, match="format v1"):
        stream2.encode_profile(y, geom, CURVE, method="cut", b0_db=0.0, value_bits=0)
    with pytest.raises(CodecError, match="format v1"):
        stream2.encode_profile(y, geom, CURVE, method="cut", b0_db=0.3, value_bits=16)
    with pytest.raises(CodecError):
        stream2.encode_profile(y, geom, CURVE, method="zip")


# ---------------------------------------------------------------- golden vectors


def test_there_are_v2_golden_vectors():
    assert len(V2_NAMES) >= 6


@pytest.mark.parametrize("name", V2_NAMES)
def test_v2_vectors_decode_to_their_values_and_are_reproduced(name):
    from tests.vectors.make_stream_vectors import build_v2

    data = (VECTORS / f"{name}.vtx").read_bytes()
    want = json.loads((VECTORS / f"{name}.json").read_text())
    got = vtx.decode(data).summary()
    for key in ("version", "n", "n_keep", "length_mm", "speed_mm_s", "fmax_hz", "method", "coder",
                "threshold_id", "bytes", "ref_P", "ref_A", "levels", "b0_db", "value_bits", "g_db",
                "guard_wsnr_db"):
        assert got.get(key) == want.get(key), key
    assert got["coefficients"] == want["coefficients"]
    assert build_v2(name) == data


FIRST_LAYOUT = sorted((VECTORS / "v2_first_layout").glob("*.vtx"))


@pytest.mark.parametrize("path", FIRST_LAYOUT, ids=lambda p: p.stem)
def test_streams_of_the_first_v2_layout_still_decode_to_their_values(path):
    """Streams written before the explicit geometry became 4N + 2 bits (byte 1's nibble 2 with
    an explicit geometry of 4 varints) decode as they did; the current encoder writes the same
    texture in the compact layout (nibble 3), 6 bytes shorter."""
    data = path.read_bytes()
    assert data[1] >> 4 == 2 and data[1] & stream2.FLAG_EXPLICIT_GEOMETRY
    want = json.loads(path.with_suffix(".json").read_text())
    got = vtx.decode(data).summary()
    for key in ("version", "n", "n_keep", "length_mm", "speed_mm_s", "fmax_hz", "method", "threshold_id",
                "bytes", "ref_P", "ref_A", "levels", "b0_db", "value_bits", "g_db", "guard_wsnr_db"):
        assert got.get(key) == want.get(key), key
    assert got["coefficients"] == want["coefficients"]
    now = (VECTORS / path.name).read_bytes()
    assert now[1] >> 4 == 3 and len(now) == len(data) - 6
    assert vtx.decode(now).summary()["coefficients"] == want["coefficients"]


# ---------------------------------------------------------------- malformed input


def _good() -> bytes:
    return (VECTORS / "v2_shaped_gm9.vtx").read_bytes()


def _recrc(body: bytes) -> bytes:
    return body + stream2._crc(body)


@settings(max_examples=200, deadline=None)
@given(cut=st.integers(min_value=0))
def test_every_truncation_is_refused(cut):
    data = _good()
    with pytest.raises(StreamError):
        vtx.decode(data[: cut % len(data)])


@settings(max_examples=400, deadline=None)
@given(pos=st.integers(min_value=0), bit=st.integers(min_value=0, max_value=7))
def test_every_single_bit_flip_is_refused(pos, bit):
    data = bytearray(_good())
    data[pos % len(data)] ^= 1 << bit
    with pytest.raises(StreamError):
        vtx.decode(bytes(data))


@settings(max_examples=500, deadline=None)
@given(flags=st.integers(min_value=0, max_value=15), layout=st.sampled_from([0x20, 0x30]),
       body=st.binary(min_size=0, max_size=300))
def test_arbitrary_bodies_with_a_valid_crc_never_crash(flags, layout, body):
    data = _recrc(bytes([0x56, layout | flags]) + body)
    try:
        s = vtx.decode(data)
    except StreamError:
        return
    assert np.all(np.isfinite(s.coefficients)) and 1 <= s.n_keep < s.n
    assert s.coefficients.size == s.n_keep


def test_typed_one_line_errors():
    good = _good()
    cases = [
        (bytes([0x56, 0x28]) + b"\xff" * 12, "longer than 10 bytes"),  # absurd N varint
        (bytes([0x56, 0x28]) + b"\xff\xff\xff\x7f", "N = "),
        (bytes([0x56, good[1] | 0x03]) + good[2:-2], "method"),
        (bytes([0x56, 0x28]) + b"\x02\x00\x02\x02", "zero or too small"),
        (bytes([0x56, 0x28]) + b"\x02\x02\x02\x02", "N' = 0"),  # first layout: N, spacing, v, f
        (bytes([0x56, 0x38]) + b"\x0b\x02\x02\x02", "N' = 0"),  # 4N + 3: v_ref, f_max follow
        (bytes([0x56, 0x38]) + b"\x08\x02", "N' = 0"),  # 4N + 0: the paper's v_ref and f_max
        (bytes([0x56, 0x38]) + b"\x0a\x02\x02", "N' = 0"),  # 4N + 2: v_ref only
        (bytes([0x56, 0x38]) + b"\x09\x02\x02", "N' = 0"),  # 4N + 1: f_max only
        (bytes([0x56, 0x38]) + b"\x0b\x02\x02", "truncated"),  # the bits promise two more
        (bytes([0x56, 0x38]) + b"\xff\xff\xff\x7f", "N = "),
        (bytes([0x56, 0x20]), "truncated"),
    ]
    for body, msg in cases:
        with pytest.raises(StreamError, match=msg) as ei:
            vtx.decode(_recrc(body))
        assert "\n" not in str(ei.value)
    with pytest.raises(StreamError, match="CRC"):
        vtx.decode(good[:-1] + bytes([good[-1] ^ 1]))
    big = bytes([0x56, 0x20]) + bytes(5000)
    with pytest.raises(StreamError, match="CRC"):
        vtx.decode(big + struct.pack("<H", binascii.crc_hqx(big, 0xFFFF)))  # CRC-16 on > 4 KiB
    assert vtx.decode(_recrc(good[:-2])).method == "shaped"
    assert zlib.crc32(b"") == 0  # (the CRC-32 is zlib's; see the spec)


# ---------------------------------------------------------------- everywhere a stream is read


def test_daemon_library_and_quality_log_read_v1_and_v2(tmp_path):
    from hostd.service.library import Library
    from hostd.service.qualitylog import score_row

    y, geom = _wood()
    lib = Library(tmp_path)
    for data in (stream2.encode_profile(y, geom, CURVE, method="shaped", g_db=-6.0),
                 vtx.v1.encode_profile(y, geom, CURVE, method="quant", levels=8)):
        s = lib.validate(data)
        row = score_row(data, "t", "0" * 64, 0.0, *indices.DEFAULT_AB)
        assert row["method"] == s.method and 0 <= row["iobj"] < 0.5


def test_cli_encode_defaults_to_v2_and_writes_v1_on_request(tmp_path, capsys):
    from hostd.cli import main

    out2, out1 = tmp_path / "a.vtx", tmp_path / "b.vtx"
    assert main(["encode", "synthetic:wood:5", "-o", str(out2), "--method", "shaped", "--g-db", "-6"]) == 0
    assert main(["encode", "synthetic:wood:5", "-o", str(out1), "--format", "v1", "--method", "quant",
                 "--levels", "14"]) == 0
    assert vtx.decode(out2.read_bytes()).version == 2 and vtx.decode(out1.read_bytes()).version == 1
    capsys.readouterr()
    assert main(["inspect", "--json", str(out2)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["guard_wsnr_db"] > 10 and info["g_db"] == -6.0
    assert main(["iobj", "--json", "synthetic:wood:5", str(out1)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["guard_source"] == "profile" and 0 < info["wsnr_db"] < 30
    assert main(["encode", "synthetic:wood:5", "-o", str(out1), "--format", "v1", "--method",
                 "shaped", "--g-db", "0"]) == 2
    assert "format v2" in capsys.readouterr().err


def _spec_decode_indices(payload: bytes, n_keep: int) -> list[int]:
    """An independent decoder written from docs/stream-format.md ("Entropy coder (exact)" and
    "Context model"), sharing no code with hostd/codec/rangecoder.py."""
    st = {"code": int.from_bytes((payload[:4] + bytes(4))[:4], "big"), "range": 0xFFFFFFFF,
          "pos": 4}

    def norm():
        while st["range"] < 1 << 24:
            st["range"] <<= 8
            nxt = payload[st["pos"]] if st["pos"] < len(payload) else 0
            st["pos"] += 1
            st["code"] = ((st["code"] << 8) | nxt) % (1 << 32)

    def abit(probs, i):
        p = probs[i]
        bound = (st["range"] >> 11) * p
        if st["code"] < bound:
            st["range"] = bound
            probs[i] = p + ((2048 - p) >> 4)
            b = 0
        else:
            st["code"] -= bound
            st["range"] -= bound
            probs[i] = p - (p >> 4)
            b = 1
        norm()
        return b

    def bbit():
        st["range"] >>= 1
        b = 0
        if st["code"] >= st["range"]:
            st["code"] -= st["range"]
            b = 1
        norm()
        return b

    def eg(probs):
        n = 0
        while abit(probs, min(n, 15)):
            n += 1
        v1 = 1
        for _ in range(n):
            v1 = 2 * v1 + bbit()
        return v1 - 1

    p_sig, p_mag, p_zero, p_gt1 = [1024] * 16, [1024] * 16, [1024] * 5, [1024] * 5
    n_sig = eg(p_sig)
    q = [0] * n_keep
    a = {0: 0, -1: 0}
    for k in range(1, n_sig + 1):
        c = min(2, a[k - 1]) + min(2, a[k - 2])
        nz = 1 if k == n_sig else abit(p_zero, c)
        mag = 0
        if nz:
            neg = bbit()
            mag = 2 + eg(p_mag) if abit(p_gt1, c) else 1
            q[k - 1] = -mag if neg else mag
        a[k] = mag
    return q


@pytest.mark.parametrize("name", V2_NAMES)
def test_an_independent_decoder_from_the_spec_reads_the_vectors(name):
    data = (VECTORS / f"{name}.vtx").read_bytes()
    s = vtx.decode(data)
    crc = 2 if len(data) < stream2.CRC16_LIMIT else 4
    payload = data[len(data) - crc - s.payload_bytes : len(data) - crc]
    q = np.array(_spec_decode_indices(payload, s.n_keep), dtype=np.float64)
    if s.method == "shaped":
        want = q * (CURVE(s.frequencies_hz) * (10.0 ** (s.g_db / 20.0)))
        assert np.allclose(s.coefficients, want, rtol=1e-12, atol=0)
    else:
        nz = q != 0
        step = s.coefficients[nz] / q[nz]
        assert np.all(s.coefficients[~nz] == 0) and np.ptp(step) <= 1e-15 * np.max(np.abs(step))
