"""Sensor calibration against the seed tables and synthetic rig signals with known truth."""

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.ident import calibration as cal

REF = Path(__file__).resolve().parent / "fixtures"  # provenance: fixtures/README.md
LSB_12BIT = 20.0 / 4096  # V, 12-bit ADC over +-10 V


def _pot_volts(theta_deg, Kp, deadband, rng, noise=0.003):
    """Potentiometer: wraps at +-180 deg, holds its end voltage inside the dead band, noisy, 12-bit."""
    phi = np.mod(theta_deg + 180.0, 360.0) - 180.0
    half = 180.0 - deadband / 2
    v = np.clip(phi, -half, half) / Kp + noise * rng.standard_normal(phi.size)
    return np.round(v / LSB_12BIT) * LSB_12BIT


def _table(path):
    return pd.read_csv(path, comment="#")


def test_seed_kp_and_ke():
    assert cal.kp_from_wrap_voltages(5.0635, -5.0732) == pytest.approx(35.5145, abs=1e-4)
    d = _table(REF / "seed_strain_gauge_comb_000.csv")
    g = cal.ke_from_comb(d["angle_deg"], d["gauge_v"])
    assert round(g.Ke, 4) == -3.3636
    assert g.r2 > 0.999
    with pytest.raises(ValueError, match="v_max > v_min"):
        cal.kp_from_wrap_voltages(-5.0, 5.0)


def test_second_lab_table_gives_1511_not_134():
    d = _table(REF / "seed_calibration_001.csv")
    sg = d[d["table"] == "strain_gauge"]
    pot = d[d["table"] == "potentiometer"]
    ke = cal.ke_from_comb(sg["angle_deg"], sg["volts"]).Ke
    assert round(ke, 3) == 1.511
    assert abs(ke - 1.34) > 0.15
    assert round(cal.kp_from_table(pot["angle_deg"], pot["volts"]), 3) == 35.313


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_kp_from_ramp_beats_span_formula(direction):
    rng = np.random.default_rng(11)
    Kp, db, Ts = 35.5, 8.0, 0.02
    t = np.arange(1500) * Ts
    tau, speed = 0.03, 67.0  # 1 V step at t = 0, one sample of delay, first-order speed lag to 67 deg/s
    s = np.maximum(t - Ts, 0.0)
    theta = 37.0 + direction * speed * (s - tau * (1 - np.exp(-s / tau)))
    res = cal.kp_from_ramp(t, _pot_volts(theta, Kp, db, rng))
    assert res.lag_s == pytest.approx(tau + Ts, abs=0.003)  # the ramp asymptote lags by delay + tau
    turns = np.floor((theta + 180.0) / 360.0)
    assert res.n_wraps == abs(turns[-1] - turns[0]) >= 5
    assert res.Kp == pytest.approx(Kp, rel=0.005)
    span_err = res.Kp_span / Kp - 1  # 360 / 352 - 1 = 2.27 %
    assert 0.020 < span_err < 0.026
    assert res.deadband_deg == pytest.approx(db, abs=0.5)
    with pytest.raises(ValueError, match="wrap"):
        cal.kp_from_ramp(t[:30], _pot_volts(theta[:30], Kp, db, rng))


def _ramp_onset_record(Vth, slope, Ts, *, K=101.0, tau=0.03, delay=1, Kp=35.5, rng=None, theta0=12.0):
    """Shaft on a slow ramp u = slope t: theta'' = (K drive - theta') / tau, drive = sign(u) (|u| - Vth)+,
    the amplifier seeing u ``delay`` samples late; closed form (motor at rest until the threshold)."""
    T = 0.6 / abs(slope)
    t = np.arange(int(T / Ts)) * Ts
    u = slope * t
    s = np.maximum(t - delay * Ts - Vth / abs(slope), 0.0)  # time since the amplifier passed the threshold
    theta = theta0 + np.sign(slope) * K * abs(slope) * (s**2 / 2 - tau * s + tau**2 * (1 - np.exp(-s / tau)))
    return t, u, Kp * _pot_volts(theta, Kp, 8.0, rng)


def test_dead_zone_from_ramps_within_one_percent():
    rng = np.random.default_rng(5)
    Vth, Ts, tau = 0.34, 0.02, 0.03
    for slope in (0.02, 0.05):
        est = []
        for sign in (1.0, -1.0):
            t, u, th = _ramp_onset_record(Vth, sign * slope, Ts, tau=tau, rng=rng)
            v = cal.dead_zone_estimate(t, u, th).v_th
            assert v == pytest.approx(Vth, rel=0.01), (slope, sign, v)
            v_corr = cal.dead_zone_estimate(t, u, th, lag_s=tau + Ts).v_th  # lag as PotCalibration.lag_s gives
            assert v_corr == pytest.approx(Vth, rel=0.003), (slope, sign, v_corr)
            est.append(cal.dead_zone_estimate(t, u, th))
        both = cal.dead_zone_merge(*est)
        assert both.v_up is not None and both.v_down is not None
        assert both.v_th == pytest.approx((both.v_up + both.v_down) / 2)
    # one record going up then down: both directions found, mean reported
    t1, u1, th1 = _ramp_onset_record(Vth, 0.03, Ts, rng=rng)
    t2, u2, th2 = _ramp_onset_record(Vth, -0.03, Ts, rng=rng, theta0=th1[-1])
    t = np.r_[t1, t1[-1] + Ts + np.arange(50) * Ts, t1[-1] + 51 * Ts + t2]
    u = np.r_[u1, np.zeros(50), u2]
    th = np.r_[th1, np.full(50, th1[-1]), th2]
    dz = cal.dead_zone_estimate(t, u, th)
    assert dz.v_up == pytest.approx(Vth, rel=0.01) and dz.v_down == pytest.approx(Vth, rel=0.01)
    with pytest.raises(ValueError, match="no motion onset"):
        cal.dead_zone_estimate(t1, u1, np.full(t1.size, 3.0))


def test_comb_table_averages_settled_part_and_recovers_ke():
    rng = np.random.default_rng(2)
    Ts, Ke, off = 0.002, -3.3636, 0.05
    angles = np.array([5.28, 3.43, 1.58, 0.0, -2.0, -4.72, -7.41])
    holds = [(3.0 * i + 0.2, 3.0 * i + 2.8) for i in range(angles.size)]
    t = np.arange(int(3.0 * angles.size / Ts)) * Ts
    alpha = np.zeros_like(t)
    for (a, b), ang in zip(holds, angles, strict=True):
        m = (t >= a) & (t < b)
        ring = 3.0 * np.exp(-(t[m] - a) / 0.08) * np.cos(2 * np.pi * 3 * (t[m] - a))  # settles in < 0.5 s
        alpha[m] = ang + ring
    volts = alpha / Ke + off + 0.002 * rng.standard_normal(t.size)
    ang, v = cal.comb_table(t, volts, angles, holds)
    np.testing.assert_array_equal(ang, angles)
    g = cal.ke_from_comb(ang, v)
    assert g.Ke == pytest.approx(Ke, rel=2e-3)
    assert g.offset_v == pytest.approx(off, abs=2e-3)
    ang2, v2 = cal.comb_table(t, volts, alpha, holds)  # true angle as a time series
    np.testing.assert_allclose(ang2, angles, atol=1e-4)
    np.testing.assert_allclose(v2, v)
    with pytest.raises(ValueError, match="no samples"):
        cal.comb_table(t, volts, angles[:1], [(1.0, 1.3)])


def test_calibration_json_round_trip_and_conversions(tmp_path):
    c = cal.Calibration(Kp=35.5145, Ke=-3.3636, gauge_offset_v=0.0085, source={"Kp": "wrap"})
    p = tmp_path / "calibration.json"
    c.to_json(p)
    raw = json.loads(p.read_text())
    assert list(raw) == sorted(raw) and raw["dead_zone_v"] is None
    back = cal.Calibration.from_json(p)
    assert back.Kp == c.Kp and back.Ke == c.Ke and math.isnan(back.dead_zone_v) and back.source == c.source
    assert [f.name for f in tmp_path.iterdir()] == ["calibration.json"]  # no temp file left behind
    p.write_text(json.dumps({**raw, "Kq": 1.0}))
    with pytest.raises(ValueError, match="unknown field.*Kq"):
        cal.Calibration.from_json(p)
    # pot through 3 wraps with an 8 deg dead band: unwrapped within the dead band's error, no drift
    rng = np.random.default_rng(3)
    theta = np.linspace(-100.0, 1000.0, 4000)
    v = _pot_volts(theta, 35.5, 8.0, rng)
    c = cal.Calibration(Kp=35.5, Ke=1.5, gauge_offset_v=0.25)
    err = cal.theta_deg(v, c) - theta
    err -= 360.0 * np.round(np.median(err) / 360.0)  # the pot reads theta modulo 360
    phi = np.mod(theta + 180.0, 360.0) - 180.0
    assert np.max(np.abs(err)) < 4.8  # half the dead band plus noise
    assert np.max(np.abs(err[np.abs(phi) < 175])) < 0.8  # 5 sigma noise + half an LSB, no drift per wrap
    np.testing.assert_allclose(cal.alpha_deg(np.array([0.25, 1.25]), c), [0.0, 1.5])
    tip = cal.tip_deg(v, np.full(v.size, 1.25), c)
    np.testing.assert_allclose(tip, cal.theta_deg(v, c) + 1.5)


def test_calibrate_in_memory_gives_calibrate_run_to_the_last_bit(tmp_path):
    """``calibrate`` on a campaign's columns in memory (arrays or DataFrames) gives what ``calibrate_run`` gives on
    the same data written to a run directory: the same numbers to the last bit, the same calibration.json bytes."""
    from harness.rundir import ExperimentEntry, Manifest, RunDir, write_dataset

    rng = np.random.default_rng(7)
    Kp, Ke, off, Vth, Ts = 35.5, -3.3636, 0.05, 0.34, 0.02
    t = np.arange(1500) * Ts  # pot ramp: a 1 V step turning the shaft through 5 wraps
    s = np.maximum(t - Ts, 0.0)
    theta = 37.0 + 67.0 * (s - 0.03 * (1 - np.exp(-s / 0.03)))
    quiet = 0.002 * rng.standard_normal(t.size)
    cols = {"pot_ramp": {"t": t, "u": np.ones(t.size), "theta_v": _pot_volts(theta, Kp, 8.0, rng), "alpha_v": quiet}}
    angles = np.array([5.28, 2.58, 0.0, -2.86, -5.57])  # comb: 2.5 s holds, 1 s moves between (comb_angle NaN)
    tc = np.arange(int(3.5 * angles.size / Ts)) * Ts
    comb_angle = np.where(np.mod(tc, 3.5) >= 1.0, angles[np.minimum((tc // 3.5).astype(int), angles.size - 1)], np.nan)
    alpha = np.nan_to_num(comb_angle)
    alpha_v = alpha / Ke + off + 0.002 * rng.standard_normal(tc.size)
    cols["comb"] = {"t": tc, "u": np.zeros(tc.size), "theta_v": np.zeros(tc.size), "alpha_v": alpha_v}
    cols["comb"]["comb_angle"] = comb_angle
    for name, slope in (("deadzone_up", 0.05), ("deadzone_down", -0.05)):
        tr, u, th = _ramp_onset_record(Vth, slope, Ts, rng=rng)
        cols[name] = {"t": tr, "u": u, "theta_v": th / Kp, "alpha_v": np.zeros(tr.size)}
    signals = {"pot_ramp": "constant", "comb": "comb", "deadzone_up": "ramp", "deadzone_down": "ramp"}
    entries = [ExperimentEntry(name=n, role="calibration", signal=s) for n, s in signals.items()]
    run = tmp_path / "run"
    for name, c in cols.items():
        write_dataset(RunDir(run).dataset(name), c)
    Manifest(kind="campaign", experiments=entries, sample_rate=1 / Ts).write(run)
    kept = {n: {k: v.copy() for k, v in c.items()} for n, c in cols.items()}

    on_disk = cal.calibrate_run(run)
    in_memory = cal.calibrate(entries, cols)
    as_frames = cal.calibrate(entries, {n: pd.DataFrame(c) for n, c in cols.items()})

    def numbers(c: cal.Calibration) -> tuple[float, ...]:
        return c.Kp, c.Ke, c.gauge_offset_v, c.dead_zone_v

    for c in (in_memory, as_frames):
        assert numbers(c) == numbers(on_disk)  # ==, not approx: the same bits
        c.to_json(tmp_path / "calibration.json")
        assert (tmp_path / "calibration.json").read_bytes() == RunDir(run).calibration.read_bytes()
    # the numbers are measured, not lab 1's stand-ins
    assert in_memory.Kp == pytest.approx(Kp, rel=0.005) and in_memory.Ke == pytest.approx(Ke, rel=2e-3)
    assert in_memory.gauge_offset_v == pytest.approx(off, abs=2e-3)
    assert in_memory.dead_zone_v == pytest.approx(Vth, rel=0.01)
    assert in_memory.source["dead_zone_v"]["experiments"] == ["deadzone_up", "deadzone_down"]
    for name, c in cols.items():  # the caller's arrays are left as they were (a sweep goes on using them)
        for k, v in c.items():
            np.testing.assert_array_equal(v, kept[name][k])
    # only the experiments used need data; without any, lab 1's numbers and a source that says so
    assert cal.calibrate(entries[:1], {"pot_ramp": cols["pot_ramp"]}).Kp == on_disk.Kp
    none = cal.calibrate([], {})
    assert (none.Kp, none.Ke) == (cal.LAB1_CALIBRATION["Kp"], cal.LAB1_CALIBRATION["Ke"])
    assert math.isnan(none.dead_zone_v) and "no pot ramp" in none.source["Kp"]["method"]
