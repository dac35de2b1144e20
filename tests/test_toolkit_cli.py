"""Issue 16: the command line and the loader as a researcher uses them."""

import json
import subprocess
import sys

import numpy as np
import pytest

from hostd.cli import main
from hostd.errors import ProfileError
from hostd.texture import synth
from hostd.texture.load import LoadOptions, load_profile, read_columns


def run(*args):
    return subprocess.run([sys.executable, "-m", "hostd", *args], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def wood_vtx(tmp_path_factory):
    out = tmp_path_factory.mktemp("tk") / "wood1.vtx"
    assert main(["encode", "synthetic:wood:1", "-o", str(out), "--method", "quant", "--levels", "14"]) == 0
    return out


def test_options_between_positionals(wood_vtx):
    p = run("iobj", "synthetic:wood:1", "--length-mm", "10", str(wood_vtx), "--json")
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["reference"] == "profile" and out["reference_mismatch"] is False
    assert "warning" not in p.stderr


def test_reference_mismatch_is_flagged_and_warned(wood_vtx):
    p = run("iobj", "synthetic:wood:2", str(wood_vtx), "--json")
    assert p.returncode == 0
    assert json.loads(p.stdout)["reference_mismatch"] is True
    assert p.stderr.count("not this stream's original") == 1


@pytest.mark.parametrize("args,msg", [
    (["encode", "synthetic:wood:-1", "-o", "/tmp/x.vtx", "--method", "quant", "--levels", "4"], ">= 0"),
    (["encode", "synthetic:wood:x", "-o", "/tmp/x.vtx"], "bad seed"),
    (["encode", "synthetic:wood:1"], "--output"),
    (["iobj", "--bogus", "a.vtx"], "unrecognized"),
    (["encode", "synthetic:wood:1", "-o", "/tmp/x.vtx", "--method", "quant", "--levels", "4",
      "--ref-speed-mm-s", "9000"], "--x-unit"),
])
def test_mistakes_are_one_line_with_a_hint(args, msg):
    p = run(*args)
    assert p.returncode == 2
    assert "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert msg in p.stderr


def test_bench_all_runs_pipeline_codec_and_scoring(monkeypatch, capsys):
    """`hostd bench all` runs them; `hostd bench` alone shows the help and exits 2 (tests/test_hints.py)."""
    from hostd.bench import codec2, micro, pipeline

    monkeypatch.setattr(pipeline, "run", lambda d: {"bench": "pipeline"})
    monkeypatch.setattr(micro, "bench_codec", lambda step: [{"bench": "codec"}])
    monkeypatch.setattr(codec2, "time_rows", lambda: [])
    monkeypatch.setattr(codec2, "rate_rows", lambda step: [])
    monkeypatch.setattr(micro, "bench_scoring", lambda: [{"bench": "scoring"}])
    assert main(["bench", "all"]) == 0
    out = capsys.readouterr().out
    assert "bench=pipeline" in out and "bench=codec" in out and "bench=scoring" in out


def test_ignored_options_warn_once(tmp_path):
    out = str(tmp_path / "o.vtx")
    p = run("encode", "synthetic:wood:1", "-o", out, "--method", "quant", "--levels", "8", "--b0-db", "3",
            "--x-unit", "mm", "--spacing", "2", "--json")
    assert p.returncode == 0, p.stderr
    assert p.stderr.count("--b0-db is ignored with --method quant") == 1
    assert p.stderr.count("--spacing, --x-unit ignored for synthetic:wood:1") == 1
    info = json.loads(p.stdout)
    assert info["method"] == "quant" and info["levels"] == 8 and info["bytes"] > 0
    assert 0 < info["Iobj"] < 1 and info["kept"] > 0


def test_wrong_y_unit_leaving_nothing_kept_warns(tmp_path):
    prof = synth.wood(seed=3)
    f = tmp_path / "w.csv"
    np.savetxt(f, np.column_stack([np.arange(prof.n) * 0.5, prof.heights_um]), delimiter=",")
    p = run("encode", str(f), "-o", str(tmp_path / "o.vtx"), "--method", "cut", "--b0-db", "0",
            "--y-unit", "nm", "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["kept"] == 0
    assert p.stderr.count("keeps no component") == 1 and "--y-unit" in p.stderr


def test_loader_matches_loadtxt_and_skips_a_preamble(tmp_path):
    rng = np.random.default_rng(0)
    data = np.column_stack([np.arange(5000) * 0.25, rng.normal(0, 2, 5000)])
    f = tmp_path / "p.csv"
    np.savetxt(f, data, delimiter=",", header="Instrument X\nScan,1\nx,y", comments="")
    got = read_columns(f)
    assert np.array_equal(got, np.loadtxt(f, delimiter=",", skiprows=3))
    # a patch of a long file stops early but gives the same patch as the whole file
    a = load_profile(f, LoadOptions(length_mm=0.1))
    b = load_profile(f, LoadOptions(length_mm=None))
    assert a.n == 400 and np.array_equal(a.heights_um, b.heights_um[:400])


def test_columns_and_decimal_comma(tmp_path):
    f = tmp_path / "c.txt"
    f.write_text("t;x;h\n" + "".join(f"{i};{str(i * 0.5).replace('.', ',')};"
                                     f"{str((-1) ** i * 1.25).replace('.', ',')}\n" for i in range(50)))
    arr = read_columns(f, columns=(1, 2), decimal_comma=True)
    assert arr.shape == (50, 2) and arr[3, 0] == 1.5 and arr[3, 1] == -1.25
    p = load_profile(f, LoadOptions(columns=(1, 2), decimal_comma=True, length_mm=None))
    assert p.spacing_um == 0.5 and p.n == 50
    with pytest.raises(ProfileError, match="--columns"):
        read_columns(f)  # three numeric columns once commas are decimals: ask which


def test_complex_npy_one_sample_and_nan_lines(tmp_path):
    f = tmp_path / "c.npy"
    np.save(f, np.ones(10) + 1j)
    with pytest.raises(ProfileError, match="complex"):
        load_profile(f, LoadOptions(spacing=1.0))
    one = tmp_path / "one.csv"
    one.write_text("0.0,1.0\n")
    p = run("encode", str(one), "-o", str(tmp_path / "o.vtx"), "--method", "quant", "--levels", "4")
    assert p.returncode == 2 and "at least 2" in p.stderr and "offset" not in p.stderr
    nan = tmp_path / "nan.csv"
    nan.write_text("# x,y\n0,1\n1,2\n2,nan\n3,4\n4,inf\n")
    with pytest.raises(ProfileError, match=r"lines 4, 6"):
        load_profile(nan, LoadOptions(length_mm=None))


def test_huge_file_is_refused_before_parsing_with_a_hint(tmp_path, monkeypatch):
    import hostd.texture.load as load

    f = tmp_path / "big.csv"
    np.savetxt(f, np.column_stack([np.arange(3000.0), np.zeros(3000)]), delimiter=",")
    monkeypatch.setattr(load, "MAX_ROWS", 1000)
    called = []
    monkeypatch.setattr(load, "_parse", lambda *a: called.append(1))
    with pytest.raises(ProfileError, match="--length-mm"):
        load_profile(f, LoadOptions(length_mm=None))
    assert not called  # refused from the size, before any parsing


def test_fit_reads_synthetic_profiles_refuses_off_scale_and_gives_intervals(tmp_path):
    rows = ["texture,method,level,score,stream,profile"]
    for lv, sc in ((4, 2.5), (6, 2.0), (8, 1.6), (12, 1.0), (16, 0.7)):
        out = tmp_path / f"q{lv}.vtx"
        assert main(["encode", "synthetic:wood:1", "-o", str(out), "--method", "quant", "--levels",
                     str(lv)]) == 0
        rows.append(f"wood,quant,{lv},{sc},{out.name},synthetic:wood:1")
    for b0, sc in ((-8, 0.4), (0, 1.1), (8, 2.2)):
        out = tmp_path / f"c{b0}.vtx"
        assert main(["encode", "synthetic:wood:1", "-o", str(out), "--method", "cut",
                     "--b0-db", str(b0)]) == 0
        rows.append(f"wood,cut,{b0},{sc},{out.name},synthetic:wood:1")
    f = tmp_path / "scores.csv"
    f.write_text("\n".join(rows) + "\n")
    p = run("fit", str(f), "--json", "--length-mm", "10")
    assert p.returncode == 0, p.stderr
    res = json.loads(p.stdout)
    assert res["n_used"] == 8 and res["se_a"] > 0 and res["se_b"] > 0
    assert res["ci_a"][0] <= res["a"] <= res["ci_a"][1]
    assert "fewer than 5 per parameter" in p.stderr and res["warnings"]
    text = run("fit", str(f)).stdout
    assert "+ -" not in text and ("Ip - " in text or "Ip + " in text)
    f.write_text("\n".join([*rows, "wood,quant,2,4.5,q4.vtx,synthetic:wood:1"]) + "\n")
    p = run("fit", str(f))
    assert p.returncode == 2 and "outside the rating scale" in p.stderr


def test_doctor_and_report_speak_json(tmp_path, capsys):
    main(["doctor", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert doc["problems"] == sum(c["status"] == "fail" for c in doc["checks"])
    assert {c["section"] for c in doc["checks"]} >= {"config", "device"}
    assert main(["report", "rate-quality", "synthetic:sandpaper:1", "--length-mm", "1", "-o",
                 str(tmp_path), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert len(rep["rows"]) > 50 and all(np.isfinite(r["Iobj"]) for r in rep["rows"])
    assert (tmp_path / "rate_quality.png").stat().st_size > 10_000
