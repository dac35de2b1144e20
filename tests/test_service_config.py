"""One meaning for every number: one default (a, b), the quality log's a and b, config validated
at load (transport, writable paths), doctor checks what the config names, journald logging."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import pytest

from hostd.cli import main
from hostd.errors import ConfigError
from hostd.perception.indices import DEFAULT_AB
from hostd.service import qualitylog
from hostd.service.config import load
from tests.test_daemon import ROOT


def test_one_default_ab_everywhere(tmp_path, capsys):
    assert (load(None).quality.a, load(None).quality.b) == DEFAULT_AB
    shipped = load(ROOT / "config" / "hostd.toml").quality
    assert (shipped.a, shipped.b) == DEFAULT_AB
    s = tmp_path / "w.vtx"
    assert main(["encode", "synthetic:wood:2", "-o", str(s), "--method", "quant", "--levels", "6"]) == 0
    capsys.readouterr()
    assert main(["iobj", str(s), "--json"]) == 0
    import json

    cli = json.loads(capsys.readouterr().out)
    q = load(None).quality
    row = qualitylog.score_row(s.read_bytes(), "w", "0" * 64, 0.0, q.a, q.b, None)
    assert row["iobj"] == pytest.approx(cli["Iobj"], rel=1e-12)  # the daemon's log = the CLI
    con = qualitylog.connect(tmp_path / "q.sqlite")
    qualitylog.insert(con, row)
    con.close()
    assert main(["quality", "--db", str(tmp_path / "q.sqlite")]) == 0
    out = capsys.readouterr().out
    header, line = out.splitlines()[:2]
    assert header.split()[-2:] == ["a", "b"]
    assert line.split()[-2:] == [f"{DEFAULT_AB[0]:.3f}", f"{DEFAULT_AB[1]:.3f}"]


@pytest.mark.parametrize("spec, good", [
    ("auto", True), ("sim", True), ("hid", True), ("hid:/dev/hidraw3", True), ("usb", True),
    ("serial", True), ("serial:/dev/ttyACM0", True), ("usb:001/002", True), ("usb:1/x", False),
    ("bogus", False), ("hid:", False), ("usb:/dev/x", False), ("sim:1", False), ("", False),
])
def test_device_transport_is_validated_at_load(tmp_path, spec, good):
    p = tmp_path / "c.toml"
    p.write_text(f'[device]\ntransport = "{spec}"\n')
    if good:
        assert load(p).device.transport == spec
    else:
        with pytest.raises(ConfigError, match=r"device\.transport must be"):
            load(p)


def test_unwritable_paths_refused_at_start_and_by_doctor(tmp_path, capsys):
    p = tmp_path / "c.toml"
    p.write_text('[device]\ntransport = "serial:/dev/hostd-no-such-port"\n[library]\n'
                 f'dir = "/etc/hostname/library"\nspool = "{tmp_path}/spool"\n'
                 f'[control]\nsocket = "{tmp_path}/s.sock"\ngroup = ""\n'
                 f'[quality]\ndb = "{tmp_path}/q.sqlite"\n')
    r = subprocess.run([sys.executable, "-m", "hostd", "run", "--config", str(p)], capture_output=True,
                       text=True, cwd=tmp_path, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "library.dir" in r.stderr and "not a directory" in r.stderr
    assert main(["doctor", "--config", str(p)]) == 1
    out = capsys.readouterr().out
    assert "FAIL  library.dir /etc/hostname/library" in out
    assert "will be created" not in out.split("library.dir")[1].split("\n")[0]
    assert "FAIL  device.transport = 'serial:/dev/hostd-no-such-port'" in out


def test_repeated_messages_are_rate_limited_with_backoff():
    from hostd.service.logsetup import RepeatFilter

    now = [0.0]
    f = RepeatFilter(clock=lambda: now[0])

    def rec(msg: str) -> logging.LogRecord:
        return logging.LogRecord("hostd", logging.WARNING, __file__, 1, msg, (), None)

    passed = []
    for i in range(100):  # one message a second for 100 s, as the pump's "no device" did
        now[0] = float(i)
        r = rec("device: no display found")
        if f.filter(r):
            passed.append((i, r.getMessage()))
    assert passed[0] == (0, "device: no display found")
    assert [t for t, _ in passed] == [0, 1, 3, 7, 15, 31, 63]  # back-off 1, 2, 4, 8, 16, 32 s
    assert "repeated 15 more times" in passed[-2][1] and "repeated 31 more times" in passed[-1][1]
    assert f.filter(rec("another message"))  # a different message is not held back


def test_journald_gets_priority_prefixes_a_terminal_gets_timestamps(tmp_path, monkeypatch):
    from hostd.service import logsetup

    log = logging.getLogger("hostd.test")
    for journal in (True, False):
        out = open(tmp_path / f"j{journal}.txt", "w")
        st = os.fstat(out.fileno())
        if journal:
            monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        else:
            monkeypatch.delenv("JOURNAL_STREAM", raising=False)
        old = logging.getLogger().handlers[:], logging.getLogger().level
        try:
            logsetup.setup("info", out)
            log.error("e1")
            log.warning("w1")
            log.info("i1")
        finally:
            logging.getLogger().handlers[:], _ = old[0], None
            logging.getLogger().setLevel(old[1])
            out.close()
        lines = (tmp_path / f"j{journal}.txt").read_text().splitlines()
        if journal:
            assert [ln[:3] for ln in lines] == ["<3>", "<4>", "<6>"], lines
        else:
            assert all(ln[:4].isdigit() and not ln.startswith("<") for ln in lines), lines
