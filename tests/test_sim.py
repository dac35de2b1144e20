"""Scenes: only the named effects exist; the ideal chain delivers the codec's quality; each
effect changes delivered quality in the expected direction; bad scenes name the field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hostd.cli import main
from hostd.errors import ConfigError
from hostd.paths import scenes_dir
from hostd.sim import effects as fx
from hostd.sim import scene

SHIPPED = ("ideal", "paper-experiment", "usb-jitter", "clock-drift", "worst-case")


def write_scene(tmp_path: Path, effects: str = "", hand: str = 'model = "metronome"',
                duration: float = 1.6, extra: str = "") -> Path:
    p = tmp_path / "s.toml"
    p.write_text(f'name = "t"\nduration_s = {duration}\nseed = 5\n{extra}[texture]\n'
                 f'profile = "synthetic:wood:1"\nlevels = 14\n[hand]\n{hand}\n{effects}')
    return p


def test_shipped_scenes_load():
    for name in SHIPPED:
        sc = scene.load(scenes_dir() / f"{name}.toml")
        assert sc.name == name


def test_ideal_scene_delivers_the_codec_only_iobj():
    r = scene.run(scene.load(scenes_dir() / "ideal.toml"))
    assert abs(r["Iobj"] - r["codec_iobj"]) <= 1e-6
    assert r["rms_error_um"] <= 1e-6 * r["rms_texture_um"]
    assert r["closed_loop"] is False


def test_an_effect_the_scene_does_not_name_is_never_constructed(tmp_path, monkeypatch):
    def forbidden(name):
        class Forbidden(fx.Effect):
            def __init__(self, *a, **k):
                raise AssertionError(f"effect {name} was constructed")

            def __getattr__(self, attr):
                raise AssertionError(f"effect {name} was called")
        return Forbidden

    for name in fx.REGISTRY:
        if name != "dac":
            monkeypatch.setitem(fx.REGISTRY, name, forbidden(name))
    r = scene.run(scene.load(write_scene(tmp_path, "[effects.dac]\n")))
    assert r["effects"] == ["dac"] and np.isfinite(r["Iobj"])
    r0 = scene.run(scene.load(write_scene(tmp_path, "")))  # no effects at all
    assert r0["effects"] == [] and not r0["closed_loop"]


def _change(tmp_path, effects: str) -> dict:
    sc = scene.load(write_scene(tmp_path, effects))
    base = scene.run(sc, [])
    r = scene.run(sc)
    r["spec"] = float(np.sqrt(np.mean((r["_trace"]["fit"][1:] - base["_trace"]["fit"][1:]) ** 2)))
    r["base"] = base
    return r


def test_each_effect_worsens_delivered_quality_in_the_expected_direction(tmp_path):
    # the encoder: quantization, then noise on top, hurt more and more
    q = _change(tmp_path, "[effects.encoder]\nresolution_um = 0.4\n")
    qn = _change(tmp_path, "[effects.encoder]\nresolution_um = 0.4\nnoise_counts = 3.0\n")
    assert 0 < q["spec"] < qn["spec"]
    assert qn["rms_error_um"] > q["base"]["rms_error_um"]
    # transport: a longer and jittery link costs more
    t1 = _change(tmp_path, "[effects.transport]\nlatency_ms = 1.0\nbuffer_ms = 3.0\n")
    t8 = _change(tmp_path, "[effects.transport]\nlatency_ms = 8.0\njitter_ms = 3.0\nbuffer_ms = 12.0\n")
    assert 0 < t1["spec"] < t8["spec"]
    assert t8["latency_ms"] > t1["latency_ms"]
    # clock drift: more ppm, more change
    d1 = _change(tmp_path, "[effects.clock_drift]\nppm = 500.0\n")
    d2 = _change(tmp_path, "[effects.clock_drift]\nppm = 20000.0\n")
    assert 0 < d1["spec"] < d2["spec"]
    # CPU stalls longer than the device's buffer: underruns, and the texture suffers
    c = _change(tmp_path, "[effects.cpu_load]\nstall_prob = 0.01\nstall_ms = 10.0\n")
    assert c["underruns"] > 0 and c["rms_error_um"] > c["base"]["rms_error_um"]
    # the DAC: a tiny but real quantization
    dac = _change(tmp_path, "[effects.dac]\n")
    assert 0 < dac["spec"] < 1e-3
    # finger load: the displacement drops by 1/(1 + r)
    f = _change(tmp_path, "[effects.finger_load]\nstiffness_ratio = 0.25\n")
    rms = lambda r: np.sqrt(np.mean(r["_trace"]["delivered"] ** 2))  # noqa: E731
    ratio = rms(f) / rms(f["base"])
    assert 0.7 < ratio < 0.82
    assert f["Iobj"] > f["base"]["Iobj"]
    # the actuator, equalized by the host: a change, but a small one (the equalizer works)
    a = _change(tmp_path, "[effects.actuator]\n")
    assert 0 < a["spec"] < 0.1 * f["spec"]


@pytest.mark.parametrize("effects, extra, needle", [
    ("[effects.wobble]\n", "", "effects.wobble"),
    ("[effects.encoder]\nresolution = 0.4\n", "", "'resolution'"),
    ("[effects.transport]\nlatency_ms = -1\n", "", "effects.transport.latency_ms"),
    ("", "colour = 1\n", "'colour'"),
    ("", "", "hand.model"),
])
def test_bad_scene_fields_give_one_line_naming_the_field(tmp_path, capsys, effects, extra, needle):
    hand = 'model = "teleport"' if needle == "hand.model" else 'model = "metronome"'
    p = write_scene(tmp_path, effects, hand=hand, extra=extra)
    with pytest.raises(ConfigError):
        scene.load(p)
    assert main(["sim", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err and "Traceback" not in err


def test_sim_cli_json_and_plots(tmp_path, capsys):
    p = write_scene(tmp_path, "[effects.encoder]\n[effects.dac]\n")
    assert main(["sim", str(p), "--json", "--plot", str(tmp_path / "plots")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["effects"] for r in out["runs"]] == [[], ["encoder"], ["dac"], ["encoder", "dac"]]
    for r in out["runs"]:
        for k in ("Ip", "Ia", "Iobj", "rms_error_um", "underruns", "latency_ms"):
            assert k in r and np.isfinite(r[k])
    assert len(out["plots"]) == 2 and all(Path(x).stat().st_size > 5000 for x in out["plots"])


def test_a_hand_at_the_reference_speed_feels_every_kept_component(tmp_path):
    """Issue 16: at v_ref = 50 mm/s with no effect the renderer plays the whole coded band, so
    the delivered Iobj is the stream's (before: 0.2674 against 0.2769, 8 % RMS error)."""
    r = scene.run(scene.load(write_scene(tmp_path, hand='model = "constant"\nspeed_mm_s = 50.0',
                                         duration=1.0)))
    assert abs(r["Iobj"] - r["codec_iobj"]) <= 1e-6
    assert r["rms_error_um"] <= 1e-6 * r["rms_texture_um"]


def test_series_transforms_match_the_direct_sums():
    from hostd.render import series

    rng = np.random.default_rng(4)
    n, length, K = 20000, 10.0, 200
    c = rng.normal(0, 1, K + 1)
    x = np.cumsum(np.abs(rng.normal(0.02, 0.01, 3000)))  # a hand wandering over many periods
    th = series.phase_rad(x, n, length)
    basis = np.cos(np.multiply.outer(th, np.arange(K + 1)))
    assert np.allclose(series.evaluate(c, th, k0=0), basis @ c, rtol=0, atol=1e-10)
    y = basis @ c + rng.normal(0, 0.1, th.size)
    want = np.linalg.lstsq(basis, y, rcond=None)[0]
    assert np.allclose(series.project(th, y, K), want, rtol=0, atol=1e-9)
    m = np.arange(500)
    th_u = series.phase_rad(0.0, n, length) + m * 0.0123
    assert np.allclose(series.evaluate_uniform(c[1:], float(th_u[0]), 0.0123, 500),
                       np.cos(np.multiply.outer(th_u, np.arange(1, K + 1))) @ c[1:], atol=1e-9)


def test_threshold_crossings_and_band_limited_intended(tmp_path):
    f = np.array([10.0, 20.0, 30.0, 40.0])
    err = np.array([0.1, 0.3, 0.3, 0.1])
    b = np.full(4, 0.2)
    assert np.allclose(scene.threshold_crossings(f, err, b), [15.0, 35.0])
    res = scene.report(scene.load(write_scene(tmp_path, "[effects.dac]\n", duration=1.0)), progress=False)
    tr = res["runs"][0]["_trace"]
    sl = slice(0, 600)
    # the no-effect chain delivers the band-limited texture, not the full-band one
    assert np.allclose(scene.band_limited(tr, sl), tr["delivered"][sl], atol=1e-6)
    paths = scene.plot(res, tmp_path / "plots")
    assert all(p.stat().st_size > 10_000 for p in paths)
