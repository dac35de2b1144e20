"""Recovery, health figures, the adaptive jitter buffer, motion re-lock and transient I/O,
on the simulated device with a manual clock (deterministic; the firmware end to end is in
tests/test_playback.py)."""

from __future__ import annotations

import errno

import numpy as np
import pytest

from hostd.device import protocol as pr
from hostd.device.health import DeviceHealth
from hostd.device.link import DeviceLink
from hostd.device.pump import LOW_WATER_MARGIN, JitterConfig, Pump
from hostd.device.simdev import SimTransport
from hostd.errors import DeviceBusy, DeviceGone
from hostd.render.motion import MotionConfig, MotionEstimator
from hostd.render.output import OutputConfig, OutputStage
from tests.test_device import _renderer


def _playing(target_fill: int = 12, **jitter):
    t = SimTransport(realtime=False)
    link = DeviceLink(t, target_fill=target_fill)
    t.advance(3)
    link.handshake(timeout_s=0.1)
    logs: list[str] = []
    pump = Pump(link, None, log=logs.append,
                jitter=JitterConfig(base_fill=target_fill, **jitter) if jitter else None)
    pump.begin(_renderer())
    return t, link, pump, logs


def _cycles(t, pump, n, per=3):
    played = []
    for _ in range(n):
        t.advance(per)
        pump.step()
        played.append(t.device.samples_played)
    return np.array(played)


@pytest.mark.parametrize("stall_ms, cause", [(20, "underrun"), (100, "host timeout"), (300, "host timeout"),
                                             (2000, "host timeout")])
def test_after_a_stall_playback_resumes_in_the_first_cycle_and_is_counted_once(stall_ms, cause):
    t, _link, pump, logs = _playing()
    _cycles(t, pump, 500)
    t.advance(stall_ms * 3)  # the host does not run; the device does
    played = _cycles(t, pump, 500)
    assert played[1] > played[0] or played[2] > played[1], "not playing again within 2 ms"
    assert t.device.state == pr.STATES["RUNNING"]
    assert pump.stats.recoveries == 1 and len(logs) == 1 and cause in logs[0]
    assert pump.health.underruns == t.device.underruns  # the device's count, not ours
    # the fraction is the device's: played over due since selection
    due = (t.device.ticks - 3) - 12
    assert abs(pump.health.played_fraction - t.device.samples_played / due) < 0.01
    assert pump.target_fill > 12  # the jitter buffer rose after the underrun


def test_a_selected_texture_is_restarted_after_the_device_went_idle_on_its_own():
    t, _link, pump, logs = _playing()
    _cycles(t, pump, 200)
    t.device.on_message(pr.encode("STOP"))  # e.g. a device that reset its playout
    _cycles(t, pump, 200)
    assert t.device.state == pr.STATES["RUNNING"] and pump.stats.recoveries == 1
    assert "device idle" in logs[0]


def soft_start_limit(played: np.ndarray, peak_code: float) -> np.ndarray:
    """The most |code| the soft start lets out at each tick from a restart on: the k-th sample
    rendered after OutputStage.restart_from is the texture's equalized signal (whose peak the
    output reaches at full envelope: peak_code) times an envelope of at most k x ramp_step.
    After STOP and START the device drops none of them, so the k-th played is the k-th
    rendered; `played` marks the ticks that played one (one that did not ramps toward zero)."""
    ramp_step = OutputStage(OutputConfig(sample_rate_hz=pr.SAMPLE_RATE_HZ)).ramp_step
    return np.minimum(np.cumsum(played) * ramp_step, 1.0) * peak_code


@pytest.mark.parametrize("stall_ms", [100, 300, 2000])
def test_restart_is_a_soft_start_and_the_old_buffer_is_not_played(stall_ms):
    t, _link, pump, _logs = _playing()
    t.device.played_log = []
    _cycles(t, pump, 1000)
    t.advance(stall_ms * 3)  # host timeout: the device ramps to zero and goes idle
    n0 = len(t.device.played_log)
    _cycles(t, pump, 600)
    log = np.abs(np.array(t.device.played_log))
    after = log[n0:]
    ramp = round(OutputConfig().ramp_s * pr.SAMPLE_RATE_HZ)
    # the texture's equalized peak: what it reaches at full envelope, before and after
    peak = max(log[ramp:n0].max(), after[ramp:].max())
    # fades in from zero: within the envelope times the texture (the equalizer restarts on the
    # texture where the hand is now, not on its state from before the pause: that rang at
    # 7x the texture's peak through the envelope's first samples)
    lim = soft_start_limit(np.ones(ramp, dtype=bool), peak)
    assert np.all(after[:ramp] <= lim), (after[:ramp] / lim).max()
    assert after[ramp:].max() >= 0.5 * peak  # and comes back to the texture's amplitude


def test_jitter_buffer_rises_after_underruns_bounded_and_comes_down_after_a_quiet_period():
    t, link, pump, _logs = _playing(target_fill=12, max_fill=90, quiet_s=0.05)
    peak = 0
    _cycles(t, pump, 50)
    for _ in range(6):  # underrun after underrun, each within the quiet period after the last
        t.advance(60)  # 20 ms
        _cycles(t, pump, 20)
        peak = max(peak, pump.target_fill)
    assert peak == 90  # bounded
    assert link.target_fill == pump.target_fill  # the link's flow control follows it
    under = pump.health.underruns
    # the host kept the device's buffer near the target: after one quiet period of the device's
    # counters the target is back at its base at once, not a sample per period
    _cycles(t, pump, 60)
    assert pump.target_fill == 12 and link.target_fill == 12
    _cycles(t, pump, 500)
    assert pump.target_fill == 12 and pump.health.underruns == under


def test_a_raised_target_keeps_what_the_device_buffer_needed_in_its_quiet_period():
    t, _link, pump, _logs = _playing(target_fill=12, max_fill=90, quiet_s=0.2)
    _cycles(t, pump, 100)
    t.advance(60)  # 20 ms: an underrun, the target doubles
    _cycles(t, pump, 5)
    assert pump.target_fill == 24
    under = pump.health.underruns
    _cycles(t, pump, 50)
    assert pump.target_fill == 24  # within the quiet period: the evidence is still being gathered
    t.advance(15)  # a 5 ms pause the raised target covers: the device's buffer dips, no underrun
    _cycles(t, pump, 160)
    assert pump.health.underruns == under
    low = 24 - 3 - 15  # the dip: a cycle's samples and the pause's below the target
    # the quiet period ended: the target came down by what the buffer did not use, keeping the dip
    assert pump.target_fill == 24 - (low - LOW_WATER_MARGIN), pump.target_fill
    kept = pump.target_fill
    _cycles(t, pump, 250)  # a quiet period with no dip: back to base
    assert kept > 12 and pump.target_fill == 12 and pump.health.underruns == under


def test_health_counters_unwrap_and_rebaseline_on_a_device_reset():
    h = DeviceHealth()
    h.select(True)

    def st(t_us, played, under, state=1, flags=0):
        h.update({"state": state, "fault_flags": flags, "device_time_us": t_us & 0xFFFFFFFF,
                  "samples_played": played & 0xFFFFFFFF, "underruns": under & 0xFFFF})

    base_t, base_p = (1 << 32) - 2000, (1 << 32) - 6
    st(base_t, base_p, 0xFFFF)
    st(base_t + 1000, base_p + 3, 0xFFFF)
    st(base_t + 4000, base_p + 12, 1, flags=pr.FAULTS["UNDERRUN"])  # both wrap here
    assert h.samples_played == 12 and h.underruns == 2
    assert "underrun" in h.recent_faults()
    st(500, 0, 0, state=0)  # a reset: the clock and the counters went back
    st(1500, 3, 0, state=0)
    assert h.resets == 1 and h.samples_played == 15 and h.underruns == 2
    assert h.state_name == "idle"


def test_single_glitch_is_rejected_but_a_real_jump_relocks_within_5_reports():
    m = MotionEstimator(MotionConfig())
    for i in range(50):
        m.update(i * 1e-3, 20.0 * i * 1e-3)
    m.update(50e-3, 5.0)  # one wild reading
    assert m.glitches == 1 and m.relocks == 0 and abs(m.predict_one(51e-3) - 20.0 * 51e-3) < 1e-3
    for i in range(51, 100):
        m.update(i * 1e-3, 20.0 * i * 1e-3)
    jump = 0.5
    locked_at = None
    for k, i in enumerate(range(100, 130)):
        x = 20.0 * i * 1e-3 + jump
        m.update(i * 1e-3, x)
        if locked_at is None and abs(m.predict_one(i * 1e-3) - x) < 1e-3 and abs(m.velocity_mm_s - 20) < 1:
            locked_at = k + 1
    assert m.relocks == 1 and locked_at is not None and locked_at <= 5


def test_speed_estimate_stays_physical():
    m = MotionEstimator(MotionConfig(order=1, window=3, relock_reports=1, glitch_um=1e9))
    m.update(0.0, 0.0)
    m.update(1e-3, 0.0)
    m.update(2e-3, 50.0)  # 50 mm in 1 ms: 50,000 mm/s
    assert abs(m.velocity_mm_s) <= MotionConfig().max_speed_mm_s and m.implausible == 1


class _Port:
    """A serial port stand-in: takes `accept` bytes per write, then EAGAIN."""

    def __init__(self):
        self.fd = -1
        self.accept = 1 << 30
        self.data = b""


def test_serial_write_that_would_block_is_kept_and_sent_in_order(monkeypatch):
    from hostd.device import seriallink

    tr = seriallink.SerialTransport.__new__(seriallink.SerialTransport)
    tr.port, tr._pending, tr._queue = "/dev/fake", b"", []
    port = _Port()

    def write(fd, data):
        if port.accept <= 0:
            raise BlockingIOError(errno.EAGAIN, "would block")
        n = min(len(data), port.accept)
        port.accept -= n
        port.data += bytes(data[:n])
        return n

    monkeypatch.setattr(seriallink.os, "write", write)
    tr.ser = port
    port.accept = 5
    tr.send_raw(b"0123456789")  # half taken, half kept
    tr.send_raw(b"abc")  # nothing taken: kept behind the first
    port.accept = 1 << 30
    tr.flush_pending()
    assert port.data == b"0123456789abc"
    port.accept = 0
    with pytest.raises(DeviceBusy):  # a port that never takes anything: dropped, not "gone"
        for _ in range(1000):
            tr.send_raw(b"x" * 63)

    def gone(fd, data):
        raise OSError(errno.EIO, "I/O error")

    monkeypatch.setattr(seriallink.os, "write", gone)
    with pytest.raises(DeviceGone):
        tr.send_raw(b"y")


def test_transient_errors_are_retried_within_the_cycle_and_not_a_lost_device():
    t = SimTransport(realtime=False)
    link = DeviceLink(t, target_fill=12)
    t.advance(3)
    link.handshake(timeout_s=0.1)
    real, fails = t.send, [3]

    def flaky(msg):
        if fails[0] > 0:
            fails[0] -= 1
            raise DeviceBusy("EAGAIN")
        real(msg)

    t.send = flaky
    link.retry_budget_s = 1.0
    assert link.send_samples([1, 2, 3]) == 3
    assert link.stats.io_retries == 3 and link.in_flight == 3
