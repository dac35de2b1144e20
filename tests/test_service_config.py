"""One meaning for every number: one default (a, b), the quality log's a and b, config validated
at load (transport, writable paths), doctor checks what the config names, journald logging."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

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
    assert header.split()[7:9] == ["a", "b"]
    assert line.split()[8:10] == [f"{DEFAULT_AB[0]:.3f}", f"{DEFAULT_AB[1]:.3f}"]  # date and time: 2 words


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


def test_clients_and_daemon_read_the_installed_config_by_default(tmp_path, monkeypatch, capsys):
    """After editing control.socket in /etc/hostd/hostd.toml, `hostd status` (and send, select,
    list, stop, quality, doctor, run) look where the daemon listens, without --config;
    $HOSTD_CONFIG and --config override it, in that order."""
    from hostd.service import config as cfgmod

    def conf(name: str) -> Path:
        p = tmp_path / f"{name}.toml"
        p.write_text(f'[control]\nsocket = "{tmp_path}/{name}.sock"\n'
                     f'[quality]\ndb = "{tmp_path}/{name}.db"\n')
        return p

    etc, env, given = conf("etc"), conf("env"), conf("given")
    monkeypatch.delenv("HOSTD_CONFIG", raising=False)
    monkeypatch.delenv("HOSTD_SOCKET", raising=False)
    monkeypatch.setattr(cfgmod, "DEFAULT_PATH", str(tmp_path / "absent.toml"))
    assert cfgmod.resolve_path(None) is None  # nothing installed: the built-in defaults
    monkeypatch.setattr(cfgmod, "DEFAULT_PATH", str(etc))
    for argv, want in ((["status"], "etc"), (["list"], "etc"), (["select", "x"], "etc"),
                       (["stop"], "etc"), (["send", str(etc)], "etc"),
                       (["status", "--config", str(given)], "given")):
        assert main(argv) == 2, argv
        assert f"{tmp_path}/{want}.sock" in capsys.readouterr().err, argv
    assert main(["quality"]) == 2  # the db named by the installed config (absent here)
    assert f"{tmp_path}/etc.db" in capsys.readouterr().err
    monkeypatch.setenv("HOSTD_CONFIG", str(env))
    assert main(["status"]) == 2 and f"{tmp_path}/env.sock" in capsys.readouterr().err
    assert main(["status", "--config", str(given)]) == 2 and "given.sock" in capsys.readouterr().err
    from hostd.cli import build_parser
    from hostd.service.cli import _config

    assert _config(build_parser().parse_args(["run"])) == str(env)  # the daemon: the same resolution


# ---------------------------------------------------------------- issue 32: two displays on one PC


def test_device_serial_picks_one_of_two_displays(monkeypatch):
    """device.serial: the display with that USB serial number (the identity udev's
    /dev/hostd/by-serial/ names), on whichever transport finds it; none: the serials seen."""
    from hostd.device import transport
    from hostd.errors import DeviceNotFound

    opened = []
    found = {"hid": [{"spec": "hid:/dev/hidraw3", "node": "/dev/hidraw3", "serial": "A1"},
                     {"spec": "hid:/dev/hidraw5", "node": "/dev/hidraw5", "serial": "B2"}],
             "usb": [{"spec": "usb:001/007", "node": "/dev/bus/usb/001/007", "serial": "A1"},
                     {"spec": "usb:001/009", "node": "/dev/bus/usb/001/009", "serial": "B2"}],
             "serial": []}

    def attr(kind, which):
        if which == "enumerator":
            return lambda: found[kind]
        return lambda arg: opened.append((kind, arg)) or f"{kind}:{arg}"

    monkeypatch.setattr(transport, "_attr", attr)
    assert transport.open_transport("auto", serial="B2") == "hid:/dev/hidraw5"
    assert transport.open_transport("usb", serial="A1") == "usb:001/007"
    assert opened == [("hid", "/dev/hidraw5"), ("usb", "001/007")]
    assert [d["spec"] for d in transport.present("auto", "A1")] == ["hid:/dev/hidraw3", "usb:001/007"]
    with pytest.raises(DeviceNotFound,
                       match=r"no display with serial number .C3..*hid:/dev/hidraw3 \(serial A1\)"):
        transport.open_transport("hid", serial="C3")


@pytest.mark.parametrize("text, needle", [
    ('[device]\ntransport = "hid:/dev/hidraw0"\nserial = "A1"\n', "device.serial picks a display"),
    ('[device]\ntransport = "sim"\nserial = "A1"\n', "device.serial picks a display"),
    ('[device]\nserial = "../x"\n', "device.serial must be a USB serial number"),
])
def test_device_serial_config_errors(tmp_path, text, needle):
    p = tmp_path / "h.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        load(p)


def test_device_serial_loads(tmp_path):
    p = tmp_path / "h.toml"
    p.write_text('[device]\ntransport = "auto"\nserial = "0042A1"\n')
    assert load(p).device.serial == "0042A1"


def test_udev_rule_names_each_display_by_its_serial():
    """Two displays, serials A1 and B2: the rule's names for their hidraw and tty nodes are all
    different (before: one SYMLINK for both, the second replaced the first)."""
    import re

    rules = (ROOT / "systemd" / "70-hostd.rules").read_text()
    names = {}
    for serial in ("A1", "B2"):
        for line in rules.splitlines():
            m = re.search(r'SUBSYSTEM=="(\w+)".*SYMLINK\+="([^"]+)"', line)
            if m and "$attr{serial}" in m.group(2):
                assert 'ATTRS{serial}=="?*"' in line  # a display without one gets no empty name
                names[(m.group(1), serial)] = m.group(2).replace("$attr{serial}", serial)
    assert names == {("hidraw", "A1"): "hostd/by-serial/hid-A1", ("tty", "A1"): "hostd/by-serial/tty-A1",
                     ("hidraw", "B2"): "hostd/by-serial/hid-B2", ("tty", "B2"): "hostd/by-serial/tty-B2"}


def test_udev_reads_the_rule_without_complaint(tmp_path):
    """udev itself (udevadm test, in a private mount namespace where /etc/udev/rules.d holds only
    this rule) reads every line: a key it does not know ('Invalid key') or a malformed line
    would be ignored by udev on a display PC without a word. The group hostd need not exist here."""
    import shutil

    if os.geteuid() != 0 or not shutil.which("udevadm") or not shutil.which("unshare"):
        pytest.skip("needs root, udevadm and unshare (a private mount namespace)")
    (tmp_path / "rules").mkdir()
    shutil.copy(ROOT / "systemd" / "70-hostd.rules", tmp_path / "rules")
    (tmp_path / "rules" / "71-broken.rules").write_text('SUBSYSTEM=="tty", NOSUCHKEY=="1", SYMLINK+="x"\n')
    script = (f"mount --bind {tmp_path / 'rules'} /etc/udev/rules.d && "
              "udevadm test --action=add /sys/class/tty/tty0")
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=60)
    if "Reading rules file: /etc/udev/rules.d/70-hostd.rules" not in r.stderr + r.stdout:
        pytest.skip(f"udevadm test did not read the rule here: {(r.stderr + r.stdout)[-300:]}")
    said = [ln for ln in (r.stderr + r.stdout).splitlines() if "/etc/udev/rules.d/" in ln
            and not ln.startswith("Reading rules file")]
    assert any("71-broken.rules:1" in ln and "NOSUCHKEY" in ln for ln in said), said  # it would tell
    assert not [ln for ln in said if "70-hostd.rules" in ln and "Unknown group 'hostd'" not in ln], said


def test_each_config_key_is_declared_once_and_the_shipped_file_and_reference_are_generated():
    """One declaration per key (hostd.service.config.key): its doc is not empty, and the shipped
    hostd.toml and docs/reference/config.md are exactly what the declarations generate
    (python -m hostd.service.config toml|markdown)."""
    from dataclasses import fields

    from hostd.service import config

    root = Path(__file__).resolve().parent.parent
    for section, _doc, keys in config._declared():
        for name, _default, meta in keys:
            assert meta.get("doc"), f"{section}.{name} has no doc"
    assert (root / "config" / "hostd.toml").read_text() == config.shipped_toml(), \
        "config/hostd.toml is stale: python -m hostd.service.config toml > config/hostd.toml"
    assert (root / "docs" / "reference" / "config.md").read_text() == config.reference_markdown(), \
        "docs/reference/config.md is stale: python -m hostd.service.config markdown > " \
        "docs/reference/config.md"
    assert config.load(root / "config" / "hostd.toml") == config.load(None).__class__(
        path=str(root / "config" / "hostd.toml"))
    assert [f.name for f in fields(config.Config)][-1] == "path"


def test_a_key_declared_with_bounds_and_choices_is_validated_from_the_declaration(tmp_path):
    p = tmp_path / "h.toml"
    p.write_text('[render]\nsamples_per_batch = 30\n')
    with pytest.raises(ConfigError, match=r"render.samples_per_batch must be within 1..29, not 30"):
        load(p)
    p.write_text('[render]\ndtype = "float16"\n')
    with pytest.raises(ConfigError, match=r"render.dtype must be one of float32, float64"):
        load(p)
    p.write_text('[control]\nsocket = ""\n')
    with pytest.raises(ConfigError, match=r"control.socket must not be empty"):
        load(p)
    p.write_text('[quality]\nthresholds = "curve.csv"\n')
    with pytest.raises(ConfigError, match=r"quality\.thresholds"):  # resolved beside the file, then read
        load(p)
