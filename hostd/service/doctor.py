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
    from hostd.service.config import load, shipped_config

    try:
        cfg = load(config)
        ok(f"{cfg.path} is valid")
    except HostdError as e:
        bad(str(e), f"correct the key named above ({shipped_config()} documents every key)")
        cfg = load(None)
    head("device")
    from hostd.device.backend import node_owner
    from hostd.device.hotplug import watch
    from hostd.device.transport import BACKENDS, find_displays

    transport = cfg.device.transport
    kind, _, node = transport.partition(":")
    backend = BACKENDS.get(kind)
    # every display plugged in, with its transport spec and who may open its node
    displays = []
    for d in find_displays():
        entry = {"spec": d["spec"], "node": d.get("node"), "serial": d.get("serial", "")}
        if d.get("node"):
            entry.update({k: v for k, v in node_owner(d["node"]).items() if k != "node"})
        displays.append(entry)
        where = (f" ({entry['node']} {entry['owner']}:{entry['group']} {entry['mode']}"
                 f"{'' if entry['access'] else ', NOT accessible to this user'})" if "mode" in entry else "")
        note(f"display {entry['spec']}{where}, serial number {entry['serial'] or 'none'}")
    if backend is not None and backend.enumerator is None:
        ok(f"transport = {kind} (simulated display)")
    elif node and backend is not None and backend.arg_is_node:  # hid:/dev/hidrawN, serial:PORT: that node
        if not os.path.exists(node):
            bad(f"device.transport = {transport!r}: {node} does not exist",
                "plug the display in, or correct device.transport (hostd doctor lists what it finds)")
        elif not os.access(node, os.R_OK | os.W_OK):
            o = node_owner(node)
            bad(f"device.transport = {transport!r}: {node} ({o['owner']}:{o['group']} {o['mode']}) is not "
                "readable and writable by this user",
                "sudo hostd install-service (installs the udev rule), add the user to group 'hostd', "
                "then replug the display")
        else:
            ok(f"device.transport = {transport!r}: {node} is accessible")
    else:
        found = [d["spec"] for d in displays]
        wanted = [d["spec"] for d in displays
                  if (kind == "auto" or d["spec"] == transport
                      or (d["spec"].startswith(kind + ":") and not node))
                  and (not cfg.device.serial or d["serial"] == cfg.device.serial)]
        if wanted:
            ok(f"device.transport = {transport!r}: found {', '.join(wanted)}")
            for d in displays:
                if d["spec"] in wanted and d.get("access") is False:
                    bad(f"{d['node']} ({d['owner']}:{d['group']} {d['mode']}) is not readable and writable "
                        "by this user", "sudo hostd install-service (installs the udev rule), add the user "
                        "to group 'hostd', then replug the display")
        else:
            bad(f"device.transport = {transport!r}: no display {pr.USB_VID:04x}:{pr.USB_PID:04x} found"
                + (f" with serial number {cfg.device.serial!r} (device.serial)" if cfg.device.serial else "")
                + (f" (found only {', '.join(found)})" if found else ""),
                "plug it in; or set [device] transport = \"sim\" in the config to run without one")
    hot = watch(transport)
    hotplug_mode = hot.mode
    note(f"hotplug: {hot.describe()}")
    hot.close()
    for node in sorted(glob.glob("/dev/hidraw*")):
        if not os.access(node, os.R_OK | os.W_OK) and node not in {d.get("node") for d in displays}:
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
    from hostd.device.realtime import hypervisor, preemption_model

    model, source = preemption_model()
    if model in ("full", "lazy", "rt"):
        ok(f"kernel preemption: {model} ({source}): a real-time pump gets its CPU back from kernel code")
    else:
        note(f"kernel preemption: {model} ({source}): a real-time pump can wait for kernel code on its "
             "CPU for as long as that code runs without yielding, and the display's buffer holds 4 ms; "
             "on a display PC boot with preempt=full (a PREEMPT_DYNAMIC kernel) or run a PREEMPT_RT kernel")
    where = hypervisor()
    if where is not None:
        note(f"virtual machine ({where}): the hypervisor can leave a virtual CPU unrun for "
             "milliseconds without counting it as steal (2.3-4.4 ms traced, and the display's 4 ms buffer "
             "ran dry); a display PC that renders on the host runs on bare metal, or on virtual CPUs "
             "pinned to host cores of their own")
    ml_soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    note(f"RLIMIT_MEMLOCK {ml_soft if ml_soft >= 0 else 'unlimited'} bytes (mlockall needs it large)")
    head("storage")
    from hostd.service.config import WRITABLE, path_problem

    for section, key, is_dir in WRITABLE:
        value = getattr(getattr(cfg, section), key)
        why = path_problem(value, is_dir)
        if why:
            bad(f"{section}.{key} {value}: {why}",
                "sudo hostd install-service (systemd-tmpfiles creates /var/lib/hostd, /var/spool/hostd), "
                f"or point {section}.{key} at a writable path")
        elif Path(value).exists():
            ok(f"{section}.{key} {value} is writable")
        else:
            ok(f"{section}.{key} {value} will be created")
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
    from hostd.service import qualitylog

    for pending in qualitylog.pending_paths(db, cfg.library.dir):
        try:
            kept = qualitylog.load_pending(pending)
        except OSError as e:
            bad(f"quality log: cannot read its pending-rows file {pending}: {e}",
                "let the daemon's user read it")
            continue
        if kept:
            note(f"quality log: {len(kept)} rows pending in {pending} (not written when hostd last stopped; "
                 "the next start writes them once the disk has space)")
    from hostd.service.outbox import status_of

    _fleet, fleet_line = status_of(db)  # rows waiting for the shipper (hostd fleet), if it runs here
    if fleet_line:
        note(fleet_line)
    head("codec")
    from hostd.codec import rangecoder

    if rangecoder.IMPLEMENTATION == "c":
        ok(f"stream-v2 index coder: compiled ({Path(rangecoder._C.__file__).name})")
    else:
        note("stream-v2 index coder: pure Python (same streams, slower decode: about 0.5 ms more "
             "per stream); " + ("HOSTD_PURE_PYTHON is set" if os.environ.get("HOSTD_PURE_PYTHON")
                                else "install a C compiler and reinstall hostd to build it"))
    from hostd.device import fastpump

    head("host rendering")
    if fastpump.IMPLEMENTATION == "c":
        ok(f"host-rendering cycle: compiled ({Path(fastpump._C.__file__).name}; serial and hidraw displays)")
    else:
        note("host-rendering cycle: Python (the same samples; about 100-150 µs of CPU per 1 ms cycle "
             "instead of 30-50 µs when the display cannot render itself); " +
             ("HOSTD_PURE_PYTHON is set" if os.environ.get("HOSTD_PURE_PYTHON")
              else "install a C compiler and reinstall hostd to build it"))
    sock = Path(cfg.control.socket)
    head("daemon")
    if sock.exists():
        try:
            from hostd.service.client import request

            st = request(str(sock), {"cmd": "status"}, timeout_s=2.0)
            ok(f"running (pid {st['pid']}), {st['state']} on {st.get('transport') or 'no display'} (hotplug: "
               f"{st.get('hotplug')}); device {st['device_state']}"
               f"{' ' + ','.join(st['device_faults']) if st['device_faults'] else ''}, "
               f"played {st['played_fraction']:.2%} of the current texture, device underruns "
               f"{st['device_underruns']}, host stalls {st['stalls']} (longest "
               f"{st['longest_stall_ms']:.0f} ms), recoveries {st['recoveries']}")
            if st.get("quality_pending"):
                note(f"quality log: {st['quality_pending']} rows pending in the running daemon "
                     "(retried until written: free 64 kB or more on the quality log's file system if "
                     "the disk is full)")
            if "render_reason" in st:
                ok(f"rendered on the {st['render_at']}: {st['render_reason']}")
            if st["texture"] and st["played_fraction"] < 0.99:
                note("the display played less than 99 % of the time: see `hostd status`; host stalls "
                     "are what it recovers from (the real-time checks above; hostd bench soak "
                     "measures it)")
        except HostdError as e:
            bad(str(e), "systemctl restart hostd")
    else:
        note(f"not running (no socket at {sock}); [render] where = \"{cfg.render.where}\"")
    if json_out:
        import json

        print(json.dumps({"problems": problems, "checks": checks, "displays": displays,
                          "hotplug": hotplug_mode}))
    else:
        print(f"{problems} problem(s)")
    return 1 if problems else 0
