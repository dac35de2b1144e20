"""The optional Prometheus endpoint: off by default, loopback only, the health and quality figures
over a real HTTP GET on loopback from a running daemon."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from hostd.errors import ConfigError
from hostd.service.client import ClientError, request, send_file
from hostd.service.config import load
from hostd.service.metrics import parse_listen
from tests.test_daemon import stream, write_cfg


@pytest.mark.parametrize("value, ok", [
    ("", None), ("127.0.0.1:9470", ("127.0.0.1", 9470)), ("127.0.0.2:80", ("127.0.0.2", 80)),
    ("[::1]:9470", ("::1", 9470)), ("localhost:9470", ("127.0.0.1", 9470)),
    ("0.0.0.0:9470", False), ("192.168.1.20:9470", False), ("[::]:9470", False), ("example.org:9470", False),
    ("127.0.0.1", "HOST:PORT"), ("127.0.0.1:0", "HOST:PORT"), ("127.0.0.1:http", "HOST:PORT"),
])
def test_listen_is_loopback_only(value, ok):
    if ok is False:
        with pytest.raises(ConfigError, match="loopback only"):
            parse_listen(value, "metrics.listen")
    elif isinstance(ok, str):
        with pytest.raises(ConfigError, match=ok):
            parse_listen(value, "metrics.listen")
    else:
        assert parse_listen(value, "metrics.listen") == ok


def test_metrics_off_by_default_and_a_public_bind_refused_at_load(tmp_path):
    assert load(None).metrics.listen == ""
    p = tmp_path / "c.toml"
    p.write_text('[metrics]\nlisten = "0.0.0.0:9470"\n')
    with pytest.raises(ConfigError, match=r"c\.toml: metrics\.listen.*loopback only"):
        load(p)


def test_under_the_unit_a_refused_socket_says_which_drop_in(monkeypatch):
    """The unit allows no IP socket (RestrictAddressFamilies: socket() fails EAFNOSUPPORT): the
    one-line error gives the drop-in, which the installed user has no docs/ to look up."""
    import errno

    prometheus_client = pytest.importorskip("prometheus_client")
    from hostd.service import metrics, notify

    def refused(port, addr, registry=None):
        raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")

    monkeypatch.setattr(prometheus_client, "start_http_server", refused)
    monkeypatch.setattr(notify, "service_unit", lambda: "hostd.service")
    with pytest.raises(ConfigError) as e:
        metrics.start(("127.0.0.1", 9470), lambda: {}, lambda: [])
    msg = str(e.value)
    assert "sudo systemctl edit hostd" in msg and "IPAddressAllow=localhost" in msg and "AF_INET6" in msg
    assert "\n" not in msg and "docs/" not in msg
    monkeypatch.setattr(notify, "service_unit", lambda: None)  # outside systemd: no unit to edit
    with pytest.raises(ConfigError) as e:
        metrics.start(("127.0.0.1", 9470), lambda: {}, lambda: [])
    assert "systemctl" not in str(e.value) and "cannot listen" in str(e.value)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_metrics_endpoint_serves_health_and_quality(tmp_path):
    pytest.importorskip("prometheus_client")
    port = _free_port()
    cfg = write_cfg(tmp_path, f'[metrics]\nlisten = "127.0.0.1:{port}"\n')
    proc = subprocess.Popen([sys.executable, "-m", "hostd", "run", "--config", str(cfg)],
                            stderr=open(tmp_path / "log.txt", "w"), cwd=tmp_path)
    sock = str(tmp_path / "hostd.sock")
    try:
        for _ in range(900):
            try:
                if request(sock, {"cmd": "status"}, timeout_s=2)["connected"]:
                    break
            except ClientError:
                pass
            time.sleep(0.1)
        send_file(sock, str(stream(tmp_path, "wood8")), None)
        request(sock, {"cmd": "select", "name": "wood8"})
        for _ in range(300):
            body = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
            if 'hostd_stream_iobj{name="wood8"}' in body and 'hostd_state{state="playing"} 1.0' in body:
                break
            time.sleep(0.1)
        else:
            pytest.fail(body + (tmp_path / "log.txt").read_text()[-2000:])
        st = request(sock, {"cmd": "status"})
        lines = dict(ln.rsplit(" ", 1) for ln in body.splitlines() if ln and not ln.startswith("#"))
        assert lines["hostd_device_connected"] == "1.0"
        assert float(lines["hostd_device_samples_played_total"]) <= st["device_samples_played"]
        assert float(lines['hostd_stream_iobj{name="wood8"}']) == pytest.approx(
            request(sock, {"cmd": "quality"})["rows"][0]["iobj"], rel=1e-9)
        assert "# TYPE hostd_device_underruns_total counter" in body
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
    with pytest.raises(OSError):  # stopped with the daemon
        urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2)
