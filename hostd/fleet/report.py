"""`hostd fleet report`: the fleet at a glance, from the central store, as its read-only role.

What it shows (each as a CSV, a panel of report.png, and a table of report.html):
- quality_by_texture.csv, quality_by_display.csv: the distribution of Iobj (the quality log's
  objective quality index, per stream) per texture name and per display PC, over the window;
- plays_by_display.csv: per display and per hour (or day), plays, device time, played fraction
  (device-time weighted, as the local log weighs it) and underruns; the hour is the PC's own play
  end corrected by its clock offset, so a PC whose clock is hours wrong lands where it played;
- silent.csv: displays (members of hostd_pc) with nothing received for more than --silent-hours,
  or never;
- firmware.csv: firmware versions in the fleet, from each display's latest health summary;
- waiting.csv: rows waiting on each PC, from the latest health summary that PC sent.

Every figure comes from one SQL query here (the CSV holds what the query returned; the PNG and the
HTML draw the CSV's rows). Per-display "latest" questions are driven by the PCs' roles, one index
probe per PC and table (pc_id, received_at), never a scan of the fleet's rows.
"""

from __future__ import annotations

import csv
import datetime as dt
import html
import json
import os
from pathlib import Path

from hostd.errors import HostdError

# the roles of display PCs, each with its latest row of each kind (an index probe per PC; the role
# name as text in the column's collation: a `name` (collation "C") compared with the text pc_id
# would not use the index, a scan per PC: minutes at 10^4 PCs)
_PCS = "SELECT m.rolname::text COLLATE \"default\" AS pc_id FROM pg_roles m JOIN pg_auth_members a " \
       "ON a.member = m.oid JOIN pg_roles g ON g.oid = a.roleid WHERE g.rolname = 'hostd_pc'"
_LATEST_HEALTH = (f"SELECT p.pc_id, h.received_at, h.taken_at, h.pc_clock_offset_s, h.serial, h.firmware, "
                  f"h.device_underruns, h.played_fraction, h.waiting_rows, h.waiting_since "
                  f"FROM ({_PCS}) p CROSS JOIN LATERAL (SELECT * FROM fleet.health x WHERE x.pc_id = p.pc_id "
                  f"ORDER BY x.received_at DESC, x.taken_at DESC LIMIT 1) h")


def _dist_sql(key: str) -> str:
    q = ", ".join(f"percentile_cont({p}) WITHIN GROUP (ORDER BY iobj) AS p{round(p * 100):02d}"
                  for p in (0.1, 0.25, 0.5, 0.75, 0.9))
    other = "count(DISTINCT pc_id) AS displays" if key == "name" else "count(DISTINCT name) AS textures"
    return (f"SELECT {key}, count(*) AS rows, {other}, min(iobj) AS min, {q}, max(iobj) AS max, "
            f"avg(iobj) AS mean FROM fleet.quality WHERE received_at >= %(since)s GROUP BY {key} "
            f"ORDER BY {key}")


QUERIES = {
    "quality_by_texture": _dist_sql("name"),
    "quality_by_display": _dist_sql("pc_id"),
    "plays_by_display": (
        "SELECT pc_id, date_trunc(%(bucket)s, ended_at - make_interval(secs => pc_clock_offset_s)) "
        "AS bucket, "
        "count(*) AS plays, sum(device_s) AS device_s, sum(played_s) AS played_s, "
        "sum(played_fraction * device_s) / NULLIF(sum(CASE WHEN played_fraction IS NULL THEN 0 ELSE device_s "
        "END), 0) AS played_fraction, sum(underruns) AS underruns FROM fleet.plays "
        "WHERE received_at >= %(since)s GROUP BY 1, 2 ORDER BY 1, 2"),
    "silent": (  # MATERIALIZED: each PC's probes once, not once per use of last_seen
        "WITH s AS MATERIALIZED (SELECT p.pc_id, greatest("
        + ", ".join(f"(SELECT max(received_at) FROM fleet.{t} x WHERE x.pc_id = p.pc_id)"
                    for t in ("quality", "plays", "health"))
        + f") AS last_seen FROM ({_PCS}) p) SELECT pc_id, last_seen, "
        "extract(epoch FROM %(now)s - last_seen) / 3600 AS silent_hours FROM s WHERE last_seen IS NULL "
        "OR last_seen < %(now)s - make_interval(secs => %(silent_s)s) ORDER BY last_seen NULLS FIRST, pc_id"),
    "firmware": (f"SELECT coalesce(firmware, '(unknown)') AS firmware, count(*) AS displays, "
                 f"string_agg(pc_id, ' ' ORDER BY pc_id) AS pcs FROM ({_LATEST_HEALTH}) l "
                 f"GROUP BY 1 ORDER BY displays DESC, firmware"),
    "waiting": (f"SELECT pc_id, taken_at - make_interval(secs => pc_clock_offset_s) AS reported_at, "
                f"waiting_rows, waiting_since - make_interval(secs => pc_clock_offset_s) AS waiting_since, "
                f"extract(epoch FROM %(now)s - (waiting_since - make_interval(secs => pc_clock_offset_s))) "
                f"/ 3600 AS waiting_hours FROM ({_LATEST_HEALTH}) l "
                f"ORDER BY waiting_rows DESC NULLS LAST, pc_id"),
}
TITLES = {"quality_by_texture": "Quality (Iobj) per texture",
          "quality_by_display": "Quality (Iobj) per display",
          "plays_by_display": "Played fraction and underruns per display over time",
          "silent": "Silent displays", "firmware": "Firmware versions in the fleet",
          "waiting": "Rows waiting on each PC (its latest report)"}


def connect(url: str, role: str | None, password_file: str | None):
    """A connection as the views' read-only role. The password from a root-only file
    (--password-file), else the systemd credential hostd-fleet-password, else libpq's own places
    (PGPASSFILE, ~/.pgpass, a service file), or a TLS client certificate in the URL: never argv.
    A role that is a display PC's (it would see only its own rows) is refused."""
    try:
        import psycopg
    except ImportError:
        from hostd.extras import pip_install

        raise HostdError(f"psycopg is not installed: {pip_install('fleet')}") from None
    from hostd.fleet.config import FleetCfg, password

    pw = password(FleetCfg(password_file=password_file or ""))
    kw = {"user": role} if role else {}
    try:
        conn = psycopg.connect(url, password=pw, autocommit=True, application_name="hostd-fleet-report",
                               options="-c TimeZone=UTC -c default_transaction_read_only=on",
                               connect_timeout=10, **kw)
    except psycopg.Error as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise HostdError(f"cannot connect to {url.split('?')[0]} ({first}): check --db and --role, and give "
                         "the reader's password in --password-file (mode 0600), PGPASSFILE or ~/.pgpass"
                         ) from None
    reader, pc, su = conn.execute(
        "SELECT pg_has_role(current_user, 'hostd_reader', 'MEMBER'), pg_has_role(current_user, 'hostd_pc', "
        "'MEMBER'), rolsuper FROM pg_roles WHERE rolname = current_user").fetchone()
    if pc or not (reader or su):
        who = conn.info.user
        conn.close()
        raise HostdError(f"role {who} is not the fleet's read-only role: create one with `hostd fleet add-pc "
                         "NAME --reader --url URL` and pass --role NAME")
    return conn


def collect(conn, now: dt.datetime | None = None, silent_hours: float = 24.0, since_days: float = 30.0,
            bucket: str = "hour") -> dict[str, tuple[list[str], list[tuple]]]:
    """{name: (columns, rows)} for every query, in one read-only snapshot."""
    now = now or conn.execute("SELECT now()").fetchone()[0]
    args = {"now": now, "since": now - dt.timedelta(days=since_days), "silent_s": silent_hours * 3600.0,
            "bucket": bucket}
    out = {}
    with conn.transaction():
        conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")
        for name, sql in QUERIES.items():
            cur = conn.execute(sql, args)
            out[name] = ([d.name for d in cur.description], cur.fetchall())
    return out


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, dt.datetime):
        return v.astimezone(dt.UTC).isoformat(timespec="seconds")
    if isinstance(v, float):
        return repr(v)
    return str(v)


def write_csv(path: Path, cols: list[str], rows: list[tuple]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        w.writerows([[_cell(v) for v in r] for r in rows])


def figure(data: dict, path: Path, silent_hours: float, bucket: str = "hour", top: int = 12) -> None:
    """report.png: Iobj boxes (p10/p25/p50/p75/p90, from the queries' percentiles) per texture and
    per display, played fraction and underruns over time of the displays with most underruns,
    firmware versions, rows waiting per PC."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 2, figsize=(13, 12))

    def boxes(ax, key, title):
        cols, rows = data[key]
        ix = {c: i for i, c in enumerate(cols)}
        rows = sorted(rows, key=lambda r: -r[ix["rows"]])[:top]
        stats = [{"label": f"{r[0]} ({r[ix['rows']]})", "whislo": r[ix["p10"]], "q1": r[ix["p25"]],
                  "med": r[ix["p50"]], "q3": r[ix["p75"]], "whishi": r[ix["p90"]], "fliers": [],
                  "mean": r[ix["mean"]]} for r in rows]
        if stats:
            import inspect

            horizontal = {"orientation": "horizontal"} \
                if "orientation" in inspect.signature(ax.bxp).parameters else {"vert": False}  # < 3.10
            ax.bxp(stats, showmeans=True, **horizontal)
        ax.set_title(f"{title} (p10-p90 whiskers, busiest {top})", fontsize=10)
        ax.set_xlabel("Iobj")
        ax.tick_params(axis="y", labelsize=7)

    boxes(axes[0][0], "quality_by_texture", "Iobj per texture")
    boxes(axes[0][1], "quality_by_display", "Iobj per display")
    cols, rows = data["plays_by_display"]
    ix = {c: i for i, c in enumerate(cols)}
    per: dict[str, list[tuple]] = {}
    for r in rows:
        per.setdefault(r[ix["pc_id"]], []).append(r)
    worst = sorted(per, key=lambda pc: -sum(r[ix["underruns"]] or 0 for r in per[pc]))[:8]
    for pc in worst:
        t = [r[ix["bucket"]] for r in per[pc]]
        axes[1][0].plot(t, [r[ix["played_fraction"]] for r in per[pc]], marker=".", label=pc)
        axes[1][1].plot(t, [r[ix["underruns"]] for r in per[pc]], marker=".", label=pc)
    axes[1][0].set_title(f"Played fraction per {bucket} (the {len(worst)} displays with most "
                         "underruns)", fontsize=10)
    axes[1][1].set_title("Underruns per bucket (same displays)", fontsize=10)
    import matplotlib.dates as mdates

    for ax in axes[1]:
        loc = mdates.AutoDateLocator()
        ax.xaxis.set_major_locator(loc)
        ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc))
        if worst:
            ax.legend(fontsize=6, ncol=2)
        ax.tick_params(axis="x", labelsize=7, rotation=20)
    cols, rows = data["firmware"]
    axes[2][0].barh([r[0] for r in rows], [r[1] for r in rows])
    axes[2][0].set_title("Firmware versions (displays, latest health)", fontsize=10)
    cols, rows = data["waiting"]
    rows = [r for r in rows if r[2]][:top]
    axes[2][1].barh([r[0] for r in rows], [r[2] for r in rows])
    n_silent = len(data["silent"][1])
    axes[2][1].set_title(f"Rows waiting per PC (top {top}); {n_silent} displays silent > {silent_hours:g} h",
                         fontsize=10)
    for ax in axes[2]:
        ax.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_html(data: dict, path: Path, generated: dt.datetime, silent_hours: float, limit: int = 200) -> None:
    parts = ["<!doctype html><html><head><meta charset='utf-8'><title>hostd fleet report</title>",
             "<style>body{font-family:sans-serif}table{border-collapse:collapse;font-size:12px}"
             "td,th{border:1px solid #ccc;padding:2px 6px}</style></head><body>",
             f"<h1>hostd fleet report</h1><p>Generated {html.escape(_cell(generated))} (UTC); silent: "
             f"nothing received for more than {silent_hours:g} h.</p>",
             "<img src='report.png' alt='fleet report'>"]
    for name, (cols, rows) in data.items():
        parts.append(f"<h2>{html.escape(TITLES[name])}</h2><p><a href='{name}.csv'>{name}.csv</a>, "
                     f"{len(rows)} rows{f' (the first {limit} below)' if len(rows) > limit else ''}</p>")
        parts.append("<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in cols) + "</tr>")
        for r in rows[:limit]:
            parts.append("<tr>" + "".join(f"<td>{html.escape(_cell(v))}</td>" for v in r) + "</tr>")
        parts.append("</table>")
    parts.append("</body></html>")
    path.write_text("\n".join(parts))


def write(conn, out: Path, silent_hours: float = 24.0, since_days: float = 30.0, bucket: str = "hour",
          now: dt.datetime | None = None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    generated = now or conn.execute("SELECT now()").fetchone()[0]
    data = collect(conn, generated, silent_hours, since_days, bucket)
    for name, (cols, rows) in data.items():
        write_csv(out / f"{name}.csv", cols, rows)
    figure(data, out / "report.png", silent_hours, bucket)
    write_html(data, out / "report.html", generated, silent_hours)
    return data


def cmd_report(args) -> int:
    if args.silent_hours <= 0 or args.since_days <= 0:
        raise HostdError("--silent-hours and --since-days must be > 0")
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        from hostd.extras import pip_install

        raise HostdError(f"matplotlib is not installed (the report's figure): {pip_install('plot')}"
                         ) from None
    try:  # before the connection: a report that cannot be written is said at once
        Path(args.output).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise HostdError(f"-o {args.output}: cannot make the report's directory ({e.strerror}): "
                         "give -o a directory you can write") from None
    conn = connect(args.db, args.role, args.password_file)
    try:
        data = write(conn, Path(args.output), args.silent_hours, args.since_days, args.bucket)
    finally:
        conn.close()
    if args.json:
        print(json.dumps({"output": str(args.output), "csv_files": len(data),
                          "displays_with_quality_rows": len(data["quality_by_display"][1]),
                          "silent_displays": len(data["silent"][1]), "silent_hours": args.silent_hours}))
        return 0
    print(f"fleet report in {args.output}: report.html, report.png, {len(data)} CSV files; "
          f"{len(data['quality_by_display'][1])} displays with quality rows, {len(data['silent'][1])} silent "
          f"> {args.silent_hours:g} h")
    return 0


def add_parser(fsub) -> None:
    r = fsub.add_parser("report", help="the fleet's report (HTML, PNG, CSV) from the central store, as "
                        "its read-only role")
    r.add_argument("--db", required=True, metavar="URL", help="postgresql://HOST:PORT/DB (no password in it)")
    r.add_argument("--role", default=os.environ.get("PGUSER"), help="the read-only role (hostd fleet add-pc "
                   "NAME --reader); default: PGUSER or the URL's user")
    r.add_argument("--password-file", default=None, metavar="FILE",
                   help="a file (mode 0600) with the role's password; else the systemd credential "
                   "hostd-fleet-password, PGPASSFILE or ~/.pgpass")
    r.add_argument("-o", "--output", required=True, metavar="DIR", help="where the report is written")
    r.add_argument("--silent-hours", type=float, default=24.0,
                   help="a display with nothing received for longer is silent (default 24)")
    r.add_argument("--since-days", type=float, default=30.0, help="the window of quality rows and plays "
                   "(by the server's receive time; default 30)")
    r.add_argument("--bucket", choices=("minute", "hour", "day"), default="hour", help="plays' time bucket")
    r.add_argument("--json", action="store_true", help="what was written, as JSON")
    r.set_defaults(func=cmd_report)
