"""The independent rig simulator (tests/indeprig.py): beam, motor, friction, backlash, DAQ, run directories."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from indeprig import (
    DEG,
    IndepRig,
    beam_of,
    clamped_free_roots,
    closed_loop_poles,
    comb_run,
    equivalent_Ks,
    gauge_scale,
    make_run,
    mode_frequencies,
    motor_constants,
    simulate,
    simulate_closed,
    zoh,
)

TS = 0.02
QUIET = {"noise_theta": 0.0, "noise_alpha": 0.0}


# ------------------------------------------------------------------ beam


def test_clamped_modes_from_EI_match_the_closed_form_and_the_mode_ratios():
    rig = IndepRig(n_modes=3, EI=0.15)
    rhoA, L = rig.m_link / rig.L_link, rig.L_link
    f = mode_frequencies(rig, hub="clamped")  # eigenvalues of the quadrature mass and stiffness matrices
    w1 = 2 * math.pi * f[0]
    assert w1 == pytest.approx(1.875**2 * math.sqrt(rig.EI / (rhoA * L**4)), rel=2e-4)  # textbook 1.875
    assert w1 == pytest.approx(1.8751040687**2 * math.sqrt(rig.EI / (rhoA * L**4)), rel=1e-9)
    assert f[1] / f[0] == pytest.approx(6.267, abs=1e-3)
    assert f[2] / f[0] == pytest.approx(17.547, abs=1e-3)
    assert clamped_free_roots(3) == pytest.approx((1.87510, 4.69409, 7.85476), abs=1e-5)
    b = beam_of(rig)  # tip-normalised clamped-free shapes: int psi^2 = L / 4, rigid link m L^2 / 3
    assert b.mass == pytest.approx(np.eye(3) * rig.m_link / 4, abs=1e-12)
    assert b.J_rigid == pytest.approx(rig.m_link * L**2 / 3, rel=1e-12)


def test_equivalent_Ks_round_trip():
    assert equivalent_Ks(IndepRig()) == pytest.approx(1.3, rel=1e-12)
    for Ks in (0.8, 1.5, 2.9):
        rig = IndepRig.from_Ks(Ks, n_modes=2)
        assert equivalent_Ks(rig) == pytest.approx(Ks, rel=1e-12)
        Jl = rig.m_link * rig.L_link**2 / 3
        assert 2 * math.pi * mode_frequencies(rig, hub="clamped")[0] == pytest.approx(math.sqrt(Ks / Jl), rel=1e-9)
    assert IndepRig.from_Ks(1.5).EI / IndepRig().EI == pytest.approx(1.5 / 1.3, rel=1e-12)


def test_gauge_sees_root_curvature_mode_two_reversed_and_6_27_times_stronger():
    rig = IndepRig(n_modes=2)
    curv = beam_of(rig).curv0  # per unit tip deflection of each mode
    assert curv[1] / curv[0] == pytest.approx(-((4.694091 / 1.875104) ** 2), rel=1e-5)
    # a static tip load reads its own deflection: the gauge scale makes curvature -> alpha exact for statics
    assert gauge_scale(IndepRig(n_modes=1)) * curv[0] == pytest.approx(1.0 / rig.L_link, rel=1e-12)
    assert gauge_scale(rig) != pytest.approx(gauge_scale(IndepRig(n_modes=1)), rel=1e-3)


def test_free_hub_mode_agrees_with_the_project_twin():
    from harness.fmu.plant import PlantParams
    from harness.fmu.plant import mode_frequencies as twin_modes

    ours = mode_frequencies(IndepRig())[0]
    twin = twin_modes(PlantParams())[0][0]
    assert ours == pytest.approx(twin, rel=0.03)
    assert 4.0 < ours < 6.0  # free-hub first mode above the 2.94 Hz clamped one


# ------------------------------------------------------------------ motor, friction, backlash


@pytest.mark.parametrize("motor_gain", [1.0, 0.8])
def test_steady_speed_at_2V_is_the_motor_formula(motor_gain):
    rig = IndepRig(motor_gain=motor_gain, **QUIET)
    r = simulate(rig, np.full(600, 2.0), TS)
    eg_em = 0.9 * 0.69 * motor_gain
    w = eg_em * 70 * 7.68e-3 * 2.0 / (2.6 * 0.004 + eg_em * 70**2 * 7.68e-3 * 7.68e-3)
    assert r["theta_dot"][-1] / DEG == pytest.approx(w, rel=1e-4)
    slope = (r["theta"][-1] - r["theta"][-251]) / (250 * TS) / DEG  # mean rate over the last 5 s
    assert slope == pytest.approx(w, rel=1e-4)


def test_amplifier_saturation_caps_the_motor_voltage():
    sat = simulate(IndepRig(amp_limit=1.5, **QUIET), np.full(300, 3.0), TS)
    free = simulate(IndepRig(**QUIET), np.full(300, 1.5), TS)
    assert np.all(sat["u_plant"] == 1.5)
    assert np.allclose(sat["theta"], free["theta"], atol=1e-9, rtol=0)
    assert not np.allclose(simulate(IndepRig(**QUIET), np.full(300, 3.0), TS)["theta"], free["theta"], atol=1.0)


def test_stribeck_friction_sticks_below_breakaway_and_slides_above():
    Fc = 0.044
    rig = IndepRig(coulomb_torque=Fc, **QUIET)
    G, Bemf = motor_constants(rig)
    Fs = 1.3 * Fc
    n = 250  # 5 s
    # above Coulomb but below static friction: a plain Coulomb law would slide here, Stribeck holds
    for V in (0.5 * Fc / G, 1.15 * Fc / G, 0.95 * Fs / G):
        r = simulate(rig, np.full(n, V), TS)
        assert np.max(np.abs(r["theta"])) < 0.1  # deg: only the tanh creep, below a 12-bit pot LSB (0.17 deg)
    V = 1.1 * Fs / G
    r = simulate(rig, np.full(n, V), TS)
    assert r["theta"][-1] > 20.0
    assert r["theta_dot"][-1] / DEG == pytest.approx((G * V - Fc) / (rig.Beq + Bemf), rel=1e-3)  # kinetic = Fc
    r = simulate(rig, np.full(n, -V), TS)
    assert r["theta"][-1] < -20.0


def test_backlash_hysteresis_is_the_play_plus_contact_compliance():
    b = 0.01
    t = np.arange(700) * TS
    u = 0.5 * np.sin(2 * np.pi * 0.2 * t)  # slow reversals: small contact torques
    r = simulate(IndepRig(backlash=b, **QUIET), u, TS)
    phi = np.radians(r["theta_m"] - r["theta"])[150:]  # after the first crossing of the play
    width = np.ptp(phi)
    # contact torque ~ (Jh + Jl) x hub acceleration ~ 6e-3 N m at 50 N m/rad: 1.2e-4 rad per side
    assert b < width < b * 1.05
    # the loop: driving forward the motor side leads the hub by half the play, driving back it lags by as much
    dm = np.diff(r["theta_m"])[149:]
    assert np.median(phi[dm > 1e-3]) == pytest.approx(b / 2, rel=0.05)
    assert np.median(phi[dm < -1e-3]) == pytest.approx(-b / 2, rel=0.05)
    rigid = simulate(IndepRig(**QUIET), u, TS)
    assert np.array_equal(rigid["theta_m"], rigid["theta"])
    assert np.max(np.abs(rigid["theta"] - r["theta"])) > 0.2  # the play is seen at the hub (deg)


def test_default_tolerance_is_converged_on_a_nonsmooth_rig():
    t = np.arange(300) * TS
    u = 1.2 * np.sin(2 * np.pi * (0.2 + 0.15 * t) * t)
    rig = IndepRig(coulomb_torque=0.044, backlash=0.006, n_modes=2, **QUIET)
    a = simulate(rig, u, TS)
    ref = simulate(rig, u, TS, rtol=1e-9)
    assert np.max(np.abs(a["theta"] - ref["theta"])) < 1e-3  # deg, vs 0.07 deg pot noise
    assert np.max(np.abs(a["alpha"] - ref["alpha"])) < 1e-3


# ------------------------------------------------------------------ DAQ


def test_pot_wraps_with_a_10_degree_dead_band():
    rig = IndepRig(**QUIET)
    r = simulate(rig, np.full(400, 2.0), TS)
    w = np.mod(r["theta"] + 180.0, 360.0) - 180.0
    dead = np.abs(w) > 175.0
    assert dead.sum() > 5 and (~dead).sum() > 300
    assert np.allclose(r["theta_v"][~dead], w[~dead] / 35.5, atol=1e-12, rtol=0)
    assert np.allclose(r["theta_v"][dead], np.sign(w[dead]) * 175.0 / 35.5, atol=1e-12, rtol=0)
    assert r["theta_v"].max() == pytest.approx(175.0 / 35.5, abs=1e-12)
    assert r["theta_v"].min() == pytest.approx(-175.0 / 35.5, abs=1e-12)
    wraps = np.sum(np.diff(w) < -180.0)
    assert wraps >= 3 and np.sum(np.diff(r["theta_v"]) < -5.0) == wraps  # one jump per wrap, top to bottom


def test_adc_samples_lie_on_the_lsb_lattice():
    rig = IndepRig(adc_bits=12)
    t = np.arange(500) * TS
    r = simulate(rig, 1.5 * np.sign(np.sin(2 * np.pi * 0.5 * t)), TS, seed=3)
    lsb = 20.0 / 4096
    for ch in ("theta_v", "alpha_v"):
        codes = r[ch] / lsb
        assert np.max(np.abs(codes - np.round(codes))) < 1e-9
        assert codes.min() >= -2048 and codes.max() <= 2047
        assert np.unique(codes).size > 10
    ideal = simulate(IndepRig(adc_bits=0), 1.5 * np.sign(np.sin(2 * np.pi * 0.5 * t)), TS, seed=3)
    assert 0 < np.max(np.abs(ideal["theta_v"] - r["theta_v"])) <= lsb / 2 + 1e-12


def test_delay_shifts_the_response_by_exactly_n_samples():
    rng = np.random.default_rng(7)
    u = np.repeat(rng.choice([-1.0, 1.0], 60), 5)
    base = simulate(IndepRig(**QUIET), u, TS)
    assert base["theta"][0] == 0.0 and base["theta"][1] != 0.0  # sample k is read before command k acts
    d = 3
    late = simulate(IndepRig(delay_samples=d, **QUIET), u, TS)
    for ch in ("theta_v", "alpha_v", "theta"):
        assert np.allclose(late[ch][d:], base[ch][:-d], atol=1e-9, rtol=0)
        assert np.max(np.abs(late[ch][d - 1 :] - base[ch][: -d + 1])) > 1e-3  # not a shift by d - 1
    assert np.all(late["theta_v"][: d + 1] == 0.0)
    assert np.all(late["alpha_v"][: d + 1] == 0.01)  # gauge offset at rest


def test_dac_clamp_noise_level_and_seeds():
    r = simulate(IndepRig(**QUIET), np.full(50, 15.0), TS)
    assert np.all(r["u_plant"] == 10.0)
    u = np.zeros(2000)
    a = simulate(IndepRig(), u, TS, seed=1)
    assert np.std(a["theta_v"]) == pytest.approx(0.002, rel=0.05)
    assert np.std(a["alpha_v"] - 0.01) == pytest.approx(0.002, rel=0.05)
    assert abs(np.corrcoef(a["theta_v"], a["alpha_v"])[0, 1]) < 0.05
    assert np.array_equal(simulate(IndepRig(), u, TS, seed=1)["theta_v"], a["theta_v"])
    assert not np.array_equal(simulate(IndepRig(), u, TS, seed=2)["theta_v"], a["theta_v"])


def test_gauge_cubic_and_offset():
    rig = IndepRig(gauge_cubic=0.05, **QUIET)
    tau, comb = comb_run(rig, {"deflections_cm": [-5.0, 5.0], "hold": 3.0, "ramp": 1.0}, 8.0, TS)
    r = simulate(rig, np.zeros(tau.size), TS, tau_tip=tau, hub_locked=True)
    a = r["alpha_gauge"]
    assert np.allclose(r["alpha_v"], a / -3.36 * (1 + 0.05 * (a / 10) ** 2) + 0.01, atol=1e-12, rtol=0)


def test_pot_bow_and_gauge_drift_are_the_sensor_errors_named():
    """The out-of-library sensor errors, in this simulator's own DAQ: the pot's track bowed by pot_bow x 180 deg
    sin(theta), the gauge's bridge voltage about its offset scaled by 1 + gauge_drift t, in open and closed loop."""
    rig = IndepRig(pot_bow=0.02, gauge_drift=0.01, **QUIET)
    u = 1.5 * np.sign(np.sin(np.arange(500) * TS * 2.0))
    r, plain = simulate(rig, u, TS), simulate(replace(rig, pot_bow=0.0, gauge_drift=0.0), u, TS)
    np.testing.assert_allclose(r["theta"], plain["theta"], rtol=0, atol=0)  # a sensor error: the rig moves alike
    w = np.clip(np.mod(r["theta"] + 180.0, 360.0) - 180.0, -175.0, 175.0)  # wrapped, held in the 10 deg dead band
    np.testing.assert_allclose(r["theta_v"], (w + 0.02 * 180.0 * np.sin(np.radians(w))) / 35.5, rtol=0, atol=1e-12)
    t = np.arange(500) * TS
    np.testing.assert_allclose(r["alpha_v"], (plain["alpha_v"] - 0.01) * (1.0 + 0.01 * t) + 0.01, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ run directories and calibration


@pytest.fixture(scope="module")
def blind_run(tmp_path_factory):
    from harness.spec import load

    spec = load("blind")
    dest = make_run(tmp_path_factory.mktemp("indeprig") / "run", spec, IndepRig(), seed=11)
    return spec, dest


def test_make_run_writes_the_campaign_format(blind_run):
    spec, dest = blind_run
    manifest = json.loads((dest / "manifest.json").read_text())
    assert manifest["kind"] == "campaign" and manifest["generator"] == "tests/indeprig.py"
    assert "fmus" not in manifest
    assert manifest["spec"] == spec.raw and manifest["spec_sha256"] == spec.sha256()
    assert manifest["sample_rate"] == 50.0
    names = [e.name for e in spec.all_experiments()]
    assert [e["name"] for e in manifest["experiments"]] == names
    for e in manifest["experiments"]:
        df = pd.read_parquet(dest / "data" / f"{e['name']}.parquet")
        assert len(df) == e["n"]
        assert {"t", "u", "theta_v", "alpha_v", "theta", "alpha"} <= set(df.columns)
    comb = pd.read_parquet(dest / "data" / "comb.parquet")
    held = comb["comb_angle"].notna().to_numpy()
    assert 0 < held.sum() < len(comb) and np.isnan(comb["comb_angle"].to_numpy()[~held]).all()
    # each hold's true mean deflection is its comb angle (own beam statics; residual ringing averages out)
    starts = np.flatnonzero(np.diff(np.concatenate([[0], held.astype(int)])) == 1)
    stops = np.flatnonzero(np.diff(np.concatenate([held.astype(int), [0]])) == -1) + 1
    assert starts.size == 8
    for a, b in zip(starts, stops, strict=True):
        assert comb["alpha"][a:b].mean() == pytest.approx(comb["comb_angle"][a], abs=0.02)


def test_calibration_recovers_Kp_and_Ke(blind_run):
    from harness.pipeline import calibrate_run

    _, dest = blind_run
    cal = calibrate_run(dest)
    assert cal.Kp == pytest.approx(35.5, rel=0.01)
    assert cal.Ke == pytest.approx(-3.36, rel=0.02)
    assert cal.gauge_offset_v == pytest.approx(0.01, abs=1e-3)
    assert (dest / "calibration.json").exists()


# ------------------------------------------------------------------ closed loop

TS_CL = 0.002  # 500 Hz, as specs/blind_closed.toml
LINEAR_TWIN = {  # the textbook linear rig with the twin DAQ's default calibration, noise off, ideal ADC
    "noise_theta": 0.0,
    "noise_alpha": 0.0,
    "pot_gain": 35.5145,
    "gauge_Ke": -3.3636,
    "gauge_offset": 0.0,
}


def _blind_closed(duration: float | None = None, calibration: bool = True):
    from harness import spec as specmod

    raw = specmod.load("blind_closed").raw
    if duration is not None:
        raw["experiment"] = [dict(e, duration=duration) for e in raw["experiment"]]
    if not calibration:
        raw["calibration"] = []
    return specmod.from_dict(raw, str(specmod.resolve_path("blind_closed")))


def _square(amplitude: float = 20.0, f: float = 0.25, n: int = 3000) -> np.ndarray:
    """A square theta reference [rad] (harness.rig.signals, degrees in)."""
    from harness.rig.signals import generate

    return np.radians(generate("square", n, TS_CL, {"f": f, "amplitude": amplitude}))


def _angles_read(r, rig):
    """The angles [rad] the controller reads: the logged volts through the rig's nominal calibration."""
    th = np.radians(rig.pot_gain * (r["theta_v"] - rig.pot_offset))
    al = np.radians(rig.gauge_Ke * (r["alpha_v"] - rig.gauge_offset))
    return th, al


@pytest.fixture(scope="module")
def lqr():
    return _blind_closed().controller


@pytest.fixture(scope="module")
def linear_closed(lqr):
    """The independent closed loop on the linear smooth rig: LQR of blind_closed.toml, +-20 deg square, 6 s."""
    rig = IndepRig(**LINEAR_TWIN)
    return rig, simulate_closed(rig, _square(), TS_CL, lqr)


def test_closed_loop_tracks_and_steps_exactly(linear_closed):
    rig, r = linear_closed
    assert r["ref"][0] == pytest.approx(20.0, abs=1e-12) and set(np.round(r["ref"], 9)) == {-20.0, 20.0}
    settled = (r["t"] % 2.0) > 1.5  # 1.5 s after each reversal of the reference
    assert np.max(np.abs(r["theta"] - r["ref"])[settled]) < 0.01  # deg: type-1 loop, no friction
    assert 10.0 < np.ptp(r["alpha"]) < 20.0  # the steps bend the link
    # the largest command is the 40 deg reversal through k_theta (the shaft at rest on the old reference)
    assert np.max(np.abs(r["u"])) == pytest.approx(9.231 * math.radians(40.0), rel=0.01)
    # one DOP853 step per sample: its states are the exact zero-order-hold propagation of the applied command
    Ad, Bd, C = zoh(rig, TS_CL)
    s = np.zeros(Ad.shape[0])
    worst = 0.0
    for k in range(r["t"].size):
        worst = max(worst, np.max(np.abs(C @ s * DEG - (r["theta"][k], r["alpha_gauge"][k]))))
        s = Ad @ s + Bd * r["u_plant"][k]
    assert worst < 1e-9  # deg (measured 7e-13)


def test_closed_loop_agrees_with_the_project_twin(linear_closed, lqr):
    """The independent closed loop against the twin's (plant, DAQ and controller FMUs in harness.fmu.cosim).

    On the linear 1-mode rig both link models are the clamped-free first mode (free-hub mode 4.82 Hz in both), so
    the gap is the twin's RK4 (1 ms) against DOP853: the twin's plant model stepped by RK4 in numpy under this
    controller differs by 4e-8 deg, the open-loop FMU run by 5e-8 deg. Tolerance 1e-4 deg: 2000 times that,
    700 times below the pot noise (0.07 deg), and 4000 times below what a 3 % error of the link's mode (the
    open-loop agreement test's tolerance) makes in this closed loop, 0.42 deg (a 0.1 % one: 0.014 deg).
    """
    from harness.fmu.build import build_all
    from harness.fmu.cosim import Rig

    rig, r = linear_closed
    fmus = build_all()
    daq = {
        "pot_gain": rig.pot_gain,
        "pot_offset": rig.pot_offset,
        "gauge_gain": rig.gauge_Ke,
        "gauge_offset": rig.gauge_offset,
        "noise_theta": 0.0,
        "noise_alpha": 0.0,
    }
    with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as twin:
        q = twin.run_closed(_square(), TS_CL, lqr.fmu_parameters(1 / TS_CL), plant={"n_modes": 1}, daq=daq)
    assert np.max(np.abs(q["theta"] - r["theta"])) < 1e-4  # deg
    assert np.max(np.abs(q["alpha"] - r["alpha"])) < 1e-4  # deg
    assert np.max(np.abs(q["u"] - r["u"])) < 1e-5  # V (du/dtheta ~ 0.25 V/deg)
    # and the tolerance discriminates: a 3 % stiffer link is 0.4 deg away
    stiff = simulate_closed(IndepRig.from_Ks(1.3 * 1.03**2, **LINEAR_TWIN), _square(), TS_CL, lqr)
    assert np.max(np.abs(stiff["theta"] - r["theta"])) > 0.3


def test_stick_slip_closed_loop_agrees_with_the_twins_stribeck_friction():
    """A P-only loop (kp 8 V/rad) on +-10 deg steps with hub friction Fc 0.044 N m, breakaway 2 Fc and a Stribeck drop
    over 0.02 rad/s: the hub sticks and slips again five times in 6 s. The independent rig (a smooth tanh sign
    integrated by LSODA) and the twin's hybrid plant (exact stops, stribeck_speed) with the same friction law agree to
    0.006 deg (measured); the twin without the drop (stribeck_speed 0, Karnopp at the Coulomb level) is 0.1 deg away,
    so the tolerance, 0.02 deg, sees the law."""
    from harness.fmu.build import build_all
    from harness.fmu.cosim import Rig
    from harness.rig.controller import Controller

    Fc, ratio, vs = 0.044, 2.0, 0.02
    ref = _square(amplitude=10.0)
    ctrl = Controller(kind="pid", kp=8.0, cutoff=25.0)
    r = simulate_closed(
        IndepRig(coulomb_torque=Fc, stribeck_ratio=ratio, stribeck_velocity=vs, **LINEAR_TWIN), ref, TS_CL, ctrl
    )
    daq = {"pot_gain": 35.5145, "gauge_gain": -3.3636, "gauge_offset": 0.0, "noise_theta": 0.0, "noise_alpha": 0.0}
    params = ctrl.fmu_parameters(1 / TS_CL)
    params.pop("alpha_bias", None)
    fmus = build_all()
    friction = {"coulomb_torque": Fc, "stiction_ratio": ratio}
    with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as twin:
        q = twin.run_closed(ref, TS_CL, params, plant={**friction, "stribeck_speed": vs}, daq=daq)
        karnopp = twin.run_closed(ref, TS_CL, params, plant=friction, daq=daq)
    stops = np.count_nonzero(np.diff((q["theta_dot"] == 0.0).astype(int)) == 1)
    assert stops >= 4  # a stick-slip record, not one stop per step
    assert abs(r["ref"][-1] - r["theta"][-1]) > 0.3  # deg: it stops short of the reference
    assert np.max(np.abs(q["theta"] - r["theta"])) < 0.02  # deg (measured 0.006)
    assert np.max(np.abs(q["u"] - r["u"])) < 0.005  # V (measured 0.0008)
    assert np.max(np.abs(karnopp["theta"] - r["theta"])) > 0.05  # deg (measured 0.10)


@pytest.mark.parametrize("kind", ["state_feedback", "pid"])
def test_logged_command_is_the_law_of_the_logged_volts(kind, lqr):
    """On a rig with every effect the controller sees through (noise, 12-bit ADC, gauge cubic, offsets, delay,
    friction, play), the logged u is the project's law (harness.rig.controller.law) recomputed from the logged
    volts, not from the true angles; the PID is clamped often enough that its anti-windup acts."""
    from harness.rig.controller import Controller, law

    ctrl = lqr if kind == "state_feedback" else Controller(kind="pid", kp=8.0, ki=4.0, kd=0.4, cutoff=25.0, u_limit=3.0)
    rig = IndepRig(
        coulomb_torque=0.044,
        backlash=0.004,
        adc_bits=12,
        delay_samples=1,
        gauge_cubic=0.05,
        pot_offset=0.02,
        noise_theta=0.003,
    )
    r = simulate_closed(rig, _square(20.0, 0.5, 2000), TS_CL, ctrl, seed=5)
    th, al = _angles_read(r, rig)
    u = law(ctrl, np.radians(r["ref"]), th, al, TS_CL)
    assert np.max(np.abs(u - r["u"])) < 1e-9
    true = law(ctrl, np.radians(r["ref"]), np.radians(r["theta"]), np.radians(r["alpha_gauge"]), TS_CL)
    assert np.max(np.abs(true - r["u"])) > 0.05  # V: it reads volts (noise, ADC, offsets), not the state
    assert r["u_plant"][0] == 0.0 and np.array_equal(r["u_plant"][1:], np.clip(r["u"][:-1], -10, 10))  # 1 sample
    if kind == "pid":
        assert 20 < np.sum(np.abs(r["u"]) == 3.0) < 1000  # clamped at the steps, and released
    settled = (r["t"] % 1.0) > 0.8
    assert np.median(np.abs(r["theta"] - r["ref"])[settled]) < 2.0  # deg: it tracks despite friction and play


def test_a_destabilising_gain_is_one_clear_value_error(lqr):
    from harness.rig.controller import Controller

    flipped = Controller(K=[14.142, 28.073, 1.725, 0.223], cutoff=25.0, u_limit=10.0)  # k_alpha of the wrong sign
    msg = r"destabilises the rig: closed-loop pole \|z\| = 1\.009\d > 1 \(3\.\d+ Hz\)"
    with pytest.raises(ValueError, match=msg) as e:
        simulate_closed(IndepRig(), _square(n=500), TS_CL, flipped)
    assert "\n" not in str(e.value)
    assert np.max(np.abs(closed_loop_poles(IndepRig(), lqr, TS_CL))) == pytest.approx(0.98517, abs=1e-5)
    # with friction the linearisation at rest is not the rig: the run itself is watched, and stopped when it diverges
    msg = r"^closed loop diverged at t = 0\.\d+ s .*alpha -?4\d\.\d deg\): the controller destabilises the rig$"
    with pytest.raises(ValueError, match=msg):
        simulate_closed(IndepRig(coulomb_torque=0.044), _square(n=500), TS_CL, flipped)
    with pytest.raises(ValueError, match="sample_rate 1000 Hz differs from the DAQ's 500 Hz"):
        simulate_closed(IndepRig(), _square(n=50), TS_CL, {**lqr.to_dict(), "sample_rate": 1000.0})


def test_linear_poles_predict_the_growth_of_an_unstable_loop(lqr):
    """The continuous-time LQR of the textbook model (Q = diag(200, 1000, 1, 1), 25 Hz velocity filter) on the rig
    with a second mode and one sample of delay: the linear loop loses its 21 Hz second mode (|z| = 1.00083 a
    sample), which the run (unchecked) shows growing at that rate; Coulomb friction at the hub holds it (the check is
    not applied to a rig with friction, which runs). The specs' discrete LQR keeps that rig stable."""
    from harness.rig.controller import Controller

    rig = IndepRig(n_modes=2, delay_samples=1, noise_theta=0.0, noise_alpha=0.0)
    assert np.max(np.abs(closed_loop_poles(rig, lqr, TS_CL))) == pytest.approx(0.98976, abs=1e-5)
    lqr = Controller(K=[14.142, -28.073, 1.725, 0.223], cutoff=25.0, u_limit=10.0)
    z = closed_loop_poles(rig, lqr, TS_CL)
    worst = z[np.argmax(np.abs(z))]
    assert abs(worst) == pytest.approx(1.000835, abs=2e-6)
    assert abs(np.angle(worst)) / (2 * math.pi * TS_CL) == pytest.approx(20.86, abs=0.01)
    with pytest.raises(ValueError, match=r"\|z\| = 1\.0008 > 1 \(20\.86 Hz\)"):
        simulate_closed(rig, np.radians(np.full(50, 5.0)), TS_CL, lqr)
    ref = np.radians(np.r_[np.zeros(50), np.full(2950, 5.0)])
    r = simulate_closed(rig, ref, TS_CL, lqr, check=False)
    early, late = (np.ptp(r["alpha"][k : k + 300]) for k in (600, 2400))  # 1.2-1.8 s and 4.8-5.4 s
    assert late / early == pytest.approx(abs(worst) ** 1800, rel=0.03)  # 4.49
    held = simulate_closed(replace(rig, coulomb_torque=0.044), ref, TS_CL, lqr)
    assert np.ptp(held["alpha"][2400:2700]) < 0.2 * late


def test_closed_loop_make_run_writes_the_campaign_format(tmp_path, lqr):
    from harness.rig.controller import law
    from harness.rig.signals import generate
    from harness.rundir import Manifest

    spec = _blind_closed(duration=3.0)
    rig = IndepRig()
    dest = make_run(tmp_path / "run", spec, rig, seed=4)
    manifest = json.loads((dest / "manifest.json").read_text())
    assert manifest["generator"] == "tests/indeprig.py" and manifest["spec"] == spec.raw
    assert manifest["sample_rate"] == 500.0
    entries = {e["name"]: e for e in manifest["experiments"]}
    assert list(entries) == ["comb", "square_small", "square_large", "square_mid", "square_slow"]
    assert "loop" not in entries["comb"] and "controller" not in entries["comb"]
    for exp in spec.experiments:
        e = entries[exp.name]
        assert e["loop"] == "closed" and e["controller"] == lqr.to_dict() and e["n"] == 1500
        df = pd.read_parquet(dest / "data" / f"{exp.name}.parquet")
        assert list(df.columns) == ["t", "u", "theta_v", "alpha_v", "theta", "alpha", "ref"]
        ref = generate(exp.signal, 1500, TS_CL, exp.params, e["seed"])
        assert np.array_equal(df["ref"].to_numpy(), ref)  # degrees, as the spec writes them
        th, al = _angles_read({k: df[k].to_numpy() for k in ("theta_v", "alpha_v")}, rig)
        assert np.max(np.abs(law(lqr, np.radians(ref), th, al, TS_CL) - df["u"].to_numpy())) < 1e-9
        settled = (df["t"].to_numpy() % (0.5 / exp.params["f"])) > 0.8  # 0.8 s after each reversal
        assert np.max(np.abs(df["theta"] - df["ref"])[settled]) < 0.3  # deg (0.06-0.16): the noise fed back
    m = Manifest.load(dest)  # the project's reader takes it
    assert m.entry("square_mid").loop == "closed" and m.entry("square_mid").controller["K"] == lqr.K
