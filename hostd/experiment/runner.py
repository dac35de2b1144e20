"""The two experiments as sessions the page drives: present a trial (play it on the display),
take one answer (committed to the store before anything else happens), until done.

Both are deterministic given their plan and the answers: a session resumes by replaying the
answers recorded, and must meet the same trials (checked: a plan that no longer matches is an
error, not a silent divergence). A display that disconnects while a trial plays is an event;
the trial is presented again and nothing is recorded for it.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from hostd.errors import DeviceError, ExperimentError
from hostd.experiment.display import Sinusoid
from hostd.experiment.session import Store

SIMILARITY_SCALE = ("same", "possibly the same", "possibly different", "different")  # 0..3 (paper IV-A)


class Session:
    kind = ""

    def __init__(self, store: Store, token: str, display) -> None:
        self.store, self.token, self.display = store, token, display
        self.lock = threading.Lock()
        self.paused = False
        self.presented_at: float | None = None
        self.display_lost = 0

    # ------------------------------------------------------------------ for the page
    def state(self, present: bool = True) -> dict:
        """The trial to answer (played on the display first when `present`), or done."""
        with self.lock:
            if self.store.state(self.token) == "aborted":
                return {"done": True, "aborted": True, **self.progress()}
            t = self.current()
            if t is None:
                return {"done": True, **self.progress()}
            if self.paused:
                return {"done": False, "paused": True, **self.progress()}
            if present:
                try:
                    self.present(t)
                except DeviceError as e:
                    self.display_lost += 1
                    self.store.event(self.token, "display_lost", f"trial {t['index']}: {e}")
                    return {"done": False, "retry": True, "message": f"The display is not answering ({e}). "
                            "The trial will be repeated: press Try again.", **self.progress()}
                self.presented_at = time.time()
            return {"done": False, "paused": False, "trial": self.public(t), **self.progress()}

    def answer(self, index: int, value: int) -> dict:
        with self.lock:
            t = self.current()
            if t is None or t["index"] != index:
                return {"ignored": True}  # an answer to a trial already answered (a double click)
            self.check_answer(value)
            if not self.store.record(self.token, index, value, t, self.presented_at):
                return {"ignored": True}
            self.advance(t, value)
            self.presented_at = None
            if self.current() is None:
                self.store.set_state(self.token, "done")
                self.store.event(self.token, "done", "")
        return {"ok": True}

    def pause(self, paused: bool) -> None:
        with self.lock:
            if paused != self.paused:
                self.paused = paused
                self.store.event(self.token, "paused" if paused else "unpaused", "")

    def abort(self) -> None:
        with self.lock:
            self.store.set_state(self.token, "aborted")
            self.store.event(self.token, "aborted", "by the experimenter")

    def resume(self) -> None:
        for a in self.store.answers(self.token):
            t = self.current()
            if t is None or t["index"] != a["trial"] or not self.same_trial(t, a["stimulus"]):
                raise ExperimentError(f"session {self.token}: answer {a['trial']} does not match the plan "
                                      "(a different questplus or hostd version?): start a new session")
            self.advance(t, a["answer"])
        if self.store.state(self.token) == "aborted":
            self.store.set_state(self.token, "running")
        self.store.event(self.token, "resumed", f"at trial {self.answered()}")

    # ------------------------------------------------------------------ per experiment
    def current(self) -> dict | None: ...
    def public(self, t: dict) -> dict: ...
    def present(self, t: dict) -> None: ...
    def check_answer(self, value: int) -> None: ...
    def advance(self, t: dict, value: int) -> None: ...
    def answered(self) -> int: ...
    def total(self) -> int: ...

    def same_trial(self, t: dict, recorded: dict) -> bool:
        return t == recorded

    def progress(self) -> dict:
        return {"answered": self.answered(), "total": self.total(), "kind": self.kind}


class ThresholdSession(Session):
    """n-AFC: n intervals, one holds the sinusoid; the answer is the interval (1..n)."""

    kind = "threshold"

    def __init__(self, store: Store, token: str, display, cfg) -> None:
        from hostd.experiment.procedure import make_run

        super().__init__(store, token, display)
        self.cfg = cfg
        self.run = make_run(cfg)

    def current(self):
        t = self.run.next_trial()
        return None if t is None else t.as_dict()

    def public(self, t):
        return {"index": t["index"], "n_afc": t["n_afc"],
                "prompt": f"Which interval held the vibration? (1..{t['n_afc']})",
                "choices": [{"value": i, "label": f"Interval {i}", "key": str(i)}
                            for i in range(1, t["n_afc"] + 1)]}

    def present(self, t):
        c = self.cfg
        for i in range(1, t["n_afc"] + 1):
            if i > 1:
                self.display.wait(c.gap_s)  # between intervals: nothing is played
            if i == t["target"]:
                self.display.play(Sinusoid(t["frequency_hz"], t["amplitude_um"], c.duration_s))
            else:
                self.display.play_silence(c.duration_s)

    def check_answer(self, value):
        if not 1 <= value <= self.cfg.n_afc:
            raise ExperimentError(f"answer {value}: an interval 1..{self.cfg.n_afc}")

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

    def __init__(self, store: Store, token: str, display, plan: dict) -> None:
        super().__init__(store, token, display)
        self.plan = plan
        self.trials = plan["trials"]
        self.i = 0

    def current(self):
        return self.trials[self.i] if self.i < len(self.trials) else None

    def public(self, t):
        return {"index": t["index"], "prompt": "How similar were the two textures?",
                "choices": [{"value": v, "label": lab, "key": str(v)}
                            for v, lab in enumerate(SIMILARITY_SCALE)]}

    def present(self, t):
        s = self.plan["seconds"]
        self.display.play_stream(t["reference"], s)
        self.display.wait(self.plan.get("gap_s", 1.0))
        self.display.play_stream(t["stream"] or t["reference"], s)  # the control: reference twice

    def check_answer(self, value):
        if not 0 <= value < len(SIMILARITY_SCALE):
            raise ExperimentError(f"answer {value}: a grade 0..{len(SIMILARITY_SCALE) - 1}")

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
