"""The flexjoint plant FMU against the independent analytic model (harness.fmu.plant) and closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fmpy.fmi1 import FMICallException
from scipy.integrate import solve_ivp

from harness.fmu.plant import (
    OUTPUTS,
    PlantParams,
    beam_integrals,
    beam_roots,
    dead_zone_voltage,
    gauge_weights,
    mass_stiffness,
    mode_frequencies,
    motor_constants,
    state_space,
    steady_speed,
)

BETA = (1.875104068711961, 4.694091132974175, 7.854757438237613)  # published clamped-free roots


def zoh_reference(p: PlantParams, u: np.ndarray, tau: np.ndarray, dt: float) -> np.ndarray:
    """Outputs at t_1..t_n of the linear rig under a zero-order-hold input, by solve_ivp (rtol 1e-10)."""
    A, B, C, _ = state_space(p)
    x = np.zeros(A.shape[0])
    x[0] = p.theta_start
    out = np.empty((len(u), C.shape[0]))
    for k in range(len(u)):
        f = B @ np.array([u[k], tau[k]])
        sol = solve_ivp(lambda t, z, f=f: A @ z + f, (0.0, dt), x, method="DOP853", rtol=1e-10, atol=1e-13)
        x = sol.y[:, -1]
        out[k] = C @ x
    return out


def prony_poles(channels: list[np.ndarray], order: int, dt: float) -> np.ndarray:
    """Continuous-time poles [1/s] of a free response (linear prediction shared by all channels)."""
    rows, rhs = [], []
    for x in channels:
        for k in range(order, len(x)):
            rows.append(x[k - order : k][::-1])
            rhs.append(x[k])
    c, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    return np.log(np.roots(np.r_[1.0, -c]).astype(complex)) / dt


# ---------------------------------------------------------------- the Python model itself


def test_beam_quadrature_matches_closed_forms():
    ints = beam_integrals(3)
    np.testing.assert_allclose(beam_roots(3), BETA, rtol=1e-14)
    sgn = np.array([1.0, -1.0, 1.0])
    bl = np.array(BETA)
    np.testing.assert_allclose(ints["mass"], np.eye(3), atol=1e-10)  # int phi_i phi_j = L delta_ij
    np.testing.assert_allclose(ints["tip"], 1.0, rtol=1e-12)  # phi_i(L) = 2
    np.testing.assert_allclose(ints["first"], 2 * sgn / bl**2, rtol=1e-10)  # int xi phi_i = 2(-1)^(i+1)/(bL)^2
    np.testing.assert_allclose(ints["curv"], 2 * sgn * bl**2, rtol=1e-10)  # phi_i''(0)
    # beam statics: the modes' share of the tip compliance, sum 4/(bL)^4, tends to the exact 1/3 (F L^3 / 3EI)
    assert 0.3316 < np.sum(4 / bl**4) < 1 / 3


def test_default_rig_numbers():
    p = PlantParams(n_modes=2)
    M, K, D = mass_stiffness(p)
    Jl = 0.065 * 0.419**2 / 3
    assert M[0, 0] == pytest.approx(2.08e-3 + Jl, rel=1e-12)
    assert Jl == pytest.approx(3.8e-3, rel=0.01)  # the textbook rig's link inertia
    f = mode_frequencies(p)
    assert f[1, 0] == pytest.approx(math.sqrt(1.3 / Jl) / (2 * math.pi), rel=1e-12)
    assert f[1, 0] == pytest.approx(2.94, abs=0.005)  # Quanser torsion-spring model: ~2.94 Hz
    assert f[1, 1] / f[1, 0] == pytest.approx(6.267, abs=0.001)  # clamped-free 1 : 6.27
    g, c_g = gauge_weights(p)
    assert g[1] == pytest.approx(-((BETA[1] / BETA[0]) ** 2), rel=1e-10)  # mode 2 reads 6.27x (opposite sign)
    assert gauge_weights(PlantParams())[1] == pytest.approx(1.0, abs=1e-12)  # c_g = 1 for one mode
    r2 = (BETA[1] / BETA[0]) ** 2
    assert c_g == pytest.approx((1 + 1 / r2**2) / (1 - 1 / r2), rel=1e-10)
    assert dead_zone_voltage(PlantParams(coulomb_torque=0.044)) == pytest.approx(0.343, abs=0.001)


def test_invalid_params_raise_one_line():
    with pytest.raises(ValueError, match="n_modes"):
        state_space(PlantParams(n_modes=4))
    with pytest.raises(ValueError, match="Jeq"):
        mass_stiffness(PlantParams(Jeq=-1.0))


# ---------------------------------------------------------------- FMU vs independent solutions


@pytest.mark.parametrize("n_modes, internal_step", [(1, 1e-3), (2, 2.5e-4)])
def test_linear_rig_matches_state_space(fmu_runner, n_modes, internal_step):
    dt, n = 0.01, 400
    t = np.arange(n) * dt
    rng = np.random.default_rng(7)
    u = (
        1.5 * np.sin(2 * np.pi * 0.7 * t)
        + 0.8 * np.sin(2 * np.pi * 3.1 * t)
        + np.repeat(rng.choice([-1.0, 1.0], n // 20), 20)
    )
    tau = np.where((t >= 1.0) & (t < 1.05), 0.02, 0.0) - np.where((t >= 2.5) & (t < 2.6), 0.01, 0.0)
    p = PlantParams(n_modes=n_modes, internal_step=internal_step, theta_start=0.2)
    res = fmu_runner["flexjoint"].run(
        {"n_modes": n_modes, "internal_step": internal_step, "theta_start": 0.2},
        {"u": u, "tau_tip": tau},
        OUTPUTS,
        dt,
        n,
    )
    got = np.column_stack([res[k] for k in OUTPUTS])
    ref = zoh_reference(p, u, tau, dt)
    assert np.abs(ref[:, 1]).max() > 0.1 and np.abs(ref[:, 0]).max() > 1.0  # a real excitation
    err = np.abs(got - ref).max(axis=0)
    assert err.max() < 1e-6, dict(zip(OUTPUTS, err, strict=True))
    assert res["init"]["theta"] == 0.2 and res["init"]["alpha"] == 0.0


def test_steady_speed_2V(fmu_runner):
    res = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": 2.0}, ["theta_dot", "alpha"], 0.02, 400)
    w = 0.9 * 70 * 0.69 * 7.68e-3 * 2.0 / (2.6 * 0.004 + 0.9 * 0.69 * 7.68e-3 * 7.68e-3 * 70**2)
    assert res["theta_dot"][-1] == pytest.approx(w, rel=1e-6)
    assert steady_speed(PlantParams(), 2.0) == pytest.approx(w, rel=1e-12)
    assert abs(res["alpha"][-1]) < 1e-6  # constant speed: no deflection left


def test_non_minimum_phase_tip(fmu_runner):
    # the linear model: the tip angle y = theta + alpha has right-half-plane zeros for any number of modes
    from scipy.linalg import eigvals

    for n_modes in (1, 2, 3):
        A, B, C, _ = state_space(PlantParams(n_modes=n_modes))
        nx = A.shape[0]
        rosenbrock = np.block([[A, B[:, [0]]], [C[[2]], np.zeros((1, 1))]])
        E = np.zeros((nx + 1, nx + 1))
        E[:nx, :nx] = np.eye(nx)
        z = eigvals(rosenbrock, E)
        z = z[np.isfinite(z)]  # invariant zeros of u -> y
        assert np.any(z.real > 10), z
    # the FMU: a positive step bends the link back (alpha < 0) while the hub turns forward ...
    for n_modes in (1, 2, 3):
        res = fmu_runner["flexjoint"].run({"n_modes": n_modes}, {"u": 2.0}, ["theta", "alpha", "y"], 1e-3, 60)
        assert np.all(res["theta"][:30] > 0) and np.all(res["alpha"][:30] < 0)
        assert res["y"][-1] > 0
    # ... and with one mode the tip itself first moves against the hub
    res = fmu_runner["flexjoint"].run({"n_modes": 1}, {"u": 2.0}, ["y"], 1e-3, 200)
    assert res["y"][:20].max() < 0 and res["y"][-1] > 0


def test_mode_frequencies_from_free_vibration(fmu_runner):
    dt, n = 1e-3, 2500
    tau = np.zeros(n)
    tau[:5] = 0.01  # tip torque pulse, then free vibration
    p = PlantParams(n_modes=2)
    f = mode_frequencies(p)
    # clamped hub (the comb set-up): both modes, and their ratio
    res = fmu_runner["flexjoint"].run(
        {"n_modes": 2, "hub_locked": 1}, {"tau_tip": tau}, ["theta", "alpha", "alpha_gauge"], dt, n
    )
    assert np.all(res["theta"] == 0.0)
    s = prony_poles([res["alpha"][10:], res["alpha_gauge"][10:]], 4, dt)
    fc = np.sort(np.abs(s[s.imag > 0])) / (2 * np.pi)
    np.testing.assert_allclose(fc, f[1], rtol=0.01)
    assert fc[1] / fc[0] == pytest.approx(6.27, abs=0.01)
    # free hub: the second mode is lightly damped (within 1 % of the undamped eigenproblem); the first is
    # heavily damped by the back-EMF, so compare it with the eigenvalues of the damped linear model
    res = fmu_runner["flexjoint"].run({"n_modes": 2}, {"tau_tip": tau}, ["theta_dot", "alpha", "alpha_gauge"], dt, n)
    s = prony_poles([res["alpha"][10:], res["alpha_gauge"][10:], res["theta_dot"][10:]], 6, dt)
    ff = np.sort(np.abs(s[(s.imag > 0) & (np.abs(s) < 2 * np.pi * 100)])) / (2 * np.pi)
    assert ff[1] == pytest.approx(f[0, 1], rel=0.01)
    A, *_ = state_space(p)
    ev = np.linalg.eigvals(A)
    np.testing.assert_allclose(ff, np.sort(np.abs(ev[ev.imag > 0])) / (2 * np.pi), rtol=0.01)


def test_static_tip_load_gauge_reads_deflection(fmu_runner):
    # hub clamped, constant tip torque, heavy modal damping to settle quickly
    for n_modes in (1, 2, 3):
        p = PlantParams(n_modes=n_modes, zeta_link=0.7, hub_locked=1)
        res = fmu_runner["flexjoint"].run(
            {"n_modes": n_modes, "zeta_link": 0.7, "hub_locked": 1},
            {"tau_tip": 0.01},
            ["alpha", "alpha_gauge"],
            0.02,
            150,
        )
        K = mass_stiffness(p)[1]
        static = 0.01 * np.sum(1 / np.diag(K)[1:])
        assert res["alpha"][-1] == pytest.approx(static, rel=1e-8)
        assert res["alpha_gauge"][-1] == pytest.approx(static, rel=1e-8)


# ---------------------------------------------------------------- effects


def test_coulomb_dead_zone(fmu_runner):
    fc = 0.044
    vth = fc * 2.6 / (0.9 * 70 * 0.69 * 7.68e-3)
    assert vth == pytest.approx(0.3427, abs=1e-4)
    run = fmu_runner["flexjoint"].run
    below = run(
        {"coulomb_torque": fc, "n_modes": 2, "theta_start": 0.3}, {"u": 0.95 * vth}, ["theta", "alpha"], 0.02, 250
    )
    assert np.all(below["theta"] == 0.3)  # 5 s, exactly still
    above = run({"coulomb_torque": fc, "n_modes": 2}, {"u": 1.05 * vth}, ["theta", "theta_dot"], 0.02, 250)
    G = 0.9 * 70 * 0.69 * 7.68e-3 / 2.6
    w = (G * 1.05 * vth - fc) / (0.004 + G * 70 * 7.68e-3)
    assert above["theta"][-1] > 0.1
    assert above["theta_dot"][-1] == pytest.approx(w, rel=1e-6)
    # negative direction is symmetric
    neg = run({"coulomb_torque": fc, "n_modes": 2}, {"u": -1.05 * vth}, ["theta"], 0.02, 250)
    assert neg["theta"][-1] == pytest.approx(-above["theta"][-1], rel=1e-12)


def test_coulomb_stops_without_creep_or_chatter(fmu_runner):
    # after the command drops, the link's swing may break the hub loose a few times; then it stays put
    u = np.r_[np.full(100, 2.0), np.zeros(400)]
    res = fmu_runner["flexjoint"].run(
        {"coulomb_torque": 0.044, "n_modes": 2}, {"u": u}, ["theta", "theta_dot"], 0.01, 500
    )
    assert np.all(res["theta"][-250:] == res["theta"][-1])  # stopped and stuck exactly
    assert np.all(res["theta_dot"][-250:] == 0.0)
    t = np.arange(1000) * 0.01
    res = fmu_runner["flexjoint"].run(
        {"coulomb_torque": 0.044, "n_modes": 2}, {"u": np.sin(2 * np.pi * 0.5 * t)}, ["theta_dot"], 0.01, 1000
    )
    td = res["theta_dot"]
    changes = np.count_nonzero(np.diff(np.sign(td)))
    assert changes == 20  # 10 reversals in 10 s: moving -> stuck -> moving the other way, nothing more
    assert np.count_nonzero(td == 0.0) > 50  # it does stick around each reversal


def test_stribeck_drop_slows_the_steady_speed_and_keeps_exact_stops(fmu_runner):
    """With a Stribeck speed the sliding friction falls from the breakaway level Fs to Fc: the hub breaks away only
    above Fs, slides at the speed where drive = friction + damping (harness.fmu.plant.steady_speed, a root of the
    Stribeck law), slower than at the Coulomb level alone, and still stops exactly, without creep."""
    fric = {"coulomb_torque": 0.044, "stiction_ratio": 2.0, "stribeck_speed": 1.0, "n_modes": 2, "zeta_link": 0.2}
    p = PlantParams(**fric)
    run = fmu_runner["flexjoint"].run
    w = steady_speed(p, 1.0)
    karnopp = steady_speed(PlantParams(**{**fric, "stribeck_speed": 0.0}), 1.0)
    assert 0.7 * karnopp < w < 0.85 * karnopp  # the drop's friction at the steady speed is well above Fc
    res = run(fric, {"u": 1.0}, ["theta_dot"], 0.02, 250)
    assert res["theta_dot"][-1] == pytest.approx(w, rel=1e-6)
    assert run(fric, {"u": -1.0}, ["theta_dot"], 0.02, 250)["theta_dot"][-1] == pytest.approx(-w, rel=1e-6)
    vth = 2.0 * 0.044 / motor_constants(p)[0]  # breakaway voltage Fs / G
    assert np.all(run({**fric, "theta_start": 0.3}, {"u": 0.98 * vth}, ["theta"], 0.02, 100)["theta"] == 0.3)
    u = np.r_[np.full(100, 2.0), np.zeros(400)]
    res = run({**fric, "stribeck_speed": 0.05}, {"u": u}, ["theta", "theta_dot"], 0.01, 500)
    assert np.all(res["theta"][-250:] == res["theta"][-1]) and np.all(res["theta_dot"][-250:] == 0.0)
    assert res["theta"][-1] > 0.5  # it did slide


@pytest.mark.parametrize("effects", [{}, {"stribeck_speed": 0.005, "stiction_ratio": 1.3}])
def test_a_hub_sliding_one_way_is_the_linear_rig_with_friction_as_a_command_offset(fmu_runner, effects):
    """A hub that slides one way throughout feels Coulomb friction as a constant torque Fc: the linear rig driven
    with the command less Fc / G (G the motor torque per volt), which the linear fast path integrates. The friction
    rig's stepper (its modes checked every step, a step past the Stribeck speeds as its configuration's RK4
    polynomial with friction in its forcing) and the linear path take the same RK4 steps by other routes: they agree
    to rounding while the hub is past the Stribeck speeds."""
    fc, n, dt = 0.044, 400, 0.01
    G = 0.9 * 70 * 0.69 * 7.68e-3 / 2.6
    t = np.arange(n) * dt
    u = 2.0 + 0.8 * np.sin(2 * np.pi * 1.3 * t)  # always forward: the hub never slows to the Stribeck speeds
    outs = ["theta", "alpha", "theta_dot"]
    start = {"n_modes": 2, "theta_dot_start": 1.0}
    run = fmu_runner["flexjoint"].run
    fric = run({**start, "coulomb_torque": fc, **effects}, {"u": u}, outs, dt, n)
    lin = run(start, {"u": u - fc / G}, outs, dt, n)
    assert fric["theta_dot"].min() > 0.5  # rad/s: it slid forward throughout
    for k in outs:
        np.testing.assert_allclose(fric[k], lin[k], rtol=0, atol=1e-9 * np.abs(lin[k]).max())


def test_stribeck_speed_zero_is_the_karnopp_law_bit_for_bit(fmu_runner):
    t = np.arange(500) * 0.01
    u = 1.5 * np.sin(2 * np.pi * 0.5 * t)
    fric = {"coulomb_torque": 0.044, "stiction_ratio": 1.5, "n_modes": 2}
    run = fmu_runner["flexjoint"].run
    a = run(fric, {"u": u}, ["theta", "alpha"], 0.01, 500)
    b = run({**fric, "stribeck_speed": 0.0}, {"u": u}, ["theta", "alpha"], 0.01, 500)
    c = run({**fric, "stribeck_speed": 0.05}, {"u": u}, ["theta", "alpha"], 0.01, 500)
    np.testing.assert_array_equal(a["theta"], b["theta"])
    np.testing.assert_array_equal(a["alpha"], b["alpha"])
    assert np.max(np.abs(c["theta"] - a["theta"])) > 1e-3  # rad: the drop changes the motion


def test_backlash_hysteresis(fmu_runner):
    b = 0.004
    n, dt = 1000, 0.01
    u = 0.5 * np.sin(2 * np.pi * 0.2 * np.arange(n) * dt)
    res = fmu_runner["flexjoint"].run(
        {"backlash": b, "coulomb_torque": 0.01}, {"u": u}, ["theta", "theta_motor", "theta_dot"], dt, n
    )
    gap = res["theta_motor"] - res["theta"]
    assert np.abs(gap).max() <= b / 2 * (1 + 1e-9)  # never beyond the play
    fwd, back = res["theta_dot"] > 0.05, res["theta_dot"] < -0.05
    assert fwd.sum() > 100 and back.sum() > 100
    # the hub trails the motor side by half the play in each direction: loop width = backlash
    np.testing.assert_allclose(gap[fwd], b / 2, rtol=1e-9)
    np.testing.assert_allclose(gap[back], -b / 2, rtol=1e-9)
    rigid = fmu_runner["flexjoint"].run({"coulomb_torque": 0.01}, {"u": u}, ["theta"], dt, n)
    assert np.abs(res["theta"] - rigid["theta"]).max() < b


def test_backlash_zero_is_the_rigid_model(fmu_runner):
    n, dt = 500, 0.01
    u = np.sign(np.sin(2 * np.pi * 0.4 * np.arange(n) * dt))
    outs = ["theta", "alpha", "theta_motor"]
    a = fmu_runner["flexjoint"].run({"backlash": 0.0, "Jm_share": 0.3, "n_modes": 2}, {"u": u}, outs, dt, n)
    b = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": u}, outs, dt, n)
    for k in outs:
        np.testing.assert_array_equal(a[k], b[k])
    np.testing.assert_array_equal(a["theta_motor"], a["theta"])
    # a tiny play converges to the rigid response
    c = fmu_runner["flexjoint"].run({"backlash": 1e-5, "n_modes": 2}, {"u": u}, outs, dt, n)
    assert np.abs(c["theta"] - b["theta"]).max() < 1e-4


def test_amp_limit(fmu_runner):
    n, dt = 300, 0.01
    u = np.where(np.arange(n) < 150, 8.0, -8.0)
    a = fmu_runner["flexjoint"].run({"amp_limit": 5.0, "n_modes": 2}, {"u": u}, ["theta", "alpha"], dt, n)
    b = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": np.clip(u, -5, 5)}, ["theta", "alpha"], dt, n)
    np.testing.assert_array_equal(a["theta"], b["theta"])
    np.testing.assert_array_equal(a["alpha"], b["alpha"])
    c = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": u}, ["theta"], dt, n)
    assert np.abs(c["theta"]).max() > 1.5 * np.abs(a["theta"]).max()


def test_large_internal_step_stays_stable(fmu_runner):
    # internal_step larger than the RK4 stability limit of the 3rd mode: the FMU limits its step itself
    p = PlantParams(n_modes=3, internal_step=0.02)
    res = fmu_runner["flexjoint"].run({"n_modes": 3, "internal_step": 0.02}, {"u": 1.0}, ["theta_dot"], 0.02, 400)
    assert res["theta_dot"][-1] == pytest.approx(steady_speed(p, 1.0), rel=1e-6)


# ---------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "params, name",
    [
        ({"Jeq": -1e-3}, "Jeq"),
        ({"Rm": float("nan")}, "Rm"),
        ({"n_modes": 4}, "n_modes"),
        ({"n_modes": 0}, "n_modes"),
        ({"backlash": -0.01}, "backlash"),
        ({"coulomb_torque": -0.1}, "coulomb_torque"),
        ({"stiction_ratio": 0.5}, "stiction_ratio"),
        ({"stribeck_speed": -0.1}, "stribeck_speed"),
        ({"hub_locked": 2}, "hub_locked"),
        ({"internal_step": 0.0}, "internal_step"),
        ({"m_tip": -1.0}, "m_tip"),
        ({"m_tip": float("inf")}, "m_tip"),
        ({"hub_locked": 1, "theta_dot_start": 0.5}, "theta_dot_start"),
    ],
)
def test_invalid_parameter_is_an_fmi_error(fmu_runner, params, name):
    run = fmu_runner["flexjoint"]
    run.messages.clear()
    with pytest.raises(FMICallException, match="fmi2ExitInitializationMode"):
        run.run(params, {"u": 0.0}, ["theta"], 0.02, 1)
    assert any(f"parameter {name} " in m for m in run.messages), run.messages


def test_non_finite_state_is_an_fmi_error(fmu_runner):
    run = fmu_runner["flexjoint"]
    run.messages.clear()
    with pytest.raises(FMICallException, match="fmi2DoStep"):
        run.run({}, {"u": 1e308}, ["theta"], 0.02, 3)
    assert any("non-finite" in m for m in run.messages), run.messages
    with pytest.raises(FMICallException, match="fmi2DoStep"):
        run.run({}, {"u": float("nan")}, ["theta"], 0.02, 3)


def test_fixed_parameter_cannot_change_after_init(fmu_runner):
    run = fmu_runner["flexjoint"]
    run.messages.clear()
    with run.instance({"n_modes": 2}) as h, pytest.raises(FMICallException):
        h.set(Jeq=1.0)
    assert any("Jeq" in m and "fixed" in m for m in run.messages)


def test_linear_fast_path_equals_the_generic_rk4_path(fmu_runner):
    # a negligible friction torque forces the generic (hybrid) stepper; it must give the same RK4 result
    # (up to the RK4 local error of splitting a step at each velocity reversal)
    n, dt = 300, 0.02
    u = 2 * np.sign(np.sin(2 * np.pi * 0.5 * np.arange(n) * dt))
    tau = np.where(np.arange(n) == 100, 0.02, 0.0)
    outs = ["theta", "alpha", "alpha_gauge", "theta_dot"]
    fast = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": u, "tau_tip": tau}, outs, dt, n)
    slow = fmu_runner["flexjoint"].run({"n_modes": 2, "coulomb_torque": 1e-15}, {"u": u, "tau_tip": tau}, outs, dt, n)
    for k in outs:
        np.testing.assert_allclose(slow[k], fast[k], rtol=0, atol=1e-7 * np.abs(fast[k]).max())


# ---------------------------------------------------------------- tip mass and initial state


def test_tip_mass_frequency_is_the_exact_cantilever_with_tip_mass():
    """The assumed modes with a tip mass against the exact first root of a clamped-free beam with a tip mass mu
    m_link: 1 + cos(x) cosh(x) + mu x (cos(x) sinh(x) - sin(x) cosh(x)) = 0 (Ritz: from above, converging)."""
    from scipy.optimize import brentq

    from harness.fmu.plant import ks_for_first_mode

    f_bare = mode_frequencies(PlantParams(n_modes=1))[1, 0]
    for mu, tol in [(0.5, 1.5e-3), (1.0, 2e-3), (2.0, 2.5e-3)]:

        def char(x: float, mu: float = mu) -> float:
            return 1 + math.cos(x) * math.cosh(x) + mu * x * (math.cos(x) * math.sinh(x) - math.sin(x) * math.cosh(x))

        exact = f_bare * (brentq(char, 0.3, BETA[0]) / BETA[0]) ** 2
        f = [mode_frequencies(PlantParams(n_modes=n, m_tip=mu * 0.065))[1, 0] for n in (1, 2, 3)]
        assert f[0] > f[1] > f[2] > exact  # Ritz bounds from above
        # the clamped-free shapes are not the modes of the loaded beam, so assumed modes overestimate: measured
        # +0.68/0.97/1.19 % with one mode, +0.105/0.150/0.184 % with two, +0.033/0.047/0.058 % with three
        assert f[0] == pytest.approx(exact, rel=0.015)  # the textbook rig's single mode: within 1.5 %
        assert f[1] == pytest.approx(exact, rel=tol)  # two modes (the FMU's usual) within 0.25 %
    p = PlantParams(m_tip=0.05, L_link=0.45, m_link=0.06, n_modes=2)
    ks = ks_for_first_mode(p, 2.5)
    assert mode_frequencies(PlantParams(m_tip=0.05, L_link=0.45, m_link=0.06, n_modes=2, Ks=ks))[1, 0] == (
        pytest.approx(2.5, rel=1e-9)
    )
    with pytest.raises(ValueError, match="first mode must be a frequency > 0 Hz"):
        ks_for_first_mode(p, 0.0)


def test_tip_mass_fmu_matches_state_space_and_zero_changes_nothing(fmu_runner):
    dt, n = 0.01, 300
    t = np.arange(n) * dt
    u = 1.5 * np.sin(2 * np.pi * 0.7 * t) + np.sign(np.sin(2 * np.pi * 0.4 * t))
    tau = np.zeros(n)
    params = {"n_modes": 2, "internal_step": 2.5e-4, "m_tip": 0.04}
    res = fmu_runner["flexjoint"].run(params, {"u": u, "tau_tip": tau}, OUTPUTS, dt, n)
    got = np.column_stack([res[k] for k in OUTPUTS])
    ref = zoh_reference(PlantParams(**params), u, tau, dt)
    assert np.abs(got - ref).max() < 1e-6
    # the clamped link rings at the oracle's tip-mass frequencies
    pulse = np.zeros(2000)
    pulse[:5] = 0.01
    res = fmu_runner["flexjoint"].run(
        {**params, "hub_locked": 1}, {"tau_tip": pulse}, ["alpha", "alpha_gauge"], 1e-3, 2000
    )
    s = prony_poles([res["alpha"][10:], res["alpha_gauge"][10:]], 4, 1e-3)
    fc = np.sort(np.abs(s[s.imag > 0])) / (2 * np.pi)
    np.testing.assert_allclose(fc, mode_frequencies(PlantParams(**params))[1], rtol=0.01)
    # m_tip = 0 (the default) is the model without it, to the bit: the FMU keeps the tip-mass-free code path
    a = fmu_runner["flexjoint"].run({"n_modes": 2}, {"u": u}, OUTPUTS, dt, n)
    b = fmu_runner["flexjoint"].run({"n_modes": 2, "m_tip": 0.0}, {"u": u}, OUTPUTS, dt, n)
    assert all(np.array_equal(a[k], b[k]) for k in OUTPUTS)


@pytest.mark.parametrize(
    "effects", [{}, {"hub_locked": 1}, {"coulomb_torque": 0.044}, {"backlash": 0.004, "coulomb_torque": 0.01}]
)
def test_vanishing_tip_mass_joins_the_massless_code_path(fmu_runner, effects):
    """m_tip = 0 takes the arrow-matrix branches (free, clamped, stuck hub); a negligible tip mass takes the
    general ones (full mass-matrix inverse): both must describe the same rig."""
    dt, n = 0.01, 300
    t = np.arange(n) * dt
    u = 1.5 * np.sin(2 * np.pi * 0.7 * t) + np.sign(np.sin(2 * np.pi * 0.4 * t))
    tau = np.where((t >= 1.0) & (t < 1.05), 0.02, 0.0)
    outs = ["theta", "alpha", "alpha_gauge", "theta_dot", "theta_motor"]
    base = {"n_modes": 2, **effects}
    a = fmu_runner["flexjoint"].run(base, {"u": u, "tau_tip": tau}, outs, dt, n)
    b = fmu_runner["flexjoint"].run({**base, "m_tip": 1e-12}, {"u": u, "tau_tip": tau}, outs, dt, n)
    assert np.abs(a["alpha"]).max() > 1e-3
    for k in outs:
        np.testing.assert_allclose(b[k], a[k], rtol=0, atol=1e-7 * max(np.abs(a[k]).max(), 1e-3), err_msg=k)


def _zero_crossing_frequency(x: np.ndarray, dt: float) -> float:
    """Frequency [Hz] of a zero-mean oscillation from its linearly interpolated zero crossings."""
    k = np.nonzero(np.signbit(x[1:]) != np.signbit(x[:-1]))[0]
    tz = (k - x[k] / (x[k + 1] - x[k])) * dt
    return (len(tz) - 1) / (2 * (tz[-1] - tz[0]))


def _fft_peak(x: np.ndarray, dt: float, f_lo: float, f_hi: float) -> float:
    """Frequency [Hz] of the largest peak in [f_lo, f_hi) of the Hann-windowed, zero-padded spectrum of x."""
    nfft = 1 << 22  # ~0.24 mHz bins at dt = 1 ms
    spec = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(len(x)), nfft))
    f = np.fft.rfftfreq(nfft, dt)
    band = (f >= f_lo) & (f < f_hi)
    return float(f[band][np.argmax(spec[band])])


@pytest.mark.parametrize("m_tip", [0.02, 0.13])
def test_tip_mass_free_hub_rings_at_the_oracle_frequencies(fmu_runner, m_tip):
    """Free hub, every damping off (Beq = km = zeta_link = 0), released from alpha_start: alpha rings at the
    oracle's undamped free-hub frequencies (mode_frequencies row 0), measured < 1 % (in fact ~1e-5)."""
    dt, n = 1e-3, 20000
    undamped = {"Beq": 0.0, "km": 0.0, "zeta_link": 0.0, "m_tip": m_tip, "alpha_start": 0.01}
    run = fmu_runner["flexjoint"].run
    one = run({"n_modes": 1, **undamped}, {"u": 0.0}, ["alpha", "theta"], dt, n)
    f1 = mode_frequencies(PlantParams(n_modes=1, **undamped))[0, 0]
    assert np.ptp(one["theta"]) > 0  # the hub swings against the link: free, not clamped
    assert _zero_crossing_frequency(one["alpha"], dt) == pytest.approx(f1, rel=0.01)
    two = run({"n_modes": 2, **undamped}, {"u": 0.0}, ["alpha"], dt, n)
    f = mode_frequencies(PlantParams(n_modes=2, **undamped))[0]
    split = math.sqrt(f[0] * f[1])  # one peak on each side
    got = (_fft_peak(two["alpha"], dt, 0.1, split), _fft_peak(two["alpha"], dt, split, 100.0))
    np.testing.assert_allclose(got, f, rtol=0.01)
    assert f[0] < mode_frequencies(PlantParams(n_modes=2, Beq=0.0, km=0.0, zeta_link=0.0))[0, 0]  # mass lowers it


@pytest.mark.parametrize("effects", [{}, {"backlash": 0.004}, {"coulomb_torque": 0.02}])
def test_initial_state_parameters(fmu_runner, effects):
    """theta_start, alpha_start (mode 1), theta_dot_start, alpha_dot_start are the outputs at t = 0, and the linear
    rig then follows the state-space solution from that state."""
    start = {"theta_start": 0.3, "alpha_start": 0.02, "theta_dot_start": -1.5, "alpha_dot_start": 0.4}
    dt, n = 0.005, 200
    u = np.full(n, 0.5)
    outs = [*OUTPUTS, "theta_motor"]
    res = fmu_runner["flexjoint"].run({"n_modes": 2, **start, **effects}, {"u": u}, outs, dt, n)
    init = res["init"]
    assert (init["theta"], init["alpha"], init["theta_dot"], init["alpha_dot"]) == pytest.approx(
        (0.3, 0.02, -1.5, 0.4), abs=1e-15
    )
    assert init["y"] == pytest.approx(0.32, abs=1e-15) and init["theta_motor"] == 0.3  # motor side with the hub
    if effects.get("backlash"):  # teeth start mid-play and both sides share the initial speed: never beyond it
        assert np.abs(res["theta_motor"] - res["theta"]).max() <= 0.002 * (1 + 1e-9)
    if effects:
        return
    p = PlantParams(n_modes=2)
    A, B, C, _ = state_space(p)
    x = np.zeros(A.shape[0])
    x[0], x[1], x[3], x[4] = 0.3, 0.02, -1.5, 0.4
    sol = solve_ivp(
        lambda t, z: A @ z + B[:, 0] * 0.5,
        (0, n * dt),
        x,
        t_eval=(np.arange(n) + 1) * dt,
        rtol=1e-10,
        atol=1e-13,
        method="DOP853",
    )
    np.testing.assert_allclose(res["theta"], (C @ sol.y)[0], atol=1e-6)
    np.testing.assert_allclose(res["alpha"], (C @ sol.y)[1], atol=1e-6)


def test_negative_tip_mass_is_refused(fmu_runner):
    run = fmu_runner["flexjoint"]
    run.messages.clear()
    with pytest.raises(FMICallException, match="fmi2ExitInitializationMode"):
        run.run({"m_tip": -1.0}, {"u": 0.0}, ["theta"], 0.01, 2)
    msg = [m for m in run.messages if "m_tip" in m]
    assert msg == ["invalid parameter m_tip = -1: tip mass must be >= 0"], run.messages  # one line, named
    with pytest.raises(ValueError, match=r"invalid parameter m_tip = -1.0: must be in \[0, 10\]"):
        PlantParams(m_tip=-1.0).validate()  # the range modelDescription.xml declares
    with pytest.raises(ValueError, match="invalid parameter theta_dot_start = 0.5: must be 0 with hub_locked = 1"):
        PlantParams(hub_locked=1, theta_dot_start=0.5).validate()


@pytest.mark.parametrize("effects", [{}, {"coulomb_torque": 0.044, "backlash": 0.004}])
def test_a_finer_communication_step_gives_the_same_numbers_on_the_grid(fmu_runner, effects):
    """A master that steps every FMU at a quarter of the sample period: the plant keeps its state on the grid of
    whole internal steps and previews the part past it, so at every sample theta and alpha are those of a step of a
    whole sample, to the bit (linear fast path and with friction and backlash), while the command changes only at
    the samples; in between the preview lies within RK4 of them."""
    Ts, n, q = 0.002, 400, 4
    params = {"n_modes": 2, "internal_step": 0.001, **effects}
    u = np.repeat(np.random.default_rng(5).uniform(-3.0, 3.0, n // 20), 20)
    whole = fmu_runner["flexjoint"].run(params, {"u": u}, ["theta", "alpha"], Ts, n)
    fine = fmu_runner["flexjoint"].run(params, {"u": np.repeat(u, q)}, ["theta", "alpha"], Ts / q, n * q)
    for name in ("theta", "alpha"):
        np.testing.assert_array_equal(fine[name][q - 1 :: q], whole[name])
        between = np.interp(np.arange(n * q) + 1.0, np.arange(1, n + 1) * q, whole[name])
        assert np.abs(fine[name] - between).max() < 0.05 * np.ptp(whole[name])
    assert np.ptp(whole["theta"]) > 0.2  # rad: the rig moves


def test_process_noise_has_the_likelihood_engines_stationary_covariance():
    """White torques on the hub and at the link's tip (hub_torque_noise 0.02, tip_torque_noise 0.002 N m sqrt(s),
    held over each 1 ms step) on the one-mode rig at rest, 120 s each on four seeds: the hub speed's and the link
    deflection's variances are those of the likelihood engine's sampled model (its Van Loan process covariance, the
    discrete Lyapunov equation's stationary solution) within 10 % on the seeds' mean (measured 1.8 % and 6.6 %). The
    same seed gives the same bytes, another seed another record, no noise the noise-free run."""
    from scipy.linalg import solve_discrete_lyapunov
    from test_likelihood import _truth

    from harness.fmu.build import build_all
    from harness.fmu.cosim import Rig
    from harness.likelihood.model import Noise, rig_model

    one, Ts, n = {"n_modes": 1}, 1e-3, 120_000
    noisy = one | {"hub_torque_noise": 0.02, "tip_torque_noise": 0.002}
    d = rig_model(one, _truth(one), Noise(0.0, 0.0, 0.02, 0.002)).discretise(Ts)
    on = [1, 2, 3]  # a_1, theta_dot, a_dot_1: the hub's angle drifts, the rest is stationary
    P = solve_discrete_lyapunov(d.A[np.ix_(on, on)], d.Q[np.ix_(on, on)])
    fmus = build_all()
    ratios = []
    with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
        runs = [rig.run(np.zeros(n), Ts, plant=noisy | {"noise_seed": s}) for s in range(4)]
        again = rig.run(np.zeros(n), Ts, plant=noisy | {"noise_seed": 0})
        quiet = rig.run(np.ones(200), Ts, plant=one | {"noise_seed": 5})
        plain = rig.run(np.ones(200), Ts, plant=one)
    for out in runs:
        speed, alpha = np.radians(out["theta_dot"][1000:]), np.radians(out["alpha"][1000:])
        ratios.append((np.var(speed) / P[1, 1], np.var(alpha) / P[0, 0]))
    assert np.mean(ratios, axis=0) == pytest.approx([1.0, 1.0], rel=0.1)
    np.testing.assert_array_equal(again["theta"], runs[0]["theta"])
    assert not np.array_equal(runs[1]["theta"], runs[0]["theta"])
    np.testing.assert_array_equal(quiet["theta"], plain["theta"])
