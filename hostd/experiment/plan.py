"""The session plan: what a participant meets, declared as data (a TOML file; the default is the
shipped config/experiment-plan.toml), in this order:

    instructions -> consent (optional) -> practice trials (not scored) -> main trials in blocks,
    with breaks -> end page

`SECTIONS` is the one table of what a plan may say: the file is checked against it (unknown
sections or keys, wrong types: one line naming the file and the key), the runner reads the
checked plan, and the CLI's --plan help and docs/experiments.md show the same file.
"""

from __future__ import annotations

from pathlib import Path

from hostd.errors import ExperimentError

# section -> key -> type: what a plan may say. The values a plan leaves out are the default
# plan's (the shipped file); consent is the one optional section (absent: no consent step).
SECTIONS: dict[str, dict[str, type]] = {
    "instructions": {"title": str, "text": str, "button": str},
    "consent": {"text": str, "agree": str, "decline": str},
    "practice": {"trials": int, "feedback": bool},
    "main": {"blocks": int, "text": str, "button": str},
    "breaks": {"every_trials": int, "every_minutes": float, "text": str, "button": str},
    "end": {"title": str, "text": str},
}
OPTIONAL = {"consent"}
WORDS = {str: "text", int: "a whole number", float: "a number", bool: "true or false"}
CONSENT_BUTTONS = {"agree": "I agree", "decline": "I do not agree"}


def default_path() -> Path:
    from hostd.paths import shipped_dir

    return shipped_dir() / "experiment-plan.toml"


def _read(p: Path) -> dict:
    from hostd.tomlfile import read

    return read(p, "session plan", "see hostd experiment threshold --help", exc=ExperimentError)


def read_plan(path: str | Path | None = None) -> dict:
    """The checked plan of `path` (None: the shipped default), every key filled in."""
    p = Path(path) if path is not None else default_path()
    return check_plan(_read(p), p)


def check_plan(doc: dict, where: str | Path = "plan") -> dict:
    """`doc` checked against SECTIONS, what it leaves out taken from the default plan."""
    base = _read(default_path()) if Path(where) != default_path() else doc
    unknown = set(doc) - set(SECTIONS)
    if unknown:
        raise ExperimentError(f"{where}: unknown section(s) {', '.join(sorted(unknown))} "
                              f"(a plan has {', '.join(SECTIONS)})")
    plan: dict = {}
    for name, keys in SECTIONS.items():
        sec = doc.get(name)
        if sec is None and name in OPTIONAL:
            plan[name] = None
            continue
        if sec is not None and not isinstance(sec, dict):
            raise ExperimentError(f"{where}: [{name}] must be a table")
        sec = sec or {}
        bad = set(sec) - set(keys)
        if bad:
            raise ExperimentError(f"{where}: [{name}] unknown key(s) {', '.join(sorted(bad))} "
                                  f"(expected {', '.join(keys)})")
        fallback = {**CONSENT_BUTTONS, **(base.get(name) or {})}
        out = {}
        for key, kind in keys.items():
            if key not in sec and key not in fallback:
                raise ExperimentError(f"{where}: [{name}] needs {key}")
            v = sec.get(key, fallback.get(key))
            if kind is float and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)
            if not isinstance(v, kind) or (kind is int and isinstance(v, bool)):
                raise ExperimentError(f"{where}: [{name}] {key} = {v!r:.40}: must be {WORDS[kind]}")
            if kind in (int, float) and v < 0:
                raise ExperimentError(f"{where}: [{name}] {key} = {v}: not negative")
            out[key] = v.strip() if isinstance(v, str) else v
        plan[name] = out
    if plan["main"]["blocks"] < 1:
        raise ExperimentError(f"{where}: [main] blocks = {plan['main']['blocks']}: at least 1")
    return plan


def break_due(plan: dict, answered: int, total: int, minutes_since_break: float) -> bool:
    """After `answered` scored trials of `total`: is a break due before the next one?"""
    if answered <= 0 or answered >= total:
        return False
    b = plan["breaks"]
    blocks = plan["main"]["blocks"]
    if blocks > 1 and any(answered == round(total * k / blocks) for k in range(1, blocks)):
        return True
    if b["every_trials"] and answered % b["every_trials"] == 0:
        return True
    return bool(b["every_minutes"]) and minutes_since_break >= b["every_minutes"]
