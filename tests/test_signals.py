"""Excitation signals: statistics, periods, spectra, dispatcher errors."""

import math

import numpy as np
import pytest

from harness.rig import signals


def test_prbs_switching_rate_within_3_sigma_and_deterministic():
    n = 100_000
    for B, amp, off in [(0.05, 1.5, 0.0), (0.10, 1.0, 0.2), (0.20, 2.0, -0.1)]:
        x = signals.prbs(n, B, amp, offset=off, seed=7)
        assert x.dtype == np.float64 and x.size == n
        assert set(np.unique(x)) == {off - amp, off + amp}
        switches = int(np.count_nonzero(np.diff(x)))
        mean, sigma = (n - 1) * B, math.sqrt((n - 1) * B * (1 - B))
        assert abs(switches - mean) < 3 * sigma, (B, switches, mean, sigma)
        np.testing.assert_array_equal(x, signals.prbs(n, B, amp, offset=off, seed=7))
        assert np.any(x != signals.prbs(n, B, amp, offset=off, seed=8))


def test_prbs_rejects_bad_probability():
    for B in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="B"):
            signals.prbs(10, B, 1.0)


def test_square_period_levels_duty_and_phase():
    Ts = 0.02
    x = signals.square(500, Ts, 0.5, 2.0, offset=0.5)  # period 2 s = 100 samples
    pattern = np.r_[np.full(50, 2.5), np.full(50, -1.5)]
    np.testing.assert_array_equal(x, np.tile(pattern, 5))
    x = signals.square(400, Ts, 0.5, 1.0, duty=0.25)
    np.testing.assert_array_equal(x[:100], np.r_[np.ones(25), -np.ones(75)])
    x = signals.square(400, Ts, 0.5, 1.0, phase=math.pi)  # half a period later: starts low
    np.testing.assert_array_equal(x[:100], np.r_[-np.ones(50), np.ones(50)])
    # 0.3 Hz at 50 Hz: period of 166.67 samples; rising edges at the first sample with k Ts >= j / f
    x = signals.square(3000, Ts, 0.3, 1.0)
    rising = np.flatnonzero(np.diff(x) > 0) + 1
    expected = np.ceil(np.arange(1, 18) / 0.3 / Ts - 1e-9).astype(int)
    np.testing.assert_array_equal(rising, expected)


def test_step_ramp_constant_and_chirp():
    Ts = 0.02
    x = signals.step(100, Ts, 0.5, 1.2, offset=-0.2)
    assert np.all(x[:25] == -0.2) and np.all(x[25:] == 1.0)
    r = signals.ramp(1000, Ts, 0.05, t0=2.0, offset=0.1, limit=0.6)
    t = np.arange(1000) * Ts
    np.testing.assert_allclose(r, np.clip(0.1 + 0.05 * np.maximum(t - 2.0, 0), None, 0.6), atol=1e-15)
    assert r[-1] == 0.6
    with pytest.raises(ValueError, match="limit"):
        signals.ramp(10, Ts, -0.05, limit=0.5)
    np.testing.assert_array_equal(signals.constant(5, 1.0, offset=0.25), np.full(5, 1.25))
    # linear chirp 1 -> 5 Hz over 10 s: the phase advances by (1 + 5) / 2 * 10 = 30 cycles = 60 zero crossings
    n, Ts = 10001, 0.001
    c = signals.chirp(n, Ts, 1.0, 5.0, 2.0, method="linear")
    assert c[0] == pytest.approx(0.0, abs=1e-12) and np.max(np.abs(c)) == pytest.approx(2.0, rel=1e-4)
    assert np.count_nonzero(np.diff(np.signbit(c[1:]))) == pytest.approx(59, abs=1)
    # log chirp 0.1 -> 10 Hz over 20 s: 20 s * (10 - 0.1) / ln(100) = 42.99 cycles
    c = signals.chirp(20001, Ts, 0.1, 10.0, 1.0)
    assert np.count_nonzero(np.diff(np.signbit(c[1:]))) == pytest.approx(2 * 42.99, abs=2)
    with pytest.raises(ValueError, match="Nyquist"):
        signals.chirp(100, 0.02, 1.0, 30.0, 1.0)


def test_chirp_is_scipy_signal_chirp_to_the_bit():
    """The swept sine's phase is written out (scipy.signal is not imported by a spec's reader): the same numbers as
    scipy.signal.chirp, starting at the offset (phi = -90 deg), for log and linear sweeps, up, down and flat."""
    from scipy.signal import chirp as scipy_chirp

    rng = np.random.default_rng(5)
    for _ in range(60):
        n, Ts = int(rng.integers(2, 20_000)), float(rng.choice([0.001, 0.002, 0.01, 0.02]))
        f0, f1 = (float(np.exp(rng.uniform(math.log(0.01), math.log(0.45 / Ts)))) for _ in range(2))
        amp, off = float(rng.uniform(0.1, 5.0)), float(rng.uniform(-1.0, 1.0))
        for ours, theirs in (("log", "logarithmic"), ("linear", "linear")):
            for g1 in (f1, f0):
                t = np.arange(n) * Ts
                expected = off + amp * scipy_chirp(t, f0, t[-1], g1, method=theirs, phi=-90.0)
                assert signals.chirp(n, Ts, f0, g1, amp, method=ours, offset=off).tobytes() == expected.tobytes()


def test_multisine_power_only_on_designed_odd_lines():
    N, P, Ts = 1000, 4, 0.01  # df = 0.1 Hz per period, 4 periods
    x, bins = signals.multisine(N * P, Ts, 0.25, 20.0, 0.8, period_samples=N, seed=3)
    lines = signals.multisine_lines(N, Ts, 0.25, 20.0, seed=3)
    np.testing.assert_array_equal(bins, lines.excited)
    np.testing.assert_array_equal(x[:N], x[N : 2 * N])  # periodic
    assert math.sqrt(np.mean(x**2)) == pytest.approx(0.8, rel=1e-12)
    assert abs(x.mean()) < 1e-12
    # band 0.25..20 Hz -> bins 3..200; odd candidates 3, 5, ..., 199 (99 lines = 33 groups of 3)
    assert np.all(bins % 2 == 1) and bins.min() >= 3 and bins.max() <= 199
    assert bins.size == 66
    groups = (bins - 3) // 6  # consecutive odd lines 3,5,7 | 9,11,13 | ...
    assert np.all(np.bincount(groups, minlength=33) == 2)
    np.testing.assert_array_equal(np.sort(np.r_[bins, lines.odd_detection]), np.arange(3, 200, 2))
    np.testing.assert_array_equal(lines.even_detection, np.arange(4, 201, 2))
    X = np.abs(np.fft.rfft(x)) ** 2
    on = bins * P
    off = np.setdiff1d(np.arange(X.size), on)
    assert X[off].max() < 1e-10 * X[on].max()
    np.testing.assert_allclose(X[on], X[on].mean(), rtol=1e-9)  # flat amplitude spectrum
    cf = signals.crest_factor(x)
    print(f"multisine crest factor: {cf:.3f}")
    assert math.sqrt(2) < cf < 5.0
    x2, _ = signals.multisine(N * P, Ts, 0.25, 20.0, 0.8, period_samples=N, seed=3)
    np.testing.assert_array_equal(x, x2)
    with pytest.raises(ValueError, match="multiple"):
        signals.multisine(N * P + 1, Ts, 0.25, 20.0, 0.8, period_samples=N)


def test_generate_dispatches_with_spec_names_and_rejects_bad_input():
    n, Ts = 2000, 0.02
    np.testing.assert_array_equal(
        signals.generate("prbs", n, Ts, {"B": 0.1, "amplitude": 1.5}, 4), signals.prbs(n, 0.1, 1.5, seed=4)
    )
    np.testing.assert_array_equal(
        signals.generate("square", n, Ts, {"f": 0.35, "amplitude": 1.0}, 0), signals.square(n, Ts, 0.35, 1.0)
    )
    ms = {"f_min": 0.1, "f_max": 5.0, "amplitude_rms": 0.5, "period": 10.0}
    x = signals.generate("multisine", n, Ts, ms, 2)
    ref, _ = signals.multisine(n, Ts, 0.1, 5.0, 0.5, period_samples=500, seed=2)
    np.testing.assert_array_equal(x, ref)
    np.testing.assert_array_equal(signals.generate("constant", 3, Ts, {"amplitude": 1.0}, 0), np.ones(3))
    with pytest.raises(ValueError, match="valid: constant, prbs, square, step, ramp, chirp, multisine"):
        signals.generate("sine", n, Ts, {}, 0)
    with pytest.raises(ValueError, match="unknown parameter.*freq.*valid: f, amplitude, offset, duty, phase"):
        signals.generate("square", n, Ts, {"freq": 1.0, "amplitude": 1.0}, 0)
    with pytest.raises(ValueError, match="missing parameter.*amplitude"):
        signals.generate("prbs", n, Ts, {"B": 0.1}, 0)
    signals.check_params("multisine", Ts, ms)
    with pytest.raises(ValueError, match="whole number of samples"):
        signals.check_params("multisine", Ts, {**ms, "period": 10.001})
