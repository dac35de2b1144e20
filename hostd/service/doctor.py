"""`hostd doctor`: what the daemon would find, with the exact fix for each problem."""

from __future__ import annotations

import glob
import os
import resource
import sqlite3
from pathlib import Path

from hostd.device import protocol as pr
from hostd.errors import HostdError


def doctor(config: str | None, json_out: bool = False) -> int:
    """Print the checks (or, with json_out, one JSON object: checks and problem count)."""
    problems = 0
    checks: list[dict] = []
    section = ""

    def head(name: str) -> None:
        nonlocal section
        section = name
        if not json_out:
            print(name)

    def ok(msg: str) -> None:
        checks.append({"section": section, "status": "ok", "message": msg})
        if not json_out:
            print(f"  ok    {msg}")

    def bad(msg: str, fix: str) -> None:
        nonlocal problems
        problems += 1
        checks.append({"section": section, "status": "fail", "message": msg, "fix": fix})
        if not json_out:
            print(f"  FAIL  {msg}\n        fix: {fix}")

    def note(msg: str) -> None:
        checks.append({"section": section, "status": "note", "message": msg})
        if not json_out:
            print(f"  note  {msg}")

    head("config")
    from hostd.service.config import load

    try:
        cfg = load(config)
        ok(f"{cfg.path} is valid")
    except HostdError as e:
        bad(str(e), "correct the key named above (config/hostd.toml documents every key)")
        cfg = load(None)
    head("device")
    from hostd.device.transport import find_devices

    found = find_devices()
    if found:
        ok(f"found {', '.join(found)}")
    elif cfg.device.transport == "sim":
        ok("transport = sim (simulated display)")
    else:
        bad(f"no display {pr.USB_VID:04x}:{pr.USB_PID:04x} on HID, USB or serial",
            "plug it in; or set device.transport = \"sim\" to run without one")
    for node in sorted(glob.glob("/dev/hidraw*")):
        if not os.access(node, os.R_OK | os.W_OK):
            note(f"{node} is not accessible to this user (only a problem if it is the display)")
    rule = Path("/etc/udev/rules.d/70-hostd.rules")
    if rule.exists():
        ok(f"udev rule installed: {rule}")
    else:
        bad("udev rule not installed: a non-root daemon cannot open the display",
            "sudo hostd install-service (installs the rule and reloads udev)")
    head("real time")
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    if soft > 0 or os.geteuid() == 0:
        ok(f"SCHED_FIFO allowed (RLIMIT_RTPRIO {soft})")
    else:
        note("SCHED_FIFO not allowed for this user (RLIMIT_RTPRIO 0): the pump runs SCHED_OTHER; "
             "the systemd unit grants LimitRTPRIO=20")
    ml_soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    note(f"RLIMIT_MEMLOCK {ml_soft if ml_soft >= 0 else 'unlimited'} bytes (mlockall needs it large)")
    head("storage")
    for what, d in (("library", cfg.library.dir), ("spool", cfg.library.spool)):
        p = Path(d)
        if p.is_dir() and os.access(p, os.W_OK):
            ok(f"{what} {p} is writable")
        elif not p.exists() and os.access(p.parent if p.parent.exists() else Path("/"), os.W_OK):
            ok(f"{what} {p} will be created")
        else:
            bad(f"{what} {p} is not writable by this user",
                f"sudo install -d -o hostd -g hostd {p} "
                "(sudo hostd install-service sets up systemd-tmpfiles for it)")
    db = Path(cfg.quality.db)
    if db.exists():
        try:
            con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
            res = con.execute("PRAGMA integrity_check").fetchone()[0]
            n = con.execute("SELECT count(*) FROM streams").fetchone()[0]
            con.close()
            (ok if res == "ok" else lambda m: bad(m, "restore from backup"))(f"quality log {db}: "
                                                                               f"integrity {res}, {n} rows")
        except sqlite3.Error as e:
            bad(f"quality log {db}: {e}", f"move {db} away; hostd creates a new one")
    else:
        ok(f"quality log {db} will be created")
    sock = Path(cfg.control.socket)
    head("daemon")
    if sock.exists():
        try:
            from hostd.service.client import request

            st = request(str(sock), {"cmd": "status"}, timeout_s=2.0)
            ok(f"running (pid {st['pid']}), {st['state']}; device {st['device_state']}"
               f"{' ' + ','.join(st['device_faults']) if st['device_faults'] else ''}, "
               f"played {st['played_fraction']:.2%} of the current texture, device underruns "
               f"{st['device_underruns']}, host stalls {st['stalls']} (longest "
               f"{st['longest_stall_ms']:.0f} ms), recoveries {st['recoveries']}")
            if st["texture"] and st["played_fraction"] < 0.99:
                note("the display played less than 99 % of the time: see `hostd status`; host stalls "
                     "are what it recovers from (docs/daemon.md, real-time settings)")
        except HostdError as e:
            bad(str(e), "systemctl restart hostd")
    else:
        note(f"not running (no socket at {sock})")
    if json_out:
        import json

        print(json.dumps({"problems": problems, "checks": checks}))
    else:
        print(f"{problems} problem(s)")
    return 1 if problems else 0
