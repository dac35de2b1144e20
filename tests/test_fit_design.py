"""`hostd fit` reads the paper's design: control rows (method none, empty stream cell), and the
indices spelt Ip/Ia or ip/ia (as `hostd quality --csv` once wrote them), from the CLI and the API."""

import csv
import io
import json

import pytest

from hostd import api
from hostd.cli import main
from hostd.errors import FitError
from hostd.perception import fit


def _design(tmp_path):
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
    rows += ["wood,none,,0.1,,synthetic:wood:1", "wood,none,,0.0,,"]  # the uncompressed controls
    f = tmp_path / "scores.csv"
    f.write_text("\n".join(rows) + "\n")
    return f


def test_cli_fit_takes_the_control_rows_of_the_papers_design(tmp_path, capsys):
    f = _design(tmp_path)
    capsys.readouterr()
    assert main(["fit", str(f), "--json", "--length-mm", "10", "--bootstrap", "0"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_used"] == 10  # 8 compressed + 2 controls at Ip = Ia = 0
    stim = fit.read_scores(f, lambda *_: (1.0, 1.0))
    assert [(s.Ip, s.Ia) for s in stim if s.method == "none"] == [(0.0, 0.0), (0.0, 0.0)]


def test_an_empty_stream_cell_outside_the_control_is_one_line(tmp_path, capsys):
    f = tmp_path / "s.csv"
    f.write_text("texture,method,level,score,stream\nwood,quant,4,1.0,\nwood,quant,8,0.5,x.vtx\n")
    assert main(["fit", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert "s.csv:2" in err and "no stream" in err and "\n" not in err and "directory" not in err


def test_api_fit_takes_controls_and_either_spelling():
    ip = [0.1, 0.3, 0.5, 0.9, 1.2, 0.2, 0.6, 1.0]
    ia = [0.4, 0.1, 0.8, 0.3, 0.9, 1.1, 0.5, 0.2]
    score = [0.6 * p + 0.4 * a for p, a in zip(ip, ia, strict=True)]
    recs = [{"method": "quant", "ip": p, "ia": a, "score": s} for p, a, s in zip(ip, ia, score, strict=True)]
    recs.append({"method": "none", "texture": "wood", "score": 0.0})  # control: no Ip, Ia
    res = api.fit(recs, n_boot=0)
    assert res["n_used"] == 9 and res["a"] == pytest.approx(0.6) and res["b"] == pytest.approx(0.4)
    cols = {"method": ["quant"] * 8 + ["none"], "Ip": [*ip, float("nan")], "Ia": [*ia, float("nan")],
            "score": [*score, 0.0]}  # pandas' missing value in a control row
    assert api.fit(cols, n_boot=0)["a"] == pytest.approx(0.6)
    with pytest.raises(FitError, match="record 0: no Ip and Ia"):
        api.fit([{"method": "quant", "score": 1.0}])
    with pytest.raises(FitError, match="no score"):
        api.fit([{"Ip": 1.0, "Ia": 1.0}])


def test_quality_csv_spells_ip_ia_iobj_and_fit_reads_it(tmp_path, capsys):
    from hostd.service import qualitylog

    db = tmp_path / "q.sqlite"
    con = qualitylog.connect(db)
    for i, (p, a) in enumerate(((0.1, 0.4), (0.3, 0.1), (0.5, 0.8), (0.9, 0.3))):
        qualitylog.insert(con, {"sha256": str(i), "name": f"t{i}", "received_at": 1.0 + i, "scored_at": 2.0,
                                "bytes": 9, "method": "quant", "n": 8, "n_keep": 4, "length_mm": 1.0,
                                "speed_mm_s": 50.0, "curve_id": "00", "ratio_coeffs": 1.0,
                                "ratio_profile": 1.0, "ip": p, "ia": a, "iobj": p + a, "a": 1.0, "b": 1.0})
    con.close()
    assert main(["quality", "--db", str(db), "--csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert {"Ip", "Ia", "Iobj"} <= set(rows[0]) and "ip" not in rows[0]
    # the log's rows plus a score column are a scores file for `hostd fit`, old spelling too
    for spell in ("Ip,Ia", "ip,ia"):
        f = tmp_path / "s.csv"
        lines = [f"texture,method,level,score,{spell}"]
        lines += [f"{r['name']},quant,1,{0.5 * float(r['Ip']) + 0.2 * float(r['Ia']):.6f},{r['Ip']},{r['Ia']}"
                  for r in rows]
        f.write_text("\n".join(lines) + "\n")
        assert main(["fit", str(f), "--json", "--bootstrap", "0"]) == 0
        res = json.loads(capsys.readouterr().out)
        assert res["a"] == pytest.approx(0.5, abs=1e-5) and res["b"] == pytest.approx(0.2, abs=1e-5)
