"""harness.ident.armax against independent solutions, a public data set with reference figures, and the lab 1 report."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.signal import lfilter

from benchmarks.problems import demo_problem
from harness.ident import armax as ax

DAISY = Path(__file__).resolve().parent / "fixtures" / "daisy_robot_arm.dat"  # provenance: fixtures/README.md


def _loss(theta: np.ndarray, u: np.ndarray, y: np.ndarray, na: int, nb: int, nc: int, nk: int) -> np.ndarray:
    """Independent zero-initial-condition prediction error, sample by sample (no lfilter)."""
    a, b, c = theta[:na], theta[na : na + nb], theta[na + nb :]
    e = np.zeros(y.size)
    for t in range(y.size):
        v = y[t]
        for i in range(1, na + 1):
            v += a[i - 1] * y[t - i] if t - i >= 0 else 0.0
        for j in range(nb):
            v -= b[j] * u[t - nk - j] if t - nk - j >= 0 else 0.0
        for i in range(1, nc + 1):
            v -= c[i - 1] * e[t - i] if t - i >= 0 else 0.0
        e[t] = v
    return e


@pytest.fixture(scope="module")
def recovery():
    out = []
    for seed in range(20):
        true, u, y = demo_problem(seed)
        out.append((true, u, y, ax.estimate(u, y, 4, 3, 4, 1, Ts=true.Ts)))
    return out


def test_recovery_over_20_seeds(recovery):
    theta = recovery[0][0].theta
    errs = [np.linalg.norm(m.theta - theta) / np.linalg.norm(theta) for _, _, _, m in recovery]
    z = np.concatenate([np.abs(m.theta - theta) / m.std for _, _, _, m in recovery])
    assert np.median(errs) <= 0.015
    assert np.mean(z <= 2.58) >= 0.90
    assert np.all(np.abs(recovery[0][3].theta - theta) <= 3 * recovery[0][3].std)
    assert all(m.converged and m.stable for *_, m in recovery)
    assert all(np.max(np.abs(np.roots(m.C))) < 1 for *_, m in recovery)


def test_estimate_is_the_prediction_error_minimum(recovery):
    true, u, y, m = recovery[3]
    f = lambda th: ax._pred_error(*ax._polys(th, 4, 3, 4, 1), y, u)  # noqa: E731
    ref = least_squares(f, true.theta, xtol=1e-14, ftol=1e-14, gtol=1e-14, method="lm")
    np.testing.assert_allclose(m.theta, ref.x, atol=1e-4)
    e_indep = _loss(m.theta, u, y, 4, 3, 4, 1)
    assert m.loss == pytest.approx(np.mean(e_indep**2), rel=1e-10)
    assert m.loss <= np.mean(_loss(true.theta, u, y, 4, 3, 4, 1) ** 2)
    assert m.fit_onestep == pytest.approx(100 * (1 - np.linalg.norm(e_indep) / np.linalg.norm(y - y.mean())))


def test_analytic_gradient_matches_finite_differences():
    true, u, y = demo_problem(7, n=300)
    th = true.theta + 0.01
    A, B, C = ax._polys(th, 4, 3, 4, 1)
    e = ax._pred_error(A, B, C, y, u)
    psi = ax._jacobian(y, u, e, C, 4, 3, 4, 1)
    h = 1e-6
    for k in range(th.size):
        d = np.zeros(th.size)
        d[k] = h
        fd = (_loss(th + d, u, y, 4, 3, 4, 1) - _loss(th - d, u, y, 4, 3, 4, 1)) / (2 * h)
        np.testing.assert_allclose(-psi[:, k], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


def test_arx_is_plain_least_squares_without_padding():
    true, u, y = demo_problem(1, n=400)
    m = ax.estimate(u, y, 3, 2, 0, 2)
    rows = [[-y[t - 1], -y[t - 2], -y[t - 3], u[t - 2], u[t - 3]] for t in range(3, y.size)]
    ref = np.linalg.lstsq(np.array(rows), y[3:], rcond=None)[0]
    np.testing.assert_allclose(m.theta, ref, rtol=1e-9, atol=1e-12)
    assert m.B.tolist()[:2] == [0.0, 0.0] and m.n_iter == 0


@pytest.fixture(scope="module")
def daisy():
    d = np.loadtxt(DAISY)
    return d[:512, 0], d[:512, 1], d[512:, 0], d[512:, 1]


@pytest.mark.parametrize(
    ("n", "nc", "ref_z", "ref_e", "ref_1"),
    [(6, 0, 84.2, 95.2, 82.9), (6, 6, 82.9, 97.6, 96.9), (8, 8, 83.0, 97.3, 96.9)],
)
def test_daisy_robot_arm_matches_reference_table(daisy, n, nc, ref_z, ref_e, ref_1):
    ue, ye, uv, yv = daisy
    m = ax.estimate(ue, ye, n, n, nc, 1, max_iter=100)
    assert m.stable
    assert np.all(np.abs(np.roots(m.C)) < 1.0)
    fz, fe, f1 = ax.compare(m, uv, yv, ic="z"), ax.compare(m, uv, yv, ic="e"), ax.fit_onestep(m, uv, yv)
    assert fz == pytest.approx(ref_z, abs=1.0)
    assert fe == pytest.approx(ref_e, abs=1.0)
    assert f1 == pytest.approx(ref_1, abs=1.0)
    assert fe >= (97.0 if nc else 95.0)


@pytest.mark.parametrize("nc", [0, 5])
def test_daisy_order_5_is_reported_unstable(daisy, nc):
    ue, ye, uv, yv = daisy
    m = ax.estimate(ue, ye, 5, 5, nc, 1)
    assert not m.stable
    assert math.isnan(ax.compare(m, uv, yv, ic="z")) and math.isnan(ax.compare(m, uv, yv, ic="e"))
    rep = ax.compare_report(m, uv, yv)
    assert rep.status == "unstable" and str(rep) == "unstable"


def test_lab1_rounded_coefficients_are_unstable_and_full_precision_round_trips(lab1_model):
    lab1 = lab1_model
    assert np.max(np.abs(lab1.poles)) == pytest.approx(1.1678, abs=1e-3)
    assert not lab1.stable
    u = np.sin(0.1 * np.arange(200))
    assert math.isnan(ax.compare(lab1, u, np.cos(0.05 * np.arange(200))))

    true, u, y = demo_problem(2)
    m = ax.estimate(u, y, 4, 3, 4, 1, Ts=0.02)
    back = ax.ArmaxModel.from_dict(json.loads(json.dumps(m.to_dict())))
    for name in ("A", "B", "C", "cov"):
        assert np.array_equal(getattr(back, name), getattr(m, name))
    for name in ("na", "nb", "nc", "nk", "Ts", "loss", "noise_variance", "fit_onestep", "n_iter", "converged"):
        assert getattr(back, name) == getattr(m, name)
    rounded = ax.ArmaxModel(A=np.round(m.A, 2), B=m.B, C=m.C, na=4, nb=3, nc=4, nk=1)
    assert not np.array_equal(rounded.poles, m.poles)


def test_compare_with_estimated_initial_state_is_exact_on_noise_free_data():
    true, u, _ = demo_problem(4)
    y_long = lfilter(true.B, true.A, u)
    u2, y2 = u[700:], y_long[700:]  # the model is in a non-zero state at the cut
    assert ax.compare(true, u2, y2, ic="e") == pytest.approx(100.0, abs=1e-8)
    assert ax.compare(true, u2, y2, ic="z") < 99.0
    assert ax.compare(true, u, y_long, ic="z") == pytest.approx(100.0, abs=1e-10)


def test_k_step_predictor_error_is_ma_of_innovations():
    true, u, _ = demo_problem(5, n=600)
    e = 0.02 * np.random.default_rng(9).standard_normal(600)
    y = ax.generate(true, u, e)
    # F_k: first k terms of C/A by long division, written out independently
    k = 3
    f = np.zeros(k)
    for i in range(k):
        f[i] = (true.C[i] if i < true.C.size else 0.0) - sum(true.A[j] * f[i - j] for j in range(1, min(i, 4) + 1))
    err = y - ax.predict(true, u, y, k)
    np.testing.assert_allclose(err, np.convolve(e, f)[:600], atol=1e-12)
    np.testing.assert_allclose(y - ax.predict(true, u, y, 1), e, atol=1e-12)


def test_resid_white_on_true_innovations_not_on_wrong_order():
    true, u, y = demo_problem(11)
    r = ax.resid(true, u, y, lags=25)
    assert r.white and r.independent
    assert r.bound == pytest.approx(2.58 / math.sqrt(1500))
    assert r.acf[0] == pytest.approx(1.0) and r.acf.size == 26 and r.ccf.size == 51
    wrong = ax.estimate(u, y, 2, 2, 0, 1)
    rw = ax.resid(wrong, u, y, lags=25)
    assert not rw.white and not rw.independent
    assert abs(rw.acf[1]) > 5 * rw.bound and rw.n_out_acf > rw.allowed_acf


@pytest.mark.parametrize(
    ("args", "msg"),
    [
        ((np.ones((10, 2)), np.ones(10), 1, 1, 0), "1-D"),
        ((np.ones(100), np.ones(99), 1, 1, 0), "equal length"),
        ((np.r_[np.nan, np.ones(99)], np.ones(100), 1, 1, 0), "finite"),
        ((np.ones(100), np.ones(100), -1, 1, 0), "na must be an integer >= 0"),
        ((np.ones(100), np.ones(100), 1.5, 1, 0), "na must be an integer >= 0"),
        ((np.ones(20), np.ones(20), 4, 3, 4), "need at least"),
        ((np.ones(100), np.ones(100), 0, 0, 0), "nothing to estimate"),
    ],
)
def test_bad_input_gives_one_clear_line(args, msg):
    with pytest.raises(ValueError, match=msg) as info:
        ax.estimate(*args)
    assert "\n" not in str(info.value)


def test_compare_rejects_bad_ic():
    true, u, y = demo_problem(0, n=100)
    with pytest.raises(ValueError, match="ic must be"):
        ax.compare(true, u, y, ic="x")


def test_estimate_warns_when_the_output_integrates_the_input():
    """A raw angle integrates the command: its ARMAX has a pole at 1 and simulates a drift. estimate says so and
    names the preprocessing; the same data differentiated (what harness.prepare does) fit without a warning."""
    _, u, y = demo_problem(0)
    angle = np.cumsum(y)  # the integrated output, as a hub angle integrates its rate
    with pytest.warns(ax.IntegratorWarning, match=r"pole at (0\.999|1\.0).*differentiate and low-pass"):
        m = ax.estimate(u, angle, 4, 3, 4, 1)
    assert max(abs(m.poles)) >= ax.INTEGRATOR_POLE
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ax.estimate(u, y, 4, 3, 4, 1)


def test_the_schur_cohn_check_agrees_with_the_roots_of_c():
    """C's roots inside the clipping radius by the step-down test exactly where numpy's roots say so, clear of the
    circle (2000 random C of degree 1-8 with roots on both sides of it); on the circle it defers to the roots."""
    rng = np.random.default_rng(7)
    agree = 0
    for _ in range(2000):
        deg = int(rng.integers(1, 9))
        pair = rng.uniform(0.3, 1.2, deg // 2) * np.exp(1j * rng.uniform(0.0, np.pi, deg // 2))
        C = np.real(np.poly(np.concatenate([pair, np.conj(pair), rng.uniform(-1.1, 1.1, deg % 2)])))
        top = float(np.abs(np.roots(C)).max())
        inside = ax._inside(C, ax._C_RADIUS_MAX)
        assert not inside or top <= ax._C_RADIUS_MAX
        if abs(top - ax._C_RADIUS_MAX) > 1e-6:
            assert inside == (top < ax._C_RADIUS_MAX)
            agree += 1
    assert agree > 1900
    on_circle = np.real(np.poly([ax._C_RADIUS_MAX, 0.5]))
    assert not ax._inside(on_circle, ax._C_RADIUS_MAX)
