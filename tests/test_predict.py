"""flexjoint predict: the ensemble's bands, the twin's spread, specs, references, and bad input."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from harness import spec as specmod
from harness.behaviour import POOLED_BY
from harness.diagnosis.result import NoiseFloor
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.prediction import (
    LoopSpecs,
    MetricBand,
    judge_specs,
    pooled,
    predict,
    reference_from,
    simulate_loop,
)
from harness.rig.controller import Controller
from harness.spec import controller_table
from harness.twin import Spread, draw, measurement_noise, spread_of_diagnosis, twin_of_spec

LQR = Controller(K=[9.231, -18.769, 1.203, -0.041], cutoff=15.0, sample_rate=500.0)  # specs/closed_loop.toml's


@pytest.fixture(scope="module")
def lab():
    """The lab rig (friction, second mode, 12-bit ADC, noise, a command delay) as a spec twin."""
    return twin_of_spec(specmod.load("closed_loop"))


def test_without_spread_or_noise_every_member_is_the_one_loop(lab):
    twin = dataclasses.replace(lab, spread=Spread(), noise_deg={"theta": 0.0, "alpha": 0.0})
    ref = reference_from("square:f=0.5;amplitude=20;duration=4", 500.0)
    pred = predict(twin, LQR, ref, n=6, seed=3, workers=1)
    f = build_all()
    with Rig(f["flexjoint"], f["daq"], f["controller"]) as rig:
        one = simulate_loop(rig, twin.tables(noise=False), LQR, ref.ref_deg, ref.Ts, 0.0)
    want = pooled(ref.t, ref.ref_deg, one["theta"], one["alpha"], one["u"], 5.0, 0.0)
    for m, b in pred.metric_bands().items():
        if math.isnan(want[m]):
            assert math.isnan(b.median), m
            continue
        assert b.lo == b.median == b.hi == pytest.approx(want[m], rel=1e-12, abs=1e-12), m
    np.testing.assert_array_equal(pred.bands["theta"][0], pred.bands["theta"][2])
    np.testing.assert_allclose(pred.bands["theta"][1], one["theta"], atol=1e-12)
    assert pred.values["stop_error_deg"][0] > 0.05  # the lab's Coulomb friction stops the hub short


def test_the_band_holds_the_members_and_the_same_seed_gives_the_same_numbers(lab):
    ref = reference_from("square:f=0.5;amplitude=20;duration=4", 500.0)
    a = predict(lab, LQR, ref, n=40, seed=1, workers=1)
    b = predict(lab, LQR, ref, n=40, seed=1, workers=2)
    assert json.dumps(a.to_json(), sort_keys=True) == json.dumps(b.to_json(), sort_keys=True)
    for m, band in a.metric_bands().items():
        v = a.values[m]
        if POOLED_BY.get(m) == "median" or np.isnan(v).all():
            continue
        inside = np.mean((v >= band.lo) & (v <= band.hi))
        assert band.lo <= band.median <= band.hi and inside >= 0.95, m
    s = a.metric_bands()["settling_s"]
    assert s.hi > s.lo  # the sheet's uncertainty and the noise spread the loop


def test_a_diagnosis_spread_is_its_intervals_plus_its_folds():
    """A fitted row's draw: lognormal about its fit, sd of its 95 % interval (ln(hi/lo) / 3.92) and of its two folds'
    fits added; implied physical rows and kept rows are not drawn; an Integer effect parameter is not drawn."""
    doc = {
        "parameters": {
            "plant.Ks": {"fitted": 1.5, "ci95": [1.4, 1.6], "folds": [[1.45, 1.4, 1.5], [1.55, 1.5, 1.6]]},
            "rig.drive_gain": {"fitted": 2.0, "ci95": [1.8, 2.2]},
            "plant.Beq": {"fitted": 0.01, "ci95": [0.009, 0.011]},  # implied by the drive: not an override
            "plant.zeta_link": {"fitted": 0.01, "ci95": [None, None]},  # kept at the spec's value
            "daq.delay_samples": {"fitted": 2, "ci95": [1, 3]},
        },
        "effects": [{"params": {"daq.delay_samples": 2}}],
    }
    over, sp = spread_of_diagnosis(doc)
    assert over == {"plant.Ks": 1.5, "rig.drive_gain": 2.0, "plant.zeta_link": 0.01, "daq.delay_samples": 2.0}
    assert sp.names == ("plant.Ks", "rig.drive_gain")
    sd = sp.sd()
    ks = math.sqrt((math.log(1.6 / 1.4) / 3.92) ** 2 + np.var(np.log([1.45, 1.55])))
    assert sd["plant.Ks"] == pytest.approx(ks) and sd["rig.drive_gain"] == pytest.approx(math.log(2.2 / 1.8) / 3.92)
    twin = dataclasses.replace(twin_of_spec(specmod.load("nominal")), overrides=over, spread=sp)
    draws = draw(twin, 4000, 5)
    logks = np.log([d["plant.Ks"] for d in draws])
    assert np.exp(np.median(logks)) == pytest.approx(1.5, rel=0.01) and np.std(logks) == pytest.approx(ks, rel=0.05)
    assert {d["daq.delay_samples"] for d in draws} == {2.0}


def _under_a_lattice(daq: dict, bits: int) -> NoiseFloor:
    """The noise floor a diagnosis finds where an ADC of ``bits`` over +-10 V reads a rig's 0.002 V of noise per
    channel [deg as read through ``daq``'s gains]: the noise plus the lattice's LSB^2 / 12, the noise alone
    estimated apart."""
    gains = {
        "theta": specmod.fmu_value(daq, "daq", "pot_gain"),
        "alpha": abs(specmod.fmu_value(daq, "daq", "gauge_gain")),
    }
    lsb = 20.0 / 2**bits
    noise = {c: 0.002 * g for c, g in gains.items()}
    total = {c: math.hypot(noise[c], g * lsb / math.sqrt(12.0)) for c, g in gains.items()}
    return NoiseFloor(total["theta"], total["alpha"], "", [], 0.0, 100.0, bits, estimated_deg=noise)


def test_an_adc_the_diagnosis_found_gets_the_noise_under_its_lattice():
    """A twin whose sheet has no ADC but which simulates the 8-bit ADC a diagnosis found takes the noise without the
    lattice's share (its DAQ adds it): its DAQ's noise is the rig's 0.002 V again, not the lattice's share twice."""
    sheet = twin_of_spec(specmod.load("blind_closed"))
    floor = _under_a_lattice(sheet.daq, 8)
    assert measurement_noise(floor, sheet.daq, {}) == {"theta": floor.theta_deg, "alpha": floor.alpha_deg}
    found = {"daq.adc_bits": 8.0}
    twin = dataclasses.replace(sheet, overrides=found, noise_deg=measurement_noise(floor, sheet.daq, found))
    daq = twin.tables().daq
    assert daq["adc_bits"] == 8
    assert daq["noise_theta"] == pytest.approx(0.002, rel=1e-12)
    assert daq["noise_alpha"] == pytest.approx(0.002, rel=1e-12)


def test_the_bands_of_a_twin_with_the_adc_found_hold_the_rig_through_that_adc():
    """The blind rig read through an 8-bit ADC, under its LQR (the loop hunts on the lattice): 20 runs of the rig,
    each with noise of its own seed, against the bands of a twin with the ADC found and the noise under the lattice
    (no parameter spread: the noise alone). Every run's overshoot and ringing lie inside; a twin that took the floor
    with the lattice's share (and adds the lattice again) puts its ringing band above all 20 and its overshoot on
    another point of the lattice."""
    spec = specmod.load("blind_closed")
    rig = twin_of_spec(specmod.load("blind_closed", ["daq.adc_bits=8"]))
    sheet = dataclasses.replace(twin_of_spec(spec), spread=Spread(), overrides={"daq.adc_bits": 8.0})
    ctl = controller_table(spec.raw["controller"])
    ref = reference_from("square:f=0.25;amplitude=30;duration=4", spec.sample_rate)
    f = build_all()
    with Rig(f["flexjoint"], f["daq"], f["controller"]) as sim:
        runs = [simulate_loop(sim, rig.tables(seed=1000 + k), ctl, ref.ref_deg, ref.Ts, 0.0) for k in range(20)]
    true = [pooled(ref.t, ref.ref_deg, r["theta"], r["alpha"], r["u"], 5.0, 0.0) for r in runs]
    floor = _under_a_lattice(spec.daq, 8)
    twin = dataclasses.replace(sheet, noise_deg=measurement_noise(floor, sheet.daq, sheet.overrides))
    assert twin.noise_deg == pytest.approx(rig.noise_deg, rel=1e-12)
    bands = predict(twin, ctl, ref, n=60, seed=2, workers=1).metric_bands()
    for m in ("overshoot_pct", "ring_alpha_deg", "peak_alpha_deg", "stop_error_deg"):
        assert sum(bands[m].lo <= t[m] <= bands[m].hi for t in true) == 20, m
    twice = dataclasses.replace(sheet, noise_deg={"theta": floor.theta_deg, "alpha": floor.alpha_deg})
    wrong = predict(twice, ctl, ref, n=60, seed=2, workers=1).metric_bands()
    assert wrong["ring_alpha_deg"].lo > max(t["ring_alpha_deg"] for t in true)
    assert sum(wrong["overshoot_pct"].lo <= t["overshoot_pct"] <= wrong["overshoot_pct"].hi for t in true) == 0


def test_a_rig_object_gives_its_overrides_and_covariance():
    """diagnosis.json's ``rig`` (harness.diagnosis.result.RigFit): its overrides as they are, its covariance in the
    fit's coordinates, a row's fold spread added to its variance."""
    cov = [[0.01, 0.008], [0.008, 0.01]]
    doc = {"rig": {"overrides": {"rig.drive_gain": 2.0, "rig.drive_tau": 0.05, "plant.Ks": 1.4},
                   "names": ["rig.drive_gain", "rig.drive_tau"], "log": [True, True], "covariance": cov},
           "parameters": {"rig.drive_tau": {"fitted": 0.05, "ci95": [0.04, 0.06],
                                            "folds": [[0.045, 0.04, 0.05], [0.055, 0.05, 0.06]]}}}  # fmt: skip
    over, sp = spread_of_diagnosis(doc)
    assert over == {"rig.drive_gain": 2.0, "rig.drive_tau": 0.05, "plant.Ks": 1.4}
    assert sp.names == ("rig.drive_gain", "rig.drive_tau") and sp.cov[0][1] == 0.008
    assert sp.cov[1][1] == pytest.approx(0.01 + np.var(np.log([0.045, 0.055])))
    twin = dataclasses.replace(twin_of_spec(specmod.load("nominal")), overrides=over, spread=sp)
    z = np.log([[d["rig.drive_gain"], d["rig.drive_tau"]] for d in draw(twin, 3000, 0)])
    want = 0.008 / math.sqrt(0.01 * sp.cov[1][1])
    assert np.corrcoef(z.T)[0, 1] == pytest.approx(want, abs=0.05)


def test_specs_and_their_judgement():
    s = LoopSpecs.parse("settling=1.5,overshoot=5,alpha=15,voltage=5,stop=1,band=4")
    assert s.band_pct == 4.0 and s.limits["peak_u_v"] == 5.0 and s.limits["stop_error_deg"] == 1.0
    bands = {"settling_s": MetricBand(1.0, 0.8, 1.6), "overshoot_pct": MetricBand(1, 0, 2),
             "peak_alpha_deg": MetricBand(9, 8, 10), "peak_u_v": MetricBand(4, 3, 4.9),
             "stop_error_deg": MetricBand(0.2, -1.2, 0.5)}  # fmt: skip
    j = judge_specs(bands, s)
    assert {m for m, v in j.items() if not v["met"]} == {"settling_s", "stop_error_deg"}
    assert j["stop_error_deg"]["predicted"] == 1.2  # a stopping error's magnitude
    for bad, why in [("settling=-1", "must be a number > 0"), ("speed=3", "'speed' is not a spec"),
                     ("settling=fast", "is not a number")]:  # fmt: skip
        with pytest.raises(ValueError, match=why):
            LoopSpecs.parse(bad)


def test_references():
    r = reference_from("square:f=0.25;amplitude=30;duration=8", 1000.0)
    assert r.ref_deg.size == 8000 and set(np.unique(r.ref_deg)) == {-30.0, 30.0} and r.initial_deg == 0.0
    for bad, why in [("square:f=0.25;amplitude=30", "give its duration"), ("sine:f=1;duration=2", "KIND one of"),
                     ("square:f=x;duration=2", "is not a number")]:  # fmt: skip
        with pytest.raises(ValueError, match=why):
            reference_from(bad, 500.0)


def flexjoint(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "harness.cli", *args], capture_output=True, text=True, timeout=300)


def test_bad_input_is_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "p"
    cases = [
        (["predict", "nominal", "--controller", "state_feedback:K=1,2", "--out", str(out)], "4 gains"),
        (["predict", "nominal", "--controller", "lqr:K=1,2,3,4", "--out", str(out)], "KIND one of"),
        (["predict", str(tmp_path), "--controller", "pid:kp=1", "--out", str(out)], "no closed-loop model"),
        (["predict", "nominal", "--out", str(out)], "no controller"),
        (["predict", "nominal", "--controller", "pid:kp=1", "--specs", "settling=0", "--out", str(out)], "> 0"),
        (["predict", "no_such_spec", "--controller", "pid:kp=1", "--out", str(out)], "no_such_spec"),
        (["design", str(tmp_path), "--method", "lqr", "--out", str(out)], "no closed-loop model"),
    ]
    for args, why in cases:
        r = flexjoint(*args)
        assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, (args, r.stderr)
        assert why in r.stderr, (args, r.stderr)
        assert not out.exists()


def test_which_option_gives_the_controller():
    """--controller first, then --controller-from, then the record's own; both of the first two, or none of the
    three, is one line."""
    from harness.loopspecs import controller_source

    assert controller_source("pid:kp=1", None, True) == "controller"
    assert controller_source(None, "design", True) == "controller_from"
    assert controller_source(None, None, True) == "record"
    with pytest.raises(ValueError, match="not both"):
        controller_source("pid:kp=1", "design", False)
    with pytest.raises(ValueError, match="no controller: give --controller"):
        controller_source(None, None, False)


def test_the_members_draw_the_process_noise_the_engine_found(lab, tmp_path):
    """A twin without spread or measurement noise but with the likelihood engine's white torques (the best model's,
    read from ``likelihood.json`` by process_noise): its members differ (the theta band is open, by more than 0.01
    deg somewhere), each member's plant its own noise seed, the DAQ's; without them every member is the one loop."""
    from harness.twin import process_noise

    (tmp_path / "likelihood.json").write_text(json.dumps({
        "parameters": {"noise.hub_torque": {"fitted": 0.05}, "noise.link_torque": {"fitted": 0.0}},
        "final": {"noise": {"noise.hub_torque": 0.004, "noise.link_torque": 0.0005}}}))  # fmt: skip
    found = process_noise(tmp_path)
    assert found == {"hub_torque_noise": 0.004, "tip_torque_noise": 0.0005}
    assert process_noise(tmp_path / "nothing") == {}
    quiet = dataclasses.replace(lab, spread=Spread(), noise_deg={"theta": 0.0, "alpha": 0.0})
    noisy = dataclasses.replace(quiet, process=found)
    tables = noisy.tables(seed=7)
    assert tables.plant["hub_torque_noise"] == 0.004 and tables.plant["noise_seed"] == tables.daq["seed"] == 7
    assert "hub_torque_noise" not in noisy.tables(seed=7, noise=False).plant
    ref = reference_from("square:f=0.5;amplitude=20;duration=2", 500.0)
    lo, _, hi = predict(noisy, LQR, ref, n=6, seed=3, workers=1).bands["theta"]
    assert np.max(hi - lo) > 0.01
    lo, _, hi = predict(quiet, LQR, ref, n=6, seed=3, workers=1).bands["theta"]
    np.testing.assert_array_equal(lo, hi)
