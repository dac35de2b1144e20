"""Rendering over long runs and with measured actuators: each test asserts a bound."""

import json

import numpy as np
import pytest

from hostd.cli import main
from hostd.codec import transform
from hostd.paths import actuators_dir
from hostd.render import RenderConfig, Renderer
from hostd.render.equalizer import DENORMAL_GUARD, ActuatorModel, Equalizer, load_actuator
from hostd.render.height import HeightEvaluator
from hostd.render.motion import MotionConfig
from hostd.sim import chain
from hostd.sim.hand import Constant, Metronome, Recorded
from hostd.texture import synth

FS = 3000.0


@pytest.fixture(scope="module")
def wood():
    p = synth.wood(seed=1)
    return transform.analyze(p.heights_um, 160), p.n, p.length_mm


def test_one_simulated_hour_has_no_drift_and_no_subnormal_state(wood):
    """An hour at 50 mm/s in one direction (180 m of travel, as a mouse could): the error
    against the exact series at the true position is the same in the last minute as in the
    first, and the equalizer's state never holds a subnormal number."""
    c, n, length = wood
    chunk = 300  # 100 ms per call: the vectorized paths, so an hour takes seconds
    cfg = RenderConfig(latency_s=0.0, motion=MotionConfig(max_predict_s=0.2))
    r = Renderer(c, n, length, cfg)
    r.start()
    hand = Constant(speed_mm_s=50.0)
    ev = HeightEvaluator(c, n, length)
    calls = int(3600 * FS / chunk)
    errs = {}
    for i in range(calls):
        t0 = i * chunk / FS
        r.on_encoder(t0, int(np.floor(hand.position_mm(t0) * 1000 / 0.4)))
        t = t0 + np.arange(chunk) / FS
        y = r.render_um(t)
        zi = r.eq.zi
        assert np.all((zi == 0) | (np.abs(zi) >= DENORMAL_GUARD))
        if i in range(10, 600) or i in range(calls - 600, calls):
            # the command is the texture pre-equalized: compare after the actuator model
            key = "first" if i < 600 else "last"
            errs.setdefault(key, []).append((t, y))
    out = {}
    for key, parts in errs.items():
        t = np.concatenate([p[0] for p in parts])
        y = np.concatenate([p[1] for p in parts])
        ideal = ev.series(hand.position_mm(t), 50.0)
        out[key] = np.sqrt(np.mean((y - ideal) ** 2)) / np.sqrt(np.mean(ideal**2))
    assert r.position.counts > 4e8  # it really travelled ~180 m
    assert out["last"] <= 1.05 * out["first"] + 1e-3
    assert r.out.nonfinite == 0


def test_equalizer_state_decays_to_exact_zero_not_subnormals():
    eq = Equalizer()
    eq(np.full(3000, 20.0))
    for _ in range(20000):  # 20 s of 3-sample silence through the scalar path
        y = eq(np.zeros(3))
    assert np.all(eq.zi == 0.0)
    assert np.all(y == 0.0)


def test_scalar_and_vector_equalizer_paths_agree(rng):
    x = rng.normal(0, 10, 3000)
    a, b = Equalizer(), Equalizer()
    ya = a(x)  # one sosfilt call
    yb = np.concatenate([b(x[i : i + 3]) for i in range(0, x.size, 3)])  # scalar path
    assert np.max(np.abs(ya - yb)) <= 1e-9 * np.max(np.abs(ya))


def test_float32_keeps_phase_far_from_the_origin(wood):
    ev64 = HeightEvaluator(*wood)
    ev32 = HeightEvaluator(*wood, dtype=np.float32)
    x = 180_000.0 + np.linspace(0, 10, 2001)  # 180 m along, as after an hour at 50 mm/s
    ref = ev64.series(x, 50.0)
    err = np.sqrt(np.mean((ev32.series(x, 50.0) - ref) ** 2)) / np.sqrt(np.mean(ref**2))
    assert err <= 1e-4


def test_actuator_fit_recovers_a_known_model():
    true = ActuatorModel(corner_hz=310.0, damping=0.55, dc_gain=0.97, delay_s=60e-6)
    f = np.geomspace(10, 800, 25)
    h = true.response(f)
    fit = ActuatorModel.fit_table(f, 20 * np.log10(np.abs(h)), np.rad2deg(np.unwrap(np.angle(h))))
    assert fit.corner_hz == pytest.approx(310.0, rel=1e-3)
    assert fit.damping == pytest.approx(0.55, rel=1e-3)
    assert fit.dc_gain == pytest.approx(0.97, rel=1e-3)
    assert fit.delay_s == pytest.approx(60e-6, abs=1e-6)


def test_shipped_actuators_load_and_equalize_flat_within_1_db():
    names = sorted(p.stem for p in actuators_dir().glob("*.toml"))
    assert {"paper-parametric", "example-measured"} <= set(names)
    for name in names:
        model = load_actuator(actuators_dir() / f"{name}.toml")
        lo, hi = Equalizer(model).flatness_db(10, 400)  # against the measured table if any
        assert -1.0 <= lo and hi <= 1.0, (name, lo, hi)


@pytest.mark.parametrize("text, msg", [
    ("[model]\ncorner_hz = 270\nbogus = 1\n", "model.bogus"),
    ("[model]\ncorner_hz = -5\n", "corner_hz"),
    ("[response]\nhz = [1, 2, 3, 4]\ngain_db = [0, 0, 0, 0]\n", "phase_deg"),
    ("[response]\nhz = [1, 2, 2, 4]\ngain_db = [0, 0, 0, 0]\nphase_deg = [0, 0, 0, 0]\n", "increasing"),
    ("colour = 3\n", "colour"),
    ("[model\n", "TOML"),
])
def test_bad_actuator_files_name_the_problem(tmp_path, text, msg):
    p = tmp_path / "a.toml"
    p.write_text(text)
    with pytest.raises(ValueError, match=msg):
        load_actuator(p)


def test_metronome_is_the_papers_protocol():
    h = Metronome()
    t = np.linspace(0, h.period_s, 24001)
    x = h.position_mm(t)
    assert h.period_s == pytest.approx(2.4)  # one beat forward, two back, 1.25 Hz
    assert x.min() == pytest.approx(0.0, abs=1e-9) and x.max() == pytest.approx(40.0, abs=1e-6)
    assert h.mean_forward_speed_mm_s == pytest.approx(50.0)
    v = h.velocity_mm_s(t)
    assert np.max(np.abs(np.gradient(x, t) - v)) <= 0.05  # velocity is the derivative
    assert abs(v[0]) <= 1e-9 and abs(h.velocity_mm_s(np.array([0.8]))[0]) <= 1e-9  # rest at reversals


def test_recorded_trajectory_interpolates_without_overshoot(tmp_path):
    p = tmp_path / "traj.csv"
    p.write_text("# time_s, position_mm\n0,0\n0.1,5\n0.2,5\n0.3,0\n")
    h = Recorded.from_csv(p)
    x = h.position_mm(np.linspace(0, 0.3, 301))
    assert x.min() >= -1e-12 and x.max() <= 5.0 + 1e-12
    bad = tmp_path / "bad.csv"
    bad.write_text("0,0\n0.1,1\n0.1,2\n")
    with pytest.raises(ValueError, match="increasing"):
        Recorded.from_csv(bad)


def test_closed_loop_error_is_small_with_defaults_and_large_without_prediction(wood):
    """The accuracy bench's physics in one assertion: prediction and the equalizer pay."""
    c, n, length = wood
    hand = Metronome()
    errs = {}
    for name, cfg in {"default": RenderConfig(), "no-predict": RenderConfig(predict=False)}.items():
        r = Renderer(c, n, length, cfg)
        res = chain.run_loop(r, hand, 2.4)
        got = chain.actuate(res.command_um, r.eq.model, FS)
        ideal = chain.reference(c, n, length, hand, res.t_play_s, r)
        k = res.t_play_s > 0.2
        errs[name] = np.sqrt(np.mean((got[k] - ideal[k]) ** 2)) / np.sqrt(np.mean(ideal[k] ** 2))
    assert errs["default"] <= 0.015
    assert errs["no-predict"] >= 20 * errs["default"]


def test_bench_accuracy_json_contract(capsys, tmp_path):
    png = tmp_path / "acc.png"
    assert main(["bench", "accuracy", "--json", "--duration", "0.6", "--repeats", "2", "--plot",
                 str(png)]) == 0
    rows = json.loads(capsys.readouterr().out)
    for r in rows:
        for key in ("knob", "setting", "default", "rms_error_um", "rms_error_pct", "cpu_ms_per_s",
                    "cpu_min_ms_per_s", "cpu_max_ms_per_s", "repeats", "fw_cpu_ms_per_s"):
            assert key in r
        assert np.isfinite(r["rms_error_um"])
        if r["knob"] == "render_at" and r["setting"] == "device":  # the host only supervises
            assert r["cpu_ms_per_s"] == 0 and r["fw_tick_p99_us"] > 0
            _check_firmware_cost(r)
        else:
            assert r["cpu_ms_per_s"] > 0 and r["fw_tick_p99_us"] is None
            assert r["repeats"] == 2 and all(len(v["cpu_runs_ms_per_s"]) == 2
                                             for v in r["per_texture"].values())
            assert r["cpu_min_ms_per_s"] <= r["cpu_ms_per_s"] <= r["cpu_max_ms_per_s"]
    knobs = {r["knob"] for r in rows}
    assert {"height_method", "dtype", "prediction", "equalizer", "samples_per_batch", "render_at"} <= knobs
    for k in knobs - {"table_oversample"}:
        assert sum(r["default"] for r in rows if r["knob"] == k) == 1, k
    # the daemon's default ([render] where = "auto") renders on a v2 display: the default row
    assert [r["setting"] for r in rows if r["knob"] == "render_at" and r["default"]] == ["device"]
    assert len(rows[0]["per_texture"]) == 3  # wood, sandpaper and the bundled real profile
    assert png.stat().st_size > 10_000


def _check_firmware_cost(row):
    """The device row's firmware cost is QEMU's instruction count (not 0): compared with the
    share of the 170 MHz core's 3 kHz period that bench_tick.elf itself prints."""
    import re
    import shutil
    import subprocess

    from hostd.device import hostport

    if not (shutil.which("qemu-system-arm") and shutil.which("arm-none-eabi-gcc")):
        assert row["fw_cpu_ms_per_s"] is None and "qemu" in row["fw_cost_source"]
        return
    out = subprocess.run(["make", "-s", "-C", str(hostport.FIRMWARE), "qemu-bench"],
                         capture_output=True, text=True, timeout=600, check=True).stdout
    pct = float(re.search(r"N'=512, 4 sections \(mean\):.*= *([0-9.]+) %", out).group(1))
    assert row["fw_cpu_ms_per_s"] / 10.0 == pytest.approx(pct, abs=0.01)  # ms per s -> % of a core
    assert row["fw_insn_per_tick"] > 1000 and row["fw_insn_per_tick_max"] >= row["fw_insn_per_tick"]


def test_bench_pipeline_reports_percentiles(capsys):
    assert main(["bench", "pipeline", "--json", "--duration", "1"]) == 0
    row = json.loads(capsys.readouterr().out)["rows"][0]
    assert row["batches"] == 1000
    assert 0 < row["cpu_p50_us"] <= row["cpu_p99_us"] <= row["cpu_p999_us"] <= row["cpu_max_us"]
