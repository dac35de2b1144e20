"""The CLI contract: commands, JSON fields, exit codes and one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from hostd.codec import transform
from tests.conftest import real_profile_path


def run(*args, check=True):
    p = subprocess.run([sys.executable, "-m", "hostd", *args], capture_output=True, text=True,
                       timeout=120)
    if check:
        assert p.returncode == 0, p.stderr
    return p


@pytest.fixture(scope="module")
def wood_csv(tmp_path_factory):
    from hostd.texture import synth

    d = tmp_path_factory.mktemp("cli")
    prof = synth.wood(seed=7)
    x_mm = np.arange(prof.n) * prof.spacing_um / 1000
    path = d / "wood.csv"
    np.savetxt(path, np.column_stack([x_mm, prof.heights_um]), delimiter=",",
               header="x_mm,height_um")
    return path, prof


def test_encode_inspect_decode_iobj(tmp_path, wood_csv):
    path, _prof = wood_csv
    out = tmp_path / "w.vtx"
    run("encode", str(path), "-o", str(out), "--method", "quant", "--levels", "14",
        "--x-unit", "mm")
    info = json.loads(run("inspect", str(out), "--json").stdout)
    for key in ("n", "length_mm", "speed_mm_s", "fmax_hz", "n_keep", "method", "levels",
                "threshold_id", "bytes", "ratio_coeffs", "ratio_profile", "ref_P", "ref_A",
                "coefficients"):
        assert key in info, key
    assert info["n"] == 20000 and info["n_keep"] == 160 and len(info["coefficients"]) == 160
    assert info["bytes"] == out.stat().st_size
    rec = tmp_path / "r.csv"
    run("decode", str(out), "-o", str(rec))
    y = np.loadtxt(rec)
    assert y.size == 20000
    want = transform.synthesize(np.array(info["coefficients"]), 20000)
    assert np.max(np.abs(y - want)) <= 1e-12 * np.max(np.abs(want))
    alone = json.loads(run("iobj", str(out), "--json").stdout)
    both = json.loads(run("iobj", str(path), str(out), "--json", "--x-unit", "mm").stdout)
    for key in ("P_prime", "A_prime", "a", "b"):
        assert alone[key] == pytest.approx(both[key], rel=1e-12), key
    # a v2 header (the default) keeps P and A to 17 significant bits
    for key in ("P", "A"):
        assert alone[key] == pytest.approx(both[key], rel=2.0**-17), key
    for key in ("Ip", "Ia", "Iobj"):
        assert alone[key] == pytest.approx(both[key], abs=1e-4), key
    assert alone["a"] == 0.581 and alone["b"] == 0.464
    assert "peer_note" in alone
    assert ("st_sim" in both and 0 <= both["spqi"] <= 1) or "peer_note" in both


def test_cut_and_target_iobj(tmp_path, wood_csv):
    path, _ = wood_csv
    out = tmp_path / "c.vtx"
    run("encode", str(path), "-o", str(out), "--method", "cut", "--b0-db", "-4", "--x-unit", "mm")
    info = json.loads(run("inspect", str(out), "--json").stdout)
    assert info["method"] == "cut" and info["b0_db"] == -4.0
    p = run("encode", str(path), "-o", str(out), "--target-iobj", "0.1", "--x-unit", "mm")
    assert "chose" in p.stderr
    assert json.loads(run("iobj", str(out), "--json").stdout)["Iobj"] <= 0.1


def test_real_dektak_file_encodes_from_the_cli(tmp_path):
    src = real_profile_path("dektak-1.csv")
    out = tmp_path / "d.vtx"
    run("encode", str(src), "-o", str(out), "--method", "quant", "--levels", "8")
    info = json.loads(run("inspect", str(out), "--json").stdout)
    assert info["n"] == 9600 and abs(info["length_mm"] - 1.5) < 1e-3


@pytest.mark.parametrize("args,msg", [
    (["encode", "/no/such.csv", "-o", "/tmp/x.vtx", "--method", "quant", "--levels", "4"],
     "no such profile"),
    (["encode", "synthetic:wood", "-o", "/tmp/x.vtx", "--method", "quant", "--levels", "1"],
     ">= 2"),
    (["encode", "synthetic:wood", "-o", "/tmp/x.vtx", "--method", "quant"], "--levels"),
    (["encode", "synthetic:wood", "-o", "/tmp/x.vtx", "--method", "cut", "--fmax-hz", "1e6",
      "--b0-db", "0"], "N' must be < N"),
    (["inspect", "/no/such.vtx"], "no such stream file: /no/such.vtx"),
    (["encode", "synthetic:marble", "-o", "/tmp/x.vtx", "--method", "quant", "--levels", "4"],
     "unknown synthetic"),
])
def test_user_mistakes_exit_2_with_one_line_and_no_traceback(args, msg):
    p = run(*args, check=False)
    assert p.returncode == 2
    assert msg in p.stderr
    assert "Traceback" not in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1


def test_corrupt_stream_exit_2(tmp_path):
    from tests.conftest import VECTORS

    data = bytearray((VECTORS / "quant_l14_deflate.vtx").read_bytes())
    data[90] ^= 0x10
    bad = tmp_path / "bad.vtx"
    bad.write_bytes(bytes(data))
    for cmd in (["inspect", str(bad)], ["decode", str(bad)], ["iobj", str(bad)]):
        p = run(*cmd, check=False)
        assert p.returncode == 2 and "Traceback" not in p.stderr and "CRC" in p.stderr


def test_nan_in_profile_file_refused(tmp_path):
    p = tmp_path / "nan.csv"
    p.write_text("0,1\n1,nan\n2,3\n")
    r = run("encode", str(p), "-o", str(tmp_path / "o.vtx"), "--method", "quant", "--levels",
            "4", check=False)
    assert r.returncode == 2 and "NaN" in r.stderr


def test_fit_command(tmp_path):
    rng = np.random.default_rng(1)
    lines = ["texture,method,level,score,Ip,Ia"]
    for i in range(12):
        ip, ia = rng.uniform(0, 1, 2)
        lines.append(f"wood,quant,{i},{0.6 * ip + 0.5 * ia:.6f},{ip:.6f},{ia:.6f}")
    (tmp_path / "s.csv").write_text("\n".join(lines) + "\n")
    out = json.loads(run("fit", str(tmp_path / "s.csv"), "--json").stdout)
    assert out["a"] == pytest.approx(0.6, abs=1e-4) and out["b"] == pytest.approx(0.5, abs=1e-4)
    assert set(out["metrics"]) == {"Iobj", "Ip", "Ia"}
