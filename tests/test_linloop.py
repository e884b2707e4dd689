"""The loop as a linear system (harness.linloop) against independent routes: scipy's Riccati solver, python-control's
disk margins, and the plant, DAQ and controller FMUs co-simulated on the same rig."""

from __future__ import annotations

import dataclasses

import control
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from harness import spec as specmod
from harness.design import lqg_controller, lqr_controller
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.linloop import (
    Frequencies,
    closed_loop,
    controller_lti,
    dare,
    design_model,
    kalman_gain,
    lqr_gain,
    step_response,
)
from harness.loopspecs import Weights
from harness.prediction import simulate_loop
from harness.rig.controller import Controller
from harness.twin import twin_of_spec

# a rig with every linear DAQ dynamic the model holds: a command delay, the gauge's low-pass and reading delay, two
# modes, and sensors that read 5 % and -20 % off their calibration
SETS = ["daq.delay_samples=1", "daq.gauge_delay=2", "plant.n_modes=2", "daq.gauge_tau=0.004"]
OVER = {"sensor.theta_gain": 1.05, "sensor.alpha_gauge_gain": 0.8, "plant.Ks": 1.5}


@pytest.fixture(scope="module")
def rig():
    twin = twin_of_spec(specmod.load("nominal", SETS))
    return dataclasses.replace(twin, overrides=OVER)


def test_riccati_by_doubling_equals_scipy(rig):
    m = design_model(rig.tables(noise=False), 1 / 500)
    Q, R = m.weights((100.0, 30.0, 1.0, 0.1)), np.array([[1.0]])
    X = dare(m.Phi, m.Gamma, Q, R)
    np.testing.assert_allclose(X, solve_discrete_are(m.Phi, m.Gamma, Q, R), rtol=1e-9, atol=1e-9 * np.abs(X).max())
    K = lqr_gain(m.Phi, m.Gamma, Q, R)
    Kc, _, _ = control.dlqr(m.Phi, m.Gamma, Q, R)
    np.testing.assert_allclose(K, Kc, rtol=1e-8, atol=1e-12)
    G = np.zeros((m.n, 1))
    G[: m.n_plant] = m.gamma_plant
    Rv = np.diag([1e-6, 2e-6])
    P = solve_discrete_are(m.Phi.T, m.C.T, G @ G.T, Rv)
    np.testing.assert_allclose(kalman_gain(m.Phi, m.C, G @ G.T, Rv), P @ m.C.T @ np.linalg.inv(m.C @ P @ m.C.T + Rv),
                               rtol=1e-7, atol=1e-10)  # fmt: skip


def test_the_textbook_lqr_of_the_closed_loop_spec():
    """specs/closed_loop.toml's gains are the course's discrete LQR on the textbook model at 500 Hz, Q = diag(100,
    500, 1, 1), R = 1 (its comment): the design model and lqr_controller give them again to the printed digits."""
    s = specmod.load("closed_loop", ["plant.n_modes=1"])
    m = design_model(twin_of_spec(s).tables(noise=False), s.Ts, n_modes=1)
    c = lqr_controller(m, Weights((100.0, 500.0, 1.0, 1.0)), 15.0, s.sample_rate)
    np.testing.assert_allclose(c.K, s.controller.K, atol=6e-4)


@pytest.mark.parametrize("kind", ["state_feedback", "lqg", "pid"])
def test_the_linear_loop_is_the_co_simulated_one(rig, kind):
    """The linear loop (ZOH model, DAQ delays and filter, the controller's filters or estimator) and the FMUs
    co-simulated on the same rig without noise or effects agree to the plant's RK4 error (1e-3 deg on a 50 deg move)."""
    Ts = 1 / 500
    tables = rig.tables(noise=False)
    full, one = design_model(tables, Ts), design_model(tables, Ts, n_modes=1)
    assert full.n == 10  # 6 plant states, the gauge's filter and 2 reading delays, the command's delay
    c = {
        "state_feedback": lqr_controller(one, Weights((100.0, 100.0, 1.0, 1.0)), 25.0, 500.0),
        "lqg": lqg_controller(full, Weights((100.0, 30.0, 1.0, 0.1), 1.0, 1.0), (1e-3, 1e-3), 500.0),
        "pid": Controller(kind="pid", kp=3.0, ki=1.0, kd=0.2, cutoff=20.0),
    }[kind]
    ref = np.r_[np.zeros(10), np.full(700, 30.0), np.full(790, -20.0)]
    y = step_response(closed_loop(full, c), np.radians(ref))
    f = build_all()
    with Rig(f["flexjoint"], f["daq"], f["controller"]) as r:
        sim = simulate_loop(r, tables, c, ref, Ts, 0.0, OVER["sensor.theta_gain"])
    assert np.ptp(sim["theta"]) > 45.0 and np.ptp(sim["alpha"]) > 5.0
    np.testing.assert_allclose(np.degrees(y[0]), sim["theta"], atol=1e-3)
    np.testing.assert_allclose(np.degrees(y[1]), sim["alpha"], atol=1e-3)
    np.testing.assert_allclose(y[2], sim["u"], atol=1e-3)


@pytest.mark.parametrize("kind", ["state_feedback", "lqg"])
def test_disk_margins_equal_python_controls(rig, kind):
    full = design_model(rig.tables(noise=False), 1 / 500)
    one = design_model(rig.tables(noise=False), 1 / 500, n_modes=1)
    c = (lqr_controller(one, Weights((30.0, 10.0, 0.3, 0.1)), 25.0, 500.0) if kind == "state_feedback"
         else lqg_controller(full, Weights((30.0, 10.0, 0.3, 0.1), 1.0, 1.0), (1e-3, 1e-3), 500.0))  # fmt: skip
    F = Frequencies(full, 800)
    got = F.disk_margin(c)
    k = controller_lti(c, full.Ts)
    P = control.ss(full.Phi, full.Gamma, full.C, np.zeros((2, 1)), full.Ts)
    K = control.ss(k.A, k.B[:, 1:], k.C, k.D[:, 1:], full.Ts)
    dm, dgm, dpm = control.disk_margins(-(K * P), F.omega, skew=0.0)
    assert 0.3 < got["disk_margin"] < 2.0
    assert got["disk_margin"] == pytest.approx(dm, rel=1e-9)
    assert got["gain_margin_db"] == pytest.approx(dgm, rel=1e-9)
    assert got["phase_margin_deg"] == pytest.approx(dpm, rel=1e-9)
