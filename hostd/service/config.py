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


def key(default, doc: str, *, choices: tuple | None = None, bounds: tuple | None = None,
        path: bool = False, required: bool = False):
    """One config key, declared once: its default (hence its type), what it does (doc), and what
    it may be (choices, bounds = (lo, hi) inclusive; path: a relative value is relative to the
    config file's folder; required: not empty). The validation (_check), the shipped hostd.toml
    and the reference (reference_markdown) are generated from these declarations."""
    return field(default=default, metadata={"doc": doc, "choices": choices, "bounds": bounds,
                                            "path": path, "required": required})


@dataclass
class DeviceCfg:
    """The display: which one, and how the host keeps its buffer."""
    transport: str = key("auto", "which display: auto | hid | hid:/dev/hidrawN | usb | usb:BUS/ADDR | "
                         "serial | serial:/dev/ttyACM0 | sim (without a path the display is found by "
                         "its VID:PID; hostd doctor lists the displays it finds)")
    serial: str = key("", "two displays on one PC: the USB serial number of this daemon's one (\"\" = "
                      "any; hostd doctor lists them; udev names each /dev/hostd/by-serial/hid-SERIAL)")
    target_fill: int = key(12, "device buffer target, samples (12 = 4 ms at 3 kHz)", bounds=(1, 227))
    max_fill: int = key(90, "after an underrun the target rises up to this (90 = 30 ms), then falls "
                        "after 1 s quiet by what the device's buffer did not use", bounds=(1, 227))
    host_timeout_ms: int = key(50, "the device ramps to zero after this much host silence",
                               bounds=(5, 60000))
    reconnect_s: float = key(1.0, "retry interval: without udev (else udev's event), or a display "
                             "that failed", bounds=(0.05, 3600))
    host_cycle_ms: int = key(1, "host rendering: pump wake-ups every this many ms; longer costs less "
                             "CPU but renders further ahead (less accurate; hostd bench cycle)",
                             bounds=(1, 10))


@dataclass
class LibraryCfg:
    """Where accepted streams are kept, and what is refused."""
    dir: str = key("/var/lib/hostd/library", "accepted streams, stored atomically", path=True,
                   required=True)
    spool: str = key("/var/spool/hostd", "drop .vtx files here to have them taken in", path=True,
                     required=True)
    max_stream_bytes: int = key(1 << 20, "larger uploads are refused", bounds=(100, 1 << 30))
    max_n: int = key(1 << 20, "streams with more samples N are refused (memory of the pump)",
                     bounds=(2, 1 << 22))
    max_n_keep: int = key(16384, "streams with more coefficients N' are refused (render cost)",
                          bounds=(1, 1 << 22))
    spool_settle_s: float = key(1.0, "a spooled file is taken once unchanged (size, mtime) this long",
                                bounds=(0.05, 600))


@dataclass
class ControlCfg:
    """The control socket clients (hostd send, status, ...) talk to."""
    socket: str = key("/run/hostd/hostd.sock", "Unix-domain socket, mode 0660; nothing listens on "
                      "the network", path=True, required=True)
    group: str = key("hostd", "group owning the socket (\"\" = the daemon's own)")
    max_clients: int = key(16, "clients served at once; more are refused with a message",
                           bounds=(1, 256))


# the paper's fit over both materials: the one default (a, b) of the CLI, the daemon and the log
_A, _B = DEFAULT_AB


@dataclass
class QualityCfg:
    """The quality log and what scores it."""
    db: str = key("/var/lib/hostd/quality.sqlite", "the quality log (SQLite): one row per accepted "
                  "stream, one per play", path=True, required=True)
    a: float = key(_A, "Iobj = a Ip + b Ia: the paper's fit (both materials), as in the CLI; hostd "
                   "fit estimates it from your scores; each log row records a and b", bounds=(-1e6, 1e6))
    b: float = key(_B, "the weight of Ia in Iobj (see a)", bounds=(-1e6, 1e6))
    thresholds: str = key("", "CSV of a detection-threshold curve; \"\" = the shipped default",
                          path=True)
    calibration: str = key("", "a calibration file (hostd experiment calibration): its curve and "
                           "(a, b) instead of the three keys above; each log row records NAME@ID of it",
                           path=True)


@dataclass
class RenderCfg:
    """How the texture becomes the piezo's displacement."""
    where: str = key("auto", "auto: the display renders from its own encoder whenever its CAPS say it "
                     "can hold the texture (protocol v2 firmware), else hostd renders and streams 3 kHz "
                     "samples (the reason: hostd status); host: always hostd; device: as auto, a "
                     "fallback to the host is a warning", choices=("auto", "device", "host"))
    host_lost_ms: int = key(1000, "device mode: host silence before the display counts the host as "
                            "lost", bounds=(100, 60000))
    height_method: str = key("series", "how the height at a position is evaluated",
                             choices=("series", "table-cubic", "table-linear", "nearest"))
    band_end_hz: float = key(1000.0, "the speed-aware fade runs from 400 Hz (f_max at v_ref) to here "
                             "(higher asks the equalized actuator for more slew than the piezo allows)",
                             bounds=(401.0, 1200.0))
    dtype: str = key("float64", "the host renderer's arithmetic", choices=("float32", "float64"))
    samples_per_batch: int = key(3, "samples rendered per pump step", bounds=(1, 29))
    predict_order: int = key(3, "motion prediction: 0 hold, 1 velocity, 2 + acceleration, 3 + jerk "
                             "(= MotionConfig's)", bounds=(0, 3))
    predict_window: int = key(40, "encoder readings in the motion fit", bounds=(2, 256))
    equalizer: bool = key(True, "equalize the actuator's response")
    equalizer_reg_hz: float = key(1400.0, "corner of the equalizer's regularizing low-pass",
                                  bounds=(300, 1499))
    actuator: str = key("paper-parametric", "a shipped actuator's name (or NAME.toml in "
                        "/etc/hostd/actuators/), or a path to a .toml")


@dataclass
class OutputCfg:
    """The piezo's limits and the amplifier and DAC that drive it."""
    travel_um: float = key(80.0, "full piezo travel, µm (output is +-travel/2)", bounds=(0.1, 1000))
    slew_um_s: float = key(60000.0, "the fastest the piezo may move, µm/s", bounds=(1, 1e7))
    um_per_volt: float = key(80.0 / 150.0, "the piezo's displacement per volt at its input, µm/V")
    amp_gain: float = key(15.0, "the amplifier's voltage gain")
    dac_full_scale_v: float = key(10.0, "the DAC's output at full scale, V")
    dac_bits: int = key(16, "the DAC's resolution, bits", bounds=(8, 24))
    ramp_s: float = key(0.05, "soft start and stop: ramps to and from zero take this long",
                        bounds=(0.001, 10))


@dataclass
class RealtimeCfg:
    """Scheduling of the real-time pump."""
    # The link's own underruns on a quiet machine were a SCHED_OTHER pump behind a busier
    # neighbour (DEVELOPMENT.md, "Link latency"); 10 is below the kernel's threaded interrupts
    # (50), which the display's bytes pass through. A pump that supervises a display rendering
    # itself stays SCHED_OTHER (hostd.device.realtime).
    sched_fifo_priority: int = key(10, "SCHED_FIFO at 1..99 for the pump while it streams, where "
                                   "permitted (the unit grants LimitRTPRIO=20; not permitted: one line, "
                                   "and it streams SCHED_OTHER); 0 = do not ask", bounds=(0, 99))
    mlockall: bool = key(False, "lock the pump's memory (needs CAP_IPC_LOCK or a memlock limit)")
    cpu: int = key(-1, "pin the pump to this CPU (-1 = do not)", bounds=(-1, 4095))


@dataclass
class MetricsCfg:
    """The optional Prometheus endpoint."""
    listen: str = key("", "\"127.0.0.1:9470\": a Prometheus endpoint (health and quality figures) on "
                      "loopback only (no authentication; other addresses are refused; \"\" = off); "
                      "needs the metrics extra; under the unit, which allows no IP socket, a drop-in "
                      "(systemctl edit hostd): [Service] IPAddressAllow=localhost and "
                      "RestrictAddressFamilies=AF_UNIX AF_NETLINK AF_INET AF_INET6")


@dataclass
class ExperimentCfg:
    """Experiments through the daemon (hostd experiment threshold --display daemon)."""
    stimuli: bool = key(False, "true: members of control.group may play sinusoidal stimuli on the "
                        "display (hostd experiment threshold --display daemon), whatever the hand "
                        "does; each is checked against the display's reach")


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


def _check(path: str, section: str, key: str, value, default, meta=None):
    where = f"{path}: {section}.{key}"
    meta = meta or {}
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
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"{where} must be one of {', '.join(meta['choices'])}, not {value!r}")
    if meta.get("bounds"):
        lo, hi = meta["bounds"]
        if not lo <= value <= hi:
            raise ConfigError(f"{where} must be within {lo}..{hi}, not {value!r}")
    if meta.get("required") and not value:
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


def _declared():
    """(section, its class's docstring, [(key, default, metadata)]) for every section, in order."""
    for sf in fields(Config):
        if sf.name == "path":
            continue
        cls = sf.default_factory
        yield sf.name, (cls.__doc__ or "").strip(), [(f.name, f.default, f.metadata) for f in fields(cls)]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(v)


def _allowed(meta) -> str:
    if meta.get("choices"):
        return "one of " + " | ".join(meta["choices"])
    if meta.get("bounds"):
        lo, hi = meta["bounds"]
        return f"{lo}..{hi}"
    return ""


def shipped_toml() -> str:
    """The shipped hostd.toml (config/hostd.toml): every key with its default and its doc,
    generated from the declarations above (tests/test_service_config.py keeps the file current:
    python -m hostd.service.config toml > config/hostd.toml)."""
    import textwrap

    out = ["# hostd daemon configuration. Every key is optional; shown here with its default.",
           "# `hostd run --config FILE` reads it; `hostd doctor --config FILE` checks it.",
           "# Relative paths are relative to this file's directory.",
           "# (Generated from hostd/service/config.py, where each key is declared once.)"]
    for section, doc, keys in _declared():
        out += ["", f"[{section}]", f"# {doc}"]
        for name, default, meta in keys:
            allowed = _allowed(meta)
            text = meta["doc"] + (f" ({allowed})" if allowed else "")
            out += textwrap.wrap(text, 98, initial_indent="# ", subsequent_indent="#   ")
            out.append(f"{name} = {_toml_value(default)}")
    return "\n".join(out) + "\n"


def reference_markdown() -> str:
    """The config reference (docs/reference/config.md), generated from the same declarations."""
    out = ["# Configuration reference", "",
           "Every key of the daemon's configuration file (`hostd run --config FILE`, default "
           "`$HOSTD_CONFIG`, else `/etc/hostd/hostd.toml`), with its type, default and the values it "
           "takes. A wrong key, type or value stops the daemon with one line naming the key and the "
           "file. Generated from `hostd/service/config.py`, where each key is declared once "
           "(`python -m hostd.service.config markdown`).", ""]
    for section, doc, keys in _declared():
        out += [f"## [{section}]", "", doc, "", "| key | type | default | allowed | what it does |",
                "|---|---|---|---|---|"]
        for name, default, meta in keys:
            kind = type(default).__name__.replace("str", "string").replace("bool", "boolean")
            allowed = _allowed(meta) + (" (a path; relative to the config file)" if meta.get("path") else "")
            cell = meta["doc"].replace("|", "\\|")
            out.append(f"| `{name}` | {kind} | `{_toml_value(default)}` | {allowed} | {cell} |")
        out.append("")
    return "\n".join(out)


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
            value = _check(str(p), section, key, value, getattr(sub, key), known[key].metadata)
            if known[key].metadata.get("path"):
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


if __name__ == "__main__":  # python -m hostd.service.config toml|markdown: the generated files
    import sys

    sys.stdout.write({"toml": shipped_toml, "markdown": reference_markdown}[sys.argv[1]]())
