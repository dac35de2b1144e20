"""Optional Prometheus endpoint of the daemon (`[metrics] listen = "127.0.0.1:9470"`, off by default).

A lab with several display PCs graphs them with the tools it already runs: the health figures
(from the device's own counters, as `hostd status` shows them) and the quality log's figures, in
the Prometheus text format, served by prometheus_client (the `metrics` extra). Loopback only: the
endpoint has no authentication, so a non-loopback address is refused at config load; a scraper on
another machine reaches it through its own tunnel or a local agent. Values are read when scraped
(a custom collector), so nothing is added to the real-time path.
"""

from __future__ import annotations

import ipaddress
import logging

from hostd.errors import ConfigError

log = logging.getLogger("hostd")

# status field -> (metric name, help, counter?)
HEALTH = (
    ("connected", "hostd_device_connected", "1 when a display is connected", False),
    ("played_fraction", "hostd_played_fraction",
     "share of the current texture's due samples the device played (device counters)", False),
    ("device_underruns", "hostd_device_underruns", "underrun episodes the device reported", True),
    ("device_samples_played", "hostd_device_samples_played", "samples the device played from its buffer",
     True),
    ("stalls", "hostd_host_stalls", "host pauses that left the device's buffer less than two cycles", True),
    ("recoveries", "hostd_recoveries", "times the device was brought back to the selected texture", True),
    ("target_fill_ms", "hostd_target_fill_ms", "the jitter buffer's fill target, ms", False),
    ("device_time_s", "hostd_device_time_seconds", "the device's clock at its latest STATUS", False),
    ("batch_p99_us", "hostd_pump_batch_p99_us", "99th percentile CPU time of one pump cycle, µs", False),
    ("accepted", "hostd_streams_accepted", "streams accepted since the daemon started", True),
    ("refused", "hostd_streams_refused", "streams refused since the daemon started", True),
    ("quality_pending", "hostd_quality_pending", "accepted streams not yet scored", False),
    ("library", "hostd_library_textures", "textures in the library", False),
)


def parse_listen(value: str, where: str) -> tuple[str, int] | None:
    """'HOST:PORT' (IPv6 as [::1]:PORT) on a loopback address, or '' (off)."""
    if not value:
        return None
    host, sep, port = value.rpartition(":")
    host = host.strip("[]")
    if not sep or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"{where} must be HOST:PORT on loopback, e.g. \"127.0.0.1:9470\", not {value!r}")
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ConfigError(f"{where} = {value!r}: the metrics endpoint has no authentication and "
                              "listens on loopback only (127.0.0.1 or [::1]); let a local agent or an "
                              "SSH tunnel carry it to your Prometheus")
    return ("127.0.0.1" if host == "localhost" else host), int(port)


class DaemonCollector:
    """Collects the daemon's figures when Prometheus scrapes."""

    def __init__(self, status, quality_rows, quality_db=None) -> None:
        self.status = status  # () -> dict, Daemon.status
        self.quality_rows = quality_rows  # () -> list[dict], the latest row per texture
        self.quality_db = quality_db  # the quality log: its rows waiting for the fleet shipper

    def collect(self):
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        st = self.status()
        for key, name, hlp, counter in HEALTH:
            value = st.get(key)
            if value is None:
                continue
            fam = CounterMetricFamily(name, hlp) if counter else GaugeMetricFamily(name, hlp)
            fam.add_metric([], float(value))
            yield fam
        state = GaugeMetricFamily("hostd_state", "the daemon's state (1 for the current one)",
                                  labels=["state"])
        for s in ("waiting", "idle", "playing", "recovering", "stopped"):
            state.add_metric([s], 1.0 if st.get("state") == s else 0.0)
        yield state
        rows = self.quality_rows()
        fams = {k: GaugeMetricFamily(f"hostd_stream_{k}", h, labels=["name"]) for k, h in (
            ("iobj", "Iobj of the latest stream of this name (quality log)"),
            ("bytes", "size of the latest stream of this name"),
            ("played_fraction", "played fraction over this stream's plays (device counters)"),
            ("played_seconds", "time the device played this stream from its buffer"),
            ("underruns", "underruns the device counted while this stream played"))}
        for r in rows:
            for k, col in (("iobj", "iobj"), ("bytes", "bytes"), ("played_fraction", "played_fraction"),
                           ("played_seconds", "played_s"), ("underruns", "underruns")):
                if r.get(col) is not None:
                    fams[k].add_metric([r["name"]], float(r[col]))
        yield from fams.values()
        yield from self._fleet()

    def _fleet(self):
        """Rows waiting for the fleet shipper (hostd.service.outbox, as `hostd status` says), when
        this PC runs one: their count and the oldest one's age (0 when none wait), in this PC's
        clock, so a scraper's clock does not enter the age."""
        import sqlite3
        import time

        from prometheus_client.core import GaugeMetricFamily

        from hostd.errors import HostdError
        from hostd.service import outbox

        if self.quality_db is None:
            return
        try:
            w = outbox.waiting(self.quality_db)
        except (sqlite3.Error, OSError, HostdError) as e:
            log.debug("metrics: cannot read what waits for the fleet shipper: %s", e)
            return
        if w is None:  # no shipper on this PC
            return
        n = GaugeMetricFamily("hostd_fleet_rows_waiting", "quality-log rows (and health summaries) "
                              "waiting to be shipped to the fleet's central store")
        n.add_metric([], float(w["waiting"]))
        age = GaugeMetricFamily("hostd_fleet_oldest_waiting_age_seconds", "age of the oldest row "
                                "waiting to be shipped (this PC's clock; 0 when none wait)")
        age.add_metric([], max(0.0, time.time() - w["since"]) if w["waiting"] and w["since"] else 0.0)
        yield n
        yield age


def start(listen: tuple[str, int], status, quality_rows, quality_db=None):
    """Serve /metrics on `listen`; returns the server (shutdown() it to stop)."""
    try:
        from prometheus_client import CollectorRegistry, start_http_server
    except ImportError:
        from hostd.extras import pip_install

        raise ConfigError("metrics.listen is set but prometheus_client is not installed: "
                          f"{pip_install('metrics')} (or leave metrics.listen empty)") from None
    reg = CollectorRegistry(auto_describe=False)
    reg.register(DaemonCollector(status, quality_rows, quality_db))
    try:
        server, _thread = start_http_server(listen[1], listen[0], registry=reg)
    except OSError as e:
        raise ConfigError(f"metrics.listen {listen[0]}:{listen[1]}: cannot listen ({e.strerror})"
                          + _unit_hint(e)) from None
    log.info("metrics on http://%s:%d/metrics", *listen)
    return server


def _unit_hint(e: OSError) -> str:
    """Under the systemd unit, which allows no IP socket (IPAddressDeny=any, AF_UNIX/AF_NETLINK
    only), the drop-in that lets the endpoint listen on loopback."""
    import errno

    from hostd.service import notify

    unit = notify.service_unit()
    if unit is None or e.errno not in (errno.EAFNOSUPPORT, errno.EPERM, errno.EACCES):
        return ""
    name = unit.removesuffix(".service")
    return (f": {unit} allows no IP socket; add a drop-in (sudo systemctl edit {name}) "
            "with [Service] IPAddressAllow=localhost and RestrictAddressFamilies=AF_UNIX AF_NETLINK AF_INET "
            "AF_INET6, then restart it")

