"""Differentiating low-pass H(z) = (1 - af)(z - 1)/(z - af) and lab 1's preprocessing pipeline."""

import control
import numpy as np
import pytest

from harness.ident import preprocess as pp


def _lowpass_loop(x, af):
    """Independent reference: w[k] = af w[k-1] + (1 - af) x[k], zero initial state."""
    w, out = 0.0, np.empty_like(x)
    for k, xk in enumerate(x):
        w = af * w + (1.0 - af) * xk
        out[k] = w
    return out


@pytest.mark.parametrize("af", [0.0, 0.6, 0.8, 0.9])
def test_gains_pole_and_zero(af):
    Ts = 0.02
    mag, ph = pp.filter_response(af, np.array([0.0, 25.0]), Ts)
    assert mag[0] == 0.0
    assert mag[1] == pytest.approx(2 * (1 - af) / (1 + af), rel=1e-12)
    H = control.tf(*pp.filter_coefficients(af), Ts)  # first order: the same coefficients in z^-1 and in z
    assert H.dt == Ts
    np.testing.assert_allclose(control.poles(H), [af], atol=1e-12)
    np.testing.assert_allclose(control.zeros(H), [1.0], atol=1e-12)
    f = np.array([0.3, 2.0, 11.0])
    resp = H(np.exp(2j * np.pi * f * Ts))
    mag, ph = pp.filter_response(af, f, Ts)
    np.testing.assert_allclose(mag, np.abs(resp), rtol=1e-12)
    np.testing.assert_allclose(ph, np.angle(resp), atol=1e-12)
    # time domain: a constant dies out (DC gain 0); (-1)^k settles at the Nyquist gain
    y = pp.diff_filter(np.full(400, 3.0), af)
    assert abs(y[-1]) < 1e-12
    y = pp.diff_filter((-1.0) ** np.arange(400), af)
    assert abs(y[-1]) == pytest.approx(2 * (1 - af) / (1 + af), rel=1e-9)


def test_preprocess_of_cumulative_sum_recovers_filtered_signal():
    rng = np.random.default_rng(0)
    x = np.sin(np.arange(600) * 0.05) + 0.1 * rng.standard_normal(600)
    u = 1.0 + rng.standard_normal(600)
    y = np.cumsum(x)
    u_d, y_f = pp.preprocess(u, y, af=0.8)
    np.testing.assert_allclose(y_f, _lowpass_loop(x, 0.8), atol=1e-9)
    np.testing.assert_allclose(u_d, u - u.mean(), atol=1e-12)
    _, y0 = pp.preprocess(u, y, af=0.0)  # af = 0: the plain first difference
    np.testing.assert_allclose(y0, x, atol=1e-9)
    # "rest": y constant at y[0] before the record -> first output 0, later the same difference
    y_r = pp.diff_filter(y + 50.0, 0.0, initial="rest")
    assert y_r[0] == 0.0
    np.testing.assert_allclose(y_r[1:], x[1:], atol=1e-9)


def test_detrend_and_bad_input():
    t = np.arange(50.0)
    np.testing.assert_allclose(pp.detrend(3.0 + 0.5 * t, "linear"), 0.0, atol=1e-12)
    np.testing.assert_allclose(pp.detrend(3.0 + 0.5 * t, "constant"), 0.5 * (t - t.mean()), atol=1e-12)
    for af in (1.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"af must be in \[0, 1\)"):
            pp.preprocess(t, t, af=af)
    bad = t.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match="NaN.*sample 7"):
        pp.preprocess(t, bad)
    with pytest.raises(ValueError, match="same length"):
        pp.preprocess(t, t[:-1])
    with pytest.raises(ValueError, match="valid: constant, linear, none"):
        pp.detrend(t, "quadratic")
