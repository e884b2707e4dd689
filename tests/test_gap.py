"""Where the sim-to-real gap lies (harness.diagnosis.where) and the BLA / FRF it compares (harness.diagnosis.frf):
synthetic residuals whose location, band and amplitude law are known."""

import json
import math

import numpy as np
import pytest
from scipy.signal import freqz, lfilter

from harness.diagnosis import frf, where
from harness.rig import signals

TS = 0.02  # s, the first lab's 50 Hz


def _servo(u: np.ndarray, Ts: float = TS) -> np.ndarray:
    """Toy rig [deg]: 1-sample delay, motor lag (30 ms), 3 Hz lightly damped mode, integrator."""
    a = math.exp(-Ts / 0.03)
    v = lfilter([100.0 * (1.0 - a)], [1.0, -a], np.r_[0.0, u[:-1]])
    w0, z = 2.0 * math.pi * 3.0, 0.05
    r = math.exp(-z * w0 * Ts)
    c = 2.0 * r * math.cos(w0 * Ts * math.sqrt(1.0 - z * z))
    return np.cumsum(lfilter([1.0 - c + r * r], [1.0, -c, r * r], v)) * Ts


def _dead_zone(u: np.ndarray, d: float) -> np.ndarray:
    return np.sign(u) * np.maximum(np.abs(u) - d, 0.0)


def _no_numpy_types(obj) -> None:
    json.dumps(obj)  # raises TypeError on numpy scalars / arrays


# --- frequency


def test_7hz_residual_sits_in_the_5_10_hz_band_with_its_sine_power():
    n = 3000
    t = np.arange(n) * TS
    e = 0.5 * np.sin(2 * np.pi * 7.0 * t)
    y = 10.0 * e + 3.0 * np.sin(2 * np.pi * 1.0 * t)
    r = where.residual_by_band(e, TS, y=y)
    edges = [(b["lo_hz"], b["hi_hz"]) for b in r["bands"]]
    assert edges == [(0.0, 0.5), (0.5, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 25.0)]
    band = r["bands"][3]
    assert band["share"] > 0.9
    assert band["power"] == pytest.approx(0.5**2 / 2, rel=0.02)  # a sine's mean square A^2 / 2
    assert band["ratio"] == pytest.approx(0.01, rel=0.02)  # e is y / 10 in that band
    assert r["bands"][1]["ratio"] < 1e-4  # y's 1 Hz line carries no residual
    assert r["dominant"]["lo_hz"] == 5.0
    _no_numpy_types(r)
    with pytest.raises(ValueError, match="Nyquist"):
        where.residual_by_band(e, TS, [0.0, 1.0, 30.0])


# --- time


def test_window_shares_and_concentration_index():
    n = 2000  # 40 s
    t = np.arange(n) * TS
    rng = np.random.default_rng(0)
    burst = np.where((t >= 12.0) & (t < 13.0), rng.normal(size=n), 0.0)
    r = where.residual_by_window(t, burst, 1.0)
    assert r["n_windows"] == 40
    assert r["top"][0]["start_s"] == pytest.approx(12.0)
    assert r["top"][0]["share"] == pytest.approx(1.0)
    assert r["top10_share"] == pytest.approx(1.0) and r["top10_uniform"] == pytest.approx(0.1)
    assert r["rms"][12] == pytest.approx(math.sqrt(np.mean(burst[600:650] ** 2)))
    white = where.residual_by_window(t, rng.normal(size=n), 1.0)
    assert 0.1 < white["top10_share"] < 0.2  # evenly spread: the top 4 of 40 windows hold ~10 %
    with pytest.raises(ValueError, match="window_s"):
        where.residual_by_window(t, burst, 0.0)


# --- events


def test_residual_at_command_reversals_is_enriched_and_noise_is_not():
    n = 3000
    t = np.arange(n) * TS
    u = signals.square(n, TS, 0.3, 1.0)
    rng = np.random.default_rng(1)
    theta = np.cumsum(u) * TS * 50.0 + rng.normal(0.0, 0.2, n)
    changes = t[np.flatnonzero(np.diff(u) != 0) + 1]
    dist = np.min(np.abs(t[:, None] - changes[None, :]), axis=1)
    e = np.where(dist <= 0.2, np.sin(2 * np.pi * 3.0 * t), 0.0)
    mask = where.reversal_mask(t, theta, u, 0.2)
    r = where.near_events(t, e, mask)
    assert r["n_events"] == changes.size
    assert r["energy_share"] == pytest.approx(1.0)
    assert r["enrichment"] > 3.0
    # the command alone marks exactly [last sample before, first sample after] +- 0.2 s around each change
    mid = changes - TS / 2
    near = np.min(np.abs(t[:, None] - mid[None, :]), axis=1) <= 0.2 + TS / 2 + 1e-9
    np.testing.assert_array_equal(where.reversal_mask(t, None, u, 0.2), near)
    flat = where.near_events(t, rng.normal(size=n), mask)
    assert 0.8 < flat["enrichment"] < 1.2
    # the shaft alone (no command) finds the same reversals: the velocity of the triangle flips there
    assert where.near_events(t, e, where.reversal_mask(t, theta, None, 0.2))["enrichment"] > 3.0


def test_shaft_reversals_are_robust_to_sensor_noise():
    n = 3000
    t = np.arange(n) * TS
    theta = 30.0 * np.sin(2 * np.pi * 0.5 * t) + np.random.default_rng(2).normal(0.0, 0.3, n)
    true = int(np.count_nonzero(np.diff(np.sign(np.cos(2 * np.pi * 0.5 * t)))))  # 60 turning points
    naive = int(np.count_nonzero(np.diff(np.sign(np.diff(theta)))))
    mask = where.reversal_mask(t, theta, None, 0.1)
    assert where.near_events(t, theta, mask)["n_events"] == true
    assert naive > 5 * true  # raw sign changes of the difference are mostly noise
    # every true turning point (cos = 0 at t = 0.5 + k s) lies inside the mask
    turns = 0.5 + np.arange(true)
    assert np.all(mask[np.round(turns / TS).astype(int)])


def test_pot_wraps_are_found_where_the_angle_crosses_180_deg():
    n = 1000  # 20 s at 90 deg/s from -170 deg: crossings of +180 + 360 k at t = (350 + 360 k) / 90
    t = np.arange(n) * TS
    theta = -170.0 + 90.0 * t
    wrapped = (theta + 180.0) % 360.0 - 180.0
    edge = 180.0 - 4.0  # 8 deg dead band: the wiper reads the track end
    volts = np.clip(wrapped, -edge, edge) / 35.5
    mask = where.wrap_mask(t, volts, 0.2)
    starts = t[np.flatnonzero(np.diff(mask.astype(int)) == 1) + 1]
    expected = (350.0 + 360.0 * np.arange(5)) / 90.0
    assert starts.size == 5
    np.testing.assert_allclose(starts, expected - 0.2, atol=2 * TS)
    e = np.random.default_rng(3).normal(size=n)
    assert 0.6 < where.near_events(t, e, mask)["enrichment"] < 1.4
    assert not where.wrap_mask(t, 0.5 * np.sin(t), 0.2).any()  # smooth motion: no wrap


# --- amplitude


def _ms(n: int = 8192, f_max: float = 10.0, seed: int = 0) -> np.ndarray:
    return signals.multisine(n, TS, 0.1, f_max, 1.0, period_samples=n // 2, seed=seed)[0]


def test_static_amplitude_classifier_dead_zone_clipping_gain():
    u = _ms()
    dz = where.by_amplitude(u, u - _dead_zone(u, 0.34))
    assert dz["trend"] == where.GROWS_SMALL and dz["ratio"] > 2.0
    assert dz["bins"][0]["hi_v"] < 0.34 and dz["bins"][0]["rel_rms"] == pytest.approx(1.0)  # all inside
    clip = where.by_amplitude(u, u - np.clip(u, -1.5, 1.5))
    assert clip["trend"] == where.GROWS_LARGE and clip["bins"][0]["rel_rms"] == 0.0
    gain = where.by_amplitude(u, 0.1 * u)
    assert gain["trend"] == where.FLAT and gain["ratio"] == pytest.approx(1.0)
    assert gain["loglog_slope"] == pytest.approx(1.0)
    prbs = signals.prbs(2000, 0.1, 1.5)
    assert where.by_amplitude(prbs, 0.1 * prbs)["trend"] == where.UNDETERMINED  # one |u| level
    _no_numpy_types(dz)


def test_amplitude_curve_sees_the_static_error_through_the_plant_lag():
    u = _ms(12000, 10.0, seed=1)
    ys = _servo(u)
    noise = np.random.default_rng(4).normal(0.0, 0.1, u.size)  # deg, pot noise + quantization scale
    dz = where.amplitude_curve(u, _servo(_dead_zone(u, 0.34)) + noise - ys, ys)
    assert dz["trend"] == where.GROWS_SMALL and dz["arx_fit"] > 0.999
    knots, g = np.array(dz["knots_v"]), np.array(dz["g_v"])
    np.testing.assert_allclose(np.abs(g[knots > 0.6]), 0.34, atol=0.05)  # the dead-zone width, in V
    cl = where.amplitude_curve(u, _servo(np.clip(u, -1.5, 1.5)) + noise - ys, ys)
    knots, g = np.array(cl["knots_v"]), np.array(cl["g_v"])
    assert cl["trend"] == where.GROWS_LARGE
    assert np.all(np.abs(g[knots < 1.4]) < 0.05) and abs(g[-1]) == pytest.approx(knots[-1] - 1.5, abs=0.15)
    gain = where.amplitude_curve(u, _servo(0.9 * u) - ys, ys)  # exact, noise-free
    assert gain["trend"] == where.FLAT
    np.testing.assert_allclose(gain["g_v"], -0.1 * np.array(gain["knots_v"]), atol=1e-8)
    late = where.amplitude_curve(u, _servo(np.r_[0.0, u[:-1]]) + noise - ys, ys)  # one more sample of delay
    assert late["trend"] == where.FLAT and late["nl_explained"] < 0.005 < 0.1 < dz["nl_explained"]
    assert where.amplitude_curve(np.sign(u), u, ys)["trend"] == where.UNDETERMINED


# --- best linear approximation


P = 512
B_LIN, A_LIN = [0.2, 0.1, -0.05], [1.0, -1.7, 0.8]  # poles |p| = 0.89: a 1-period transient of ~1e-13


def _ms_experiment(periods: int = 8):
    lines = signals.multisine_lines(P, TS, 0.1, 12.0, seed=3)
    u, _ = signals.multisine(P * periods, TS, 0.1, 12.0, 1.0, period_samples=P, seed=3)
    z = lfilter(B_LIN, A_LIN, u)  # starts from rest: the first period holds the transient
    return u, z, lines


def test_bla_of_a_linear_system_is_its_frf():
    u, z, lines = _ms_experiment()
    b = frf.bla(u, z, P, lines)
    _, H = freqz(B_LIN, A_LIN, worN=b.freqs, fs=1 / TS)
    assert np.max(np.abs(b.G - H) / np.abs(H)) < 1e-8
    assert np.max(b.var_noise / np.abs(H) ** 2) < 1e-20
    np.testing.assert_allclose(b.freqs, lines.freqs("excited"))
    assert b.n_periods == 7 and b.odd_level_db < -200
    d = b.to_dict()
    _no_numpy_types(d)
    np.testing.assert_allclose(d["mag_db"], 20 * np.log10(np.abs(H)), atol=1e-6)


def test_bla_detection_lines_separate_odd_and_even_nonlinearities():
    u, z, lines = _ms_experiment()
    noise = np.random.default_rng(5).normal(0.0, 1e-3, u.size)
    cubic = frf.bla(u, z + 0.3 * z**3 + noise, P, lines)
    assert cubic.odd_level_db - cubic.even_level_db > 20.0
    assert abs(cubic.even_level_db - cubic.noise_level_db) < 3.0  # even lines hold only noise
    assert np.median(cubic.var_nl) > 100 * np.median(cubic.var_noise)
    square = frf.bla(u, z + 0.2 * z**2 + noise, P, lines)
    assert square.even_level_db - square.noise_level_db > 20.0
    assert square.even_level_db - square.odd_level_db > 20.0  # a square law cannot reach odd lines


def test_bla_noise_variance_matches_the_injected_noise():
    u, z, lines = _ms_experiment(periods=8)
    sigma, M = 0.05, 7
    U = np.fft.rfft(u[:P])[lines.excited]
    expected = P * sigma**2 / (M * np.abs(U) ** 2)  # var of the mean of M period DFTs of white noise
    for seed in (6, 7):
        b = frf.bla(u, z + np.random.default_rng(seed).normal(0.0, sigma, u.size), P, lines)
        ratio = float(np.mean(b.var_noise / expected))
        assert 1 / 1.5 < ratio < 1.5, ratio


def test_frf_gap_flags_the_lines_where_the_model_is_off():
    u, z, lines = _ms_experiment()
    b = frf.bla(u, z + np.random.default_rng(8).normal(0.0, 0.01, u.size), P, lines)
    _, H = freqz(B_LIN, A_LIN, worN=b.freqs, fs=1 / TS)
    G_sim = np.where(b.freqs >= 5.0, 1.1 * H, H)  # model gain 10 % high above 5 Hz
    r = frf.frf_gap(b, G_sim)
    hi = b.freqs >= 5.0
    assert set(r["exceeds_hz"]) >= set(b.freqs[hi].tolist())
    assert sum(f < 5.0 for f in r["exceeds_hz"]) <= 0.2 * np.count_nonzero(~hi)
    np.testing.assert_allclose(np.array(r["err_db"])[hi], 20 * math.log10(1.1), atol=0.05)
    band = next(x for x in r["bands"] if x["lo_hz"] == 5.0)
    assert band["n_exceed"] == band["n_lines"] > 0
    _no_numpy_types(r)
    with pytest.raises(ValueError, match="G_sim"):
        frf.frf_gap(b, G_sim[:-1])


def test_bla_rejects_short_records_and_foreign_lines():
    u, z, lines = _ms_experiment(periods=2)
    with pytest.raises(ValueError, match="at least 3 whole periods"):
        frf.bla(u, z, P, lines)
    u, z, lines = _ms_experiment()
    with pytest.raises(ValueError, match="period of 512"):
        frf.bla(u, z, 256, lines)
    with pytest.raises(ValueError, match="samples"):
        frf.bla(u, z[:-1], P, lines)


# --- one experiment, pooled


def test_where_and_summary_point_at_the_dead_zone():
    n = 6000
    t = np.arange(n) * TS
    ms_lines = signals.multisine_lines(1000, TS, 0.1, 10.0, seed=2)
    ms, _ = signals.multisine(n, TS, 0.1, 10.0, 1.0, period_samples=1000, seed=2)
    prbs = signals.prbs(n, 0.05, 1.5, seed=2)
    rng = np.random.default_rng(9)
    per = {}
    for name, u, kw in (("multisine", ms, {"period_samples": 1000, "lines": ms_lines}), ("prbs", prbs, {})):
        ys = _servo(u)
        yr = _servo(_dead_zone(u, 0.34)) + rng.normal(0.0, 0.05, n)
        per[name] = where.where(t, u, yr, ys, TS, theta_deg=yr, **kw)
        _no_numpy_types(per[name])
    assert per["multisine"]["amplitude"]["trend"] == where.GROWS_SMALL
    assert per["prbs"]["amplitude"]["trend"] == where.UNDETERMINED  # a +-1.5 V PRBS has one level
    assert per["multisine"]["frequency"]["frf"]["share_exceed"] > 0.5  # friction lowers the BLA's gain
    s = where.summarise_where(per)
    assert s["amplitude"]["regime"] == where.GROWS_SMALL
    assert "grows at small commands" in s["headline"]
    assert s["nonlinearity"]["odd"] and not s["nonlinearity"]["even"]  # a dead zone is odd
    assert s["frf"]["n_lines"] == len(ms_lines.excited)
    _no_numpy_types(s)
    with pytest.raises(ValueError, match="samples"):
        where.where(t, ms, ms[:-1], ms, TS)


def test_summary_reports_concentration_at_reversals():
    n = 3000
    t = np.arange(n) * TS
    u = signals.square(n, TS, 0.3, 1.0)
    ys = np.cumsum(u) * TS * 50.0
    changes = t[np.flatnonzero(np.diff(u) != 0) + 1]
    dist = np.min(np.abs(t[:, None] - changes[None, :]), axis=1)
    bump = np.where(dist <= 0.2, 2.0 * np.cos(np.pi * dist / 0.4) ** 2, 0.0)  # smooth, 0 at +-0.2 s
    yr = ys + bump + np.random.default_rng(10).normal(0.0, 0.01, n)
    s = where.summarise_where({"square": where.where(t, u, yr, ys, TS, theta_v=((ys + 180) % 360 - 180) / 35.5)})
    rev = s["events"]["reversals"]
    assert rev["concentrates"] and rev["enrichment"] > 3.0
    assert "motion reversals" in s["headline"]
    assert not s["events"]["wraps"]["concentrates"]
