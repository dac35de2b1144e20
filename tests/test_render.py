"""Rendering stages and their hard cases; each test asserts a bound."""

import numpy as np
import pytest

from hostd.codec import transform
from hostd.render import RenderConfig, Renderer, frames
from hostd.render.equalizer import ActuatorModel, Equalizer, EqualizerConfig
from hostd.render.height import METHODS, BandLimitConfig, HeightEvaluator, band_edges_hz
from hostd.render.motion import MotionConfig, MotionEstimator
from hostd.render.output import OutputConfig, OutputStage
from hostd.render.position import EncoderPosition
from hostd.texture import synth

FS = 3000.0
COUNT_UM = 0.4


@pytest.fixture(scope="module")
def wood():
    p = synth.wood(seed=1)
    return transform.analyze(p.heights_um, 160), p.n, p.length_mm


def drive(renderer, x_of_t, seconds, glitch_at=None):
    """Encoder at 1 kHz (quantized to 0.4 µm), output batches of 3 samples at 3 kHz."""
    out = []
    for i in range(int(seconds * 1000)):
        t = i / 1000.0
        x = x_of_t(t)
        count = int(np.floor(x * 1000 / COUNT_UM)) & 0xFFFFFFFF
        if glitch_at is not None and i == glitch_at:
            count = (count + 2_000_000) & 0xFFFFFFFF
        renderer.on_encoder(t, count)
        out.append(renderer.render_um(t + np.arange(3) / FS))
    return np.concatenate(out)


def test_counter_wraps_around_without_a_jump():
    enc = EncoderPosition(COUNT_UM)
    start = (1 << 32) - 5
    xs = [enc.update((start + i) & 0xFFFFFFFF) for i in range(10)]
    assert np.allclose(np.diff(xs), COUNT_UM * 1e-3)
    enc2 = EncoderPosition(COUNT_UM)
    xs2 = [enc2.update((3 - i) & 0xFFFFFFFF) for i in range(10)]  # backwards through zero
    assert np.allclose(np.diff(xs2), -COUNT_UM * 1e-3)


def test_hand_at_rest_gives_no_output_noise_from_encoder_dither(wood):
    r = Renderer(*wood)
    r.start()
    rng = np.random.default_rng(0)
    x0 = 3.2
    y = drive(r, lambda t: x0 + rng.choice([0, COUNT_UM * 1e-3]), 1.0)
    steady = y[-1500:]
    assert np.ptp(steady) <= 1e-9  # bound: no variation at all while at rest


def test_single_glitching_sample_moves_nothing(wood):
    a = Renderer(*wood)
    b = Renderer(*wood)
    a.start()
    b.start()
    stroke = lambda t: 50.0 * t  # noqa: E731
    ya = drive(a, stroke, 0.5)
    yb = drive(b, stroke, 0.5, glitch_at=300)
    assert b.motion.glitches == 1
    assert np.max(np.abs(ya - yb)) <= 0.05  # µm; the texture is ~10 µm peak


def test_direction_reversal_follows_the_texture(wood):
    c, n, length = wood
    # the command itself is compared with the texture: no look-ahead for the actuator chain
    r = Renderer(c, n, length, RenderConfig(equalizer=EqualizerConfig(enabled=False), latency_s=0.0))
    r.start()
    x = lambda t: 2.0 + 20.0 * np.sin(2 * np.pi * 1.0 * t)  # noqa: E731  reversals at 0.25, 0.75 s
    y = drive(r, x, 1.0)
    ev = HeightEvaluator(c, n, length)
    t = np.arange(y.size) / FS
    ideal = np.array([ev.series(np.array([x(tt)]), 0.0)[0] for tt in t])
    err = (y - ideal)[300:]  # after the soft start
    assert np.sqrt(np.mean(err**2)) <= 0.2 * np.sqrt(np.mean(ideal**2))


@pytest.mark.parametrize("method", METHODS)
def test_height_methods_approximate_the_series(wood, method):
    ev = HeightEvaluator(*wood, method=method)
    x = np.linspace(0, 40, 5001)  # four patch lengths: crosses the mirror seams
    ref = ev.series(x, 50.0)
    err = np.sqrt(np.mean((ev(x, 50.0) - ref) ** 2)) / np.sqrt(np.mean(ref**2))
    bound = {"series": 1e-12, "table-cubic": 0.01, "table-linear": 0.02, "nearest": 0.2}[method]
    assert err <= bound


def test_series_is_continuous_across_the_patch_edge(wood):
    ev = HeightEvaluator(*wood)
    L = wood[2]
    eps = 1e-7
    for edge in (0.0, L, 2 * L):
        a, b = ev.series(np.array([edge - eps, edge + eps]), 0.0)
        assert abs(a - b) <= 1e-5


def test_fast_stroke_has_no_component_above_the_aliasing_limit(wood):
    ev = HeightEvaluator(*wood)
    f_pass, f_stop = band_edges_hz(ev.band)
    assert (f_pass, f_stop) == (400.0, 1000.0)  # the default band (docs/rendering.md)
    ev = HeightEvaluator(*wood, band=BandLimitConfig(stop_band_hz=None))  # up to the aliasing limit
    f_pass, f_stop = band_edges_hz(ev.band)
    assert (f_pass, f_stop) == (400.0, 1200.0)
    v = 4000.0  # 4 m/s: component 160 would sound at 3200 Hz
    t = np.arange(3000) / FS
    y = ev.series(v * t, v)
    spec = np.abs(np.fft.rfft(y * np.hanning(y.size)))
    f = np.fft.rfftfreq(y.size, 1 / FS)
    above = spec[f > f_stop + 20].max()
    assert above <= 1e-6 * max(spec.max(), 1e-12)
    assert np.all(ev.gains(v)[(np.arange(1, 161) * v / (2 * wood[2])) >= f_stop] == 0)


def test_every_kept_component_plays_at_full_amplitude_at_the_reference_speed(wood):
    c, n, length = wood
    geom = transform.Geometry(n, length)  # v_ref 50 mm/s, f_max 400 Hz
    ev = HeightEvaluator(c[: geom.n_keep], n, length)
    g = ev.gains(geom.speed_mm_s)
    assert g.size == geom.n_keep and np.all(g == 1.0)
    assert np.all(ev.gains(2 * geom.speed_mm_s)[geom.n_keep // 2 + 1 :] < 1.0)  # faster: fades
    with pytest.raises(ValueError, match="pass band"):
        band_edges_hz(BandLimitConfig(pass_band_hz=1300.0))


def test_equalizer_flat_within_1_db_over_10_to_400_hz():
    lo, hi = Equalizer().flatness_db(10, 400)
    assert -1.0 <= lo and hi <= 1.0
    off_lo, _ = Equalizer(cfg=EqualizerConfig(enabled=False)).flatness_db(10, 400)
    assert off_lo < -3.0  # without it the actuator loses more than 3 dB at 400 Hz


def test_full_scale_chirp_and_step_stay_within_limits():
    out = OutputStage()
    out.start()
    eq = Equalizer()
    t = np.arange(int(2 * FS)) / FS
    chirp = 40.0 * np.sin(2 * np.pi * (10 * t + (400 - 10) / 4 * t**2))
    step = np.where(t > 0.5, 40.0, -40.0)
    for sig in (chirp, step):
        y = out.process(eq(sig))
        assert np.max(np.abs(y)) <= out.limit_um + 1e-12
        assert np.max(np.abs(np.diff(y))) <= out.max_step_um + 1e-12
        assert np.all(np.isfinite(y))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e300, -1e300])
def test_nothing_that_enters_drives_the_output_past_a_limit(bad):
    out = OutputStage()
    out.start()
    x = np.full(2000, 10.0)
    x[100:110] = bad
    x[500] = 1e6
    y = out.process(x)
    codes = out.to_codes(y)
    assert np.max(np.abs(y)) <= out.limit_um + 1e-12
    assert np.max(np.abs(np.diff(y))) <= out.max_step_um + 1e-12
    assert np.max(np.abs(codes.astype(int))) <= OutputConfig().limit_code


def test_soft_start_and_stop_ramp(wood):
    out = OutputStage()
    out.start()
    y = out.process(np.full(300, 20.0))
    assert y[0] < 1.0 and abs(y[-1] - 20.0) < 1e-9
    out.stop()
    z = out.process(np.full(300, 20.0))
    assert z[-1] == 0.0 and np.all(np.diff(z) <= 1e-12)


@pytest.mark.parametrize("pause_s", [0.1, 0.35])
def test_a_restart_fades_in_the_texture_as_if_it_had_played_on(wood, pause_s):
    """Renderer.restart after a pause (the device ramped to zero): the k-th sample is the soft
    start's envelope times what a renderer that never paused plays there, the equalizer's state
    being the texture's where the hand is now (from before the pause, it rang: up to 1.36 µm off in
    these two cases)."""
    c, n, length = wood
    ref, r = Renderer(c, n, length, RenderConfig()), Renderer(c, n, length, RenderConfig())
    ref.start()
    r.start()
    ramp = round(OutputConfig().ramp_s * FS)
    played, paused = [], []
    for i in range(int((1.0 + pause_s) * 1000) + ramp // 3):
        t = i / 1000.0
        count = int(np.floor(20.0 * t * 1000 / COUNT_UM))  # 20 mm/s
        for x in (ref, r):
            x.on_encoder(t, count)
        y = ref.render_um(t + np.arange(3) / FS)
        if i < 1000:
            r.render_um(t + np.arange(3) / FS)
            continue
        if i == int((1.0 + pause_s) * 1000):
            r.restart(t)
        if i >= int((1.0 + pause_s) * 1000):
            played.append(r.render_um(t + np.arange(3) / FS))
            paused.append(y)
    # equal within half a DAC code (the motion fit's history differs by its encoder noise)
    env = np.arange(1, ramp + 1) / ramp
    err_um = np.abs(np.concatenate(played) - env * np.concatenate(paused)).max()
    assert err_um < 0.5 * OutputConfig().um_per_code, err_um


def test_huge_coefficient_is_limited_end_to_end(wood):
    c, n, length = wood
    c = c.copy()
    c[5] = 1e12
    r = Renderer(c, n, length)
    r.start()
    y = drive(r, lambda t: 50.0 * t, 0.3)
    assert np.max(np.abs(y)) <= r.out.limit_um + 1e-12


def test_float32_tracks_float64(wood):
    x = np.linspace(0, 20, 3001)
    a = HeightEvaluator(*wood, dtype=np.float64).series(x, 50.0)
    b = HeightEvaluator(*wood, dtype=np.float32).series(x, 50.0)
    assert np.max(np.abs(a - b)) <= 1e-3 * np.max(np.abs(a))


def test_prediction_reduces_lag_error(wood):
    def err(predict):
        mc = MotionEstimator(MotionConfig(order=1 if predict else 0, window=8 if predict else 2))
        errs = []
        for i in range(200):
            t = i / 1000
            mc.update(t, np.floor(50.0 * t * 1000 / COUNT_UM) * COUNT_UM / 1000)
            errs.append(float(mc.predict(t + 0.004)) - 50.0 * (t + 0.004))
        return np.sqrt(np.mean(np.square(errs[20:])))
    assert err(True) <= 0.05 * err(False)


def test_frames_group_samples():
    f = frames(np.arange(10), 3)
    assert [len(x) for x in f] == [3, 3, 3, 1]
    assert np.array_equal(np.concatenate(f), np.arange(10))


def test_equalizer_inverts_the_zero_order_held_actuator_exactly():
    """At the sample instants, DAC hold -> actuator -> equalizer is one sample of delay times
    the regularizing Butterworth R(z): the hold's droop and delay are inverted too."""
    import scipy.signal

    eq = Equalizer()
    fs = eq.cfg.sample_rate_hz
    b, a = eq.model.analog_ba()
    bd, ad, _ = scipy.signal.cont2discrete((b, a), 1.0 / fs, method="zoh")
    f = np.linspace(5.0, 1450.0, 300)
    held = scipy.signal.freqz(np.ravel(bd), ad, worN=f, fs=fs)[1]
    chain = held * scipy.signal.sosfreqz(eq.sos, worN=f, fs=fs)[1]
    br, ar = scipy.signal.butter(eq.cfg.reg_order, eq.cfg.reg_hz, fs=fs)
    want = np.exp(-2j * np.pi * f / fs) * scipy.signal.freqz(br, ar, worN=f, fs=fs)[1]
    assert np.max(np.abs(chain - want)) < 1e-9
    # so the band the renderer plays is flat: within 0.05 dB up to 600 Hz with the default corner
    band = f <= 600.0
    assert np.max(np.abs(20 * np.log10(np.abs(chain[band])))) < 0.05



@pytest.mark.parametrize("corner_hz, damping", [(150.0, 0.3), (270.0, 2 ** -0.5), (270.0, 1.0),
                                                (400.0, 1.0 + 1e-9), (600.0, 2.5)])
def test_equalizer_design_is_exact_for_every_damping_and_order(corner_hz, damping):
    """The closed-form design (under-, critically, over-damped; reg_order 2..8) against scipy's
    zero-order-hold discretization and Butterworth zpk: the chain is z^-1 R(z) to rounding.
    scipy's own tf2sos path is off by up to 1e-7 here at order 8 (np.roots spreads R's multiple
    zero at -1)."""
    import scipy.signal

    fs = 3000.0
    model = ActuatorModel(corner_hz=corner_hz, damping=damping)
    b, a = model.analog_ba()
    bd, ad, _ = scipy.signal.cont2discrete((b, a), 1.0 / fs, method="zoh")
    f = np.linspace(5.0, 1450.0, 300)
    held = scipy.signal.freqz(np.ravel(bd), ad, worN=f, fs=fs)[1]
    for order in range(2, 9):
        cfg = EqualizerConfig(reg_order=order, sample_rate_hz=fs)
        chain = held * scipy.signal.sosfreqz(Equalizer(model, cfg).sos, worN=f, fs=fs)[1]
        z, p, k = scipy.signal.butter(order, cfg.reg_hz, fs=fs, output="zpk")
        want = np.exp(-2j * np.pi * f / fs) * scipy.signal.freqz_zpk(z, p, k, worN=f, fs=fs)[1]
        assert np.max(np.abs(chain - want)) < 1e-12, order


# ---------------------------------------------------------------- the real-time batch's series
def _exact_cos_sum(c, theta, k0=1):
    """sum_j c_j cos((k0 + j) theta) in x87 extended precision (64-bit mantissa): the phase
    products and the sum carry 11 bits more than a double, a reference for the bounds below."""
    k = np.arange(k0, k0 + len(c), dtype=np.longdouble)
    return np.array([float(np.sum(np.asarray(c, dtype=np.longdouble) * np.cos(k * np.longdouble(t))))
                     for t in theta])


needs_extended = pytest.mark.skipif(np.finfo(np.longdouble).eps > 1e-18,
                                    reason="no extended precision long double here for the exact reference")


@needs_extended
@pytest.mark.parametrize("k", [5, 300, 1000, 16000])
@pytest.mark.parametrize("spectrum", ["decaying", "lone top component"])
def test_clenshaw_error_is_far_below_one_dac_step(k, spectrum):
    """The real-time batch's recurrence against the exact sum, where plain Clenshaw is weakest
    (theta near 0 and pi, and theta = 1/K where the top component turns once: an error growing
    with K^2, 1e-9 of sum|c| at K = 16 000 for a lone top component) and at random phases: with
    Reinsch's form below 1e-14 x sum|c| for a texture's decaying spectrum and 1e-12 for a lone
    top component (a 16-bit DAC step is 3e-5 of full scale)."""
    from hostd.render.series import clenshaw_py

    rng = np.random.default_rng(k)
    if spectrum == "decaying":
        c = rng.standard_normal(k) / np.sqrt(np.arange(1, k + 1))
    else:
        c = np.zeros(k)
        c[-1] = 1.0
    theta = np.concatenate([[0.0, 1e-9, 1e-5, 0.01, 1.0 / k, 2.0 / k, np.pi - 1e-7, np.pi, np.pi + 1e-6,
                             np.pi + 1.0 / k, 2 * np.pi - 1e-8], rng.uniform(0, 2 * np.pi, 5)])
    err = np.abs(clenshaw_py(c, theta) - _exact_cos_sum(c, theta))
    bound = 1e-14 if spectrum == "decaying" else 1e-12
    assert err.max() <= bound * np.abs(c).sum(), (k, err.max(), theta[err.argmax()])


def test_a_real_time_batch_is_the_recurrence_compiled_or_not():
    """series.evaluate on a real-time batch is clenshaw_py's values, bit for bit, compiled
    (_fastrender.clenshaw) or not: random coefficients with trailing zeros (a band limit), first
    components k0 > 1, and phases that are huge, negative, NaN or infinite."""
    from hostd.render import series

    rng = np.random.default_rng(7)
    cases = 0
    for k in (1, 2, 7, 64, 513):
        for k0 in (1, 2, 5):
            c = rng.standard_normal(k) * 10.0 ** rng.integers(-6, 6)
            if k > 2:
                c[rng.integers(1, k):] = 0.0  # a band limit: trailing zeros
            th = np.concatenate([rng.uniform(-10, 10, 3), [1e17, -3.0, np.nan, np.inf, 0.0, -0.0]])
            want = series.clenshaw_py(c, th, k0)
            assert series.clenshaw(c, th, k0).tobytes() == want.tobytes()
            if k0 == 1:
                assert series.evaluate(c, th).tobytes() == want.tobytes()
            ok = np.isfinite(th) & (np.abs(th) < 100)
            ref = np.cos(np.multiply.outer(th[ok], np.arange(k0, k0 + k))) @ c
            assert np.allclose(want[ok], ref, rtol=0, atol=1e-12 * max(1.0, np.abs(c).sum()))
            cases += 1
    assert cases == 15
    assert series.clenshaw(np.zeros(4), np.array([1.0])).tolist() == [0.0]  # no component: silence
