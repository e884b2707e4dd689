"""The step metrics of harness.behaviour on signals whose answers are known in closed form."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from harness.behaviour import reference_steps, ring_frequency, step_metrics, summarize

ZETA, WN = 0.3, 2 * math.pi * 2.0  # a second-order loop: damping ratio, natural frequency [rad/s]
WD = WN * math.sqrt(1 - ZETA**2)


def unit_step(tau: np.ndarray | float) -> np.ndarray:
    """The unit step response of wn^2 / (s^2 + 2 zeta wn s + wn^2), 0 before tau = 0."""
    tau = np.asarray(tau, dtype=float)
    phi = math.acos(ZETA)
    y = 1 - np.exp(-ZETA * WN * tau) / math.sqrt(1 - ZETA**2) * np.sin(WD * tau + phi)
    return np.where(tau >= 0, y, 0.0)


def second_order_loop(Ts: float = 1e-3):
    """A reference 0 -> 30 deg at 0.5 s, -> -10 deg at 5.5 s, and the second-order loop's response to it."""
    t = np.arange(0, 10.5, Ts)
    ref = np.where(t < 0.5 - Ts / 2, 0.0, np.where(t < 5.5 - Ts / 2, 30.0, -10.0))
    theta = 30 * unit_step(t - 0.5) - 40 * unit_step(t - 5.5)
    alpha = np.zeros_like(t)
    u = 0.1 * (ref - theta)
    return t, ref, theta, alpha, u


def exact_settling(band: float) -> float:
    """The last time the continuous unit step response leaves 1 +- band: the envelope bounds the search."""
    t_env = -math.log(band * math.sqrt(1 - ZETA**2)) / (ZETA * WN)  # beyond it the response stays inside
    grid = np.linspace(0, t_env, 200001)
    err = np.abs(unit_step(grid) - 1) - band
    k = np.flatnonzero(err >= 0)[-1]
    return brentq(lambda x: abs(float(unit_step(x)) - 1) - band, grid[k], grid[k + 1])


def test_second_order_overshoot_and_settling_against_closed_form_and_python_control():
    Ts = 1e-3
    t, ref, theta, alpha, u = second_order_loop(Ts)
    steps = step_metrics(t, ref, theta, alpha, u, band_pct=5.0)
    assert [(m.step.direction, m.step.size_deg) for m in steps] == [(1, 30.0), (-1, 40.0)]
    overshoot = 100 * math.exp(-ZETA * math.pi / math.sqrt(1 - ZETA**2))  # 37.23 %
    ts = exact_settling(0.05)
    for m in steps:
        assert m.overshoot_pct == pytest.approx(overshoot, abs=1e-3)
        # sampled: the first sample inside the band after the last exit, within one sample of the exact crossing
        assert ts <= m.settling_s < ts + Ts + 1e-12
        assert m.stop_error_deg == pytest.approx(0.0, abs=1e-6)  # the tail: 5 s after the step
        assert m.peak_u_v == pytest.approx(0.1 * m.step.size_deg)
        # python-control's step_info on the step shifted to start at 0: the same band (5 % of the step) and rule
        s, e = m.step.start, m.step.end
        y = (theta[s:e] - m.step.from_deg) * m.step.direction
        info = control.step_info(y, t[s:e] - t[s], SettlingTimeThreshold=0.05)
        assert m.settling_s == pytest.approx(info["SettlingTime"], abs=1e-12)
        # step_info's overshoot is of the final value, ours of the reference: here 1e-7 deg apart
        assert m.overshoot_pct == pytest.approx(info["Overshoot"], rel=1e-6)


def test_band_is_a_share_of_the_step_size():
    t, ref, theta, alpha, u = second_order_loop()
    wide = step_metrics(t, ref, theta, alpha, u, band_pct=10.0)
    assert wide[0].settling_s == pytest.approx(exact_settling(0.10), abs=1.1e-3)
    assert wide[0].settling_s < step_metrics(t, ref, theta, alpha, u, band_pct=2.0)[0].settling_s


def test_decaying_sinusoid_frequency_and_rms():
    f, sigma, amp = 3.1, 0.4, 2.0  # Hz, 1/s, deg
    Ts = 2e-3
    t = np.arange(0, 4.0, Ts)
    ref = np.where(t < 1.0, 0.0, 20.0)
    theta = ref.copy()
    alpha = amp * np.exp(-sigma * t) * np.sin(2 * math.pi * f * t + 0.3)
    m = step_metrics(t, ref, theta, alpha, np.zeros_like(t))[0]
    assert m.ring_hz == pytest.approx(f, rel=3e-3)
    # RMS over the step's last second with its mean removed, by quadrature of the continuous signal
    a, b = t[-1] - 1.0 + Ts / 2, t[-1] + Ts / 2

    def x(tau: float) -> float:
        return amp * math.exp(-sigma * tau) * math.sin(2 * math.pi * f * tau + 0.3)

    mean = quad(x, a, b, limit=200)[0] / (b - a)
    rms = math.sqrt(quad(lambda tau: (x(tau) - mean) ** 2, a, b, limit=200)[0] / (b - a))
    assert m.ring_alpha_deg == pytest.approx(rms, rel=1e-3)
    assert m.peak_alpha_deg == pytest.approx(np.max(np.abs(alpha[t >= 1.0 - Ts / 2])))


def test_noise_and_a_slow_drift_do_not_ring():
    rng = np.random.default_rng(0)
    t = np.arange(0, 1.0, 1e-3)
    assert math.isnan(ring_frequency(t, rng.normal(0, 0.1, t.size)))
    assert math.isnan(ring_frequency(t, np.sin(2 * math.pi * 1.2 * t)))  # 1.2 periods: too few to say
    assert ring_frequency(t, np.sin(2 * math.pi * 7.3 * t) + rng.normal(0, 0.1, t.size)) == pytest.approx(7.3, rel=3e-3)


def test_stop_error_sign_and_direction_split():
    # a hub that stops 2 deg short going up and 1 deg beyond going down (an offset pushing it up)
    Ts = 1e-2
    t = np.arange(0, 8.0, Ts)
    ref = np.where(t < 2, 0.0, np.where(t < 4, 30.0, np.where(t < 6, -30.0, 30.0)))
    theta = np.where(t < 2, 0.0, np.where(t < 4, 28.0, np.where(t < 6, -31.0, 28.0)))
    steps = step_metrics(t, ref, theta, np.zeros_like(t), np.zeros_like(t))
    assert [m.stop_error_deg for m in steps] == pytest.approx([2.0, -1.0, 2.0])
    assert [m.overshoot_pct for m in steps] == pytest.approx([0.0, 100 / 60, 0.0])
    s = summarize(steps)
    assert (s.stop_error_up_deg, s.stop_error_down_deg) == pytest.approx((2.0, -1.0))
    assert s.stop_error_deg.mean == pytest.approx(1.0)
    assert s.value("stop_error_deg") == pytest.approx(1.0)
    assert s.value("overshoot_pct") == pytest.approx(100 / 60)
    assert s.n_steps == 3


def test_ramped_transitions_spikes_and_the_first_segment():
    ref = np.array([0, 0, 0, 12, 18, 24, 30, 30, 30, 5, 30, 30, -30, -30, -30, -30, -30, -30, -30, -30, -30, -30])
    t = np.arange(ref.size) * 0.002
    steps = reference_steps(t, ref)
    # the ramp is one step; the spike down to 5 and back is none (its samples stay in the step before)
    assert [(s.start, s.end, s.from_deg, s.to_deg, s.direction) for s in steps] == [
        (3, 12, 0.0, 30.0, 1),
        (12, 22, 30.0, -30.0, -1),
    ]
    cut = reference_steps(t[:-1], ref[:-1])  # cut short, the last step still holds as many samples as the first
    assert [(s.start, s.end) for s in cut] == [(3, 12), (12, 21)]
    assert [(s.start, s.end) for s in reference_steps(t[:-3], ref[:-3])] == [(3, 12)]
    square = np.array([30.0] * 5 + [-30.0] * 5)
    assert reference_steps(np.arange(10.0), square) == reference_steps(np.arange(10.0), square)[:1]
    from_rest = reference_steps(np.arange(10.0), square, initial_deg=0.0)
    assert [(s.start, s.size_deg, s.direction) for s in from_rest] == [(0, 30.0, 1), (5, 60.0, -1)]


def test_a_step_not_settled_by_its_end_has_no_settling_time():
    t = np.arange(0, 2.0, 1e-3)
    ref = np.where(t < 0.5, 0.0, 10.0)
    theta = np.where(t < 0.5, 0.0, 10.0 * (1 - np.exp(-(t - 0.5) / 0.2)) + 3.0 * np.sin(40 * t) * (t > 1.99))
    m = step_metrics(t, ref, theta, np.zeros_like(t), np.zeros_like(t))[0]
    assert math.isnan(m.settling_s)
    assert math.isnan(summarize([m]).settling_s.worst)
