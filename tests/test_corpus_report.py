"""hostd corpus report: a stated quality range (BD-rates over little of the anchor's range are
left out of summaries, by name), a bootstrap interval over textures, encode/decode time against
the anchor, one line instead of a warning per value, an HTML page with the plots beside the
tables, the PNG cap said, log-axis labels that do not overprint."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from hostd.cli import main
from hostd.corpus import jobs, report
from hostd.corpus.store import Store


def _store(path, curves_by_texture):
    """rows of constructed curves: texture -> curve -> (rate scale, quality shift dB, encode s)."""
    q = np.linspace(5.0, 20.0, 6)
    rows = []
    for tex, cs in curves_by_texture.items():
        for curve, (scale, shift, enc) in cs.items():
            for qq in q:
                row = dict.fromkeys(jobs.COLUMNS)
                row.update(key=f"{tex}{curve}{qq}", texture=tex, input_sha256=tex, curve=curve, codec=curve,
                           codec_version="1", loader="{}", scoring="{}", speed_mm_s=50.0, fmax_hz=400.0,
                           bytes=round(100.0 * 10 ** (qq / 10.0) * scale), iobj_db=qq + shift,
                           Iobj=10 ** (-(qq + shift) / 10), spqi=(qq + shift) / 40.0, encode_cpu_s=enc,
                           decode_cpu_s=enc / 2)
                rows.append(row)
    st = Store(path)
    st.begin_run()
    st.write(rows)
    st.close()


A = "hostd-v2/shaped"


def test_summaries_use_a_stated_quality_range_with_an_interval_and_time_ratios(tmp_path, capsys):
    db = tmp_path / "r.sqlite"
    _store(db, {"t1": {A: (1.0, 0, 1e-3), "mine": (0.9, 0, 2e-3)},
                "t2": {A: (1.0, 0, 1e-3), "mine": (1.2, 0, 2e-3)},
                "t3": {A: (1.0, 0, 1e-3), "mine": (1.0, 13.5, 2e-3)},  # 10 % of the anchor's range
                "t4": {A: (1.0, 0, 1e-3), "mine": (1.05, 0, 2e-3)}})
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--max-plots", "1"]) == 0
    out, err = capsys.readouterr()
    # the package's own warning per value (and its `min_overlap=0` hint) is one line now
    assert len(err.strip().splitlines()) == 1 and "min_overlap" not in err and "note" in err
    line = next(ln for ln in out.splitlines() if ln.startswith("Iobj in dB") and " mine " in ln)
    assert "wins 1/3" in line and "excluded 1 (t3)" in line and "encode time x2" in line
    assert "decode time x2" in line and "covers >= 50 % of the anchor's quality range" in out
    assert "and 1 PNGs (of 4 textures x geometries" in out
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    s = next(x for x in res["summary"] if x["metric"] == "iobj_db" and x["curve"] == "mine")
    assert s["textures"] == 3 and s["excluded"] == 1 and s["excluded_textures"] == ["t3"]
    assert s["mean_pct"] == pytest.approx((-10 + 20 + 5) / 3, abs=0.3)
    assert s["ci95_lo_pct"] < s["mean_pct"] < s["ci95_hi_pct"]
    assert -10.5 < s["ci95_lo_pct"] and s["ci95_hi_pct"] < 20.5  # within the values' range
    assert s["encode_time_ratio"] == pytest.approx(2.0) and s["decode_time_ratio"] == pytest.approx(2.0)
    # --min-overlap 0 keeps every value; the per-texture table gives each overlap
    assert main(["corpus", "report", str(db), "-o", str(tmp_path / "all"), "--no-plots", "--json",
                 "--min-overlap", "0"]) == 0
    s0 = next(x for x in json.loads(capsys.readouterr().out)["summary"]
              if x["metric"] == "iobj_db" and x["curve"] == "mine")
    assert s0["textures"] == 4 and s0["excluded"] == 0
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "| t3 | 50 | 400 | `mine` |" in md and "| 10 % |" in md and "excluded" in md


def test_the_html_report_puts_each_textures_plot_beside_its_table(tmp_path):
    pytest.importorskip("matplotlib")
    db = tmp_path / "r.sqlite"
    _store(db, {"t1": {A: (1.0, 0, 1e-3), "mine": (0.9, 0, 2e-3)},
                "t2": {A: (1.0, 0, 1e-3), "mine": (1.2, 0, 2e-3)}})
    res = report.report(db, tmp_path / "rep", max_plots=0)
    page = (tmp_path / "rep" / "report.html").read_text()
    assert res["plots"] == {"written": 2, "of": 2}
    sections = page.split("<div class=tex>")[1:]
    assert len(sections) == 2
    for t, sec in zip(("t1", "t2"), sections, strict=True):  # its table, then its plot, in one row
        assert sec.index(f"<h3>{t} ") < sec.index("<table>") < sec.index(f"<img src='rq_{t}_v50_f400.png'")
    assert page.count("<img ") == 2 and "95 % CI" in page


@pytest.mark.parametrize("span", [(110, 165), (150, 225), (200, 1900), (400, 480), (1500, 2250),
                                  (12000, 24000), (30000, 90000), (30000, 285000), (50, 5e6)])
def test_log_axis_labels_do_not_overprint_when_bytes_span_less_than_a_decade(span):
    """The report's axes (10 x 4 in, two panels): matplotlib's own labels overprint on 7 of these
    spans (a minor label per tick, "2x10^2" beside "3x10^2")."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    ax.plot(span, [1, 2])
    ax.set_xscale("log")
    report.log_axis_labels(ax.xaxis)
    fig.tight_layout()
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    lo, hi = ax.get_xlim()
    labels = [t for t in ax.xaxis.get_majorticklabels() + ax.xaxis.get_minorticklabels()
              if t.get_text() and t.get_visible() and lo <= t.get_position()[0] <= hi]
    boxes = sorted((t.get_window_extent(r) for t in labels), key=lambda b: b.x0)
    plt.close(fig)
    assert len(boxes) >= 2, [t.get_text() for t in labels]
    assert all(a.x1 <= b.x0 for a, b in itertools.pairwise(boxes)), [t.get_text() for t in labels]


def test_a_manifests_group_column_gives_per_group_summaries(tmp_path, capsys):
    from hostd.cli import main as cli

    man = tmp_path / "m.csv"
    man.write_text("file,name,group,length_mm\n"
                   "synthetic:wood:1,w1,wood,2\nsynthetic:wood:2,w2,wood,2\n"
                   "synthetic:sandpaper:1,s1,sandpaper,2\nsynthetic:sandpaper:2,s2,,2\n")
    db = tmp_path / "r.sqlite"
    assert cli(["corpus", "run", str(man), "--codec", "hostd-v2", "--methods", "shaped,quant",
                "--g-db=-12,-6,0,6,12", "--levels", "8,16,32,64", "--no-spqi", "--workers", "1",
                "--no-progress", "-o", str(db)]) == 0
    import sqlite3

    c = sqlite3.connect(db)
    assert dict(c.execute("SELECT texture, texture_group FROM results GROUP BY texture")) == {
        "w1": "wood", "w2": "wood", "s1": "sandpaper", "s2": None}
    c.close()
    capsys.readouterr()
    assert cli(["corpus", "report", str(db), "-o", str(tmp_path / "rep"), "--no-plots", "--json",
                "--min-overlap", "0"]) == 0
    res = json.loads(capsys.readouterr().out)
    g = {(x["group"], x["metric"], x["curve"]): x for x in res["groups"]}
    assert g[("wood", "iobj_db", "hostd-v2/quant")]["textures"] == 2
    assert g[("sandpaper", "iobj_db", "hostd-v2/quant")]["textures"] == 1  # s2 has no group
    st = Store(db, create=False)
    table = report.bd_table(st.rows(), A, "iobj_db")
    st.close()
    rows = {r.texture: r for r in table if r.curve == "hostd-v2/quant"}
    assert g[("wood", "iobj_db", "hostd-v2/quant")]["mean_pct"] == pytest.approx(
        (rows["w1"].bd_rate_pct + rows["w2"].bd_rate_pct) / 2)
    assert (tmp_path / "rep" / "bdrate_groups.csv").exists()
    assert "## Per group" in (tmp_path / "rep" / "report.md").read_text()
