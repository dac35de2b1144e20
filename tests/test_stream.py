"""The .vtx stream: exact round trips, golden vectors, and refusal of malformed input."""

import json
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hostd.codec import stream as vtx
from hostd.codec import transform
from hostd.errors import CodecError, StreamError
from hostd.perception import indices, thresholds
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile
from tests.conftest import REAL, REAL_SPEED, VECTORS, real_profile_path

CURVE = thresholds.default_curve()


def _wood():
    p = synth.wood(seed=5)
    return p.heights_um, transform.Geometry(p.n, p.length_mm)


def _roundtrip(y, geom, **kw):
    data = vtx.v1.encode_profile(y, geom, CURVE, **kw)
    return data, vtx.decode(data)


@pytest.mark.parametrize("kw", [
    dict(method="quant", levels=2), dict(method="quant", levels=14),
    dict(method="quant", levels=4000), dict(method="cut", b0_db=-12.0),
    dict(method="cut", b0_db=0.0), dict(method="cut", b0_db=8.0, coder="none"),
])
def test_decoded_coefficients_equal_eq5_to_eq7(kw):
    y, geom = _wood()
    _, s = _roundtrip(y, geom, **kw)
    c = transform.analyze(y, geom.n_keep)
    expect = vtx.expected_coefficients(c, geom, CURVE, method=kw["method"],
                                       levels=kw.get("levels"), b0_db=kw.get("b0_db"))
    assert np.max(np.abs(s.coefficients - expect)) <= 1e-9 * np.max(np.abs(c))
    recon = s.reconstruct()
    assert np.max(np.abs(recon - transform.direct_synthesis(expect, geom.n))) <= 1e-9 * np.max(
        np.abs(recon))


@pytest.mark.parametrize("name", list(REAL))
def test_real_profiles_load_encode_and_decode(name):
    prof = load_profile(real_profile_path(name), LoadOptions(**REAL[name]))
    geom = transform.Geometry(prof.n, prof.length_mm, speed_mm_s=REAL_SPEED[name])
    assert geom.n_keep >= 3
    for kw in (dict(method="quant", levels=10), dict(method="cut", b0_db=-40.0)):
        _data, s = _roundtrip(prof.heights_um, geom, **kw)
        c = transform.analyze(prof.heights_um, geom.n_keep)
        expect = vtx.expected_coefficients(c, geom, CURVE, method=kw["method"],
                                           levels=kw.get("levels"), b0_db=kw.get("b0_db"))
        assert np.max(np.abs(s.coefficients - expect)) <= 1e-9 * max(np.max(np.abs(c)), 1e-300)
        P, A = indices.weighted_sums(c, CURVE(geom.frequencies_hz()))
        assert s.ref_P == pytest.approx(P, rel=1e-12) and s.ref_A == pytest.approx(A, rel=1e-12)


def test_sizes_and_ratios_are_real_byte_counts():
    y, geom = _wood()
    data, s = _roundtrip(y, geom, method="quant", levels=14)
    assert s.nbytes == len(data)
    assert s.ratio_coeffs == len(data) / (2 * 160)
    assert s.ratio_profile == len(data) / (2 * 20000)
    assert s.payload_bytes == len(data) - vtx.HEADER_SIZE - vtx.CRC_SIZE


def test_constant_profile_all_zero():
    geom = transform.Geometry(2000, 2.0)
    for kw in (dict(method="quant", levels=14), dict(method="cut", b0_db=0.0)):
        _, s = _roundtrip(np.full(2000, 7.0), geom, **kw)
        assert np.max(np.abs(s.coefficients)) <= 1e-12 * 7
        assert np.all(np.isfinite(s.reconstruct()))


def test_everything_cut_gives_a_valid_empty_stream():
    y, geom = _wood()
    _, s = _roundtrip(y, geom, method="cut", b0_db=300.0)
    assert not s.coefficients.any()
    assert s.ref_P > 0


@pytest.mark.parametrize("scale", [1e-30, 1e6])
@pytest.mark.parametrize("kw", [dict(method="quant", levels=14), dict(method="cut", b0_db=0.0)])
def test_tiny_and_huge_amplitudes_round_trip(scale, kw):
    y, geom = _wood()
    y = y * scale
    _, s = _roundtrip(y, geom, **kw)
    c = transform.analyze(y, geom.n_keep)
    expect = vtx.expected_coefficients(c, geom, CURVE, method=kw["method"],
                                       levels=kw.get("levels"), b0_db=kw.get("b0_db"))
    assert np.all(np.isfinite(s.coefficients)) and np.isfinite(s.ref_P)
    assert np.max(np.abs(s.coefficients - expect)) <= 1e-9 * np.max(np.abs(c))


def test_16_bit_survivors_are_within_half_a_step():
    y, geom = _wood()
    _, s = _roundtrip(y, geom, method="cut", b0_db=-8.0, value_bits=16)
    c = transform.analyze(y, geom.n_keep)
    keep = s.coefficients != 0
    step = np.max(np.abs(c[keep])) / 32767
    assert np.max(np.abs(s.coefficients[keep] - c[keep])) <= step / 2 * (1 + 1e-9)


def test_custom_curve_is_embedded_and_found_again(tmp_path):
    p = tmp_path / "mine.csv"
    p.write_text("10,2.0\n100,0.5\n300,0.2\n")
    mine = thresholds.load_csv(p)
    y, geom = _wood()
    s = vtx.decode(vtx.v1.encode_profile(y, geom, mine, method="quant", levels=8))
    assert s.curve is not None and s.curve.id_bytes == mine.id_bytes
    assert vtx.curve_for(s) is s.curve
    plain = vtx.decode(vtx.v1.encode_profile(y, geom, CURVE, method="quant", levels=8))
    assert plain.curve is None
    with pytest.raises(StreamError, match="pass the curve"):
        vtx.curve_for(plain, mine)


# ---------------------------------------------------------------- golden vectors

VECTOR_NAMES = sorted(p.stem for p in VECTORS.glob("*.vtx"))


def test_there_are_golden_vectors():
    assert len(VECTOR_NAMES) >= 5


@pytest.mark.parametrize("name", VECTOR_NAMES)
def test_golden_vector_decodes_to_its_recorded_values(name):
    s = vtx.decode((VECTORS / f"{name}.vtx").read_bytes())
    want = json.loads((VECTORS / f"{name}.json").read_text())
    got = s.summary()
    for key in ("n", "n_keep", "length_mm", "speed_mm_s", "fmax_hz", "method", "coder",
                "threshold_id", "bytes", "ref_P", "ref_A", "levels", "b0_db", "value_bits"):
        assert got.get(key) == want.get(key), key
    assert got["coefficients"] == want["coefficients"]  # bit-exact float64


@pytest.mark.parametrize("name", [n for n in VECTOR_NAMES if n.endswith("_none")])
def test_uncompressed_vectors_are_reproduced_byte_for_byte(name):
    from tests.vectors.make_stream_vectors import CASES, profile

    y = profile()
    data = vtx.v1.encode_profile(y, transform.Geometry(y.size, 2.0), CURVE, **CASES[name])
    assert data == (VECTORS / f"{name}.vtx").read_bytes()


# ---------------------------------------------------------------- malformed input

def _good() -> bytes:
    return (VECTORS / "quant_l14_deflate.vtx").read_bytes()


def _recrc(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def test_empty_and_foreign_input_refused():
    for data in (b"", b"VT", b"PK\x03\x04" + bytes(100), bytes(200)):
        with pytest.raises(StreamError):
            vtx.decode(data)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cut=st.integers(min_value=0))
def test_every_truncation_is_refused(cut):
    data = _good()
    with pytest.raises(StreamError):
        vtx.decode(data[: cut % len(data)])


@settings(max_examples=500, deadline=None)
@given(pos=st.integers(min_value=0), bit=st.integers(min_value=0, max_value=7))
def test_every_single_bit_flip_is_refused(pos, bit):
    data = bytearray(_good())
    data[pos % len(data)] ^= 1 << bit
    with pytest.raises(StreamError):
        vtx.decode(bytes(data))


@settings(max_examples=400, deadline=None)
@given(body=st.binary(min_size=0, max_size=400))
def test_arbitrary_bodies_with_valid_crc_never_crash(body):
    """Even a forged CRC cannot get past validation: only StreamError or a valid stream."""
    data = _recrc(vtx.MAGIC + bytes([vtx.VERSION]) + body)
    try:
        s = vtx.decode(data)
    except StreamError:
        return
    assert np.all(np.isfinite(s.coefficients)) and 1 <= s.n_keep < s.n


def _patched(**fields) -> bytes:
    data = _good()
    names = ["magic", "version", "method", "coder", "flags", "value_bits", "n", "n_keep",
             "length_mm", "speed_mm_s", "fmax_hz", "tid", "ref_P", "ref_A", "param", "levels",
             "payload_len"]
    vals = dict(zip(names, vtx.HEADER.unpack_from(data), strict=True))
    vals.update(fields)
    body = vtx.HEADER.pack(*vals.values()) + data[vtx.HEADER_SIZE:-4]
    return _recrc(body)


@pytest.mark.parametrize("fields,msg", [
    (dict(version=2), "version 2 is not supported"),
    (dict(n=1 << 30), "outside"),
    (dict(n_keep=1 << 30), "N'"),
    (dict(n_keep=0), "N'"),
    (dict(length_mm=float("nan")), "length_mm"),
    (dict(speed_mm_s=float("inf")), "speed_mm_s"),
    (dict(ref_P=float("nan")), "ref_P"),
    (dict(param=float("inf")), "not finite"),
    (dict(levels=1), "levels"),
    (dict(method=9), "method"),
    (dict(coder=7), "coder"),
    (dict(flags=0x80), "flags"),
    (dict(payload_len=0xFFFFFFFF), "promises"),
])
def test_absurd_header_fields_refused_with_a_message(fields, msg):
    with pytest.raises(StreamError, match=msg):
        vtx.decode(_patched(**fields))


def test_deflate_bomb_is_bounded():
    head = vtx.HEADER.unpack_from(_good())
    bomb = zlib.compressobj(9, zlib.DEFLATED, -15)
    payload = bomb.compress(bytes(50_000_000)) + bomb.flush()
    fields = list(head)
    fields[-1] = len(payload)
    with pytest.raises(StreamError, match="past the size"):
        vtx.decode(_recrc(vtx.HEADER.pack(*fields) + payload))


def test_encoder_refuses_bad_parameters():
    y, geom = _wood()
    with pytest.raises(CodecError):
        vtx.v1.encode_profile(y, geom, CURVE, method="quant")
    with pytest.raises(CodecError):
        vtx.v1.encode_profile(y, geom, CURVE, method="cut")
    with pytest.raises(CodecError):
        vtx.v1.encode_profile(y, geom, CURVE, method="zip", levels=3)
    with pytest.raises(CodecError):
        vtx.v1.encode_profile(y, geom, CURVE, method="cut", b0_db=0.0, value_bits=12)


def test_the_stream_formats_are_one_registry_and_the_default_is_the_default():
    """hostd.codec.formats declares each format once: the package-level encoders write the
    default (v2, as the CLI and the API), decode tells the formats apart by their magic, the
    CLI's choices and the corpus codecs come from the same table."""
    from hostd.codec import formats
    from hostd.corpus.codecs import BUILTIN
    from hostd.parser import build_parser

    y = np.random.default_rng(3).normal(size=4000)
    geom = transform.Geometry(y.size, 2.0)
    data = vtx.encode_profile(y, geom, CURVE, method="quant", levels=8)
    assert vtx.format_of(data) == formats.DEFAULT == "v2"
    assert vtx.format_of(vtx.encode_profile(y, geom, CURVE, format="v1", method="quant", levels=8)) == "v1"
    assert vtx.decode(data).n_keep == vtx.v2.int_geometry(geom).n_keep
    enc = next(a for a in build_parser()._subparsers._group_actions[0].choices["encode"]._actions
               if "--format" in a.option_strings)
    assert list(enc.choices) == list(formats.FORMATS) and enc.default == formats.DEFAULT
    assert {BUILTIN[f"hostd-{n}"] for n in formats.FORMATS} == set(formats.FORMATS)
    with pytest.raises(CodecError, match="unknown stream format 'v9': use --format v2 or v1"):
        vtx.encode_profile(y, geom, CURVE, format="v9", method="quant", levels=8)
