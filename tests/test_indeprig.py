"""The independent rig simulator (tests/indeprig.py): beam, motor, friction, backlash, DAQ, run directories."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
from indeprig import (
    DEG,
    IndepRig,
    beam_of,
    clamped_free_roots,
    comb_run,
    equivalent_Ks,
    gauge_scale,
    make_run,
    mode_frequencies,
    motor_constants,
    simulate,
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
