"""harness.ident.lti: integrator back, companion form (lab 1's eq. 10), responses."""

from __future__ import annotations

import control
import numpy as np
import pytest
from scipy.signal import lfilter

from benchmarks.problems import demo_system
from harness.ident import armax as ax
from harness.ident import lti


def _plant(n: int = 600, seed: int = 3):
    """A known u -> y system with an integrator (poles 0.9 exp(+-0.3j), 0.5, 1), PRBS-like input."""
    rng = np.random.default_rng(seed)
    u = np.where(np.cumsum(rng.random(n) < 0.2) % 2 == 0, 1.0, -1.0)
    a0 = np.real(np.poly([0.9 * np.exp(0.3j), 0.9 * np.exp(-0.3j), 0.5]))
    b0 = np.array([0.0, 0.02, 0.01])
    y = lfilter(b0, np.convolve(a0, [1.0, -1.0]), u)
    return u, y


def _sim(sys, u):
    import control

    t = sys.dt * np.arange(u.size)
    return np.asarray(control.forced_response(sys, T=t, U=u).outputs).reshape(-1)


@pytest.mark.parametrize("af", [0.8, 0.0])
def test_with_integrator_undoes_the_preprocessing(af):
    """af = 0.8 (the labs' filter) and af = 0 (the plain difference y[k] - y[k-1])."""
    u, y = _plant()
    yf = lfilter((1 - af) * np.array([1.0, -1.0]), [1.0, -af], y)
    m = ax.estimate(u, yf, 4 if af else 3, 2, 0, 1, Ts=0.02)
    g = lti.with_integrator(m, af)
    assert g.dt == 0.02
    assert np.max(np.abs(_sim(g, u) - y)) <= 1e-9 * np.max(np.abs(y))
    assert np.min(np.abs(lti.poles(g) - 1.0)) < 1e-9


def test_to_tf_evaluates_b_over_a_in_z_inverse():
    true = demo_system()
    g = lti.to_tf(true)
    z = np.exp(1j * np.array([0.05, 0.7, 2.0]))
    direct = np.polyval(true.B[::-1], 1 / z) / np.polyval(true.A[::-1], 1 / z)
    np.testing.assert_allclose(g(z), direct, rtol=1e-12)
    np.testing.assert_allclose(np.sort_complex(lti.poles(true)), np.sort_complex(np.roots(true.A)), atol=1e-12)
    nmp = lti.zeros(true)
    assert np.sum(np.abs(nmp) > 1.0) == 1  # the whiplash zero


def test_companion_form_reproduces_lab1_eq_10_from_eq_12(lab1_model):
    # eq. (12): G(z) = (-0.05 z^4 + 0.14 z^3 - 0.09 z^2) / (z^5 - 4.33 z^4 + 7.64 z^3 - 6.87 z^2 + 3.16 z - 0.59)
    s = lti.companion_ss(lti.to_tf(lab1_model))
    np.testing.assert_allclose(s.A[0], [4.33, -7.64, 6.87, -3.16, 0.59], rtol=1e-12)
    np.testing.assert_array_equal(s.A[1:], np.eye(5)[:-1])
    np.testing.assert_array_equal(s.B.ravel(), [1, 0, 0, 0, 0])
    np.testing.assert_allclose(s.C.ravel(), [-0.05, 0.14, -0.09, 0, 0], atol=1e-15)
    assert s.D[0, 0] == 0.0
    assert np.max(np.abs(lti.poles(s))) == pytest.approx(1.1678, abs=1e-3)


def test_companion_form_has_the_same_transfer_function():
    u, y = _plant()
    yf = lfilter(0.2 * np.array([1.0, -1.0]), [1.0, -0.8], y)
    g = lti.with_integrator(ax.estimate(u, yf, 4, 2, 0, 1, Ts=0.02), 0.8)
    s = lti.companion_ss(g)
    f = np.array([0.3, 1.0, 3.0, 10.0, 24.0])
    np.testing.assert_allclose(lti.bode_data(s, f).response, lti.bode_data(g, f).response, rtol=1e-9)
    np.testing.assert_allclose(_sim(s, u), _sim(g, u), rtol=1e-9, atol=1e-9 * np.max(np.abs(y)))
    # biproper case: direct term
    import control

    bp = control.tf([2.0, 0.5, 0.1], [1.0, -0.5, 0.06], 0.1)
    sb = lti.companion_ss(bp)
    assert sb.D[0, 0] == 2.0
    np.testing.assert_allclose(lti.bode_data(sb, [0.5, 2.0]).response, lti.bode_data(bp, [0.5, 2.0]).response)


def test_step_square_and_bode_numbers():
    true = demo_system()
    dc = true.B.sum() / true.A.sum()
    r = control.step_response(lti.to_tf(true), T=0.02 * np.arange(1001))
    t, y = np.asarray(r.time), np.asarray(r.outputs).reshape(-1)
    assert t[1] - t[0] == pytest.approx(0.02) and t[-1] == pytest.approx(20.0)
    assert y[0] == 0.0 and y[-1] == pytest.approx(dc, rel=1e-6)
    bd = lti.bode_data(true, [0.0, 3.0])
    assert bd.mag[0] == pytest.approx(abs(dc)) and bd.mag[1] > 5 * bd.mag[0]  # the 3 Hz link mode
    with pytest.raises(ValueError, match="Nyquist"):
        lti.bode_data(true, [30.0])
    # square wave at 0.5 Hz: the first half period (50 samples) equals the step response scaled by the amplitude
    t2, u2, y2 = lti.square_response(true, 0.5, 1.5, 5.0)
    half = 50
    assert np.all(u2[:half] == 1.5) and np.all(u2[half : 2 * half] == -1.5)
    np.testing.assert_allclose(y2[:half], 1.5 * y[:half], rtol=1e-12, atol=1e-15)


def test_bad_filter_pole(lab1_model):
    with pytest.raises(ValueError, match=r"af must be in \[0, 1\), got 1.0"):
        lti.with_integrator(lab1_model, 1.0)
