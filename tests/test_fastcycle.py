"""The compiled per-cycle code of the host-rendering path against its Python reference:
hostd/device/_fastlink.c (message decode / SAMPLES encode) against hostd.device.protocol, and
hostd/render/_fastrender.c (equalizer -> output stage -> codes) against Equalizer, OutputStage.
Same bytes, same fields, same errors, same codes and the same filter/envelope state, on random
inputs (hypothesis), on the protocol's golden vectors and on a recorded hand (the metronome)."""

import os
import shutil
import struct
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hostd import cyclestate
from hostd.device import fastlink, fastpump
from hostd.device import protocol as pr
from hostd.render import fastrender
from hostd.render.equalizer import SMALL_BATCH, Equalizer, EqualizerConfig
from hostd.render.output import OutputConfig, OutputStage
from tests.conftest import ROOT

HAVE_C = fastlink._C is not None and fastrender._C is not None
needs_c = pytest.mark.skipif(not HAVE_C, reason="the compiled fast path is not built (no C compiler, "
                             "or HOSTD_PURE_PYTHON=1): only the reference runs")
VECTORS = Path(__file__).resolve().parent / "vectors" / "protocol.txt"


def _bits(v):
    """Floats by their bits (a NaN field must decode to the same NaN; NaN != NaN)."""
    if isinstance(v, float):
        return ("f64", struct.pack("<d", v).hex())
    if isinstance(v, tuple):
        return tuple(_bits(x) for x in v)
    if isinstance(v, dict):
        return {k: _bits(x) for k, x in v.items()}
    return v


def _outcome(fn, *args):
    try:
        r = fn(*args)
    except pr.ProtocolError as e:
        return ("error", str(e))
    return ("ok", _bits(r))


def test_the_compiled_fast_path_is_built_where_a_c_compiler_is():
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if os.environ.get("HOSTD_PURE_PYTHON") or not shutil.which(cc):
        pytest.skip("pure Python asked for, or no C compiler: the reference is the expected path")
    assert fastlink.IMPLEMENTATION == fastrender.IMPLEMENTATION == fastpump.IMPLEMENTATION == "c", (
        "hostd.device._fastlink / _fastpump / hostd.render._fastrender are not built although a C compiler "
        "exists: re-run `pip install -e .` (./run does on a change of setup.py or the C sources)")


# ---------------------------------------------------------------- link messages
@needs_c
def test_every_stage_holds_its_declared_fields_in_its_record():
    """Each field of hostd/device/cycle_state.toml is an attribute of its stage stored in the
    struct the C reads (not in the instance's __dict__): a write through the buffer shows in the
    attribute, one memory; an optional field maps None to its _set flag."""
    import ctypes

    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.render.pipeline import Renderer

    class Clock:
        def now(self):
            return 0.0

    pump = Pump(DeviceLink(Clock()), None)
    r = Renderer(np.array([1.0, 0.5]), 100, 10.0)
    stages = {"pump": pump, "pump_stats": pump.stats, "link": pump.link, "link_stats": pump.link.stats,
              "health": pump.health, "renderer": r, "position": r.position, "motion": r.motion,
              "height": r.height, "output": r.out}
    assert set(stages) == set(cyclestate.SCHEMA)
    for kind, obj in stages.items():
        assert set(cyclestate.state_fields(obj)) == set(cyclestate.SCHEMA[kind]), kind
        assert not set(cyclestate.SCHEMA[kind]) & set(vars(obj)), kind  # (a class attribute would shadow one)
        assert memoryview(obj).nbytes == ctypes.sizeof(cyclestate.RECORDS[kind]), kind
    raw = cyclestate.RECORDS["output"].from_buffer(memoryview(r.out).cast("B"))
    raw.last_um = 2.5
    assert r.out.last_um == 2.5
    assert r.motion._rest_x is None and not r.motion._rest_x_set
    r.motion._rest_x = 0.25
    assert r.motion._rest_x_set and r.motion._rest_x == 0.25
    if fastpump._C is not None:
        assert fastpump._C.RECORD_SIZES == {k: ctypes.sizeof(c) for k, c in cyclestate.RECORDS.items()}


def test_golden_protocol_vectors_decode_alike():
    lines = [ln.split() for ln in VECTORS.read_text().splitlines() if ln.startswith(("msg ", "bad "))]
    assert len(lines) >= 10
    for row in lines:
        msg = bytes.fromhex(row[2])
        for m in (msg, pr.pad_report(msg) if len(msg) <= pr.REPORT_SIZE else msg):
            assert _outcome(fastlink.decode, m) == _outcome(pr.decode, m), row[1]


FIXED_IDS = sorted(fastlink._FIXED)


@needs_c
@settings(max_examples=400, deadline=None)
@given(st.sampled_from(FIXED_IDS), st.binary(max_size=70), st.integers(0, 40), st.booleans())
def test_random_fixed_messages_decode_alike(mid, body, cut, garbage):
    """Any bytes after a known id: a full message, a short one, zero padding, garbage after it."""
    size = pr.LAYOUTS[pr.NAMES[mid]].size
    msg = bytes([mid]) + body[: max(0, size - 1 - cut % 3)] if cut < 10 else bytes([mid]) + body
    if not garbage and len(msg) > size:
        msg = msg[:size] + bytes(len(msg) - size)
    assert _outcome(fastlink.decode, msg) == _outcome(pr.decode, msg)


@needs_c
@settings(max_examples=300, deadline=None)
@given(st.integers(-2, 70000), st.lists(st.integers(-32768, 32767), max_size=pr.MAX_SAMPLES + 3))
def test_samples_encode_to_the_same_bytes(seq, codes):
    arr = np.array(codes, dtype=np.int16)
    fast = _outcome(fastlink.encode_samples, seq, arr)
    ref = _outcome(lambda: pr.encode("SAMPLES", seq=seq, codes=codes))
    assert fast == ref
    if fast[0] == "ok":  # a slice of a longer array (the link sends parts of one batch)
        big = np.concatenate([arr, arr])
        assert fastlink.encode_samples(seq, big[: arr.size]) == ref[1]


def _deframed(compiled: bool, pieces) -> tuple:
    d = fastlink.deframer() if compiled else pr.Deframer()  # (the reference loop)
    got = [d.feed(p) for p in pieces]
    return got, d.bad_frames, bytes(d._buf)


# a stream's parts: valid frames, frames cut or with a byte changed, empty frames, bare COBS
# without CRC, garbage with and without zero bytes, long runs without a delimiter (the resync)
_FRAME_PART = st.one_of(
    st.binary(min_size=1, max_size=70).map(pr.frame),
    st.tuples(st.binary(min_size=1, max_size=70), st.integers(0, 80)).map(
        lambda a: pr.frame(a[0])[: a[1]]),
    st.tuples(st.binary(min_size=1, max_size=70), st.integers(0, 80), st.integers(1, 255)).map(
        lambda a: bytes(b ^ (a[2] if i == a[1] else 0) for i, b in enumerate(pr.frame(a[0])))),
    st.just(b"\x00"), st.binary(max_size=12).map(lambda b: b + b"\x00"),
    st.binary(max_size=90), st.integers(250, 700).map(lambda n: b"\x01" * n),
    st.integers(1, 3).map(lambda n: b"\xff" * 254 * n + b"\x00"))


@needs_c
@settings(max_examples=300, deadline=None)
@given(st.lists(_FRAME_PART, max_size=30), st.lists(st.integers(1, 400), min_size=1, max_size=20))
def test_compiled_deframing_gives_the_reference_messages_and_counts(parts, cuts):
    """_fastlink.deframe against protocol.Deframer's loop: the same messages from each feed, the
    same bad-frame count and the same bytes left waiting, whatever the stream and its pieces."""
    stream = b"".join(parts)
    pieces, i, k = [], 0, 0
    while i < len(stream):
        n = cuts[k % len(cuts)]
        pieces.append(bytearray(stream[i : i + n]) if k % 2 else stream[i : i + n])
        i, k = i + n, k + 1
    assert fastlink.deframer()._compiled is fastlink.DEFRAME is not None and pr.Deframer()._compiled is None
    assert _deframed(True, pieces) == _deframed(False, pieces)


@needs_c
def test_compiled_deframing_of_the_golden_frames():
    lines = [ln.split() for ln in VECTORS.read_text().splitlines() if ln.startswith(("frame ", "badframe "))]
    assert len(lines) >= 3
    for row in lines:
        raw = bytes.fromhex(row[-1])
        assert _deframed(True, [raw]) == _deframed(False, [raw]), row[1]


# ---------------------------------------------------------------- render tail
def _stages(eq_enabled: bool, seed: int):
    rng = np.random.default_rng(seed)
    eq = Equalizer(cfg=EqualizerConfig(enabled=eq_enabled, reg_order=int(rng.integers(2, 5))))
    out = OutputStage(OutputConfig(ramp_s=float(rng.choice([0.001, 0.05]))))
    return eq, out


def _state(eq: Equalizer, out: OutputStage):
    zi = None if eq.zi is None else eq.zi.tobytes()
    return (zi, out.last_um, out.envelope, out.target_envelope, out.nonfinite, out.clipped)


@needs_c
@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(),
       st.lists(st.tuples(st.integers(1, SMALL_BATCH), st.sampled_from(["run", "start", "stop", "restart"]),
                          st.sampled_from([1.0, 30.0, 1e3, 1e300])), min_size=1, max_size=40))
def test_render_tail_is_sample_equal_to_the_reference(seed, eq_enabled, batches):
    """Random heights (with NaN, Inf, jumps past the limits and the slew), batch sizes and
    start / stop / restart between batches: the same codes and the same state after each."""
    rng = np.random.default_rng(seed)
    a = _stages(eq_enabled, seed)
    b = _stages(eq_enabled, seed)
    for st_ in (a, b):
        st_[1].start()
    for n, event, scale in batches:
        h = rng.normal(0.0, scale, n)
        if rng.random() < 0.2:
            h[rng.integers(0, n)] = rng.choice([np.nan, np.inf, -np.inf])
        for _eq, out in (a, b):
            {"start": out.start, "stop": out.stop, "restart": lambda o=out: o.restart_from(0.0),
             "run": lambda: None}[event]()
        ref = fastrender.tail_py(a[0], a[1], h.copy())
        fast = fastrender.tail(b[0], b[1], h.copy())
        assert fast.dtype == ref.dtype == np.int16
        assert fast.tobytes() == ref.tobytes()
        assert _state(*b) == _state(*a)


def _metronome_codes() -> str:
    from hostd.bench.accuracy import link_for, texture_coeffs
    from hostd.render.pipeline import RenderConfig, Renderer
    from hostd.sim import chain
    from hostd.sim.hand import Metronome
    from hostd.texture import synth

    cfg = RenderConfig()
    coeffs, n, length = texture_coeffs(synth.make("wood", seed=1))
    res = chain.run_loop(Renderer(coeffs, n, length, cfg), Metronome(), 1.5, link_for(cfg))
    codes = np.rint(res.command_um / cfg.output.um_per_code).astype(np.int16)
    return codes.tobytes().hex()


@needs_c
def test_the_renderer_gives_the_same_frames_with_and_without_the_compiled_tail(monkeypatch):
    """A recorded hand (1.5 s of the paper's metronome strokes, 1500 batches of 3 samples):
    every frame equal to the pure-Python renderer's."""
    fast = _metronome_codes()
    monkeypatch.setattr(fastrender, "_C", None)
    assert _metronome_codes() == fast


def test_pure_python_can_be_forced_and_renders_the_same_frames():
    """HOSTD_PURE_PYTHON=1 selects the references at import (as a machine without a C compiler
    gets them): the same frames as this process renders, and the same link bytes."""
    code = ("from hostd.device import fastlink; from hostd.render import fastrender; "
            "from tests.test_fastcycle import _metronome_codes; import hashlib; "
            "print(fastlink.IMPLEMENTATION, fastrender.IMPLEMENTATION, "
            "hashlib.sha256(_metronome_codes().encode()).hexdigest())")
    env = {**os.environ, "HOSTD_PURE_PYTHON": "1"}
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    link_impl, render_impl, digest = r.stdout.split()
    assert (link_impl, render_impl) == ("python", "python")
    import hashlib

    assert digest == hashlib.sha256(_metronome_codes().encode()).hexdigest()


# ---------------------------------------------------------------- longer host cycles
@pytest.mark.parametrize("cycle_ms", [1, 2, 4])
def test_a_longer_host_cycle_sends_one_message_per_wake_up_and_keeps_the_margin(cycle_ms):
    """[device] host_cycle_ms: one SAMPLES message of cycle_ms x 3 samples per wake-up, the fill
    target raised by the extra samples, so just before the next wake-up the device still holds
    target_fill - 3 samples (the 1 ms cycle's margin), and it never runs dry."""
    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.device.simdev import SimTransport
    from tests.test_device import _renderer

    t = SimTransport(realtime=False)
    link = DeviceLink(t, target_fill=12)
    t.advance(3)
    link.handshake(timeout_s=0.1)
    pump = Pump(link, None, period_s=cycle_ms / 1000)
    pump.begin(_renderer())
    assert link.target_fill == 12 + 3 * (cycle_ms - 1) and pump.target_fill == 12
    lows, sent = [], []
    for i in range(600 // cycle_ms):
        t.advance(3 * cycle_ms)
        if i > 50:
            lows.append(len(t.device.ring))
        m0 = link.stats.messages_sent
        sent.append((pump.step(), link.stats.messages_sent - m0))
    steady = sent[50:]
    assert {n for n, _ in steady} == {3 * cycle_ms} and {m for _, m in steady} == {1}
    assert min(lows) >= 12 - 3 - 1  # the margin a 1 ms cycle has (one sample of rounding)
    assert t.device.underruns == 0 and pump.stats.recoveries == 0


def test_the_host_cycle_is_bounded():
    from hostd.device.link import DeviceLink
    from hostd.device.pump import Pump
    from hostd.device.simdev import SimTransport

    with pytest.raises(ValueError, match=r"1\.\.10 ms"):
        Pump(DeviceLink(SimTransport(realtime=False)), None, period_s=0.02)


def test_bench_pipeline_reports_what_a_longer_host_cycle_costs(capsys):
    import json

    from hostd.cli import main

    errs = {}
    for cycle in (1, 4):
        assert main(["bench", "pipeline", "--json", "--duration", "1", "--host-cycle-ms", str(cycle)]) == 0
        (row,) = json.loads(capsys.readouterr().out)["rows"]
        assert row["host_cycle_ms"] == cycle and row["samples_per_batch"] == 3 * cycle
        errs[cycle] = row["rms_error_pct"]
    assert 0 < errs[1] < errs[4]  # predicted further ahead: less accurate


def test_bench_cycle_splits_the_pump_cycle_into_its_parts(capsys):
    import json

    from hostd.cli import main

    try:
        main(["bench", "cycle", "--json", "--seconds", "1"])
    except SystemExit as e:
        pytest.skip(f"the firmware's host port cannot run here: {e}")
    from hostd.device import fastpump

    rows = json.loads(capsys.readouterr().out)["rows"]
    row = rows[0]
    assert row["cycle"] == "reference"
    parts = [v for k, v in row.items() if k.endswith("_us") and k not in ("cpu_us_per_cycle",)]
    assert row["cycles_per_s"] > 100 and row["idle_loop_us_per_wake"] > 0
    assert all(v >= 0 for v in parts) and row["render_us"] > 0 and row["messages_in_us"] > 0
    assert row["link"] == fastlink.IMPLEMENTATION and row["render_tail"] == fastrender.IMPLEMENTATION
    assert len(rows) == (2 if fastpump.IMPLEMENTATION == "c" else 1)
    if len(rows) == 2:  # the compiled cycle ran the stream (and says what it handed over)
        c = rows[1]
        assert c["cycle"] == "compiled" and c["cycles_per_s"] > 100 and c["cpu_us_per_cycle"] > 0
        assert c["reference_over_compiled"] > 0 and isinstance(c["handed_over"], dict)
        assert c["compiled_cycles"] > 0 and "compiled" not in c["handed_over"]


# ---------------------------------------------------------------- scalar paths of the render front
ANY_FLOAT = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(ANY_FLOAT, st.floats(-1e4, 1e4)), max_size=32),
       st.integers(1, 1 << 20), st.floats(1e-3, 1e4))
def test_phase_of_a_small_batch_is_bitwise_the_numpy_formula(xs, n, length_mm):
    """series.phase_rad's scalar path (<= 32 positions) against the numpy formula it replaces."""
    from hostd.render.series import phase_rad

    x = np.array(xs, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        ref = (np.mod(x, 2.0 * length_mm) / (length_mm / n) + 0.5) * (np.pi / n)
    assert phase_rad(x, n, length_mm).tobytes() == ref.tobytes()


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(ANY_FLOAT, st.floats(-1.0, 1.0)), max_size=32),
       st.tuples(st.floats(-1e3, 1e3), st.floats(-3e3, 3e3), st.floats(-1e5, 1e5), st.floats(-1e7, 1e7),
                 st.floats(-10.0, 10.0)))
def test_prediction_of_a_small_batch_is_bitwise_the_numpy_formula(ts, fit):
    """MotionEstimator.predict's scalar path (<= 32 instants) against the numpy formula."""
    from hostd.render.motion import MotionEstimator

    m = MotionEstimator()
    m._c0, m._c1, m._c2, m._c3, m._t_ref = fit
    t = np.array(ts, dtype=np.float64)
    lim = m.cfg.max_predict_s
    dt = (t - m._t_ref).clip(-lim, lim)
    ref = m._c0 + dt * (m._c1 + dt * (m._c2 + dt * m._c3))
    assert np.asarray(m.predict(t), dtype=np.float64).tobytes() == np.asarray(ref, dtype=np.float64).tobytes()
