"""The participant's page: in a real browser (Debian's chromium + chromedriver, selenium,
headless) a whole session through its plan, keyboard only, checked through chromium's
accessibility tree; and every attack on a display PC with several accounts, each refused:
another account, a page of another origin in the same chromium, forged and malformed requests,
slow and idle connections at a desktop's 1,024-fd limit, a second tab; and a restarted session
that the open page goes on with. Under CI=true a missing browser fails instead of skipping."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("questplus")

from hostd.errors import ExperimentError
from hostd.experiment.display import SimDisplay
from hostd.experiment.plan import check_plan
from hostd.experiment.runner import ThresholdSession
from hostd.experiment.server import REQUEST_TIMEOUT_S, ExperimentServer
from hostd.experiment.session import Store
from hostd.experiment.threshold import ThresholdConfig
from tests.page_client import PageClient, raw

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
DRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--window-size=1100,800")
SHOTS = os.environ.get("HOSTD_PAGE_SCREENSHOTS")  # a folder: the docs' screenshots go there too
NO_PRACTICE = check_plan({"practice": {"trials": 0}})


def _unavailable(why: str):
    if os.environ.get("CI") == "true":
        pytest.fail(f"browser test cannot run in CI: {why} (./run test installs chromium chromium-driver)")
    pytest.skip(why)


@pytest.fixture
def browser(tmp_path):
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        _unavailable("selenium is not installed (the dev group)")
    if not (os.path.exists(CHROMIUM) and os.path.exists(DRIVER)):
        _unavailable("Debian's chromium and chromium-driver are not installed")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for f in FLAGS:
        opts.add_argument(f)
    opts.add_argument(f"--user-data-dir={tmp_path / 'profile'}")
    drv = webdriver.Chrome(service=Service(executable_path=DRIVER), options=opts)
    drv.set_page_load_timeout(60)
    yield drv
    drv.quit()


def _wait(drv, cond, what: str, timeout_s: float = 30.0):
    """Poll the page (a condition of the DOM, not of time): fails naming what never appeared."""
    from selenium.common.exceptions import StaleElementReferenceException

    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            v = cond(drv)
        except StaleElementReferenceException:  # the page replaced it meanwhile: look again
            v = None
        if v:
            return v
        time.sleep(0.03)
    raise AssertionError(f"page never showed {what}: {drv.find_element('tag name', 'body').text!r}")


def _choices(drv):
    bs = drv.find_elements("css selector", "#choices button")
    return bs if bs and all(b.is_enabled() for b in bs) else None


def _title(drv) -> str:
    return drv.find_element("id", "title").text


def _key(drv, key: str) -> None:
    """A key press to whatever has the focus (keyboard only: no click)."""
    from selenium.webdriver.common.action_chains import ActionChains

    ActionChains(drv).send_keys(key).perform()


def _shot(drv, tmp_path: Path, name: str) -> None:
    drv.save_screenshot(str(tmp_path / f"{name}.png"))
    assert (tmp_path / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if SHOTS:
        shutil.copy(tmp_path / f"{name}.png", Path(SHOTS) / f"experiment-{name}.png")


class GatedDisplay(SimDisplay):
    """The simulated display, whose intervals wait while `gate` is cleared (a trial held in its
    first interval, for as long as a check of the page needs)."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.gate = threading.Event()
        self.gate.set()

    def play(self, s) -> None:
        assert self.gate.wait(30)
        super().play(s)

    def play_silence(self, duration_s: float) -> None:
        assert self.gate.wait(30)
        super().play_silence(duration_s)


def _session(tmp_path, steps=NO_PRACTICE, realtime=False, trials=2, duration_s=0.5, gap_s=0.4):
    st = Store(tmp_path / "s.sqlite")
    st.create("p01", "threshold", {})
    cfg = ThresholdConfig([40.0, 250.0], [3.9, 0.1], [30.0, 20.0], n_afc=2, max_trials=trials, seed=1,
                          duration_s=duration_s, gap_s=gap_s)
    disp = GatedDisplay(realtime=realtime)
    sess = ThresholdSession(st, "p01", disp, cfg, steps)
    lines: list[str] = []
    srv = ExperimentServer(sess, report=lines.append).start()
    return st, sess, disp, srv, lines


def _ax(drv) -> list[dict]:
    """Chromium's accessibility tree (what a screen reader is given), nodes not ignored."""
    nodes = drv.execute_cdp_cmd("Accessibility.getFullAXTree", {})["nodes"]
    out = []
    for n in nodes:
        if n.get("ignored"):
            continue
        props = {p["name"]: p["value"].get("value") for p in n.get("properties", [])}
        out.append({"role": n.get("role", {}).get("value"), "name": n.get("name", {}).get("value", ""),
                    **props})
    return out


WATCH = """
window.seen = [];
const note = () => {
  const live = document.getElementById('live').textContent;
  const on = [...document.querySelectorAll('#parts .part.playing')].map(e => e.id).join(',');
  const last = window.seen[window.seen.length - 1];
  if (!last || last.live !== live || last.on !== on) window.seen.push({live, on});
};
new MutationObserver(note).observe(document.body, {subtree: true, childList: true, characterData: true,
                                                   attributes: true, attributeFilter: ['class']});
"""


def test_a_whole_plan_keyboard_only_marks_each_interval_for_eyes_and_screen_readers(browser, tmp_path):
    """Instructions, consent, a practice trial (not scored), the main trials with a break, the end
    page: keys only (Enter on the focused button, digits to answer); each interval is marked while
    it plays, on screen and in the ARIA live region; chromium's accessibility tree names every
    control; a reload mid-session plays the trial in flight again and records nothing."""
    from selenium.webdriver.common.keys import Keys

    steps = check_plan({"consent": {"text": "I agree to take part."}, "practice": {"trials": 1},
                        "breaks": {"every_trials": 2}})
    st, sess, disp, srv, _ = _session(tmp_path, steps, realtime=True, duration_s=0.3, gap_s=0.2)
    d = browser
    try:
        d.get(srv.url)
        _wait(d, lambda d: _title(d) == "Before you start", "the instructions")
        _shot(d, tmp_path, "instructions")
        assert d.switch_to.active_element.text == "Start the practice"  # the focus is on the way on
        _key(d, Keys.ENTER)
        _wait(d, lambda d: _title(d) == "Consent", "the consent step")
        _key(d, Keys.ENTER)  # "I agree" has the focus
        _wait(d, lambda d: _title(d).startswith("Practice"), "the practice trial")
        d.execute_script(WATCH)
        _wait(d, _choices, "the practice trial played")
        seen = d.execute_script("return window.seen")
        lives = [s["live"] for s in seen]
        assert "Interval 1 playing" in lives and "Interval 2 playing" in lives, lives
        assert lives.index("Interval 1 playing") < lives.index("Interval 2 playing")
        assert {"live": "Interval 1 playing", "on": "part-1"} in seen  # on screen too
        assert {"live": "Interval 2 playing", "on": "part-2"} in seen
        assert lives[-1].startswith("Answer now")
        _key(d, "1")
        _wait(d, lambda d: _title(d) == "Practice complete", "the end of the practice")
        target = sess.practice_trial(0)["target"]
        want = "Right." if target == 1 else f"Not quite: it was interval {target}."
        _wait(d, lambda d: d.find_element("id", "live").text == want, "the practice's feedback")
        assert st.answers("p01") == []  # not scored
        disp.gate.clear()  # the first scored trial waits in its first interval
        _key(d, Keys.ENTER)
        _wait(d, lambda d: d.find_elements("css selector", "#part-1.playing"), "interval 1 marked")
        ax = _ax(d)  # what a screen reader has while interval 1 plays
        assert [n["name"] for n in ax if n["role"] == "listitem"] == ["Interval 1, playing now", "Interval 2"]
        assert any(n["role"] == "StaticText" and n["name"] == "Interval 1 playing" for n in ax)
        assert all(n.get("disabled") for n in ax
                   if n["role"] == "button" and n["name"].startswith("Interval"))
        _shot(d, tmp_path, "playing")
        disp.gate.set()
        answered = 0
        while answered < 4:
            if answered == 2:
                _wait(d, lambda d: _title(d) == "Break", "the break")
                _shot(d, tmp_path, "break")
                _key(d, Keys.ENTER)
            buttons = _wait(d, _choices, "the trial's buttons")
            if answered == 0:
                _shot(d, tmp_path, "answer")
                ax = _ax(d)
                named = {(n["role"], n["name"]) for n in ax}
                assert {("button", "Interval 1"), ("button", "Interval 2"), ("button", "Pause (P)")} <= named
                assert any(n["role"] == "status" and n.get("live") == "assertive" for n in ax)
                assert any(n["role"] == "StaticText" and n["name"].startswith("Answer now") for n in ax)
                assert any(n["role"] == "progressbar" for n in ax)
                assert [n["name"] for n in ax if n["role"] == "listitem"] == ["Interval 1", "Interval 2"]
                focused = [(n["role"], n["name"]) for n in ax
                           if n.get("focused") and n["role"] != "RootWebArea"]
                assert focused == [("button", "Interval 1")]  # the first answer has the focus
                assert all(n.get("keyshortcuts") for n in ax if n["role"] == "button"
                           and n["name"].startswith("Interval"))
            if answered == 1:  # a reload: the trial in flight plays again, nothing recorded
                plays = sess.presentations
                d.refresh()
                _wait(d, _choices, "the trial after the reload")
                assert sess.presentations == plays + 1 and len(st.answers("p01")) == 1
                buttons = _choices(d)
            _key(d, buttons[-1].get_attribute("data-value"))
            answered += 1
            _wait(d, lambda d, n=answered: len(st.answers("p01")) == n, "the answer recorded")
        _wait(d, lambda d: _title(d) == "Thank you", "the end page")
        _shot(d, tmp_path, "end")
        assert [a["answer"] for a in st.answers("p01")] == [2, 2, 2, 2] and st.state("p01") == "done"
        kinds = [e["kind"] for e in st.events("p01")]
        assert kinds.index("consented") < kinds.index("practice") < kinds.index("practice_done")
    finally:
        srv.close()


def test_a_similarity_session_in_chromium_names_its_parts_and_keeps_a_pause_over_a_reload(browser, tmp_path):
    from hostd.experiment.runner import SimilaritySession
    from hostd.experiment.similarity import make_plan, read_design

    dsg = tmp_path / "design.toml"
    dsg.write_text('seconds = 1\nrepetitions = 1\nlength_mm = 1\n[textures]\nwood = "synthetic:wood:1"\n'
                   '[[methods]]\nmethod = "quant"\nsettings = [4]\n')
    plan = make_plan(read_design(dsg), tmp_path / "o")
    st = Store(tmp_path / "s.sqlite")
    st.create("p02", "similarity", plan)
    sess = SimilaritySession(st, "p02", SimDisplay(), plan, NO_PRACTICE)
    srv = ExperimentServer(sess).start()
    d = browser
    try:
        d.get(srv.url)
        _wait(d, lambda d: d.find_elements("id", "step-continue"), "the instructions")
        d.find_element("id", "step-continue").click()
        buttons = _wait(d, _choices, "the first trial")
        assert [b.text.split("\n")[0] for b in buttons] == ["same", "possibly the same", "possibly different",
                                                           "different"]
        parts = [e.text for e in d.find_elements("css selector", "#parts .part")]
        assert parts == ["Reference", "Comparison"]
        d.find_element("id", "pause").click()
        _wait(d, lambda d: _title(d) == "Paused", "the pause")
        assert sess.paused and [e["kind"] for e in st.events("p02")][-1] == "paused"
        d.refresh()  # paused across a reload too
        _wait(d, lambda d: _title(d) == "Paused", "the pause after the reload")
        _key(d, "p")
        _wait(d, _choices, "the trial played again after the pause")
        for n in (1, 2):
            _wait(d, _choices, "a trial played")
            _key(d, "3")
            _wait(d, lambda d, n=n: len(st.answers("p02")) == n, "the grade recorded")
        _wait(d, lambda d: _title(d) == "Thank you", "the end page")
        assert [a["answer"] for a in st.answers("p02")] == [3, 3] and st.state("p02") == "done"
    finally:
        srv.close()


def test_a_store_that_cannot_take_the_answer_is_a_plain_message_the_page_keeps(browser, tmp_path,
                                                                              monkeypatch):
    """(The real full disk is tests/test_experiment.py's; here, what the participant sees.)"""
    from hostd.experiment.session import StorageError

    st, _, _, srv, _ = _session(tmp_path)

    def full(*a):
        raise StorageError("cannot record the answer in /x/session.sqlite: database or disk is full")

    d = browser
    try:
        d.get(srv.url)
        _wait(d, lambda d: d.find_elements("id", "step-continue"), "the instructions")
        d.find_element("id", "step-continue").click()
        _wait(d, _choices, "the first trial")
        monkeypatch.setattr(st, "record", full)
        _key(d, "1")
        _wait(d, lambda d: _title(d) == "The session has stopped", "the stop")
        text = d.find_element("id", "text").text
        assert text.startswith("Your last answer could not be saved") and "tell the experimenter" in text
        assert "/" not in text and "{" not in text and not d.find_elements("css selector", "#choices button")
        srv.close()  # the command ends: the page keeps the message
        time.sleep(2.5)  # (the page asks every 2 s meanwhile)
        assert _title(d) == "The session has stopped" and d.find_element("id", "text").text == text
        assert "Waiting" not in d.find_element("id", "message").text
    finally:
        srv.close()


def test_declining_consent_ends_the_session_and_records_only_the_decline(tmp_path):
    steps = check_plan({"consent": {"text": "I agree."}, "practice": {"trials": 2}})
    st, sess, disp, srv, _ = _session(tmp_path, steps)
    try:
        c = PageClient(srv.url)
        assert c.open()["phase"] == "instructions"
        assert c.post("step", {"action": "continue"})[0] == 200
        assert c.state()["screen"]["decline"] == "I do not agree"
        assert c.post("present")[0] == 409  # no trial before consent
        assert c.post("step", {"action": "decline"})[0] == 200
        assert c.state()["done"] and st.state("p01") == "declined"
        assert [e["kind"] for e in st.events("p01")] == ["started", "declined"] and st.answers("p01") == []
        assert disp.plays == 0
        with pytest.raises(ExperimentError, match="declined"):
            ThresholdSession(st, "p01", SimDisplay(), sess.cfg, steps).resume()
    finally:
        srv.close()


ATTACKER = """<!doctype html><html><body><iframe name="sink"></iframe><script>
const base = "BASE";
const out = [];
async function go() {
  for (const [route, body] of [["answer", '{"index": 0, "value": 1}'], ["pause", '{"paused": true}'],
                               ["present", "{}"], ["open", "{}"], ["step", '{"action": "continue"}']]) {
    try { await fetch(base + "/" + route, {method: "POST", mode: "no-cors",
                                           headers: {"Content-Type": "text/plain"}, body}); out.push("sent");
    } catch (e) { out.push("error"); }
    try { const r = await fetch(base + "/" + route, {method: "POST", body,
            headers: {"Content-Type": "application/json", "X-Hostd-Page": "forged.00"}});
          out.push("read " + r.status); } catch (e) { out.push("blocked"); }
  }
  try { const r = await fetch(base + "/state"); out.push("state " + (await r.text()).length); }
  catch (e) { out.push("state blocked"); }
  for (const path of ["/state", "/trial"]) {
    await new Promise((ok) => { const i = new Image(); i.onload = i.onerror = ok; i.src = base + path; });
  }
  const f = document.createElement("form");
  f.method = "POST"; f.action = base + "/answer"; f.enctype = "text/plain"; f.target = "sink";
  const i = document.createElement("input"); i.name = '{"index": 0, "value": 1, "x": "'; i.value = '"}';
  f.appendChild(i); document.body.appendChild(f);
  await new Promise((ok) => { document.querySelector("iframe").onload = ok; f.submit(); });
  window.results = out;
}
go();
</script></body></html>"""


def test_a_page_of_another_origin_in_the_same_chromium_can_do_nothing(browser, tmp_path):
    """Another local origin (http://localhost:PORT2) that even knows the page's address sends
    no-cors text/plain POSTs, JSON POSTs (preflighted), <img> GETs and a form POST: nothing is
    answered, paused, played or taken over; the participant's page then answers as before."""
    import http.server

    st, sess, disp, srv, lines = _session(tmp_path)
    d = browser
    evil_dir = tmp_path / "evil"
    evil_dir.mkdir()
    (evil_dir / "index.html").write_text(ATTACKER.replace("BASE", srv.url.replace("/s/", "/api/")))
    handler = lambda *a, **k: http.server.SimpleHTTPRequestHandler(*a, directory=str(evil_dir), **k)  # noqa: E731
    evil = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=evil.serve_forever, daemon=True).start()
    try:
        d.get(srv.url)
        _wait(d, lambda d: d.find_elements("id", "step-continue"), "the instructions")
        d.find_element("id", "step-continue").click()
        _wait(d, _choices, "the first trial played")
        page_tab = d.current_window_handle
        before = (disp.plays, sess.presentations, sess.holder, sess.phase)
        d.switch_to.new_window("tab")
        d.get(f"http://localhost:{evil.server_address[1]}/index.html")
        results = _wait(d, lambda d: d.execute_script("return window.results"), "the attack's end")
        assert results.count("sent") == 5 and results.count("blocked") == 5, results  # preflight refused
        assert "state blocked" in results  # nor can it read the state
        assert (disp.plays, sess.presentations, sess.holder, sess.phase) == before
        assert st.answers("p01") == [] and not sess.paused and sess.presented is not None
        assert any("Origin 'http://localhost:" in x for x in lines), lines
        assert not any(e["kind"] in ("paused", "unpaused") for e in st.events("p01"))
        d.close()
        d.switch_to.window(page_tab)
        _key(d, "2")  # the same-origin page, with its CSRF value, still works
        _wait(d, lambda d: len(st.answers("p01")) == 1, "the participant's answer recorded")
        assert st.answers("p01")[0]["answer"] == 2
    finally:
        evil.shutdown()
        srv.close()


def test_a_second_tab_takes_the_session_over_and_no_trial_plays_twice(browser, tmp_path):
    st, sess, _, srv, _ = _session(tmp_path)
    d = browser
    try:
        d.get(srv.url)
        _wait(d, lambda d: d.find_elements("id", "step-continue"), "the instructions")
        d.find_element("id", "step-continue").click()
        _wait(d, _choices, "the first trial, in tab A")
        tab_a = d.current_window_handle
        p0 = sess.presentations
        d.switch_to.new_window("tab")
        d.get(srv.url)
        _wait(d, _choices, "the first trial, in tab B")
        tab_b = d.current_window_handle
        assert sess.presentations == p0 + 1  # played once for the page that now holds the session
        d.switch_to.window(tab_a)
        _wait(d, lambda d: _title(d) == "This session continues in another tab or window", "A told")
        _key(d, "1")
        code = d.execute_async_script("""const done = arguments[0];
            fetch(location.pathname.replace(/^\\/s\\//, "/api/") + "/answer", {method: "POST",
              headers: {"Content-Type": "application/json", "X-Hostd-Page": CSRF},
              body: JSON.stringify({index: 0, value: 1})}).then(r => done(r.status));""")
        assert code == 409 and st.answers("p01") == []  # A's CSRF value is valid, but A no longer holds it
        d.switch_to.window(tab_b)
        for n in range(1, 5):
            _key(d, "1")
            _wait(d, lambda d, n=n: len(st.answers("p01")) == n, "B's answer recorded")
            if n < 4:
                _wait(d, _choices, "B's next trial")
        assert sess.presentations == p0 + 4  # one presentation per trial since the takeover
        assert [a["trial"] for a in st.answers("p01")] == [0, 1, 2, 3]
    finally:
        srv.close()


def test_forged_early_paused_and_malformed_requests_are_refused_with_one_line_each(tmp_path):
    """The attacks of a client that has the page's address and a CSRF value, and of one that has
    neither; a GET never plays; answering while a trial plays is refused at once, not held."""
    st, sess, disp, srv, lines = _session(tmp_path, realtime=True, duration_s=1.0, gap_s=0.5)
    try:
        c = PageClient(srv.url)
        c.to_main()
        api = c.api
        # forged answers to trials never presented: 12 of them, each refused
        for i in range(12):
            assert c.answer(i, 1)[0] == 409
        # a GET never plays or changes anything (the old trial GET is gone)
        for _ in range(5):
            c.state()
        assert c.request("GET", f"{api}/trial")[0] == 404 and disp.plays == 0 and sess.presentations == 0
        # playing never blocks answering: refused at once while the trial plays (2.5 s)
        assert c.post("present")[0] == 200
        t0 = time.monotonic()
        code, rep = c.answer(0, 1)
        assert code == 409 and "still playing" in rep["error"] and sess.playing is not None
        assert time.monotonic() - t0 < 1.0  # (the trial plays for 2.5 s)
        assert c.post("present")[0] == 409  # no second presentation while one plays
        s = c.wait(lambda s: s["presented"], "the trial played")
        # paused: refused, and the trial plays again afterwards
        assert c.post("pause", {"paused": True})[0] == 200
        assert c.answer(s["trial"]["index"], 1)[0] == 409
        assert c.post("pause", {"paused": False})[0] == 200 and not c.state()["presented"]
        assert st.answers("p01") == []
        # without the page's values
        ok = {"Content-Type": "application/json", "Origin": c.origin, "X-Hostd-Page": c.csrf}
        body = b'{"index": 0, "value": 1}'
        for hdrs, want in [({**ok, "Origin": "http://localhost:8999"}, 403), ({**ok, "Origin": "null"}, 403),
                           ({k: v for k, v in ok.items() if k != "Origin"}, 403),
                           ({**ok, "Content-Type": "text/plain"}, 415),
                           ({k: v for k, v in ok.items() if k != "X-Hostd-Page"}, 403),
                           ({**ok, "X-Hostd-Page": c.csrf[:-2] + "00"}, 403),
                           ({**ok, "Host": "evil.example:80"}, 403)]:
            assert c.request("POST", f"{api}/answer", body, hdrs)[0] == want, hdrs
        assert c.request("POST", f"/api/{'A' * 32}/answer", body, ok)[0] == 404  # a guessed address
        assert c.request("POST", "/api/p01/answer", body, ok)[0] == 404  # the participant's id
        assert c.request("OPTIONS", f"{api}/answer", None, ok)[0] == 405
        # malformed: one line on the terminal each, a 4xx to the client
        n = len(lines)
        head = f"POST {api}/answer HTTP/1.1\r\nHost: {c.host}:{c.port}\r\nOrigin: {c.origin}\r\n" \
               f"Content-Type: application/json\r\nX-Hostd-Page: {c.csrf}\r\n"
        rep1 = raw(c.port, (head + "Content-Length: abc\r\n\r\n").encode())
        rep2 = raw(c.port, (head + "Content-Length: 4000\r\n\r\n").encode() + b"[" * 4000)
        rep3 = raw(c.port, b"\x16\x03\x01garbage\r\n\r\n")
        assert rep1.startswith(b"HTTP/1.1 400") and rep2.startswith(b"HTTP/1.1 400")
        assert rep3.startswith(b"HTTP/1.1 400")
        new = lines[n:]
        assert len(new) == 3 and all("\n" not in x and "Traceback" not in x for x in new), new
        assert "Content-Length 'abc'" in new[0] and "not JSON" in new[1]
        assert st.answers("p01") == [] and len(st.answers("p01")) == 0
        # a failure inside (here: the state cannot be read) is a 500 and one line, and the server goes on
        view = sess.view
        sess.view = lambda page: 1 / 0
        assert c.request("GET", f"{api}/state", headers={"X-Hostd-Page": c.csrf})[0] == 500
        assert "ZeroDivisionError" in lines[-1] and len(lines) == n + 4
        sess.view = view
        # and the page's own request still works
        s = c.play()
        assert c.answer(s["trial"]["index"], s["trial"]["n_afc"]) == (200, {"ok": True})
    finally:
        srv.close()


# ---------------------------------------------------------------------------- the real command
PLAN = "[practice]\ntrials = 0\n"


def _start_cli(out: Path, *extra: str, rlimit_nofile: int | None = None) -> tuple[subprocess.Popen, str]:
    plan = out.parent / "plan.toml"
    plan.write_text(PLAN)
    args = [sys.executable, "-m", "hostd", "experiment", "threshold", "-o", str(out),
            "--participant", "p01", "--frequencies", "40,250", "--trials", "3", "--afc", "2",
            "--plan", str(plan), *extra]

    def pre():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if rlimit_nofile:
            import resource

            resource.setrlimit(resource.RLIMIT_NOFILE, (rlimit_nofile, rlimit_nofile))

    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=pre)
    url = proc.stdout.readline().strip()
    if not url:
        proc.kill()
        pytest.fail(f"no address on stdout: {proc.stderr.read()}")
    return proc, url


def _stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.stderr.read()


NOBODY_SCRIPT = r"""
import json, os, sys, urllib.request, urllib.error
out, port = sys.argv[1], sys.argv[2]
res = {}
for what, fn in [("list", lambda: os.listdir(out)),
                 ("read", lambda: open(out + "/session.sqlite", "rb").read(1))]:
    try:
        fn(); res[what] = "allowed"
    except PermissionError:
        res[what] = "denied"
cmdlines = ""
for pid in os.listdir("/proc"):
    if pid.isdigit():
        try:
            cmdlines += open(f"/proc/{pid}/cmdline", "rb").read().decode(errors="replace") + "\n"
        except OSError:
            pass
res["cmdlines"] = cmdlines
codes = []
for path, body in [("/s/p01", None), ("/api/p01/state", None),
                   ("/api/p01/answer", b'{"index": 0, "value": 1}'), ("/api/p01/pause", b'{"paused": true}'),
                   ("/api/" + "x" * 32 + "/present", b"{}")]:
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", data=body,
                                 headers={"Content-Type": "application/json", "Origin": f"http://127.0.0.1:{port}"})
    try:
        codes.append(urllib.request.urlopen(req, timeout=10).status)
    except urllib.error.HTTPError as e:
        codes.append(e.code)
res["codes"] = codes
print(json.dumps(res))
"""


def test_another_account_finds_no_secret_and_can_do_nothing(tmp_path):
    """Another uid on the display PC (nobody, through runuser): the secret is in no process's
    argv or environment, the session folder is closed to it (0700, files 0600), and what it can
    send (the participant's id, a guess) is refused; nothing is played or recorded."""
    if os.geteuid() != 0 or not shutil.which("runuser"):
        if os.environ.get("CI") == "true":
            pytest.fail("needs root and runuser (another uid)")
        pytest.skip("needs root and runuser (another uid)")
    base = Path(tempfile.mkdtemp(prefix="hostd-page-"))  # a folder another account may reach
    os.chmod(base, 0o755)
    out = base / "o"
    proc, url = _start_cli(out)
    try:
        cap = url.rsplit("/", 1)[1]
        assert len(cap) >= 22 and "p01" not in url  # >= 128 bits, and not the participant's id
        pid = proc.pid
        assert cap.encode() not in Path(f"/proc/{pid}/cmdline").read_bytes()
        assert cap.encode() not in Path(f"/proc/{pid}/environ").read_bytes()
        port = url.split(":")[2].split("/")[0]
        r = subprocess.run(["runuser", "-u", "nobody", "--", "/usr/bin/python3", "-I", "-c", NOBODY_SCRIPT,
                            str(out), port], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        res = json.loads(r.stdout)
        assert res["list"] == "denied" and res["read"] == "denied"
        assert cap not in res["cmdlines"] and "hostd" in res["cmdlines"]  # (it did see the command)
        assert res["codes"] == [404, 404, 404, 404, 404], res["codes"]
        assert (out.stat().st_mode & 0o777) == 0o700
        assert all((f.stat().st_mode & 0o777) == 0o600 for f in out.iterdir()), \
            [(f.name, oct(f.stat().st_mode)) for f in out.iterdir()]
    finally:
        err = _stop(proc)
        shutil.rmtree(base, ignore_errors=True)
    assert cap not in err


def _threads(pid: int) -> int:
    return int(re.search(r"Threads:\s+(\d+)", Path(f"/proc/{pid}/status").read_text()).group(1))


def test_a_thousand_idle_connections_and_a_slow_client_at_a_1024_fd_limit(tmp_path):
    """The command under a desktop's default fd limit (1,024): 1,000 idle connections open, the
    participant's page still plays and answers; a client sending a byte at a time is dropped
    after REQUEST_TIMEOUT_S; the server stays one thread for all of them."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 2200:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4096), hard))
    proc, url = _start_cli(tmp_path / "o", rlimit_nofile=1024)
    idle: list[socket.socket] = []
    try:
        port = int(url.split(":")[2].split("/")[0])
        threads0 = _threads(proc.pid)
        for _ in range(1000):
            s = socket.socket()
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\0" * 8)
            s.connect(("127.0.0.1", port))
            idle.append(s)
        assert _threads(proc.pid) <= threads0 + 1  # no thread per connection (numpy's pool aside)
        c = PageClient(url)  # the participant's page, behind 1,000 idle connections
        c.to_main()
        s = c.play()
        assert c.answer(s["trial"]["index"], 1) == (200, {"ok": True})
        slow = socket.create_connection(("127.0.0.1", port), timeout=REQUEST_TIMEOUT_S + 10)
        t0 = time.monotonic()
        closed_after = None
        try:
            for ch in b"GET /s/x HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 100:
                slow.send(bytes([ch]))
                time.sleep(0.25)
        except OSError:
            closed_after = time.monotonic() - t0
        if closed_after is None:
            slow.settimeout(REQUEST_TIMEOUT_S + 10)
            assert slow.recv(100) == b""
            closed_after = time.monotonic() - t0
        assert REQUEST_TIMEOUT_S - 0.5 < closed_after < REQUEST_TIMEOUT_S + 3.0, closed_after
        slow.close()
    finally:
        for s in idle:
            s.close()
        err = _stop(proc)
    assert "Traceback" not in err


def test_a_restarted_session_keeps_its_port_and_the_open_page_goes_on_within_5_s(browser, tmp_path):
    out = tmp_path / "o"
    proc, url = _start_cli(out)
    d = browser
    try:
        d.get(url)
        _wait(d, lambda d: d.find_elements("id", "step-continue"), "the instructions")
        d.find_element("id", "step-continue").click()
        _wait(d, _choices, "the first trial")
        _key(d, "1")
        st = Store(out / "session.sqlite")
        _wait(d, lambda d: len(st.answers("p01")) == 1, "the answer recorded")
        proc.kill()  # a crash
        proc.wait(30)
        _wait(d, lambda d: "Waiting for hostd" in d.find_element("id", "message").text, "the wait")
        proc, url2 = _start_cli(out, "--resume")
        t0 = time.monotonic()
        assert url2 == url  # the same port and address: the open page goes on
        _wait(d, _choices, "the next trial after the restart", timeout_s=5.0)
        assert time.monotonic() - t0 < 5.0
        _key(d, "2")
        _wait(d, lambda d: len(st.answers("p01")) == 2, "the answer after the restart")
        assert [a["trial"] for a in st.answers("p01")] == [0, 1]
    finally:
        _stop(proc)
