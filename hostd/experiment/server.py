"""The participant's page: one session, served on loopback only (127.0.0.1), no external asset.

Only the participant's browser can act on the session:
- The page's address carries a capability, CAP (`secrets.token_urlsafe(24)`: 192 bits), made by
  hostd when the session starts and printed once on stdout; it is never in argv, the
  environment or a log (the session store keeps it, 0600, so a restarted session serves the same
  address). The server compares it in constant time (hmac.compare_digest); any other is 404.
- Every request must name the server as its Host (127.0.0.1:PORT: a DNS-rebinding page names
  another); a GET only reads: the page, or the state.
- Every state-changing request is a POST whose Content-Type is application/json, whose Origin
  is http://127.0.0.1:PORT, and which carries the page's CSRF value (X-Hostd-Page): a fresh
  one in each page served, signed with the session's key (HMAC-SHA256). A page on another
  origin can send none of these without the browser's preflight, which this server refuses.
- The last page to `open` holds the session: a second tab takes it over and the first says so;
  only the holder can play a trial or answer, and an answer counts only for the trial played
  whole on that page (hostd.experiment.runner).

Connections are bounded: at most MAX_CONNECTIONS at once (a new one closes the oldest that is
still sending its request), a request must arrive whole within REQUEST_TIMEOUT_S and its reply be
taken within REPLY_TIMEOUT_S, each reply closes its connection. One event loop thread serves all
of them (asyncio; http.server's thread per connection is what 1,000 idle connections exhausted),
so with 1,000 idle connections open the page is still served. A malformed request gets a 4xx and
one line on the experimenter's terminal (`report`; a flood is cut short).

GET  /s/CAP                 the page (HTML, CSS and script inline)
GET  /api/CAP/state         the session as the page shows it (X-Hostd-Page: whose view)
POST /api/CAP/open          {}: this page takes the session over
POST /api/CAP/present       {}: play the trial of the moment (the page then polls the state)
POST /api/CAP/answer        {"index": i, "value": v}: committed before the reply
POST /api/CAP/pause         {"paused": true|false}
POST /api/CAP/step          {"action": "continue"|"agree"|"decline"}
Why not a web framework: three routes on loopback; the stdlib's asyncio streams give the bounded
single-threaded server, and the parsing below takes only what these routes need.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import logging
import secrets
import socket
import threading
import time
from collections import OrderedDict, deque
from http import HTTPStatus
from pathlib import Path

from hostd.errors import ExperimentError, HostdError
from hostd.experiment.runner import Refused

log = logging.getLogger("hostd.experiment")
MAX_BODY = 4096
MAX_HEAD = 8192
MAX_CONNECTIONS = 64
REQUEST_TIMEOUT_S = 5.0  # a request (line, headers, body) must arrive whole within this
REPLY_TIMEOUT_S = 5.0  # and its reply be taken within this
REPORTS_PER_10S = 20
BACKLOG = 4096  # (net.core.somaxconn caps it) a burst waits in the kernel's queue, not in SYN retries
UNIQUE_HEADERS = ("host", "content-length", "origin", "content-type", "x-hostd-page")
PAGE_HTML = Path(__file__).with_name("page.html")


def new_capability() -> str:
    return secrets.token_urlsafe(24)


class BadRequest(Exception):
    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class ExperimentServer:
    """Serves one session on 127.0.0.1:port (0: a free port) from one event-loop thread.
    `capability` and `csrf_key` default to fresh secrets (the CLI passes the session's, so that a
    restarted session keeps its address); `report(line)` gets the lines for the terminal."""

    def __init__(self, session, port: int = 0, capability: str | None = None, csrf_key: bytes | None = None,
                 report=None) -> None:
        self.session = session
        self.capability = capability or new_capability()
        self.csrf_key = csrf_key or secrets.token_bytes(32)
        self.report = report or (lambda line: log.warning("%s", line))
        self._reports: deque[float] = deque()
        self._suppressed = 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind(("127.0.0.1", port))
        except OSError as e:
            self.sock.close()
            raise ExperimentError(f"cannot serve the page on 127.0.0.1:{port}: {e.strerror or e} (another "
                                  "program holds the port? stop it, or give --port)") from None
        self.sock.listen(BACKLOG)
        self.port = self.sock.getsockname()[1]
        self.host = f"127.0.0.1:{self.port}"
        self.origin = f"http://{self.host}"
        self.url = f"{self.origin}/s/{self.capability}"
        self.page_html = PAGE_HTML.read_text(encoding="utf-8")
        self.conns: OrderedDict[asyncio.StreamWriter, bool] = OrderedDict()  # writer -> still reading
        self.dropped = 0  # connections closed for being slow or for the bound
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        self.thread = threading.Thread(target=self._run, name="experiment-page", daemon=True)

    # ------------------------------------------------------------------ life
    def start(self) -> ExperimentServer:
        self.thread.start()
        self.ready.wait(10)
        return self

    def close(self) -> None:
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(10)
        self.sock.close()

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        server = self.loop.run_until_complete(
            asyncio.start_server(self._connection, sock=self.sock, limit=MAX_HEAD, backlog=BACKLOG))
        self.ready.set()
        try:
            self.loop.run_forever()
        finally:
            server.close()
            for w in list(self.conns):
                w.transport.abort()
            self.loop.run_until_complete(asyncio.sleep(0))
            self.loop.close()

    def _say(self, line: str) -> None:
        """One line on the experimenter's terminal; a flood is cut to REPORTS_PER_10S lines in any
        10 s (the rest counted, and the count said with the next line)."""
        now = time.monotonic()
        while self._reports and now - self._reports[0] > 10.0:
            self._reports.popleft()
        if len(self._reports) >= REPORTS_PER_10S:
            self._suppressed += 1
            return
        more = f" ({self._suppressed} more refused meanwhile)" if self._suppressed else ""
        self._reports.append(now)
        self._suppressed = 0
        self.report(f"the page: {line}{more}")

    # ------------------------------------------------------------------ connections
    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.conns[writer] = True
        while len(self.conns) > MAX_CONNECTIONS:  # the oldest still sending its request goes
            oldest = next((w for w, reading in self.conns.items() if reading and w is not writer), None)
            if oldest is None:
                break
            self.conns.pop(oldest)
            oldest.transport.abort()
            self.dropped += 1
        try:
            try:
                method, path, headers, body = await asyncio.wait_for(self._read(reader), REQUEST_TIMEOUT_S)
                self.conns[writer] = False
                status, ctype, data = self._handle(method, path, headers, body)
            except BadRequest as e:
                self._say(f"refused a request: {e} ({e.status})")
                status, ctype, data = e.status, "text/plain; charset=utf-8", f"{e}\n".encode()
            except TimeoutError:
                self.dropped += 1
                return
            except (asyncio.IncompleteReadError, ConnectionError):
                return
            except Exception as e:  # a bug, or a store that fails a read: one line, and the page goes on
                self._say(f"could not answer a request: {type(e).__name__}: {str(e)[:120]}")
                status, ctype, data = 500, "text/plain; charset=utf-8", b"hostd could not answer: see hostd\n"
            head = (f"HTTP/1.1 {status} {HTTPStatus(status).phrase}\r\n"
                    f"Content-Type: {ctype}\r\nContent-Length: {len(data)}\r\nConnection: close\r\n"
                    "Cache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\n"
                    "Referrer-Policy: no-referrer\r\nX-Frame-Options: DENY\r\n"
                    "Content-Security-Policy: default-src 'none'; script-src 'unsafe-inline'; "
                    "style-src 'unsafe-inline'; img-src 'self'; connect-src 'self'; "
                    "frame-ancestors 'none'\r\n\r\n")
            writer.write(head.encode("latin-1") + data)
            try:
                await asyncio.wait_for(writer.drain(), REPLY_TIMEOUT_S)
            except (TimeoutError, ConnectionError):
                self.dropped += 1
        finally:
            self.conns.pop(writer, None)
            writer.transport.abort() if writer.transport.get_write_buffer_size() else writer.close()

    async def _read(self, reader: asyncio.StreamReader) -> tuple[str, str, dict, bytes]:
        try:
            head = await reader.readuntil(b"\r\n\r\n")
        except asyncio.LimitOverrunError:
            raise BadRequest(431, f"request head over {MAX_HEAD} bytes") from None
        except asyncio.IncompleteReadError as e:
            if e.partial:
                raise BadRequest(400, "request cut short") from None
            raise
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
            raise BadRequest(400, f"not an HTTP/1.x request line ({len(lines[0])} bytes)")  # (never echoed:
            # a request line may carry the address's secret)
        headers: dict[str, str] = {}
        for line in lines[1:]:
            if not line:
                continue
            name, sep, value = line.partition(":")
            name = name.strip().lower()
            if not sep or not name:
                raise BadRequest(400, f"malformed header line {name[:30]!r}")
            if name in headers and name in UNIQUE_HEADERS:
                raise BadRequest(400, f"header {name} given twice")
            headers[name] = value.strip()
        if "transfer-encoding" in headers:
            raise BadRequest(411, "chunked bodies are not taken: give Content-Length")
        cl = headers.get("content-length", "0")
        if not cl.isascii() or not cl.isdigit():
            raise BadRequest(400, f"Content-Length {cl[:30]!r} is not a number of bytes")
        n = int(cl)
        if n > MAX_BODY:
            raise BadRequest(413, f"body of {n} bytes: at most {MAX_BODY}")
        body = await reader.readexactly(n) if n else b""
        return parts[0], parts[1], headers, body

    # ------------------------------------------------------------------ requests
    def _csrf(self) -> str:
        nonce = secrets.token_urlsafe(16)
        return nonce + "." + hmac.new(self.csrf_key, nonce.encode(), hashlib.sha256).hexdigest()

    def _page_id(self, value: str | None) -> str | None:
        """The page's id (its CSRF nonce) if `value` is a CSRF value this session signed."""
        if not value or value.count(".") != 1:
            return None
        nonce, mac = value.split(".")
        good = hmac.new(self.csrf_key, nonce.encode(), hashlib.sha256).hexdigest()
        return nonce if hmac.compare_digest(mac.encode(), good.encode()) else None

    def _handle(self, method: str, target: str, headers: dict, body: bytes) -> tuple[int, str, bytes]:
        if headers.get("host") != self.host:
            raise BadRequest(403, f"Host {headers.get('host', '')[:60]!r} is not {self.host}: open the "
                             "address as hostd printed it")
        parts = target.split("?", 1)[0].split("/")
        if len(parts) < 3 or parts[0] != "" or parts[1] not in ("s", "api") or \
                not hmac.compare_digest(parts[2].encode(), self.capability.encode()):
            return 404, "text/plain; charset=utf-8", b"no such session on this server\n"
        route = "page" if parts[1] == "s" and len(parts) == 3 else \
            parts[3] if parts[1] == "api" and len(parts) == 4 else None
        if method == "GET":
            if route == "page":
                html = self.page_html.replace("__CSRF__", self._csrf())
                return 200, "text/html; charset=utf-8", html.encode()
            if route == "state":
                return self._json(self.session.view(self._page_id(headers.get("x-hostd-page"))))
            return 404, "text/plain; charset=utf-8", b"no such page\n"
        if method != "POST":
            raise BadRequest(405, f"method {method[:10]!r}: GET reads, POST acts")
        if route not in ("open", "present", "answer", "pause", "step"):
            return 404, "text/plain; charset=utf-8", b"no such action\n"
        if headers.get("origin") != self.origin:
            raise BadRequest(403, f"Origin {headers.get('origin', 'absent')[:60]!r} is not the page's")
        if headers.get("content-type", "").split(";")[0].strip().lower() != "application/json":
            raise BadRequest(415, "Content-Type must be application/json")
        page = self._page_id(headers.get("x-hostd-page"))
        if page is None:
            raise BadRequest(403, "no valid CSRF value (X-Hostd-Page) from this session's page")
        try:
            req = json.loads(body or b"{}")
        except (ValueError, RecursionError) as e:
            raise BadRequest(400, f"the body is not JSON ({str(e)[:60]})") from None
        if not isinstance(req, dict):
            raise BadRequest(400, "the body must be a JSON object")
        s = self.session
        try:
            if route == "open":
                return self._json(s.open(page))
            if route == "present":
                return self._json(s.present(page))
            if route == "answer":
                idx, val = req.get("index"), req.get("value")
                if not all(isinstance(v, int) and not isinstance(v, bool) for v in (idx, val)):
                    raise BadRequest(400, "answer: index and value must be integers")
                return self._json(s.answer(page, idx, val))
            if route == "pause":
                if not isinstance(req.get("paused"), bool):
                    raise BadRequest(400, "pause: paused must be true or false")
                s.pause(page, req["paused"])
                return self._json({"ok": True})
            if not isinstance(req.get("action"), str):
                raise BadRequest(400, "step: action must be a string")
            return self._json(s.step(page, req["action"]))
        except Refused as e:
            return self._json({"error": str(e)}, e.status)
        except HostdError as e:
            return self._json({"error": str(e)}, 400)

    @staticmethod
    def _json(obj: dict, status: int = 200) -> tuple[int, str, bytes]:
        return status, "application/json", json.dumps(obj).encode()
