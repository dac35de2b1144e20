"""The daemon's configuration: one TOML file, validated key by key before anything starts.

A wrong key, type or value gives one line naming the key and the file (ConfigError, exit 2).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from hostd import tomlfile
from hostd.errors import ConfigError
from hostd.perception.indices import DEFAULT_AB


@dataclass
class DeviceCfg:
    transport: str = "auto"
    serial: str = ""  # the display's USB serial number: one of several on this PC ("" = any)
    target_fill: int = 12
    max_fill: int = 90
    host_timeout_ms: int = 50
    reconnect_s: float = 1.0
    host_cycle_ms: int = 1  # host rendering: one pump wake-up (and SAMPLES message) per this many ms


@dataclass
class LibraryCfg:
    dir: str = "/var/lib/hostd/library"
    spool: str = "/var/spool/hostd"
    max_stream_bytes: int = 1 << 20
    max_n: int = 1 << 20
    max_n_keep: int = 16384
    spool_settle_s: float = 1.0


@dataclass
class ControlCfg:
    socket: str = "/run/hostd/hostd.sock"
    group: str = "hostd"
    max_clients: int = 16


# the paper's fit over both materials: the one default (a, b) of the CLI, the daemon and the log
_A, _B = DEFAULT_AB


@dataclass
class QualityCfg:
    db: str = "/var/lib/hostd/quality.sqlite"
    a: float = _A
    b: float = _B
    thresholds: str = ""
    calibration: str = ""  # a calibration file: its curve and (a, b) instead of the three above


@dataclass
class RenderCfg:
    # auto: the display renders when its CAPS say it can hold the texture and its parameters,
    # else the host; host: the daemon always renders and streams samples; device: as auto, but
    # a fallback to the host is a warning
    where: str = "auto"
    host_lost_ms: int = 1000  # device mode: host silence after which the display counts it lost
    height_method: str = "series"
    band_end_hz: float = 1000.0  # the speed-aware fade runs from 400 Hz (f_max at v_ref) to here
    dtype: str = "float64"
    samples_per_batch: int = 3
    predict_order: int = 3  # = MotionConfig's (tests/test_daemon.py)
    predict_window: int = 40
    equalizer: bool = True
    equalizer_reg_hz: float = 1400.0
    actuator: str = "paper-parametric"


@dataclass
class OutputCfg:
    travel_um: float = 80.0
    slew_um_s: float = 60000.0
    um_per_volt: float = 80.0 / 150.0
    amp_gain: float = 15.0
    dac_full_scale_v: float = 10.0
    dac_bits: int = 16
    ramp_s: float = 0.05


@dataclass
class RealtimeCfg:
    # the pump SCHED_FIFO at this priority while it streams (host rendering, stimuli), where
    # permitted (the systemd unit grants LimitRTPRIO=20; not permitted: one line, and it streams
    # SCHED_OTHER); 0: never asked. The link's own underruns on a quiet machine were a SCHED_OTHER
    # pump behind a busier neighbour (docs/benchmarks.md, "Link latency"); 10 is below the
    # kernel's threaded interrupts (50), which the display's bytes pass through. A pump that
    # supervises a display rendering itself stays SCHED_OTHER (hostd.device.realtime)
    sched_fifo_priority: int = 10
    mlockall: bool = False
    cpu: int = -1


@dataclass
class MetricsCfg:
    listen: str = ""  # off; "127.0.0.1:9470": the Prometheus endpoint (loopback only)


@dataclass
class ExperimentCfg:
    # play sinusoidal stimuli for `hostd experiment threshold --display daemon` (the control
    # socket's `stimulus` command): off by default, see docs/experiments.md
    stimuli: bool = False


@dataclass
class Config:
    device: DeviceCfg = field(default_factory=DeviceCfg)
    library: LibraryCfg = field(default_factory=LibraryCfg)
    control: ControlCfg = field(default_factory=ControlCfg)
    quality: QualityCfg = field(default_factory=QualityCfg)
    render: RenderCfg = field(default_factory=RenderCfg)
    output: OutputCfg = field(default_factory=OutputCfg)
    realtime: RealtimeCfg = field(default_factory=RealtimeCfg)
    metrics: MetricsCfg = field(default_factory=MetricsCfg)
    experiment: ExperimentCfg = field(default_factory=ExperimentCfg)
    path: str = "<defaults>"

    def render_config(self):
        """The RenderConfig this file describes."""
        from hostd.render import RenderConfig
        from hostd.render.equalizer import EqualizerConfig, load_actuator
        from hostd.render.height import BandLimitConfig
        from hostd.render.motion import MotionConfig
        from hostd.render.output import OutputConfig

        r = self.render
        try:
            actuator = load_actuator(r.actuator)
        except ValueError as e:
            raise ConfigError(f"{self.path}: render.actuator: {e}") from None
        o = self.output
        return RenderConfig(
            height_method=r.height_method, dtype=r.dtype, samples_per_batch=r.samples_per_batch,
            predict=r.predict_order > 0,
            band=BandLimitConfig(stop_band_hz=r.band_end_hz),
            motion=replace(MotionConfig(), order=max(r.predict_order, 0),
                           window=max(r.predict_window, r.predict_order + 2)),
            equalizer=EqualizerConfig(enabled=r.equalizer, reg_hz=r.equalizer_reg_hz),
            actuator=actuator,
            output=OutputConfig(travel_um=o.travel_um, slew_um_s=o.slew_um_s, um_per_volt=o.um_per_volt,
                                amp_gain=o.amp_gain, dac_full_scale_v=o.dac_full_scale_v,
                                dac_bits=o.dac_bits, ramp_s=o.ramp_s))


CHOICES = {
    ("render", "where"): ("auto", "device", "host"),
    ("render", "height_method"): ("series", "table-cubic", "table-linear", "nearest"),
    ("render", "dtype"): ("float32", "float64"),
}
RANGES = {
    ("device", "target_fill"): (1, 227), ("device", "max_fill"): (1, 227),
    ("device", "host_timeout_ms"): (5, 60000), ("device", "host_cycle_ms"): (1, 10),
    ("device", "reconnect_s"): (0.05, 3600), ("library", "max_stream_bytes"): (100, 1 << 30),
    ("render", "samples_per_batch"): (1, 29), ("render", "host_lost_ms"): (100, 60000),
    ("render", "band_end_hz"): (401.0, 1200.0),
    ("render", "predict_order"): (0, 3),
    ("render", "predict_window"): (2, 256), ("render", "equalizer_reg_hz"): (300, 1499),
    ("output", "travel_um"): (0.1, 1000), ("output", "slew_um_s"): (1, 1e7),
    ("output", "dac_bits"): (8, 24), ("output", "ramp_s"): (0.001, 10),
    ("realtime", "sched_fifo_priority"): (0, 99), ("realtime", "cpu"): (-1, 4095),
    ("quality", "a"): (-1e6, 1e6), ("quality", "b"): (-1e6, 1e6),
    ("library", "spool_settle_s"): (0.05, 600), ("library", "max_n"): (2, 1 << 22),
    ("library", "max_n_keep"): (1, 1 << 22),
    ("control", "max_clients"): (1, 256),
}
PATHS = {("library", "dir"), ("library", "spool"), ("control", "socket"), ("quality", "db")}


def _check(path: str, section: str, key: str, value, default):
    where = f"{path}: {section}.{key}"
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, not {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, not {value!r}")
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise ConfigError(f"{where} must be a finite number, not {value!r}")
        value = float(value)
    elif isinstance(default, str) and not isinstance(value, str):
        raise ConfigError(f"{where} must be a string, not {value!r}")
    if (section, key) in CHOICES and value not in CHOICES[(section, key)]:
        raise ConfigError(f"{where} must be one of {', '.join(CHOICES[(section, key)])}, not {value!r}")
    if (section, key) in RANGES:
        lo, hi = RANGES[(section, key)]
        if not lo <= value <= hi:
            raise ConfigError(f"{where} must be within {lo}..{hi}, not {value!r}")
    if (section, key) in PATHS and not value:
        raise ConfigError(f"{where} must not be empty")
    if (section, key) == ("device", "transport"):
        from hostd.device.transport import parse_spec  # the backends' table holds the grammar

        try:
            parse_spec(value)
        except ValueError as e:
            raise ConfigError(f"{where} {e}") from None
    if (section, key) == ("device", "serial") and (any(ord(c) < 32 for c in value) or "/" in value):
        raise ConfigError(f"{where} must be a USB serial number (as /dev/hostd/by-serial/ names it), "
                          f"not {value!r}")
    if (section, key) == ("metrics", "listen"):
        from hostd.service.metrics import parse_listen

        parse_listen(value, where)
    return value


DEFAULT_PATH = "/etc/hostd/hostd.toml"  # what `hostd install-service` installs and the unit names
ENV_VAR = "HOSTD_CONFIG"


def resolve_path(given: str | Path | None) -> str | None:
    """The config file the daemon and every client read: --config if given, else $HOSTD_CONFIG,
    else /etc/hostd/hostd.toml when it exists, else None (the built-in defaults). One function,
    so that `hostd status` after editing control.socket looks where `hostd run` listens."""
    if given:
        return str(given)
    env = os.environ.get(ENV_VAR)
    if env:
        return env
    return DEFAULT_PATH if Path(DEFAULT_PATH).is_file() else None


def shipped_config():
    """The shipped hostd.toml (every key with its default), in the installed package."""
    from hostd import paths

    return paths.shipped_dir() / "hostd.toml"


def load(path: str | Path | None) -> Config:
    """Read and validate a config file (None: the defaults)."""
    cfg = Config()
    if path is None:
        return cfg
    p = Path(path)
    doc = tomlfile.read(p, "config file", f"start from {shipped_config()}")
    cfg.path = str(p)
    sections = {f.name for f in fields(Config) if f.name != "path"}
    for section, table in doc.items():
        if section not in sections:
            raise ConfigError(f"{p}: unknown section [{section}] (expected {', '.join(sorted(sections))})")
        if not isinstance(table, dict):
            raise ConfigError(f"{p}: {section} must be a table [{section}]")
        sub = getattr(cfg, section)
        known = {f.name: f for f in fields(sub)}
        for key, value in table.items():
            if key not in known:
                raise ConfigError(f"{p}: unknown key {section}.{key} (expected one of "
                                  f"{', '.join(sorted(known))})")
            value = _check(str(p), section, key, value, getattr(sub, key))
            if (section, key) in PATHS or (section, key) in (("quality", "thresholds"),
                                                             ("quality", "calibration")):
                if value and not Path(value).is_absolute():
                    value = str((p.parent / value).resolve())
            setattr(sub, key, value)
    if cfg.device.serial and (":" in cfg.device.transport or cfg.device.transport == "sim"):
        raise ConfigError(f"{p}: device.serial picks a display among those device.transport finds: use it "
                          f"with transport auto, hid, usb or serial (no path), not {cfg.device.transport!r}")
    cfg.render_config()  # the actuator file must load, too
    if cfg.quality.calibration:
        q = doc.get("quality", {})
        clash = [k for k, dflt in (("a", _A), ("b", _B), ("thresholds", "")) if q.get(k, dflt) != dflt]
        if clash:  # two sources for one number: say which to drop rather than pick one silently
            raise ConfigError(f"{p}: quality.calibration gives the curve and (a, b): remove quality."
                              f"{', quality.'.join(clash)} (or the calibration)")
        from hostd.perception import calibration

        try:
            cal = calibration.load(cfg.quality.calibration)
        except Exception as e:
            raise ConfigError(f"{p}: quality.calibration: {e}") from None
        cfg.quality.a, cfg.quality.b = cal.a, cal.b
    if cfg.quality.thresholds:
        from hostd.perception.calibration import load_curve

        try:
            load_curve(cfg.quality.thresholds)
        except Exception as e:
            raise ConfigError(f"{p}: quality.thresholds: {e}") from None
    return cfg


def path_problem(path: str | Path, is_dir: bool) -> str | None:
    """Why the daemon could not create or write `path` (a directory, or a file), or None."""
    target = Path(path)
    d = target if is_dir else target.parent
    p = d
    while not p.exists() and not p.is_symlink() and p.parent != p:
        p = p.parent
    if not p.is_dir():
        return f"{p} is not a directory"
    if not os.access(p, os.W_OK | os.X_OK):
        return (f"{p} is not writable by this user" if p == d
                else f"{d} does not exist and {p} is not writable by this user, so it cannot be created")
    if not is_dir and target.exists() and not os.access(target, os.R_OK | os.W_OK):
        return f"{target} is not writable by this user"
    return None


WRITABLE = (("library", "dir", True), ("library", "spool", True), ("quality", "db", False),
            ("control", "socket", False))


def check_paths(cfg: Config) -> None:
    """Every path the daemon writes can be created and written: one ConfigError naming the key."""
    for section, key, is_dir in WRITABLE:
        value = getattr(getattr(cfg, section), key)
        why = path_problem(value, is_dir)
        if why:
            raise ConfigError(f"{cfg.path}: {section}.{key} = {value!r}: {why} (give the daemon's user a "
                              "writable path; sudo hostd install-service sets up /var/lib/hostd, "
                              "/var/spool/hostd and /run/hostd)")
