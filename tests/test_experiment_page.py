"""The participant's page in a real browser (Debian's chromium + chromedriver, selenium,
headless): a whole short session of each experiment, with a reload mid-session; every answer
lands once in the session store. Under CI=true a missing browser fails instead of skipping."""

from __future__ import annotations

import os
import shutil
import time

import pytest

pytest.importorskip("questplus")

from hostd.experiment.display import SimDisplay
from hostd.experiment.runner import SimilaritySession, ThresholdSession
from hostd.experiment.server import ExperimentServer
from hostd.experiment.session import Store
from hostd.experiment.threshold import ThresholdConfig

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
DRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync")


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
        time.sleep(0.05)
    raise AssertionError(f"page never showed {what}: {drv.find_element('tag name', 'body').text!r}")


def _choices(drv):
    bs = drv.find_elements("css selector", "#choices button")
    return bs if bs and all(b.is_enabled() for b in bs) else None


def _progress(drv) -> str:
    return drv.find_element("id", "progress").text


def _run_session(drv, sess, url, reload_after: int, use_key_at: int) -> list[str]:
    from selenium.webdriver.common.keys import Keys  # noqa: F401  (keys are sent as text)

    drv.get(url)
    seen = []
    n = 0
    while True:
        done = drv.find_element("id", "title").text.startswith("Thank you")
        if done:
            break
        buttons = _wait(drv, lambda d: _choices(d) or
                        d.find_element("id", "title").text.startswith("Thank you"), "a trial")
        if buttons is True:
            break
        before = sess.answered()
        seen.append(_wait(drv, _progress, "the progress"))
        if n == reload_after:
            drv.refresh()  # mid-trial: the trial in flight is presented again, nothing recorded
            _wait(drv, _choices, "the trial after the reload")
            assert sess.answered() == before
        buttons = _wait(drv, _choices, "the trial's buttons")
        if n == use_key_at:
            drv.find_element("tag name", "body").send_keys(buttons[-1].get_attribute("data-value"))
        else:
            buttons[0].click()
        _wait(drv, lambda d, b=before: sess.answered() == b + 1, "the answer recorded")
        n += 1
    return seen


def test_threshold_session_in_chromium_with_a_reload(browser, tmp_path):
    st = Store(tmp_path / "s.sqlite")
    st.create("tok1", "threshold", {})
    cfg = ThresholdConfig([40.0, 250.0], [3.9, 0.1], [30.0, 20.0], n_afc=2, max_trials=3, seed=1)
    sess = ThresholdSession(st, "tok1", SimDisplay(), cfg)
    srv = ExperimentServer(sess).start()
    try:
        seen = _run_session(browser, sess, srv.url, reload_after=2, use_key_at=4)
        assert "Trial 1 of about 6" in seen[0]
        rows = st.answers("tok1")
        assert [r["trial"] for r in rows] == list(range(6)) and st.state("tok1") == "done"
        assert rows[4]["answer"] == 2  # the key '2' answered trial 4
        # pause and the other session's token
        import urllib.request

        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(srv.url.replace("tok1", "other"), timeout=10)
    finally:
        srv.close()


def test_similarity_session_in_chromium_with_a_reload_and_pause(browser, tmp_path):
    from hostd.experiment.similarity import make_plan, read_design

    d = tmp_path / "design.toml"
    d.write_text('seconds = 1\nrepetitions = 1\nlength_mm = 1\n[textures]\nwood = "synthetic:wood:1"\n'
                 '[[methods]]\nmethod = "quant"\nsettings = [4, 8]\n'
                 '[[methods]]\nmethod = "cut"\nsettings = [0]\n')
    plan = make_plan(read_design(d), tmp_path / "o")
    st = Store(tmp_path / "s.sqlite")
    st.create("tok2", "similarity", plan)
    sess = SimilaritySession(st, "tok2", SimDisplay(), plan)
    srv = ExperimentServer(sess).start()
    try:
        browser.get(srv.url)
        _wait(browser, _choices, "the first trial")
        labels = [b.text.split("\n")[0] for b in _choices(browser)]
        assert labels == ["same", "possibly the same", "possibly different", "different"]
        browser.find_element("id", "pause").click()
        _wait(browser, lambda d: d.find_element("id", "title").text == "Paused", "the pause")
        assert sess.paused and [e["kind"] for e in st.events("tok2")][-1] == "paused"
        browser.refresh()  # paused across a reload too
        _wait(browser, lambda d: d.find_element("id", "title").text == "Paused", "the pause after reload")
        browser.find_element("tag name", "body").send_keys("p")
        _wait(browser, _choices, "the trial after the pause")
        seen = _run_session(browser, sess, srv.url, reload_after=1, use_key_at=2)
        assert len(seen) == 4
        rows = st.answers("tok2")
        assert [r["trial"] for r in rows] == list(range(4)) and st.state("tok2") == "done"
        assert rows[2]["answer"] == 3
        assert browser.find_element("id", "title").text.startswith("Thank you")
    finally:
        srv.close()
