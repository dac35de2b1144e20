"""The firmware's host port (firmware/port/host): building it and reading its DAC log."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"
EXE = FIRMWARE / "build" / "hostd-fw-host"
# one record per 3 kHz tick (port/host/main.c, log_tick); flags bit 0: the code came from the
# buffer, bit 1: underrun, bit 2: the tick ran > 1 ms late (the host port itself was held up by
# the OS: an artefact of the simulation), bit 3: the device was RUNNING, bit 4: RENDERING itself,
# bit 5: rendering the texture at full gain (no fade: what RENDER_STATUS counts as rendered)
PLAYED, UNDERRUN, LATE_TICK, RUNNING, RENDERING, FULL_GAIN = 1, 2, 4, 8, 16, 32
CLOCK_DTYPE = np.dtype([("tick", "<u4"), ("t", "<f8")])  # --clock: when each tick really ran
LOG_DTYPE = np.dtype([("tick", "<u4"), ("code", "<i2"), ("enc", "<u4"), ("flags", "<u2")])


REPLAY = FIRMWARE / "build" / "fw-replay"


def build(target: str = "host", exe: Path = EXE) -> Path:
    """`make -C firmware host` (or another target); raises RuntimeError with the reason when it
    cannot be built."""
    if not (FIRMWARE / "Makefile").exists() or shutil.which("make") is None:
        raise RuntimeError("the firmware sources or make are missing")
    r = subprocess.run(["make", "-s", "-C", str(FIRMWARE), target], capture_output=True, text=True)
    if r.returncode != 0 or not exe.exists():
        raise RuntimeError(f"cannot build the firmware's {target} (needs make and a C compiler): "
                           f"{r.stderr.strip()[:300]}")
    return exe


def build_replay() -> Path:
    """build/fw-replay: the firmware core run on a scenario (see firmware/tests/replay.c)."""
    return build("replay", REPLAY)


class HostPort:
    """The host port running as a child process: its pty path, and T0 (CLOCK_MONOTONIC of
    tick 0, = time.monotonic() in Python on Linux) to map host events to ticks."""

    def __init__(self, args: list[str], log: str | Path | None = None, stderr=None,
                 clock: str | Path | None = None) -> None:
        exe = build()
        cmd = [str(exe), *args] + (["--log", str(log)] if log is not None else [])
        cmd += ["--clock", str(clock)] if clock is not None else []
        self.clock = Path(clock) if clock is not None else None
        self.log = Path(log) if log is not None else None
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE,
                                     stderr=stderr if stderr is not None else subprocess.DEVNULL, text=True)
        words = self.proc.stdout.readline().split()
        if len(words) < 4 or words[0] != "PTY":
            self.close()
            raise RuntimeError(f"the firmware host port did not start ({' '.join(words) or 'no output'})")
        self.pty = words[1]
        self.t0 = float(words[3])

    def tick_at(self, host_monotonic_s: float) -> int:
        """The tick that ran at this host time: from the --clock log when there is one (after
        close()), else the nominal schedule (exact only while the host port kept time)."""
        if self.clock is not None and self.clock.exists():
            c = np.frombuffer(self.clock.read_bytes(), dtype=CLOCK_DTYPE)
            i = int(np.searchsorted(c["t"], host_monotonic_s))
            if 0 < i < c.size:
                return int(c["tick"][i - 1])
        return round((host_monotonic_s - self.t0) * 3000.0)

    def ticks(self) -> int:
        """The port's latest tick in its --clock log (flushed every 10 ms): its own clock."""
        if self.clock is None:
            raise RuntimeError("ticks needs the port's --clock log")
        raw = self.clock.read_bytes()
        c = np.frombuffer(raw[: len(raw) // 12 * 12], dtype=CLOCK_DTYPE)
        return int(c["tick"][-1]) if c.size else 0

    def wait_ticks(self, since_host_s: float, ticks: int, timeout_s: float = 120.0) -> float:
        """Until the port has run `ticks` ticks since host time since_host_s (its --clock log,
        flushed every 10 ms): a pause measured on the device's clock, which a loaded machine
        stretches in real time. Returns the host time then; TimeoutError past timeout_s."""
        if self.clock is None:
            raise RuntimeError("wait_ticks needs the port's --clock log")
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.ticks_since(since_host_s, ticks):
                return time.monotonic()
            time.sleep(0.002)
        raise TimeoutError(f"the host port ran fewer than {ticks} ticks in {timeout_s:g} s")

    def ticks_since(self, since_host_s: float, ticks: int) -> bool:
        """Whether the port has run `ticks` ticks since host time since_host_s (its --clock log)."""
        if self.clock is None:
            raise RuntimeError("ticks_since needs the port's --clock log")
        raw = self.clock.read_bytes()
        c = np.frombuffer(raw[: len(raw) // 12 * 12], dtype=CLOCK_DTYPE)
        i = int(np.searchsorted(c["t"], since_host_s))
        return 0 < i < c.size and int(c["tick"][-1]) - int(c["tick"][i - 1]) >= ticks

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()

    def __enter__(self) -> HostPort:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_log(path: str | Path) -> np.ndarray:
    return np.frombuffer(Path(path).read_bytes(), dtype=LOG_DTYPE)


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the runs of True in a boolean array."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    d = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(d[0::2].tolist(), d[1::2].tolist(), strict=True))


def playback_figures(rec: np.ndarray, rate_hz: float = 3000.0, to_last_played: bool = False) -> dict:
    """What the DAC log says about playback, from the first sample played from the buffer to
    the end of the log: the played fraction, the underrun episodes (the device's own count,
    rising edges of bit 1), and the silences (runs of ticks with nothing from the buffer)
    with their start ticks and lengths. The ground truth for tests and `hostd bench soak`.
    to_last_played: end at the last sample played (a run that stopped playback on purpose)."""
    played = (rec["flags"] & PLAYED) != 0
    first = int(np.argmax(played)) if played.any() else rec.size
    end = rec.size - int(np.argmax(played[::-1])) if to_last_played and played.any() else rec.size
    r = rec[first:end]
    p = played[first:end]
    gaps = runs(~p)
    silences = [(int(r["tick"][a]), (b - a) / rate_hz * 1e3) for a, b in gaps]
    under = [int(r["tick"][a]) for a, _ in runs((r["flags"] & UNDERRUN) != 0)]
    late = [(int(r["tick"][a]), int(r["tick"][b - 1])) for a, b in runs((r["flags"] & LATE_TICK) != 0)]
    return {
        "ticks": int(r.size),
        "played_fraction": float(p.mean()) if p.size else 0.0,
        "underrun_episodes": len(under),
        "underrun_ticks": under,
        "silences": silences,  # (start tick, length ms)
        "recovered_silences": sum(1 for _, b in gaps if b < p.size),  # followed by playback
        "longest_silence_ms": max((s for _, s in silences), default=0.0),
        "late_tick_runs": late,  # (first tick, last tick) where the simulated device ran late
    }
