"""Hints that lead the right way: each message names the option or the setting that fixes it."""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

import pytest

from hostd.cli import main

ROOT = Path(__file__).resolve().parent.parent
DEKTAK = str(ROOT / "config" / "profiles" / "dektak-1.csv")


def test_no_device_hint_is_a_config_line_that_works(tmp_path):
    from hostd.device import transport
    from hostd.errors import DeviceError
    from hostd.service.config import load

    try:
        transport.open_transport("auto").close()
        pytest.skip("a display is plugged in here")
    except DeviceError as e:
        msg = str(e)
    m = re.search(r"set (\[device\] transport = \"sim\")", msg)
    assert m, msg
    p = tmp_path / "c.toml"
    p.write_text(m[1].replace("] ", "]\n") + "\n")  # exactly what the hint says, as TOML
    assert load(p).device.transport == "sim"
    doctor = (ROOT / "hostd" / "service" / "doctor.py").read_text()
    assert '[device] transport = \\"sim\\"' in doctor and 'device = \\"sim\\"' not in doctor


@pytest.mark.parametrize("unit", ["m", "mm"])
def test_wrong_x_unit_errors_point_at_x_unit(unit, tmp_path, capsys):
    assert main(["encode", DEKTAK, "-o", str(tmp_path / "x.vtx"), "--method", "quant", "--levels", "8",
                 "--x-unit", unit]) == 2
    err = capsys.readouterr().err
    assert "check --x-unit" in err and len(err.strip().splitlines()) == 1, err


def test_implausible_heights_warn_about_y_unit(tmp_path, capsys):
    out = str(tmp_path / "x.vtx")
    assert main(["encode", DEKTAK, "-o", out, "--method", "quant", "--levels", "8", "--y-unit", "m"]) == 0
    err = capsys.readouterr().err
    assert "is implausible" in err and "--y-unit" in err and "read as m" in err
    assert main(["encode", DEKTAK, "-o", out, "--method", "quant", "--levels", "8"]) == 0
    assert "is implausible" not in capsys.readouterr().err


def test_iobj_swapped_arguments_name_the_file_and_the_order(tmp_path, capsys):
    s = str(tmp_path / "w.vtx")
    assert main(["encode", DEKTAK, "-o", s, "--method", "quant", "--levels", "8"]) == 0
    capsys.readouterr()
    assert main(["iobj", s, DEKTAK]) == 2
    err = capsys.readouterr().err
    assert DEKTAK in err and "REFERENCE_PROFILE then STREAM" in err and "swapped" in err, err
    assert main(["iobj", s, "--fmax-hz", "400", "--ref-speed-mm-s", "50", "--json"]) == 0  # accepted
    assert capsys.readouterr().err == ""
    assert main(["iobj", DEKTAK, s, "--ref-speed-mm-s", "30", "--json"]) == 0
    captured = capsys.readouterr()
    assert "--ref-speed-mm-s 30 ignored" in captured.err and json.loads(captured.out)["Iobj"] >= 0


def test_iobj_prints_aligned_keys_with_sensible_precision(tmp_path, capsys):
    s = str(tmp_path / "w.vtx")
    assert main(["encode", "synthetic:wood:1", "-o", s, "--method", "quant", "--levels", "8"]) == 0
    capsys.readouterr()
    assert main(["iobj", s]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1].startswith("Iobj ") and "0 = identical" in lines[-1]  # the legend, last
    lines = lines[:-1]
    assert len({ln.index(":") for ln in lines}) == 1, lines  # one column of colons
    for ln in lines:
        value = ln.split(": ", 1)[1]
        if re.fullmatch(r"-?[\d.]+(e[-+]\d+)?", value) and "." in value:
            assert len(value.replace("-", "").replace(".", "").split("e")[0].lstrip("0")) <= 6, ln


def test_encode_says_when_the_guard_set_the_size(tmp_path, capsys):
    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "w.vtx"), "--target-iobj", "0.05",
                 "--json"]) == 0
    captured = capsys.readouterr()
    res = json.loads(captured.out)
    assert res["Iobj"] < 0.025  # far under the target: the guard decided, and the output leads with it
    assert list(res)[:2] == ["binding", "size_set_by"]
    assert res["binding"] == "SPQI >= 0.9" and res["size_set_by"] == "waveform"
    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "w.vtx"), "--target-iobj", "0.05"]) == 0
    assert "the smallest stream with SPQI >= 0.9: the constraint that set its size" in \
        capsys.readouterr().err.splitlines()[0]
    assert main(["encode", "synthetic:wood:1", "-o", str(tmp_path / "w.vtx"), "--target-iobj", "0.05",
                 "--no-guard", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["size_set_by"] == "Iobj"


@pytest.mark.parametrize("group", ["bench", "report"])
def test_command_groups_without_a_subcommand_show_help_and_exit_2(group, capsys):
    assert main([group]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"usage: hostd {group}") and f"hostd {group}: error: choose" in err


def test_run_log_level_has_help(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    assert re.search(r"--log-level \{debug,info,warning,error\}\s+least severe message", out), out


def test_bench_load_and_codec_report_progress_steps():
    from hostd.bench import common, micro

    steps = []
    micro.bench_load(2000, step=lambda: steps.append(1))
    assert len(steps) == 5
    bar = common.progress(3, "x")  # stderr is not a terminal under pytest: no bar
    assert bar.disable
    assert common.progress(3, "x", enabled=True).disable  # asked for, but not a terminal: none (issue 32)


def test_sim_table_combined_row_keeps_the_columns(monkeypatch, capsys):
    from hostd.sim import cli as simcli
    from hostd.sim import scene

    effects = ["encoder", "transport", "clock_drift", "cpu_load", "dac", "actuator", "finger_load"]
    runs = [{"effects": e, "Ip": 0.1, "Ia": 0.2, "Iobj": 0.15, "rms_error_um": 0.1,
             "spectrum_change_um": 0.001, "underruns": 0, "latency_ms": 1.0}
            for e in ([], ["encoder"], effects)]
    fake = {"scene": "worst-case", "description": "d", "duration_s": 1.0, "seed": 1, "codec_iobj": 0.01,
            "runs": runs}
    monkeypatch.setattr(scene, "report", lambda sc, progress: fake)
    monkeypatch.setattr(scene, "strip", lambda r: r)
    assert main(["sim", "worst-case"]) == 0
    lines = capsys.readouterr().out.splitlines()
    table = lines[1:5]
    assert len({len(ln) for ln in table}) == 1, table  # every row as wide as the header
    assert "all 7 effects: encoder, transport" in lines[5]
    assert simcli.run_label(effects) == "all 7 effects"


def test_demo_removes_its_temporary_directory(monkeypatch, tmp_path):
    from hostd import demo

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    seen = []

    def body(rc):
        def run(out: Path) -> int:
            (out / "f").write_bytes(b"x" * 1000)
            seen.append(out)
            return rc
        return run

    assert demo._in_dir(None, body(0)) == 0 and not seen[-1].exists()  # success: removed
    assert demo._in_dir(None, body(1)) == 1 and seen[-1].exists()  # failure: kept for its logs
    assert demo._in_dir(str(tmp_path / "keep"), body(0)) == 0 and (tmp_path / "keep" / "f").exists()


def test_profile_options_live_below_both_clis():
    """cli.py <-> bench/cli.py: the profile-reading options are in hostd/cliopts.py, which both import."""
    import subprocess
    import sys

    src = (ROOT / "hostd" / "bench" / "cli.py").read_text()
    assert "from hostd.cli import" not in src and "from hostd.cliopts import read_profile" in src
    r = subprocess.run([sys.executable, "-c", "import sys, hostd.bench.cli, hostd.cliopts; "
                        "print('hostd.cli' in sys.modules)"], capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "False", r.stderr


def test_parser_lives_below_cli_and_docgen():
    """cli.py <-> docgen.py <-> service/install.py: the parser is hostd/parser.py, which cli.py and
    docgen.py import; generating the man page and completions (install-service) never imports cli.py."""
    import subprocess
    import sys

    for mod in ("docgen.py", "parser.py", "commands.py", "service/install.py"):
        assert "hostd.cli import" not in (ROOT / "hostd" / mod).read_text(), mod
    r = subprocess.run([sys.executable, "-c", "import sys, hostd.service.install, hostd.docgen as d; "
                        "from hostd.parser import build_parser as b; "
                        "d.man_page(b()); d.completion('bash', b()); print('hostd.cli' in sys.modules)"],
                       capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "False", r.stderr


def test_the_cli_says_what_iobj_means(tmp_path, capsys):
    """hostd iobj and hostd inspect print the scale in text mode (0 = identical, the paper's
    grades), and hostd demo's table gives the nearest grade."""
    from hostd.perception.indices import GRADES, grade

    s = str(tmp_path / "w.vtx")
    assert main(["encode", "synthetic:wood:1", "-o", s, "--method", "quant", "--levels", "4"]) == 0
    capsys.readouterr()
    assert main(["iobj", s]) == 0
    out = capsys.readouterr().out
    assert "0 = identical, larger = more degraded" in out and "nearest grade" in out
    assert main(["inspect", s]) == 0
    assert "0 = identical" in capsys.readouterr().out
    assert [grade(x) for x in (0.0, 0.49, 0.51, 1.6, 2.5, 9.0)] == \
        ["same", "same", "probably the same", "probably different", "different", "different"]
    assert len(GRADES) == 4
    assert main(["demo", "--codec-only", "-o", str(tmp_path / "d")]) == 0
    demo = capsys.readouterr().out
    assert "nearest grade" in demo and "0 = identical" in demo
