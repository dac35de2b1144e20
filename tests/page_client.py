"""A participant's page without a browser: what the page's script sends (tests of the
experiment page's server), and the raw requests an attacker would send instead."""

from __future__ import annotations

import http.client
import json
import re
import socket
import time
from urllib.parse import urlsplit


class PageClient:
    """One page: GETs the page (its CSRF value), then acts as the page's script does."""

    def __init__(self, url: str, load: bool = True) -> None:
        u = urlsplit(url)
        self.host, self.port, self.path = u.hostname, u.port, u.path
        self.api = self.path.replace("/s/", "/api/", 1)
        self.origin = f"http://{self.host}:{self.port}"
        self.csrf = ""
        if load:
            status, body = self.request("GET", self.path)
            assert status == 200, (status, body)
            self.csrf = re.search(r'const CSRF = "([^"]+)"', body.decode()).group(1)

    def request(self, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
                timeout_s: float = 10.0) -> tuple[int, bytes]:
        c = http.client.HTTPConnection(self.host, self.port, timeout=timeout_s)
        try:
            c.request(method, path, body=body, headers=headers or {})
            r = c.getresponse()
            return r.status, r.read()
        finally:
            c.close()

    def post(self, route: str, obj: dict | None = None, **override) -> tuple[int, dict]:
        h = {"Content-Type": "application/json", "Origin": self.origin, "X-Hostd-Page": self.csrf}
        h.update({k.replace("_", "-"): v for k, v in override.items() if v is not None})
        for k in [k.replace("_", "-") for k, v in override.items() if v is None]:
            h.pop(k, None)
        status, body = self.request("POST", f"{self.api}/{route}", json.dumps(obj or {}).encode(), h)
        try:
            return status, json.loads(body)
        except ValueError:
            return status, {"text": body.decode(errors="replace")}

    def state(self) -> dict:
        status, body = self.request("GET", f"{self.api}/state", headers={"X-Hostd-Page": self.csrf})
        assert status == 200, (status, body)
        return json.loads(body)

    def open(self) -> dict:
        status, v = self.post("open")
        assert status == 200, v
        return v

    def wait(self, cond, what: str, timeout_s: float = 30.0) -> dict:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            s = self.state()
            if cond(s):
                return s
            time.sleep(0.02)
        raise AssertionError(f"the session never showed {what}: {s}")

    def to_main(self) -> dict:
        """Past the instructions (and consent, practice's end) to the first scored trial."""
        s = self.open()
        while s["phase"] in ("instructions", "consent", "intro", "break"):
            assert self.post("step", {"action": "agree" if s["phase"] == "consent" else "continue"})[0] == 200
            s = self.state()
        return s

    def play(self) -> dict:
        """Present the trial of the moment and wait until it has played whole."""
        status, v = self.post("present")
        assert status == 200, v
        return self.wait(lambda s: s["presented"] or s["retry"], "the trial played")

    def answer(self, index: int, value: int) -> tuple[int, dict]:
        return self.post("answer", {"index": index, "value": value})


def raw(port: int, data: bytes, timeout_s: float = 10.0) -> bytes:
    """Send raw bytes, read the reply to the end."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as s:
        s.sendall(data)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
    return out
