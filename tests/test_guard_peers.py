"""The waveform guard's second criterion (sSNR) and the peer-codec runner of the codec bench."""

from __future__ import annotations

import math
import stat
import sys
from pathlib import Path

import numpy as np
import pytest

from hostd.codec import ratecontrol, transform
from hostd.codec import stream as vtx
from hostd.errors import HostdError
from hostd.perception import guard, peer, thresholds

CURVE = thresholds.default_curve()


def test_spqi_curve_weights_follow_the_spqi_models_threshold():
    # T(0) = 62 - 77 = -15 dB, minimum -77 dB at 250 Hz, held at 0 dB above its zero crossing
    t = -10.0 * np.log10(guard.spqi_curve_weights(np.array([0.0, 250.0, 40.0, 4000.0])))
    assert t[0] == pytest.approx(-15.0, abs=1e-9)
    assert t[1] == pytest.approx(-77.0, abs=1e-9)
    assert -77.0 < t[2] < -15.0 and t[3] == pytest.approx(0.0, abs=1e-9)
    try:
        from vibromaf.signal.perception import PerceptualThreshold
    except ImportError:
        return
    grid = np.linspace(0, 8000, 1024)[:512]  # vibromaf's own grid for 512-sample blocks
    ref = PerceptualThreshold(8000).calculate(512)
    low = ref < 0  # below its zero crossing (~800 Hz); above it vibromaf holds its first grid value
    mine = -10.0 * np.log10(guard.spqi_curve_weights(grid[low]))
    np.testing.assert_allclose(mine, ref[low], atol=1e-9)


def test_check_decides_like_the_db_values_and_reports_both():
    rng = np.random.default_rng(3)
    f = np.arange(1, 41) * 5.0
    b = CURVE(f)
    c = rng.normal(size=40) * b * 10
    for scale in (1e-3, 3e-2, 0.1, 0.3):
        d = c + rng.normal(size=40) * b * scale
        v = guard.check(c, d, b, f, 25.0, 27.0)
        # the definitions, written out (docs/conventions.md): power over error power, weighted by
        # 1/b^2 (wSNR) and by the SPQI curve's power weights (sSNR, checked against vibromaf above)
        w = guard.spqi_curve_weights(f)
        assert v.wsnr_db == pytest.approx(10 * np.log10(np.sum((c / b) ** 2) / np.sum(((c - d) / b) ** 2)))
        assert v.ssnr_db == pytest.approx(10 * np.log10(np.sum(w * c**2) / np.sum(w * (c - d) ** 2)))
        if abs(v.wsnr_db - 25) > 1e-6 and abs(v.ssnr_db - 27) > 1e-6:
            assert v.passed == (v.wsnr_db >= 25 and v.ssnr_db >= 27)
    assert guard.check(c, c, b, f).passed and guard.check(c, c, b, f).ssnr_db == guard.CAP_DB
    # a sign error keeps every power and fails both SNRs
    v = guard.check(c, -c, b, f)
    assert not v.passed and v.wsnr_db < 0 and v.ssnr_db < 0


def _real_profile():
    from hostd.texture.load import bundled_profile

    prof = bundled_profile()
    if prof is None:
        pytest.skip("the bundled real profile is not installed")
    return prof


def test_the_default_guard_rejects_what_wsnr_alone_accepts_on_a_real_profile():
    """The bundled dektak-1 profile at 25 mm/s, the proxy floors as explicit criteria (rate
    control's default certifies SPQI itself): wSNR >= 25 dB alone accepts a stream whose sSNR
    is < 27 dB (SPQI 0.894 measured); both floors do not."""
    prof = _real_profile()
    geom = transform.Geometry(prof.n, prof.length_mm, speed_mm_s=25.0)
    old = ratecontrol.search(prof.heights_um, geom, CURVE, 0.05, method="shaped", spqi_min=None,
                             guard_db=guard.DEFAULT_GUARD_DB)
    new = ratecontrol.search(prof.heights_um, geom, CURVE, 0.05, spqi_min=None,
                             guard_db=guard.DEFAULT_GUARD_DB, ssnr_db=guard.DEFAULT_SSNR_DB)
    assert old.best.wsnr_db >= 25.0 and old.best.ssnr_db < guard.DEFAULT_SSNR_DB
    assert new.best.wsnr_db >= 25.0 and new.best.ssnr_db >= guard.DEFAULT_SSNR_DB
    s = vtx.decode(new.best.data)
    c = transform.analyze(prof.heights_um, s.n_keep)
    # the sSNR reported is the one measured on what the receiver decodes
    assert guard.spectral_snr_db(c, s.coefficients, s.frequencies_hz) == pytest.approx(new.best.ssnr_db)
    if peer.available():
        sp_new = peer.peer_scores(c, s.coefficients, s.n, s.length_mm, s.speed_mm_s)["spqi"]
        so = vtx.decode(old.best.data)
        sp_old = peer.peer_scores(c, so.coefficients, so.n, so.length_mm, so.speed_mm_s)["spqi"]
        assert sp_new >= 0.9 > sp_old


# ---------------------------------------------------------------- the peer runner

def _fake_vcpwq(tmp_path: Path) -> Path:
    """An executable with VC-PWQ's command line that 'codes' losslessly: it copies the WAV."""
    exe = tmp_path / "VC_PWQ"
    exe.write_text(f"""#!{sys.executable}
import shutil, sys
a = sys.argv[1:]
opt = dict(zip(a[::2], a[1::2]))
b = opt["-b"]
import os
for d in (opt["-c"], opt["-o"]):
    os.makedirs(d, exist_ok=True)
shutil.copy(os.path.join(opt["-i"], "sig.wav"), os.path.join(opt["-o"], f"sig_{{b}}.wav"))
open(os.path.join(opt["-c"], f"sig_{{b}}.binary"), "wb").write(bytes(int(b)))
""")
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    return exe


def _texture():
    from hostd.bench import peers
    from hostd.texture import synth

    p = synth.make("wood", seed=1)
    geom = transform.Geometry(p.n, p.length_mm)
    c = transform.analyze(p.heights_um, geom.n_keep)
    return peers.Texture("wood:1", c, p.n, p.length_mm, geom.speed_mm_s, CURVE(geom.frequencies_hz()))


def test_peer_runner_scores_a_lossless_codec_as_lossless(tmp_path):
    from hostd.bench import peers

    t = _texture()
    r = peers.run_peer(peers.vcpwq(_fake_vcpwq(tmp_path)), t, 7, tmp_path)
    assert r["bytes"] == 7 + 4  # the file the encoder wrote + the float32 scale factor (side info)
    # float32 WAV round trip only: Iobj ~ 0, wSNR ~ float32 precision
    assert r["Iobj"] < 1e-5 and r["wsnr_db"] > 100
    if peer.available():
        assert r["spqi"] > 0.999


def test_peer_runner_fails_with_a_clear_message_on_a_missing_executable(tmp_path, monkeypatch):
    from hostd.bench import peers
    from hostd.texture import hjif

    monkeypatch.setattr(hjif, "rm_dir", lambda: None)  # nor the reference software's build cache
    codec = peers.vcpwq(tmp_path / "no-such-VC_PWQ")
    with pytest.raises(peers.PeerError, match=r"binary missing: .*no-such-VC_PWQ; set HOSTD_PEER_VCPWQ"):
        peers.run_peer(codec, _texture(), 8, tmp_path)
    assert issubclass(peers.PeerError, HostdError)  # the CLI prints one line, exit 2
    found, notes = peers.find(tmp_path)
    assert found == [] and len(notes) == 2
    assert "HOSTD_PEER_VCPWQ" in notes[0] and "not run" in notes[0]
    assert "HOSTD_PEER_MPEG_ENCODER" in notes[1]


def test_bench_codec_peers_with_a_missing_directory_exits_2(tmp_path, capsys):
    from hostd.cli import main

    assert main(["bench", "codec", "--peers", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such directory" in err[0]


def test_traverse_projection_recovers_the_coefficients():
    from hostd.bench import peers

    t = _texture()
    c = peers.coefficients_from_signal(t, peers.traverse_signal(t))
    assert np.max(np.abs(c - t.coeffs_um)) <= 1e-9 * np.max(np.abs(t.coeffs_um))
    assert math.isclose(peers.score(t, c)["Iobj"], 0.0, abs_tol=1e-12)
