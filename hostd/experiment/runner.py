"""The two experiments as sessions the page drives, through the session plan
(hostd.experiment.plan): instructions, consent, practice trials (not scored), the main trials
with breaks, the end page.

A trial is played on the display by a player thread (the page's `present`), which marks each
part as it plays; an answer counts only for the trial played whole on the page that asked for
it (`presented`), never while it plays or while the session is paused, and is committed to the
store before anything else happens. Only the page that holds the session (the last one to
`open` it: a second tab takes the session over, the first is told so) can act on it.

Both experiments are deterministic given their plan and the answers: a session resumes by
replaying the answers recorded, and must meet the same trials (checked: a plan that no longer
matches is an error, not a silent divergence). A display that disconnects while a trial plays
is an event; the trial is presented again and nothing is recorded for it. A store that cannot
take a write (disk full) stops the session: `failure` is the page's plain message,
`failure_detail` the experimenter's line.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from hostd.errors import DeviceError, ExperimentError
from hostd.experiment.display import Sinusoid
from hostd.experiment.plan import break_due, read_plan
from hostd.experiment.session import StorageError, Store

SIMILARITY_SCALE = ("same", "possibly the same", "possibly different", "different")  # 0..3 (paper IV-A)
TRIAL_PHASES = ("practice", "main")


class Refused(ExperimentError):
    """A page's request the session does not take now: an HTTP status and a plain message."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


DISK_FULL_ANSWER = ("Your last answer could not be saved: the experimenter's computer could not store it. "
                    "Please tell the experimenter. Every earlier answer is kept.")
DISK_FULL_DONE = ("Your answers are saved, but the session could not be closed: the experimenter's computer "
                  "could not store it. Please tell the experimenter.")
REFUSED = "The session had to stop: the display refused a stimulus. Please tell the experimenter."
FREE_SPACE = ". Free space, then run the same command with --resume: every answer recorded is kept"
DISK_FULL_OTHER = ("The session had to stop: the experimenter's computer could not store it. "
                   "Please tell the experimenter. Every answer you gave is kept.")


class Session:
    kind = ""
    parts: tuple[str, ...] = ()

    def __init__(self, store: Store, token: str, display, steps: dict | None = None) -> None:
        self.store, self.token, self.display = store, token, display
        self.steps = steps if steps is not None else read_plan()
        self.lock = threading.Lock()
        self.paused = False
        self.holder: str | None = None  # the page that holds the session
        self.phase = "instructions"  # instructions consent practice intro main break end declined
        self.practice_n = 0
        self.playing: dict | None = None  # {"part": i (1..), "label": ...} while a trial plays
        self.player: threading.Thread | None = None
        self.presented: dict | None = None  # {"page", "index", "at"}: played whole, awaiting its answer
        self.presentations = 0
        self.retry: str | None = None
        self.feedback: str | None = None
        self.failure: str | None = None  # the page's message when the store failed
        self.failure_detail: str | None = None  # the experimenter's line
        self.display_lost = 0
        self.last_break = time.monotonic()

    # ------------------------------------------------------------------ for the page
    def open(self, page: str) -> dict:
        """`page` takes the session over (a second tab, or the page after a restart)."""
        with self.lock:
            if self.holder != page and self.presented is not None:
                self.presented = None  # played on the other page: this one plays it again
            self.holder = page
        return self.view(page)

    def view(self, page: str | None) -> dict:
        """What the page shows now; changes nothing (the page's GET)."""
        with self.lock:
            phase = self.phase
            if self.store.state(self.token) == "aborted":
                phase = "stopped"
            v = {"phase": phase, "yours": page is not None and page == self.holder,
                 "held": self.holder is not None, "paused": self.paused, "playing": self.playing,
                 "presented": bool(self.presented and self.presented["page"] == page),
                 "retry": self.retry, "feedback": self.feedback, "practiced": self.practice_n,
                 "failure": self.failure,
                 "done": phase in ("end", "declined", "stopped"), **self.progress()}
            if phase in TRIAL_PHASES:
                t = self._trial()
                v["trial"] = None if t is None else self.public(t)
            v["screen"] = self._screen(phase)
        return v

    def present(self, page: str) -> dict:
        """Play the trial of the moment on the display (in the player thread); refused while one
        plays, while paused, outside the trial phases, or from a page not holding the session."""
        with self.lock:
            self._check(page)
            if self.paused:
                raise Refused(409, "The session is paused: resume it first.")
            if self.phase not in TRIAL_PHASES:
                raise Refused(409, "There is no trial to play now.")
            if self.playing is not None:
                raise Refused(409, "The trial is playing.")
            t = self._trial()
            self.presented = self.retry = self.feedback = None
            self.playing = {"part": 0, "label": ""}
            self.presentations += 1
            self.player = threading.Thread(target=self._play, args=(t, page), name="experiment-player",
                                           daemon=True)
            self.player.start()
        return {"ok": True}

    def answer(self, page: str, index: int, value: int) -> dict:
        with self.lock:
            self._check(page)
            if self.paused:
                raise Refused(409, "The session is paused: resume it, the trial plays again.")
            if self.playing is not None:
                raise Refused(409, "The trial is still playing: answer once it has played.")
            p = self.presented
            if p is None or p["page"] != page or p["index"] != index:
                raise Refused(409, "That trial was not played on this page: it plays again.")
            self.check_answer(value)
            t = self._trial()
            self.presented = None
            if self.phase == "practice":
                self.feedback = self.practice_feedback(t, value) if self.steps["practice"]["feedback"] \
                    else None
                self.practice_n += 1
                done = self.practice_n >= self.steps["practice"]["trials"]
                self._store(DISK_FULL_OTHER, self.store.event, self.token, "practice",
                            f"practice trial {self.practice_n}: answer {value} (not scored)")
                if done:
                    self._store(DISK_FULL_OTHER, self.store.event, self.token, "practice_done", "")
                    self.phase = "intro"
                return {"ok": True, "practice": True}
            if not self._store(DISK_FULL_ANSWER, self.store.record, self.token, index, value, t, p["at"]):
                return {"ignored": True}
            self.advance(t, value)
            if self.current() is None:
                self._finish()
            elif break_due(self.steps, self.answered(), self.total(),
                           (time.monotonic() - self.last_break) / 60.0):
                self.phase = "break"
        return {"ok": True}

    def step(self, page: str, action: str) -> dict:
        """Go past a screen: instructions, consent (agree | decline), the practice's end, a break."""
        with self.lock:
            self._check(page)
            ph = self.phase
            self.feedback = None
            if ph == "consent" and action == "decline":
                self._store(DISK_FULL_OTHER, self.store.set_state, self.token, "declined")
                self._store(DISK_FULL_OTHER, self.store.event, self.token, "declined", "")
                self.phase = "declined"
            elif ph == "consent" and action == "agree":
                self._store(DISK_FULL_OTHER, self.store.event, self.token, "consented", "")
                self.phase = self._after_consent()
            elif ph == "instructions" and action == "continue":
                self.phase = "consent" if self.steps["consent"] else self._after_consent()
            elif ph in ("intro", "break") and action == "continue":
                self.phase = "main"
                self.last_break = time.monotonic()
            else:
                raise Refused(409, "That step is not the session's now.")
        return {"ok": True}

    def pause(self, page: str, paused: bool) -> None:
        with self.lock:
            self._check(page)
            if paused != self.paused:
                self.paused = paused
                self.presented = None  # after a pause the trial plays again
                self._store(DISK_FULL_OTHER, self.store.event, self.token,
                            "paused" if paused else "unpaused", "")

    # ------------------------------------------------------------------ for the experimenter
    def abort(self) -> None:
        with self.lock:
            self.store.set_state(self.token, "aborted")
            self.store.event(self.token, "aborted", "by the experimenter")

    def resume(self) -> None:
        """Replay the recorded answers against the plan; a session already complete is marked
        done (a done mark the disk could not take)."""
        if self.store.state(self.token) == "declined":
            raise ExperimentError(f"session {self.token}: the participant declined; there is nothing to "
                                  "resume (a new session needs a new --participant)")
        for a in self.store.answers(self.token):
            t = self.current()
            if t is None or t["index"] != a["trial"] or not self.same_trial(t, a["stimulus"]):
                raise ExperimentError(f"session {self.token}: answer {a['trial']} does not match the plan "
                                      "(a different questplus or hostd version?): start a new session")
            self.advance(t, a["answer"])
        events = {e["kind"] for e in self.store.events(self.token)}
        if self.answered() or "practice_done" in events:
            self.phase = "main"
        elif "consented" in events:
            self.phase = self._after_consent()
        if self.store.state(self.token) in ("aborted", "done"):
            self.store.set_state(self.token, "running")
        self.store.event(self.token, "resumed", f"at trial {self.answered()}")
        if self.current() is None:
            self.store.set_state(self.token, "done")
            self.store.event(self.token, "done", "")
            self.phase = "end"

    def finished(self) -> bool:
        return self.phase in ("end", "declined") or self.failure is not None

    # ------------------------------------------------------------------ inside
    def _check(self, page: str) -> None:
        if self.failure is not None:
            raise Refused(507, self.failure)
        if page != self.holder:
            raise Refused(409, "This session continues in another tab or window.")
        if self.store.state(self.token) == "aborted":
            raise Refused(409, "The session was stopped by the experimenter.")

    def _store(self, page_message: str, fn, *args):
        """A store write; when the disk cannot take it, the session stops (failure) and the page
        gets `page_message` (HTTP 507)."""
        try:
            return fn(*args)
        except StorageError as e:
            self.failure, self.failure_detail = page_message, f"{e}{FREE_SPACE}"
            raise Refused(507, page_message) from None

    def _finish(self) -> None:
        self._store(DISK_FULL_DONE, self.store.set_state, self.token, "done")
        self._store(DISK_FULL_DONE, self.store.event, self.token, "done", "")
        self.phase = "end"

    def _after_consent(self) -> str:
        return "practice" if self.steps["practice"]["trials"] > 0 else "main"

    def _trial(self) -> dict | None:
        return self.practice_trial(self.practice_n) if self.phase == "practice" else self.current()

    def _screen(self, phase: str) -> dict | None:
        st = self.steps
        if phase == "instructions":
            return {**st["instructions"], "actions": ["continue"]}
        if phase == "consent":
            c = st["consent"]
            return {"title": "Consent", "text": c["text"], "button": c["agree"], "decline": c["decline"],
                    "actions": ["agree", "decline"]}
        if phase == "intro":
            return {"title": "Practice complete", "text": st["main"]["text"], "button": st["main"]["button"],
                    "actions": ["continue"]}
        if phase == "break":
            return {"title": "Break", "text": st["breaks"]["text"], "button": st["breaks"]["button"],
                    "actions": ["continue"]}
        if phase == "end":
            return {**st["end"], "actions": []}
        if phase == "declined":
            return {"title": "Thank you", "text": "You declined: the session has ended, and only your "
                    "decline was recorded.", "actions": []}
        if phase == "stopped":
            return {"title": "The session was stopped", "text": "The experimenter stopped the session.",
                    "actions": []}
        return None

    def _play(self, t: dict, page: str) -> None:
        try:
            self.play(t)
        except DeviceError as e:
            with self.lock:
                self.playing = None
                self.display_lost += 1
                self.retry = (f"The display is not answering ({e}). The trial will be repeated: "
                              "press Try again.")
                try:
                    self.store.event(self.token, "display_lost", f"trial {t['index']}: {e}")
                except StorageError as se:
                    self.failure, self.failure_detail = DISK_FULL_OTHER, f"{se}{FREE_SPACE}"
            return
        except ExperimentError as e:  # a stimulus refused (beyond the reach): not a retry
            with self.lock:
                self.playing = None
                self.failure = REFUSED
                self.failure_detail = (f"the display refused trial {t['index']}'s stimulus ({e}); nothing "
                                       "was recorded for it: fix the display's limits, then --resume")
            return
        with self.lock:
            self.playing = None
            if not self.paused and self.holder == page and self._trial() == t:
                self.presented = {"page": page, "index": t["index"], "at": time.time()}

    def mark(self, part: int, label: str = "") -> None:
        """The player: part `part` (1..) plays now, 0 between parts."""
        self.playing = {"part": part, "label": label}

    # ------------------------------------------------------------------ per experiment
    def current(self) -> dict | None: ...
    def public(self, t: dict) -> dict: ...
    def play(self, t: dict) -> None: ...
    def check_answer(self, value: int) -> None: ...
    def advance(self, t: dict, value: int) -> None: ...
    def answered(self) -> int: ...
    def total(self) -> int: ...
    def practice_trial(self, k: int) -> dict: ...
    def practice_feedback(self, t: dict, value: int) -> str | None: ...

    def same_trial(self, t: dict, recorded: dict) -> bool:
        return t == recorded

    def progress(self) -> dict:
        return {"answered": self.answered(), "total": self.total(), "kind": self.kind}


class ThresholdSession(Session):
    """n-AFC: n intervals, one holds the sinusoid; the answer is the interval (1..n)."""

    kind = "threshold"

    def __init__(self, store: Store, token: str, display, cfg, steps: dict | None = None) -> None:
        from hostd.experiment.procedure import make_run

        super().__init__(store, token, display, steps)
        self.cfg = cfg
        self.run = make_run(cfg)

    def current(self):
        t = self.run.next_trial()
        return None if t is None else t.as_dict()

    def public(self, t):
        n = t["n_afc"]
        return {"index": t["index"], "n_afc": n, "practice": bool(t.get("practice")),
                "prompt": f"Which interval held the vibration? (1..{n})",
                "parts": [f"Interval {i}" for i in range(1, n + 1)],
                "choices": [{"value": i, "label": f"Interval {i}", "key": str(i)} for i in range(1, n + 1)]}

    def play(self, t):
        c = self.cfg
        for i in range(1, t["n_afc"] + 1):
            if i > 1:
                self.mark(0)
                self.display.wait(c.gap_s)  # between intervals: nothing is played
            self.mark(i, f"Interval {i}")
            if i == t["target"]:
                self.display.play(Sinusoid(t["frequency_hz"], t["amplitude_um"], c.duration_s))
            else:
                self.display.play_silence(c.duration_s)

    def practice_trial(self, k):
        """An easy trial (12 dB above the prior, within the reach) at each frequency in turn."""
        from hostd.experiment.threshold import db

        c = self.cfg
        i = k % len(c.frequencies_hz)
        amp = float(min(c.reach_um[i], c.prior_um[i] * 10 ** (12 / 20)))
        target = int(np.random.default_rng([c.seed, 7919, k]).integers(1, c.n_afc + 1))
        return {"index": -1 - k, "practice": True, "frequency_hz": float(c.frequencies_hz[i]),
                "amplitude_um": amp, "level_db": db(amp), "n_afc": c.n_afc, "target": target}

    def practice_feedback(self, t, value):
        return "Right." if value == t["target"] else f"Not quite: it was interval {t['target']}."

    def check_answer(self, value):
        if not 1 <= value <= self.cfg.n_afc:
            raise Refused(400, f"answer {value}: an interval 1..{self.cfg.n_afc}")

    def advance(self, t, value):
        self.run.answer(t["index"], value)

    def answered(self):
        return self.run.index

    def total(self):
        return self.run.planned_trials

    def same_trial(self, t, recorded):
        return (t["frequency_hz"] == recorded["frequency_hz"] and t["target"] == recorded["target"]
                and abs(t["level_db"] - recorded["level_db"]) < 1e-9)


class SimilaritySession(Session):
    """Reference then compressed texture (the paper: 5 s each), graded 0..3 on the paper's
    scale; the trials are the plan's list (randomised once, at planning)."""

    kind = "similarity"

    def __init__(self, store: Store, token: str, display, plan: dict, steps: dict | None = None) -> None:
        super().__init__(store, token, display, steps)
        self.plan = plan
        self.trials = plan["trials"]
        self.i = 0

    def current(self):
        return self.trials[self.i] if self.i < len(self.trials) else None

    def public(self, t):
        return {"index": t["index"], "practice": bool(t.get("practice")),
                "prompt": "How similar were the two textures?", "parts": ["Reference", "Comparison"],
                "choices": [{"value": v, "label": lab, "key": str(v)}
                            for v, lab in enumerate(SIMILARITY_SCALE)]}

    def play(self, t):
        s = self.plan["seconds"]
        self.mark(1, "Reference")
        self.display.play_stream(t["reference"], s)
        self.mark(0)
        self.display.wait(self.plan.get("gap_s", 1.0))
        self.mark(2, "Comparison")
        self.display.play_stream(t["stream"] or t["reference"], s)  # the control: reference twice

    def practice_trial(self, k):
        """A trial of the plan's (in its order), played but not recorded."""
        return {**self.trials[k % len(self.trials)], "index": -1 - k, "practice": True}

    def practice_feedback(self, t, value):
        return None  # a similarity grade has no right answer

    def check_answer(self, value):
        if not 0 <= value < len(SIMILARITY_SCALE):
            raise Refused(400, f"answer {value}: a grade 0..{len(SIMILARITY_SCALE) - 1}")

    def advance(self, t, value):
        self.i += 1

    def answered(self):
        return self.i

    def total(self):
        return len(self.trials)


def threshold_results(session: ThresholdSession):
    return session.run.results()


def similarity_scores(session: SimilaritySession) -> list[dict]:
    """Mean grade per stimulus (texture, method, level) over its repetitions: the rows of the
    scores CSV (`hostd fit` reads it as-is; the control has method none and no stream)."""
    by: dict[tuple, list[int]] = {}
    first: dict[tuple, dict] = {}
    for a in session.store.answers(session.token):
        t = a["stimulus"]
        k = (t["texture"], t["method"], t["level"])
        by.setdefault(k, []).append(a["answer"])
        first.setdefault(k, t)
    rows = []
    for k, grades in by.items():
        t = first[k]
        rows.append({"texture": k[0], "method": k[1], "level": k[2], "score": float(np.mean(grades)),
                     "n": len(grades), "stream": t["stream_rel"], "profile": t["profile"],
                     "Ip": t["Ip"], "Ia": t["Ia"]})
    rows.sort(key=lambda r: (r["texture"], r["method"], r["level"]))
    return rows


def run_simulated(sess: Session, choose) -> None:
    """Go through the whole plan without a page, `choose(trial) -> value` answering (the CLI's
    --simulate): the same session steps the page takes, the display played for each trial."""
    page = "simulated"
    sess.open(page)
    while not sess.finished():
        try:
            if sess.phase in ("instructions", "intro", "break"):
                sess.step(page, "continue")
            elif sess.phase == "consent":
                sess.step(page, "agree")
            else:
                sess.present(page)
                sess.player.join()
                if sess.retry or sess.failure:
                    continue
                t = sess._trial()
                sess.answer(page, t["index"], choose(t))
        except Refused:
            if sess.failure is None:
                raise
