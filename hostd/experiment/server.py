"""The participant's page: one session, served on loopback only (127.0.0.1), no external asset.

GET  /s/TOKEN             the page (HTML, CSS and script inline)
GET  /api/TOKEN/trial     the trial to answer, played on the display first (a reload presents
                          the trial in flight again: nothing was recorded for it)
POST /api/TOKEN/answer    {"index": i, "value": v}: committed before the reply
POST /api/TOKEN/pause     {"paused": true|false}
Any other token is 404: one session per token, one token per server.
"""

from __future__ import annotations

import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from hostd.errors import HostdError

log = logging.getLogger("hostd.experiment")
MAX_BODY = 4096

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>hostd experiment</title>
<style>
 body { font-family: sans-serif; margin: 0; padding: 2rem; background: #f4f4f4; color: #111; }
 h1 { font-size: 2rem; margin: 0 0 1rem 0; }
 #prompt { font-size: 2rem; margin: 1.5rem 0; min-height: 2.5rem; }
 #choices button { font-size: 2rem; padding: 1.5rem 2.5rem; margin: 0.5rem; min-width: 12rem;
                   border-radius: 0.6rem; border: 3px solid #224; background: #fff; cursor: pointer; }
 #choices button:disabled { opacity: 0.4; cursor: default; }
 #bar { height: 1.6rem; background: #ddd; border-radius: 0.8rem; overflow: hidden; max-width: 50rem; }
 #fill { height: 100%; width: 0; background: #2a6; }
 #progress { font-size: 1.4rem; margin: 0.5rem 0 1.5rem 0; }
 #pause, #retry { font-size: 1.4rem; padding: 0.8rem 1.6rem; margin-top: 2rem; }
 #message { font-size: 1.6rem; color: #a40; min-height: 2rem; }
 .key { font-size: 1rem; color: #555; display: block; }
</style></head>
<body>
<h1 id="title">Please wait</h1>
<div id="bar"><div id="fill"></div></div>
<div id="progress"></div>
<div id="prompt"></div>
<div id="choices"></div>
<div id="message"></div>
<button id="retry" hidden>Try again</button>
<button id="pause">Pause (P)</button>
<script>
"use strict";
const api = location.pathname.replace(/^\\/s\\//, "/api/");
let current = null, paused = false, busy = false;
const $ = (id) => document.getElementById(id);
function show(s) {
  $("fill").style.width = (s.total ? 100 * s.answered / s.total : 0) + "%";
  $("progress").textContent = "Trial " + Math.min(s.answered + 1, s.total) + " of about " + s.total;
  $("choices").innerHTML = ""; $("message").textContent = ""; $("retry").hidden = true;
  current = null;
  if (s.done) {
    $("title").textContent = s.aborted ? "The session was stopped" : "Thank you: the session is complete";
    $("prompt").textContent = ""; $("pause").hidden = true; return;
  }
  if (s.retry) { $("title").textContent = "Please wait"; $("message").textContent = s.message;
                 $("retry").hidden = false; return; }
  if (s.paused) { $("title").textContent = "Paused"; $("prompt").textContent = "Press Resume (P) to go on.";
                  $("pause").textContent = "Resume (P)"; return; }
  $("pause").textContent = "Pause (P)";
  current = s.trial;
  $("title").textContent = s.kind === "threshold" ? "Detection" : "Similarity";
  $("prompt").textContent = current.prompt;
  for (const c of current.choices) {
    const b = document.createElement("button");
    b.dataset.value = c.value; b.id = "choice-" + c.value;
    b.innerHTML = c.label + '<span class="key">key ' + c.key + "</span>";
    b.onclick = () => answer(c.value);
    $("choices").appendChild(b);
  }
}
async function call(path, body) {
  const r = await fetch(api + path, body === undefined ? {} :
    {method: "POST", headers: {"Content-Type": "application/json"}, body: JSON.stringify(body)});
  if (!r.ok) throw new Error(await r.text());
  return r.json();
}
async function load() {
  busy = true;
  current = null;  // the display plays the trial while this request is out: say so, take no answer
  $("prompt").textContent = "Feel the display now: the trial is playing";
  for (const b of document.querySelectorAll("#choices button")) b.disabled = true;
  try { show(await call("/trial")); }
  catch (e) { $("message").textContent = "No answer from hostd (" + e.message + "): retrying";
              setTimeout(load, 2000); }
  finally { busy = false; }
}
async function answer(v) {
  if (busy || current === null) return;
  busy = true;
  for (const b of document.querySelectorAll("#choices button")) b.disabled = true;
  try { await call("/answer", {index: current.index, value: v}); }
  catch (e) { $("message").textContent = "Not recorded (" + e.message + "): answer again"; busy = false;
              for (const b of document.querySelectorAll("#choices button")) b.disabled = false; return; }
  busy = false; load();
}
async function togglePause() {
  if (busy) return;
  paused = !($("pause").textContent.startsWith("Resume"));
  await call("/pause", {paused: paused}); load();
}
$("pause").onclick = togglePause;
$("retry").onclick = load;
document.addEventListener("keydown", (e) => {
  if (e.key === "p" || e.key === "P") { togglePause(); return; }
  if (current === null) return;
  for (const c of current.choices) if (c.key === e.key) answer(c.value);
});
load();
</script></body></html>
"""


class ExperimentServer:
    """Serves one session on 127.0.0.1:port (0: a free port) in a background thread."""

    def __init__(self, session, port: int = 0) -> None:
        self.session = session
        token = session.token
        outer = self

        class Handler(BaseHTTPRequestHandler):
            server_version = "hostd-experiment"

            def log_message(self, fmt, *args):  # the experimenter's terminal shows progress instead
                log.debug("page: " + fmt, *args)

            def _send(self, code: int, body: bytes, ctype: str) -> None:
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.send_header("Content-Security-Policy",
                                 "default-src 'self' 'unsafe-inline'; connect-src 'self'")
                self.end_headers()
                self.wfile.write(body)

            def _json(self, obj: dict, code: int = 200) -> None:
                self._send(code, json.dumps(obj).encode(), "application/json")

            def _route(self) -> str | None:
                parts = self.path.split("?", 1)[0].strip("/").split("/")
                if len(parts) >= 2 and parts[1] == token and parts[0] in ("s", "api"):
                    return "page" if parts[0] == "s" and len(parts) == 2 else (
                        parts[2] if parts[0] == "api" and len(parts) == 3 else None)
                return None

            def do_GET(self):
                r = self._route()
                if r == "page":
                    self._send(200, PAGE.encode(), "text/html; charset=utf-8")
                elif r == "trial":
                    try:
                        self._json(outer.session.state())
                    except HostdError as e:
                        self._json({"error": str(e)}, 500)
                else:
                    self._send(404, b"no such session on this server", "text/plain")

            def do_POST(self):
                r = self._route()
                n = int(self.headers.get("Content-Length") or 0)
                if r not in ("answer", "pause") or not 0 <= n <= MAX_BODY:
                    self._send(404, b"no such session on this server", "text/plain")
                    return
                try:
                    body = json.loads(self.rfile.read(n) or b"{}")
                    if r == "answer":
                        idx, val = body["index"], body["value"]
                        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (idx, val)):
                            raise ValueError("index and value must be integers")
                        self._json(outer.session.answer(idx, val))
                    else:
                        outer.session.pause(bool(body.get("paused")))
                        self._json({"ok": True})
                except (ValueError, KeyError, TypeError) as e:
                    self._json({"error": f"bad request: {e}"}, 400)
                except HostdError as e:
                    self._json({"error": str(e)}, 400)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}/s/{token}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, name="experiment-page", daemon=True)

    def start(self) -> ExperimentServer:
        self.thread.start()
        return self

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
