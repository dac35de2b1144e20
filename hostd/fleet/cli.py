"""`hostd fleet ship|migrate|add-pc`: a display PC's quality log in the central PostgreSQL."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from hostd.errors import HostdError


def _admin(url: str):
    """A connection as the central database's owner: the password (if any) from libpq's own places
    (~/.pgpass, PGPASSFILE, PGPASSWORD; peer authentication on a unix socket), never argv."""
    try:
        import psycopg
    except ImportError:
        from hostd.extras import pip_install

        raise HostdError(f"psycopg is not installed: {pip_install('fleet')}") from None
    try:
        return psycopg.connect(url, autocommit=True, application_name="hostd-fleet-admin",
                               options="-c TimeZone=UTC", connect_timeout=10)
    except psycopg.Error as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise HostdError(f"cannot connect to {url.split('?')[0]} as its owner ({first}): check --url, "
                         "and give the password in ~/.pgpass or PGPASSFILE") from None


def cmd_migrate(args) -> int:
    from hostd.fleet import schema

    conn = _admin(args.url)
    try:
        done = schema.migrate(conn, Path(args.extra) if args.extra else None)
    finally:
        conn.close()
    if args.json:
        print(json.dumps({"applied": list(done)}))
    else:
        print(f"fleet schema: applied {', '.join(map(str, done))}" if done else "fleet schema: up to date")
    return 0


def cmd_add_pc(args) -> int:
    """A display PC's login role (member of hostd_pc), or with --reader a login role for the views
    (member of hostd_reader). Its password, from a root-only file, is sent as a SCRAM verifier
    computed here: the server never sees, nor logs, the password itself."""
    from psycopg import sql

    from hostd.fleet.config import _ROLE, read_secret

    if not _ROLE.fullmatch(args.role):
        raise HostdError(f"role {args.role!r:.40}: use lower case letters, digits and _ (it is the PC's id)")
    pw = read_secret(Path(args.password_file), "--password-file") if args.password_file else None
    conn = _admin(args.url)
    try:
        group = "hostd_reader" if args.reader else "hostd_pc"
        with conn.transaction():
            if not conn.execute("SELECT 1 FROM pg_roles WHERE rolname = %s", (args.role,)).fetchone():
                conn.execute(sql.SQL("CREATE ROLE {} LOGIN").format(sql.Identifier(args.role)))
            conn.execute(sql.SQL("GRANT {} TO {}").format(sql.Identifier(group), sql.Identifier(args.role)))
            if pw is not None:
                verifier = conn.pgconn.encrypt_password(pw.encode(), args.role.encode(), b"scram-sha-256")
                conn.execute(sql.SQL("ALTER ROLE {} PASSWORD {}").format(
                    sql.Identifier(args.role), sql.Literal(verifier.decode())))
    finally:
        conn.close()
    if args.json:
        print(json.dumps({"role": args.role, "member_of": group, "password_set": pw is not None}))
        return 0
    print(f"role {args.role}: member of {group}" + (", password set" if pw is not None else
                                                     " (no password: a TLS client certificate logs it in)"))
    return 0


def _prefer_system_libpq() -> None:
    """psycopg on the system's libpq (Debian's libpq5) when there is one, not the binary wheel's own
    copy of libpq, OpenSSL and Kerberos: the libraries other processes map too, so the shipper's
    PSS holds 25 MB (docs/fleet.md: 24.8 against 28.6 MB). Before psycopg is first imported; an
    explicit PSYCOPG_IMPL wins."""
    import ctypes.util
    import os
    import sys

    if "psycopg" not in sys.modules and ctypes.util.find_library("pq"):
        os.environ.setdefault("PSYCOPG_IMPL", "python")


def _lean_exec(args) -> None:
    """`hostd fleet ship` run as a command (the unit's ExecStart): exec the lean entry
    (hostd/fleet/__main__.py) in this same process, leaving the full parser's modules behind, and
    without docstrings (-OO: 0.5 MB of psycopg's; the shipper asserts nothing).
    Not when called in-process (main([...]) from Python: tests, scripts)."""
    import os
    import sys

    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if os.path.basename(sys.argv[0]) == "hostd" or (spec is not None and spec.name == "hostd.__main__"):
        sys.stdout.flush()
        sys.stderr.flush()
        os.execv(sys.executable, [sys.executable, "-OO", "-m", "hostd.fleet", "ship", "--config", args.config,
                                  *(["--once"] if args.once else [])])


def cmd_ship(args) -> int:
    _lean_exec(args)
    return run_ship(args.config, args.once)


def run_ship(config_path: str, once: bool) -> int:
    _prefer_system_libpq()
    try:
        import psycopg  # noqa: F401
    except ImportError:
        from hostd.extras import pip_install

        raise HostdError(f"psycopg is not installed: {pip_install('fleet')}") from None
    from hostd.fleet import config, shipper

    return shipper.main(config.load(config_path), once=once)


def add_parser(sub) -> None:
    p = sub.add_parser("fleet", help="ship this display PC's quality log to the central PostgreSQL",
                       description="The fleet's central store: `migrate` and `add-pc` on "
                       "the central server, `ship` on each display PC (the hostd-fleet unit).")
    fsub = p.add_subparsers(dest="fleet", metavar="WHAT")
    from hostd.cliopts import needs_subcommand

    p.set_defaults(func=needs_subcommand(p, "a fleet command"))
    s = fsub.add_parser("ship", help="ship the quality log's rows, plays and device health (runs until "
                        "stopped; the hostd-fleet unit)")
    s.add_argument("--config", required=True, metavar="FILE", help="the shipper's config "
                   "(/etc/hostd/fleet.toml: a [fleet] section with url and role)")
    s.add_argument("--once", action="store_true",
                   help="ship what waits now and exit (non-zero if the centre cannot be reached)")
    s.set_defaults(func=cmd_ship)
    m = fsub.add_parser("migrate", help="create or upgrade the central schema (as the database's owner)")
    m.add_argument("--url", required=True, help="postgresql://HOST/DB (no password: ~/.pgpass or PGPASSFILE)")
    m.add_argument("--extra", default=None, help=argparse.SUPPRESS)  # tests: migrations after the package's
    m.add_argument("--json", action="store_true", help="the migrations applied, as JSON")
    m.set_defaults(func=cmd_migrate)
    a = fsub.add_parser("add-pc", help="create a display PC's database role (or, --reader, the views' role)")
    a.add_argument("role", help="the role's name: the PC's id in the central store")
    a.add_argument("--url", required=True, help="postgresql://HOST/DB, as its owner")
    a.add_argument("--password-file", default=None, metavar="FILE",
                   help="a root-only file (0600) with the role's password; without it the role logs in "
                   "with a TLS client certificate (CN = the role)")
    a.add_argument("--reader", action="store_true", help="a read-only role for the views (hostd_reader)")
    a.add_argument("--json", action="store_true", help="the role made, as JSON")
    a.set_defaults(func=cmd_add_pc)
    from hostd.fleet import report

    report.add_parser(fsub)
    from hostd.fleet import simulate

    simulate.add_parser(fsub)
