"""CLI of the service: run, send, list, select, status, stop, quality, doctor."""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import sys

from hostd.errors import HostdError


def _conn_parent() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--config", default=None, metavar="FILE",
                   help="daemon config (its control.socket and quality.db); default: $HOSTD_CONFIG, "
                   "else /etc/hostd/hostd.toml if it exists, else the built-in defaults (as hostd run)")
    p.add_argument("--socket", default=None, metavar="PATH", help="control socket (overrides --config)")
    return p


def _config(args) -> str | None:
    """The config file this command reads: the daemon's own resolution (config.resolve_path)."""
    from hostd.service.config import resolve_path

    return resolve_path(args.config)


def _sock(args) -> str:
    from hostd.service.client import socket_path

    return args.socket or socket_path(_config(args))


def cmd_run(args) -> int:
    from hostd.service.lean import one_blas_thread_env

    one_blas_thread_env()  # before numpy loads: a supervisor needs no BLAS threads (nor its pump)
    from hostd.service.notify import Notifier

    notifier = Notifier()
    notifier.starting()  # before the imports and the pump's start: systemd's watchdog runs already
    from hostd.service.config import load
    from hostd.service.daemon import Daemon
    from hostd.service.logsetup import setup

    cfg = load(_config(args))
    setup(args.log_level)
    return Daemon(cfg, notifier).run()


def cmd_send(args) -> int:
    from hostd.service.client import send_file

    r = send_file(_sock(args), args.file, args.name)
    if _json_out(args, {k: v for k, v in r.items() if k != "ok"}):
        return 0
    print(f"accepted {r['name']}: {r['bytes']} bytes, {r['method']}, sha256 {r['sha256'][:16]}")
    return 0


def _json_out(args, result: dict) -> bool:
    """--json: the result as one JSON object on stdout (True), else nothing (False)."""
    if getattr(args, "json", False):
        json.dump(result, sys.stdout, indent=1)
        print()
        return True
    return False


def cmd_list(args) -> int:
    from hostd.service.client import request

    r = request(_sock(args), {"cmd": "list"})
    if _json_out(args, {"textures": r["textures"], "playing": r["playing"]}):
        return 0
    for name in r["textures"]:
        print(("* " if name == r["playing"] else "  ") + name)
    return 0


def cmd_select(args) -> int:
    from hostd.service.client import request

    request(_sock(args), {"cmd": "select", "name": args.name})
    if _json_out(args, {"playing": args.name}):
        return 0
    print(f"playing {args.name}")
    return 0


def cmd_stop(args) -> int:
    from hostd.service.client import request

    if args.daemon:
        request(_sock(args), {"cmd": "shutdown"})
        if not _json_out(args, {"stopped": "daemon"}):
            print("hostd is shutting down")
    else:
        request(_sock(args), {"cmd": "stop"})
        if not _json_out(args, {"stopped": "output"}):
            print("output ramped to zero")
    return 0


def format_status(st: dict) -> str:
    """One line: the daemon's state, then what the DEVICE reports (its state, faults, the
    share of the current texture it played from its buffer, its underruns), then the host's
    side (stalls, recoveries, the jitter buffer's target)."""
    faults = ",".join(st["device_faults"]) or "ok"
    return (f"{st['state']:<10} {st['texture'] or '-':<16} device {st['device_state']:<9} {faults:<8} "
            f"played {st['played_fraction']:7.2%}  underruns {st['device_underruns']}  "
            f"v={st['speed_mm_s']:6.1f} mm/s  stalls {st['stalls']}  recoveries {st['recoveries']}  "
            f"buffer {st['target_fill_ms']:g} ms  {st.get('transport') or 'no display'}")


def cmd_status(args) -> int:
    from hostd.service.client import request

    st = request(_sock(args), {"cmd": "status"})
    st.pop("ok", None)
    from hostd.service.config import load
    from hostd.service.outbox import status_of

    try:  # rows waiting for the shipper (hostd fleet), if this PC has one
        fleet, fleet_line = status_of(load(_config(args)).quality.db)
    except HostdError:
        fleet, fleet_line = None, None
    if fleet is not None:
        st["fleet"] = fleet
    if args.json:
        json.dump(st, sys.stdout, indent=1)
        print()
    else:
        print(format_status(st))
        print(f"device {st['device']} ({'connected' if st['connected'] else 'not connected'}), "
              f"library {st['library']} textures, accepted {st['accepted']}, refused {st['refused']}, "
              f"quality pending {st['quality_pending']}")
        if "render_reason" in st:
            print(f"rendered on the {st['render_at']}: {st['render_reason']}"
                  + (f"; host lost {st['device_host_lost']}x, re-uploads {st['device_reuploads']}"
                     if st["render_at"] == "device" else ""))
        if fleet_line:
            print(fleet_line)
    return 0


_UNITS_S = {"s": 1, "m": 60, "min": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


def parse_since(text: str | None, now: float | None = None) -> float | None:
    """--since: a duration back from now as journalctl users type it (90s, 30m, 1h, 2d, 1w,
    1h30m), an ISO date or time (2026-11-22, 2026-11-22T10:00, with or without a zone; without
    one, local time), or unix seconds. Returns unix seconds."""
    import re
    import time

    if text is None:
        return None
    t = text.strip()
    parts = re.fullmatch(r"(?:\d+(?:\.\d+)?(?:min|[smhdw]))+", t)
    if parts:
        secs = sum(float(n) * _UNITS_S[u] for n, u in re.findall(r"(\d+(?:\.\d+)?)(min|[smhdw])", t))
        return (time.time() if now is None else now) - secs
    try:
        return float(t)
    except ValueError:
        pass
    try:
        when = dt.datetime.fromisoformat(t)
    except ValueError:
        raise HostdError(f"--since {text!r}: give a duration (30m, 1h, 2d), an ISO date or time "
                         "(2026-11-22, 2026-11-22T10:00) or unix seconds") from None
    if when.tzinfo is None:
        when = when.astimezone()  # local time, as journalctl reads it
    return when.timestamp()


def iso_time(unix_s: float | None) -> str | None:
    """ISO 8601 with the local zone's offset (2026-11-22T10:00:00.123+01:00)."""
    if unix_s is None:
        return None
    return dt.datetime.fromtimestamp(unix_s).astimezone().isoformat(timespec="milliseconds")


def cmd_quality(args) -> int:
    from hostd.service import qualitylog
    from hostd.service.config import load

    db = args.db or load(_config(args)).quality.db
    import sqlite3

    since = parse_since(args.since)
    try:
        con = qualitylog.connect_readonly(db)
        try:
            rows = qualitylog.query(con, since)
        finally:
            con.close()
    except sqlite3.Error as e:
        raise HostdError(f"cannot read the quality log {db}: {e} (is quality.db right?)") from None
    for r in rows:  # machine-readable output: ISO 8601 times with the zone
        if args.json or args.csv:
            r["received_at"], r["scored_at"] = iso_time(r["received_at"]), iso_time(r["scored_at"])
    # machine-readable output spells the indices Ip, Ia, Iobj, as `hostd iobj --json` and `hostd fit`
    spelt = {"ip": "Ip", "ia": "Ia", "iobj": "Iobj"}
    if args.json:
        json.dump([{spelt.get(k, k): v for k, v in r.items()} for r in rows], sys.stdout, indent=1)
        print()
    elif args.csv:
        w = csv.DictWriter(sys.stdout, fieldnames=[spelt.get(k, k) for k in
                                                   qualitylog.COLUMNS + qualitylog.DELIVERED])
        w.writeheader()
        w.writerows({spelt.get(k, k): v for k, v in r.items()} for r in rows)
    else:
        print(f"{'received':<20} {'name':<22} {'bytes':>6} {'method':<6} {'Ip':>8} {'Ia':>8} {'Iobj':>8} "
              f"{'a':>6} {'b':>6} {'played':>8} {'for':>8} {'underruns':>9}")
        for r in rows:
            when = dt.datetime.fromtimestamp(r["received_at"]).strftime("%Y-%m-%d %H:%M:%S")
            pf = "-" if r["played_fraction"] is None else f"{r['played_fraction']:.2%}"
            ps = "-" if r["played_s"] is None else f"{r['played_s']:.1f} s"
            un = "-" if r["underruns"] is None else str(r["underruns"])
            print(f"{when:<20} {r['name']:<22} {r['bytes']:>6} {r['method']:<6} {r['ip']:>8.4f} "
                  f"{r['ia']:>8.4f} {r['iobj']:>8.4f} {r['a']:>6.3f} {r['b']:>6.3f} {pf:>8} {ps:>8} {un:>9}")
    return 0


def cmd_doctor(args) -> int:
    from hostd.service.doctor import doctor

    return doctor(_config(args), json_out=args.json)


def cmd_install_service(args) -> int:
    from hostd.service.install import install

    return install(args.root_parser, args.prefix, dry_run=args.dry_run, enable=args.enable,
                   exec_path=args.exec_path, fleet=args.fleet)


def add_parsers(sub) -> None:
    conn = _conn_parent()
    p = sub.add_parser("run", help="run the daemon (foreground; systemd runs it as a service)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="config file (every key with its default: the shipped hostd.toml, which "
                   "install-service copies to /etc/hostd); default: $HOSTD_CONFIG, else "
                   "/etc/hostd/hostd.toml if it exists, else the built-in defaults")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                   help="least severe message logged (default info; debug adds per-request detail)")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("send", parents=[conn], help="send a .vtx stream to the daemon's library")
    p.add_argument("file")
    p.add_argument("--name", default=None, help="name in the library (default: the file's stem)")
    p.add_argument("--json", action="store_true",
                   help="the accepted stream (name, bytes, method, sha256) as JSON")
    p.set_defaults(func=cmd_send)
    p = sub.add_parser("list", parents=[conn], help="list the daemon's textures (* = playing)")
    p.add_argument("--json", action="store_true", help="{textures: [...], playing: NAME or null} as JSON")
    p.set_defaults(func=cmd_list)
    p = sub.add_parser("select", parents=[conn], help="play a texture from the library")
    p.add_argument("name")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_select)
    p = sub.add_parser("status", parents=[conn], help="the daemon's state and real-time counters")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_status)
    p = sub.add_parser("stop", parents=[conn], help="stop playing (ramp to zero); --daemon stops hostd")
    p.add_argument("--daemon", action="store_true",
                   help="shut the daemon down (root or the daemon's own user only; under systemd: "
                   "systemctl stop hostd)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_stop)
    p = sub.add_parser("quality", parents=[conn], help="read the quality log (Ip, Ia, Iobj per stream)")
    p.add_argument("--since", default=None, metavar="T",
                   help="rows received since: a duration back from now (30m, 1h, 2d, 1w), an ISO date "
                   "or time (2026-11-22T10:00; local time without a zone) or unix seconds")
    p.add_argument("--db", default=None, help="the SQLite file (default: quality.db of --config)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--csv", action="store_true")
    g.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_quality)
    p = sub.add_parser("install-service", help="install the systemd unit, udev rule, sysusers, tmpfiles "
                       "and a default config (pointing the unit at this installation)")
    p.add_argument("--prefix", default="/", help="install under this root (default /; another root only "
                   "stages the files and prints the commands)")
    p.add_argument("--dry-run", action="store_true",
                   help="print exactly what the same call without --dry-run writes and runs; change nothing")
    p.add_argument("--enable", action="store_true", help="also run systemctl enable --now hostd")
    p.add_argument("--exec", dest="exec_path", default=None, metavar="PATH",
                   help="the hostd the unit runs (default: this installation's; for package builds "
                   "staged with --prefix, e.g. /opt/hostd/bin/hostd)")
    p.add_argument("--fleet", action="store_true", help="also the fleet shipper's unit (hostd-fleet.service) "
                   "and its user, for a PC that ships its quality log to a central PostgreSQL")
    p.set_defaults(func=cmd_install_service)
    p = sub.add_parser("doctor", help="check device, permissions, real-time capability, config, database")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="default: $HOSTD_CONFIG, else /etc/hostd/hostd.toml if it exists, else the defaults")
    p.add_argument("--json", action="store_true", help="print the checks as one JSON object")
    p.set_defaults(func=cmd_doctor)
