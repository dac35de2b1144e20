"""The fleet's Prometheus alert rules (config/prometheus/hostd-alerts.yml, shipped as
hostd/data/prometheus/): promtool's unit tests of each rule, the daemon's metric of rows waiting for
the fleet shipper, and a real Prometheus server scraping three running daemons (simulated displays)
whose underrun alert fires for the one display made to underrun, and for no other whose counter
does not say so. Under CI=true a missing Prometheus fails instead of skipping (./run test installs
Debian's prometheus)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from hostd.service.client import request, send_file
from tests.daemon_helpers import wait_for
from tests.test_daemon import stream, write_cfg

ROOT = Path(__file__).resolve().parents[1]
RULES_TEST = ROOT / "tests" / "prometheus" / "hostd-alerts-test.yml"


def _tool(name: str) -> str:
    path = shutil.which(name) or (f"/usr/bin/{name}" if os.path.exists(f"/usr/bin/{name}") else None)
    if path is None:
        msg = f"{name} is not installed (./run test installs it: apt-get install prometheus)"
        if os.environ.get("CI") == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return path


def _rules() -> Path:
    from hostd.paths import shipped_dir

    return Path(shipped_dir()) / "prometheus" / "hostd-alerts.yml"


def test_promtool_unit_tests_of_the_shipped_rules():
    promtool = _tool("promtool")
    assert _rules().resolve() == (ROOT / "config" / "prometheus" / "hostd-alerts.yml").resolve()
    r = subprocess.run([promtool, "check", "rules", str(_rules())], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "3 rules found" in r.stdout, r.stdout + r.stderr
    r = subprocess.run([promtool, "test", "rules", RULES_TEST.name], capture_output=True, text=True,
                       timeout=60, cwd=RULES_TEST.parent)
    assert r.returncode == 0 and "SUCCESS" in r.stdout, r.stdout + r.stderr


def test_metrics_say_how_many_rows_wait_for_the_shipper_and_how_old(tmp_path, monkeypatch):
    pytest.importorskip("prometheus_client")
    from prometheus_client import CollectorRegistry, generate_latest

    from hostd.fleet.bench import synthetic_row
    from hostd.service import outbox, qualitylog
    from hostd.service.metrics import DaemonCollector

    db, state = tmp_path / "q.sqlite", tmp_path / "outbox.sqlite"
    now = time.time()
    con = qualitylog.connect(db)
    qualitylog.insert_batch(con, [synthetic_row(i, now - 7200 + 60 * i) for i in range(5)])
    con.close()

    def scrape() -> dict[str, float]:
        reg = CollectorRegistry(auto_describe=False)
        reg.register(DaemonCollector(lambda: {}, lambda: [], str(db)))
        text = generate_latest(reg).decode()
        return {k: float(v) for k, v in (ln.rsplit(" ", 1) for ln in text.splitlines()
                                         if ln.startswith("hostd_fleet"))}

    monkeypatch.setenv(outbox.STATE_ENV, str(state))
    assert scrape() == {}  # no shipper on this PC: no such metric
    s = sqlite3.connect(state)
    s.executescript(outbox.STATE_SCHEMA)
    s.close()
    m = scrape()
    assert m["hostd_fleet_rows_waiting"] == 5
    assert 7200 <= m["hostd_fleet_oldest_waiting_age_seconds"] < 7200 + (time.time() - now) + 1
    first = qualitylog.connect(db)
    uid2 = first.execute("SELECT uuid FROM streams WHERE id = 2").fetchone()[0]
    first.close()
    s = sqlite3.connect(state)
    s.execute("INSERT INTO marks VALUES ('streams', 2, ?, ?)", (uid2, now))
    s.commit()
    s.close()
    m = scrape()  # rows 1 and 2 shipped: 3 wait, the oldest row 3's
    assert m["hostd_fleet_rows_waiting"] == 3
    assert 7080 <= m["hostd_fleet_oldest_waiting_age_seconds"] < 7080 + (time.time() - now) + 1


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _api(port: int, path: str, **q) -> dict:
    url = f"http://127.0.0.1:{port}/api/v1/{path}" + (f"?{urllib.parse.urlencode(q)}" if q else "")
    doc = json.loads(urllib.request.urlopen(url, timeout=5).read())
    assert doc["status"] == "success", doc
    return doc["data"]


def test_a_real_prometheus_fires_the_underrun_alert_for_the_display_that_underruns(tmp_path):
    """Three daemons on simulated displays, each playing, scraped each second by a real Prometheus
    that evaluates the shipped rules each second. One daemon (its pump with it) is paused for
    0.4 s at a time, as a loaded desktop pauses it: its display underruns once a pause (the
    display's own counter). Past the stated bound (more than 5 in 5 minutes) the alert fires for
    that display; for each other one it fires only if its own counter says so."""
    pytest.importorskip("prometheus_client")
    prometheus = _tool("prometheus")
    daemons, ports = [], []
    prom = None
    try:
        for k in range(3):
            d = tmp_path / f"pc{k}"
            d.mkdir()
            ports.append(_free_port())
            cfg = write_cfg(d, f'[metrics]\nlisten = "127.0.0.1:{ports[-1]}"\n')
            daemons.append((subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)],
                                             stderr=open(d / "log.txt", "w"), cwd=d, start_new_session=True),
                            str(d / "hostd.sock")))
        pport = _free_port()
        conf = tmp_path / "prometheus.yml"
        conf.write_text(
            "global:\n  scrape_interval: 1s\n  scrape_timeout: 900ms\n  evaluation_interval: 1s\n"
            f"rule_files:\n  - {_rules()}\n"
            "scrape_configs:\n  - job_name: hostd\n    static_configs:\n      - targets: ["
            + ", ".join(f"'127.0.0.1:{p}'" for p in ports) + "]\n")
        prom = subprocess.Popen([prometheus, f"--config.file={conf}",
                                 f"--storage.tsdb.path={tmp_path / 'tsdb'}",
                                 f"--web.listen-address=127.0.0.1:{pport}", "--log.level=warn"],
                                stdout=subprocess.DEVNULL, stderr=open(tmp_path / "prometheus.log", "w"))
        vtx = stream(tmp_path, "wood8")
        for _proc, sock in daemons:
            wait_for(lambda s=sock: request(s, {"cmd": "status"}, timeout_s=2)["connected"], 90, "a daemon")
            send_file(sock, str(vtx), None)
            request(sock, {"cmd": "select", "name": "wood8"})

        def all_up():
            try:
                t = _api(pport, "targets")["activeTargets"]
            except OSError:
                return False
            return len(t) == 3 and all(x["health"] == "up" for x in t)

        wait_for(all_up, 60, "Prometheus scraping the three daemons")
        victim, vsock = daemons[0]
        instance = f"127.0.0.1:{ports[0]}"
        for _ in range(30):  # a pause of 0.4 s: one underrun each (the display's buffer runs dry)
            if request(vsock, {"cmd": "status"})["device_underruns"] > 6:
                break
            os.killpg(victim.pid, signal.SIGSTOP)
            time.sleep(0.4)
            os.killpg(victim.pid, signal.SIGCONT)
            time.sleep(0.3)
        assert request(vsock, {"cmd": "status"})["device_underruns"] > 6

        def firing():
            try:
                alerts = _api(pport, "alerts")["alerts"]
            except OSError:
                return None
            got = {a["labels"]["instance"] for a in alerts
                   if a["labels"]["alertname"] == "HostdUnderruns" and a["state"] == "firing"}
            return got if instance in got else None

        got = wait_for(firing, 30, "the HostdUnderruns alert firing")
        counts = {r["metric"]["instance"]: float(r["value"][1]) for r in _api(
            pport, "query", query='increase(hostd_device_underruns_total{job="hostd"}[5m])')["result"]}
        assert counts[instance] > 5
        for p in ports[1:]:  # a display whose own counter stays within the bound has no alert
            inst = f"127.0.0.1:{p}"
            assert inst not in got or counts.get(inst, 0) > 5, (got, counts)
    finally:
        if prom is not None:
            prom.terminate()
            prom.wait(20)
        for proc, _sock in daemons:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGCONT)
                proc.send_signal(signal.SIGTERM)
        for proc, _sock in daemons:
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()

