"""The public API: the worked example in docs/api.md runs as written; hostd render writes a WAV."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hostd import api

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def test_the_worked_example_in_docs_api_md_runs(capsys):
    pytest.importorskip("pandas")
    code = re.search(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S).group(1)
    exec(compile(code, str(DOC), "exec"), {})
    out = capsys.readouterr().out
    assert "20000 10.0" in out and "Iobj" in out


def test_render_stroke_matches_the_direct_series_and_is_full_band_at_v_ref():
    prof = api.load_profile("synthetic:sandpaper:2")
    s = api.decode(api.encode(prof, method="quant", levels=10)["stream"])
    out = api.render_stroke(s, speed_mm_s=50.0, seconds=0.05, rate_hz=3000.0, x0_mm=1.0)
    k = np.arange(1, s.n_keep + 1)
    theta = (out["x_mm"] / (s.length_mm / s.n) + 0.5) * np.pi / s.n
    want = np.cos(np.multiply.outer(theta, k)) @ s.coefficients  # every gain is 1 at v_ref
    assert np.allclose(out["height_um"], want, atol=1e-9)
    assert out["t_s"].size == 150


def test_fit_accepts_columns_and_records():
    rng = np.random.default_rng(0)
    ip, ia = rng.uniform(0, 1, 12), rng.uniform(0, 1, 12)
    score = 0.6 * ip + 0.4 * ia
    cols = api.fit({"Ip": ip, "Ia": ia, "score": score}, n_boot=0)
    assert cols["a"] == pytest.approx(0.6) and cols["b"] == pytest.approx(0.4)
    recs = api.fit([{"Ip": x, "Ia": y, "score": z} for x, y, z in zip(ip, ia, score, strict=True)],
                   n_boot=0)
    assert recs["a"] == pytest.approx(cols["a"])


def test_hostd_render_writes_a_wav_scaled_to_the_full_scale(tmp_path):
    import scipy.io.wavfile

    vtx = tmp_path / "w.vtx"
    vtx.write_bytes(api.encode(api.load_profile("synthetic:wood:1"), method="quant", levels=14)["stream"])
    wav = tmp_path / "w.wav"
    p = subprocess.run([sys.executable, "-m", "hostd", "render", str(vtx), "--speed-mm-s", "50",
                        "--seconds", "0.5", "--rate-hz", "8000", "-o", str(wav), "--json"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout)
    rate, data = scipy.io.wavfile.read(wav)
    assert rate == 8000 and data.dtype == np.int16 and data.size == 4000
    h = api.render_stroke(api.decode(vtx), speed_mm_s=50, seconds=0.5, rate_hz=8000)["height_um"]
    assert np.array_equal(data, np.round(h / 40.0 * 32767).astype(np.int16))
    assert info["clipped"] == 0 and info["peak_um"] == pytest.approx(np.abs(h).max())
    p = subprocess.run([sys.executable, "-m", "hostd", "render", str(vtx), "-o", str(wav),
                        "--seconds", "0.1", "--full-scale-um", "1"], capture_output=True, text=True)
    assert p.returncode == 0 and p.stderr.count("clipped") == 1
