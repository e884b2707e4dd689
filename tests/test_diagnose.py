"""The diagnoser on short runs of the blind campaign with known hidden effects: on our twin, on our twin with its
linear parameters off the datasheet (the rows of the manual's off-datasheet table), and on rigs of an independent
simulator (tests/indeprig.py: no FMU, other friction, backlash and link models); and its building blocks checked against
independent constructions (ADC lattice, noise estimate, gauge calibration, folds, dead-band mask, candidate
rules)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from indeprig import IndepRig, make_run

from harness.diagnosis import blindtest as bt
from harness.diagnosis import diagnose as dg
from harness.diagnosis.blindtest import campaign_spec
from harness.diagnosis.effects import EFFECTS, VERDICTS, CandidateContext, candidates
from harness.diagnosis.experiments import RigExperiment, pot_track_ends, split_folds, valid_samples
from harness.diagnosis.noise import adc_lattice, decimal_resolution, noise_sigma
from harness.diagnosis.result import Diagnosis
from harness.diagnosis.rigmodel import combos
from harness.diagnosis.search import POLICY, against_record
from harness.ident.calibration import daq_calibration, gauge_volts
from harness.rig.campaign import run_campaign
from harness.rundir import DataError, Manifest, read_dataset, write_dataset

# On a rig whose truth the twin contains (the blind campaign's twin with its parameters set), the diagnoser recovers
# effects and Ks, Beq to about 0.05 % (the calibration's own error, Ke -0.016 %, is most of it): a rework that loses
# this precision must fail here, not pass inside a 20-25 % tolerance.
TWIN_REL = 1e-3


def _widen(ci: tuple[float, float], factor: float) -> tuple[float, float]:
    """An interval's half-width scaled by ``factor`` about its middle (95 % -> 99 %: 2.576 / 1.96)."""
    mid, half = 0.5 * (ci[0] + ci[1]), 0.5 * (ci[1] - ci[0])
    return mid - factor * half, mid + factor * half


def _run(tmp: Path, name: str, sets: list[str]) -> Path:
    dest = tmp / name
    run_campaign(campaign_spec(quick=True, overrides=sets), dest, workers=1)
    return dest


@pytest.fixture(scope="module")
def runs(tmp_path_factory, fmus):
    tmp = tmp_path_factory.mktemp("diag")
    return {
        "coulomb": _run(tmp, "coulomb", ["plant.coulomb_torque=0.05", "campaign.seed=11"]),
        "none": _run(tmp, "none", ["campaign.seed=12"]),
    }


@pytest.fixture(scope="module")
def coulomb_diag(runs, tmp_path_factory):
    out = tmp_path_factory.mktemp("diag_out1")
    return dg.diagnose_run(runs["coulomb"], campaign_spec(quick=True), out, workers=2), out


@pytest.mark.xdist_group("coulomb_diag")  # one process diagnoses the module's friction rig
def test_coulomb_friction_named_and_fitted(coulomb_diag):
    d, out = coulomb_diag
    assert d.verdict == "coulomb_friction"
    # the twin contains the truth: the friction level and the linear parameters come back to the data's noise
    # (measured: 0.04999, Ks -0.01 %, Beq +0.14 %), and the 95 % interval of the effect covers the truth
    fitted = d.effects[0].params["plant.coulomb_torque"]
    assert fitted == pytest.approx(0.05, rel=TWIN_REL)
    lo, hi = d.parameters["plant.coulomb_torque"].ci95
    assert lo <= 0.05 <= hi and hi - lo < 0.01 * 0.05
    assert d.parameters["plant.Ks"].fitted == pytest.approx(1.3, rel=TWIN_REL)
    assert d.parameters["plant.Beq"].fitted == pytest.approx(0.004, rel=3 * TWIN_REL)
    # the twin's gauge reads the link without an offset: each open-loop record's zero, as its least squares took it
    # in the final replay, is the data's (a record that never rests reads a swing at its quietest: -0.86 deg)
    for name, sensors in d.sensors.items():
        assert sensors.gauge_offset_deg[0] == pytest.approx(0.0, abs=0.01), name
    # the gap shrinks on held-out experiments to near the noise floor
    assert d.gap.shrink_pct > 80.0
    assert d.gap.held_out.gap_after < 3.0 * d.noise_floor.gap
    # candidates ranked by held-out share, friction first; every candidate tried has fitted parameters
    cands = Diagnosis.load(out).candidates
    shares = [c.held_out_share_pct for c in cands if c.tried]
    assert shares == sorted(shares, reverse=True) and all(c.params for c in cands if c.tried)
    assert {c.effect: c.note for c in cands if not c.tried} == {"quantization": "no ADC lattice in the data"}
    assert d.candidates[0].effect == "coulomb_friction"
    assert {c.effect for c in d.candidates} >= {"backlash", "saturation", "delay", "gauge_nonlinearity"}
    assert (out / "diagnosis.json").exists()


@pytest.mark.xdist_group("coulomb_diag")  # one process diagnoses the module's friction rig
def test_diagnosis_json_is_byte_stable(coulomb_diag, runs, tmp_path):
    _, out = coulomb_diag
    dg.diagnose_run(runs["coulomb"], campaign_spec(quick=True), tmp_path, workers=1)
    assert (tmp_path / "diagnosis.json").read_bytes() == (out / "diagnosis.json").read_bytes()


@pytest.mark.xdist_group("coulomb_diag")  # one process diagnoses the module's friction rig
def test_diagnosis_json_round_trips_through_its_dataclasses(coulomb_diag, tmp_path):
    d, out = coulomb_diag
    diag = Diagnosis.load(out)
    diag.write(tmp_path / "again.json")
    assert (tmp_path / "again.json").read_bytes() == (out / "diagnosis.json").read_bytes()
    d.write(tmp_path / "returned.json")  # diagnose_run returns what the file holds
    assert (tmp_path / "returned.json").read_bytes() == (out / "diagnosis.json").read_bytes()
    assert diag.verdict == diag.effect_names[0] == "coulomb_friction"
    assert diag.fitted_effect_params() == d.effects[0].params
    assert diag.importance_pct() == {"coulomb_friction": pytest.approx(100.0)}
    assert diag.waterfall()[-1][1] == diag.gap.held_out.gap_after


def test_none_rig_gives_none(runs, tmp_path):
    d = dg.diagnose_run(runs["none"], campaign_spec(quick=True), tmp_path, workers=1)
    assert d.verdict == "none"
    assert d.effects == []
    # the gap is the noise: within the replays' own spread, and within 1.5x the gap a right model leaves
    dec = d.gap.decomposition
    assert dec.within_noise and dec.after_recalibration <= 1.5 * dec.noise_floor
    # the estimated noise matches the rig's: 0.002 V rms on both sensors, through Kp and Ke
    assert d.noise_floor.theta_deg == pytest.approx(0.002 * 35.5145, rel=0.15)
    assert d.noise_floor.alpha_deg == pytest.approx(0.002 * 3.3636, rel=0.15)


def _exp(name: str, theta_v: np.ndarray, alpha_v: np.ndarray, kind: str = "prbs", period: int = 0) -> RigExperiment:
    n = theta_v.size
    th, al = 35.5145 * theta_v, -3.3636 * alpha_v
    u = np.sin(np.arange(n) * 2 * np.pi / period) if period else np.random.default_rng(0).choice([-1.0, 1.0], n)
    return RigExperiment(
        name=name,
        kind=kind,
        Ts=0.02,
        t=np.arange(n) * 0.02,
        u=u,
        theta=th,
        alpha=al,
        theta_v=theta_v,
        alpha_v=alpha_v,
        period=period,
    )


def test_adc_lattice_finds_the_bits():
    rng = np.random.default_rng(1)
    v = rng.uniform(-4, 4, 2000)
    for bits in (8, 10, 12, 14):
        lsb = 20.0 / 2**bits
        q = np.round(v / lsb) * lsb
        assert adc_lattice({"a": _exp("a", q, q[::-1].copy())}, 10.0) == bits
    assert adc_lattice({"a": _exp("a", v, v)}, 10.0) == 0


def test_noise_sigma_period_to_period():
    rng = np.random.default_rng(2)
    P, M = 200, 8
    base = np.sin(np.arange(P) * 2 * np.pi / P * 3)
    clean = np.tile(base, M)
    drift = np.linspace(0.0, 2.0, P * M)  # a drift of theta must not count as noise
    s_v = 0.003
    tv = clean + drift + s_v * rng.standard_normal(P * M)
    av = 0.5 * clean + s_v * rng.standard_normal(P * M)
    sig = noise_sigma({"m": _exp("m", tv, av, kind="multisine", period=P)})
    assert sig["method"] == "period-to-period"
    assert sig["theta_deg"] == pytest.approx(s_v * 35.5145, rel=0.08)
    assert sig["alpha_deg"] == pytest.approx(s_v * 3.3636, rel=0.08)


def test_sim_gauge_calibration_matches_a_least_squares_line():
    ang = np.array([-5.3, -3.4, -1.6, 0.0, 2.0, 3.8, 5.6, 7.4])
    cal = daq_calibration(35.5, 0.02, -3.3636, 0.01, 0.08, ang)
    v = 0.01 + ang / -3.3636 * (1 + 0.08 * (ang / 10) ** 2)  # the zero error outside the nonlinearity
    assert gauge_volts(ang, -3.3636, 0.01, 0.08) == pytest.approx(v, rel=1e-15)
    slope, icpt = np.polyfit(v, ang, 1)
    assert cal.Ke == pytest.approx(slope, rel=1e-12)
    assert cal.gauge_offset_v == pytest.approx(-icpt / slope, rel=1e-9)
    assert (cal.Kp, cal.pot_offset_v) == (35.5, 0.02)
    linear = daq_calibration(35.5, 0.02, -3.3636, 0.01, 0.0, ang)
    assert (linear.Ke, linear.gauge_offset_v) == (-3.3636, 0.01)
    assert daq_calibration(35.5, 0.0, -3.3636, 0.01, 0.08, None).Ke == -3.3636  # no comb: the gauge's own gain


def test_split_spans_kinds_and_levels():
    rng = np.random.default_rng(3)
    trials = {}
    for kind, amps in (("prbs", (1.0, 3.0)), ("square", (1.0, 2.5)), ("chirp", (1.5,)), ("multisine", (3.1,))):
        for a in amps:
            name = f"{kind}_{a}"
            tr = _exp(name, rng.standard_normal(100), rng.standard_normal(100), kind=kind)
            tr.u = a * np.sign(rng.standard_normal(100))
            trials[name] = tr
    a, b = split_folds(trials)
    assert sorted(a + b) == sorted(trials) and not set(a) & set(b)
    for kind in ("prbs", "square"):  # both levels of a kind never land in the same fold
        assert sum(n.startswith(kind) for n in a) == 1
    one = {"x": trials["chirp_1.5"]}
    assert split_folds(one) == (["x"], ["x"])


def test_bad_input_is_one_line(tmp_path, runs):
    with pytest.raises(ValueError, match="not a run directory") as err:
        dg.diagnose_run(tmp_path)
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="not found") as err:
        dg.diagnose_run(runs["none"], sim="no_such_spec_xyz", out=tmp_path)
    assert "\n" not in str(err.value)


def test_effect_names_are_the_interface():
    assert set(VERDICTS) == {
        "coulomb_friction",
        "backlash",
        "saturation",
        "second_mode",
        "delay",
        "quantization",
        "gauge_nonlinearity",
        "none",
        "unexplained",
    }
    assert {e.param for e in EFFECTS.values()} == {
        "plant.coulomb_torque",
        "plant.backlash",
        "plant.amp_limit",
        "plant.n_modes",
        "daq.delay_samples",
        "daq.adc_bits",
        "daq.gauge_cubic",
    }


# the manual's off-datasheet table on the quick blind campaign: a real rig's linear mismatch (stiffer link, more
# damping) plus one effect; each verdict names the effect (or none) and the linear parameters come back as findings
MISMATCH = ["plant.Ks=1.5", "plant.Beq=0.0052", "plant.zeta_link=0.02"]


@pytest.mark.parametrize(
    ("name", "sets", "verdict", "param", "value"),
    [
        ("nothing", [], "none", None, None),
        ("backlash", ["plant.backlash=0.006"], "backlash", "plant.backlash", 0.006),
        ("coulomb", ["plant.coulomb_torque=0.03"], "coulomb_friction", "plant.coulomb_torque", 0.03),
        ("delay", ["daq.delay_samples=2"], "delay", "daq.delay_samples", 2),
    ],
)
def test_mismatched_twin_recalibrates_then_names_the_effect(tmp_path, fmus, name, sets, verdict, param, value):
    run = _run(tmp_path, name, [*MISMATCH, *sets, "campaign.seed=21"])
    d = dg.diagnose_run(run, campaign_spec(quick=True), tmp_path / "out", workers=1)
    assert d.verdict == verdict
    found = d.fitted_effect_params()
    assert set(found) == ({param} if param else set())  # no spurious effect tags along
    if param:
        # the truth, to the data's noise (measured: backlash +0.13 %, Coulomb +0.004 %), inside its 95 % interval
        assert found[param] == pytest.approx(value, rel=2 * TWIN_REL if isinstance(value, float) else 0)
        if isinstance(value, float):
            lo, hi = d.parameters[param].ci95
            assert lo <= value <= hi
        # drop-one importance is a share of what the removals reopen: a lone effect has all of it
        assert d.effects[0].importance_pct == pytest.approx(100.0)
        if param == "daq.delay_samples":  # said against the record: the blind campaign runs at 50 Hz
            assert d.effects[0].against_record == "2 sample(s) of command delay: 40 ms at 50 Hz"
    truth = {"plant.Ks": 1.5, "plant.Beq": 0.0052, "plant.zeta_link": 0.02, "plant.Jeq": 0.00208, "plant.kt": 0.00768}
    for name_, value_ in truth.items():  # measured: Ks +0.02 %, Beq +0.05 %, Jeq +0.05 %, kt +0.04 %, zeta +0.3 %
        rel = 5 * TWIN_REL if name_ == "plant.zeta_link" else TWIN_REL
        assert d.parameters[name_].fitted == pytest.approx(value_, rel=rel), name_
        # its interval, with the calibration's own error in it (Ke -0.015 % moves Ks +0.013 %), holds the truth:
        # checked at 99 % over these 20 intervals (at 95 %, one of them, Coulomb's Ks, misses by 0.002 %)
        lo, hi = _widen(d.parameters[name_].ci95, 2.576 / 1.96)
        assert lo <= value_ <= hi, name_
    ks = d.parameters["plant.Ks"]
    assert ks.change_pct == pytest.approx(100 * (ks.fitted / 1.3 - 1))
    assert ks.ci95[0] <= ks.fitted <= ks.ci95[1]
    assert "higher than the spec" in ks.finding
    dec = d.gap.decomposition
    assert dec.after_effects <= dec.after_recalibration < dec.before
    assert dec.within_noise
    # where: the stiffer link is not read as a pot-wrap problem once the dead band is masked
    for stage in ("before", "after_recalibration"):
        assert "pot wraps" not in d.where[stage]["theta"].get("headline", "")


INDEPENDENT = {
    # name: (rig fields, verdict, effect parameter, truth, its tolerance, Beq tolerance). The simulator's linear rig is
    # the twin's (Ks, Beq come back within 0.03 %); its friction (Stribeck) and backlash (a contact spring that
    # bounces, not the twin's plastic impacts) are not, and bend Beq by 11 % and 6 % (measured, seed 5).
    "none": (dict(Beq=0.007, zeta_link=0.025, motor_gain=0.93), "none", None, None, 0, 1e-3),
    "coulomb": (dict(coulomb_torque=0.04, Beq=0.006), "coulomb_friction", "plant.coulomb_torque", 0.04, 0.06, 0.15),
    "delay": (dict(delay_samples=2, zeta_link=0.02, Jeq=2.3e-3), "delay", "daq.delay_samples", 2, 0, 1e-3),
    "second_mode": (dict(n_modes=2, Beq=0.006), "second_mode", "plant.n_modes", 2, 0, 1e-3),
    "saturation": (dict(amp_limit=1.6, motor_gain=1.08), "saturation", "plant.amp_limit", 1.6, 1e-3, 1e-3),
    "backlash": (dict(backlash=0.005, Beq=0.003), "backlash", "plant.backlash", 0.005, 0.08, 0.10),
}


@pytest.mark.parametrize("name", list(INDEPENDENT))
def test_independent_simulator_rigs(tmp_path, fmus, name):
    fields, verdict, param, truth, tol, beq_tol = INDEPENDENT[name]
    rig = IndepRig.from_Ks(1.45, **fields)
    spec = campaign_spec(quick=True)
    run = make_run(tmp_path / name, spec, rig, seed=5)
    d = dg.diagnose_run(run, spec, tmp_path / "out", workers=1)
    assert d.verdict == verdict
    found = d.fitted_effect_params()
    assert set(found) == ({param} if param else set())
    if param:
        assert found[param] == pytest.approx(truth, rel=tol)
    assert d.parameters["plant.Ks"].fitted == pytest.approx(1.45, rel=0.01)
    assert d.parameters["plant.Beq"].fitted == pytest.approx(rig.Beq, rel=beq_tol)


def test_identical_noise_free_data_is_none(tmp_path, fmus):
    quiet = ["daq.noise_theta=0", "daq.noise_alpha=0"]
    run = _run(tmp_path, "quiet", quiet)
    d = dg.diagnose_run(run, campaign_spec(quick=True, overrides=quiet), tmp_path / "out", workers=1)
    assert d.verdict == "none" and d.effects == []
    assert d.gap.before.fit_pct > 99.9  # the same rig: only calibration rounding separates them


def test_adc_lattice_survives_volts_written_to_six_decimals():
    rng = np.random.default_rng(4)
    v = rng.uniform(-4, 4, 3000)
    for bits in (10, 12, 14):
        lsb = 20.0 / 2**bits
        q = np.round(np.round(v / lsb) * lsb, 6)  # a DAQ's CSV export
        assert decimal_resolution(q) == pytest.approx(1e-6)
        assert adc_lattice({"a": _exp("a", q, q[::-1].copy())}, 10.0) == bits
    r = np.round(v, 6)  # not quantised, only written to 6 decimals
    assert adc_lattice({"a": _exp("a", r, r[::-1].copy())}, 10.0) == 0


def test_pot_dead_band_samples_are_masked():
    reading = np.array([170.0, 174.6, 176.0, 176.0, -176.0, -175.0, -170.0, 0.0])
    ends = pot_track_ends([reading])
    assert ends == (-176.0, 176.0)
    ok = valid_samples(reading, ends, reading / 35.5, 10.0)
    assert ok.tolist() == [True, False, False, False, False, False, True, True]
    assert pot_track_ends([np.array([-90.0, 120.0])]) is None  # the shaft never went round
    clipped = valid_samples(np.zeros(3), None, np.array([0.0, 10.0, -10.0]), 10.0)
    assert clipped.tolist() == [True, False, False]


@pytest.mark.parametrize(
    ("sensor", "nuisance"),
    [({"pot_nonlinearity": 0.015}, {"plant.Ks": 1.15, "plant.Beq": 0.006}), ({"gauge_drift": 0.2}, {})],
)
def test_out_of_library_sensor_errors_are_unexplained(tmp_path, fmus, sensor, nuisance):
    case = {"case": 0, "family": "nuisance" if nuisance else "twin", "kind": "out", "truth_effects": list(sensor),
            "truth_params": {}, "nuisance": nuisance, "sensor": sensor, "campaign_seed": 17}  # fmt: skip
    run = bt.make_rig_run(case, tmp_path / "rig", quick=True)
    d = dg.diagnose_run(run, campaign_spec(quick=True), tmp_path / "out", workers=1)
    assert d.verdict == "unexplained"
    assert d.gap.explained_pct < 100 * POLICY.explained
    if nuisance:  # the linear mismatch is still found under a sensor error
        assert d.parameters["plant.Ks"].fitted == pytest.approx(1.15, rel=0.10)


def test_candidate_rules_of_the_effect_table():
    """Which effects are worth fitting, and with which range, against a simulation and data."""

    def names(cs: list) -> list[str]:
        return [c.name for c in cs]

    plain = candidates(CandidateContext({}, {}, 3.0, 0))
    assert names(plain) == [n for n in EFFECTS if n != "quantization"]  # no lattice in the data
    by = {c.name: c for c in plain}
    assert by["saturation"].hi == 3.0 and by["delay"].values == (1, 2, 3, 4, 5)  # up to the command; not the sim's
    assert by["backlash"] == EFFECTS["backlash"] and by["backlash"].params == {"plant.backlash", "plant.Jm_share"}
    assert candidates(CandidateContext({}, {}, 0.1, 0))[2].hi == 0.2  # at least twice the lower bound
    rich = candidates(CandidateContext({"n_modes": 2}, {"delay_samples": 2}, 3.0, 12))
    by = {c.name: c for c in rich}
    assert "second_mode" not in by and by["delay"].values == (0, 1, 3, 4, 5)
    assert by["quantization"].values == (12,) and by["quantization"].signature
    assert "quantization" not in names(candidates(CandidateContext({}, {"adc_bits": 12}, 3.0, 12)))  # modelled
    assert EFFECTS["quantization"].skipped == "no ADC lattice in the data"
    assert EFFECTS["second_mode"].skipped == "already in the simulation"


def test_an_effect_is_said_against_the_records_own_range():
    """A saturation at 1.0 V on a record whose command spans +-3 V is said with both numbers and the share of the
    record it clips, a delay in milliseconds at the record's rate, a gear play beside how far the hub moves."""
    n = 1000
    x = _exp("sq", np.zeros(n), np.zeros(n))
    x.u = 3.0 * np.sign(np.sin(np.arange(n) * 2 * np.pi / 100)) * np.r_[np.ones(n // 2), np.full(n // 2, 0.5)]
    x.theta = 20.0 * np.sin(np.arange(n) * 2 * np.pi / 500)
    exps = {"sq": x}
    assert against_record("plant.amp_limit", 1.0, exps) == (
        "amplifier limit 1 V; the logged command reaches 3 V, 100 % of its samples beyond the limit"
    )
    assert against_record("plant.amp_limit", 2.0, exps).endswith("3 V, 50 % of its samples beyond the limit")
    assert against_record("daq.delay_samples", 2, exps) == "2 sample(s) of command delay: 40 ms at 50 Hz"
    play = against_record("plant.backlash", 0.006, exps)
    assert play.startswith("gear play 0.344 deg; the hub moves up to 19.") and play.endswith("(95th percentile)")
    assert against_record("plant.coulomb_torque", 0.03, exps) is None


def test_a_wrong_sheet_is_identified_not_walled(tmp_path, fmus):
    """The twin with a sheet off by more than the old search boxes allowed (kt x2.5, Jeq x2, Beq x2, Ks x0.6: the
    drive's time constant 0.55x, the inertia ratio 2x), diagnosed against the sheet: the global search and the
    priors' weight taken at the solution bring every combo back to the twin's precision, and the verdict is none
    (measured: drive gain -0.004 %, time constant -0.03 %, inertia ratio +0.16 %, Ks +0.02 %; each fold alone
    agrees). With kt, Jeq and Beq in boxes of 0.6-1.6x around the sheet, kt sat at its wall."""
    sets = ["plant.kt=0.0192", "plant.Jeq=0.00416", "plant.Ks=0.78", "plant.Beq=0.008", "campaign.seed=21"]
    truth = campaign_spec(quick=True, overrides=sets)
    run = _run(tmp_path, "wrong_sheet", sets)
    d = dg.diagnose_run(run, campaign_spec(quick=True), tmp_path / "out", workers=1)
    want = {**combos(truth.plant), "plant.Ks": 0.78, "plant.Beq": 0.008, "plant.Jeq": 0.00416, "plant.kt": 0.0192}
    for k, v in want.items():
        p = d.parameters[k]
        assert p.fitted == pytest.approx(v, rel=3 * TWIN_REL if k.startswith("rig.drive") else 3e-3), k
        assert not p.at_bound
    for k in ("rig.drive_gain", "rig.drive_tau", "plant.Ks"):
        assert not d.parameters[k].folds_disagree, k
    assert d.verdict == "none"


def test_records_in_which_nothing_moves_are_set_aside(runs, tmp_path):
    """A hub its friction holds under a weak drive: in five of the friction rig's six records the sensors read their
    rest value and noise whatever the command does. Nothing in them moves beyond the noise, so they are set aside
    (a fold of such records alone had nothing to fit: a crash in the least squares), the moving record is cut in
    two, one half per fold, and the friction is found on it."""
    run = tmp_path / "run"
    shutil.copytree(runs["coulomb"], run)
    rng = np.random.default_rng(3)
    names = [e.name for e in Manifest.load(run).experiments if e.role != "calibration"]
    names.insert(0, names.pop(names.index("prbs_large")))  # the one that moves
    for name in names[1:]:
        path = run / "data" / f"{name}.parquet"
        cols = {c: v.to_numpy() for c, v in read_dataset(path).items()}
        for c in ("theta_v", "alpha_v"):
            cols[c] = cols[c][0] + 0.002 * rng.standard_normal(cols[c].size)  # the lab spec's noise [V rms]
        write_dataset(path, cols)
    d = dg.diagnose_run(run, campaign_spec(quick=True), tmp_path / "out", workers=1)
    assert d.caveats and d.caveats[0] == (
        f"set aside, nothing in them moves beyond the noise: {', '.join(names[1:])}; diagnosed on the rest"
    )
    assert {n.split(" (")[0] for n in (*d.folds.A, *d.folds.B)} == {names[0]}
    assert d.verdict == "coulomb_friction"
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.05, rel=0.02)
    path = run / "data" / f"{names[0]}.parquet"  # the last one held too: nothing to diagnose, one line
    cols = {c: v.to_numpy() for c, v in read_dataset(path).items()}
    for c in ("theta_v", "alpha_v"):
        cols[c] = cols[c][0] + 0.002 * rng.standard_normal(cols[c].size)
    write_dataset(path, cols)
    with pytest.raises(DataError, match="^nothing moves beyond its noise in any record"):
        dg.diagnose_run(run, campaign_spec(quick=True), tmp_path / "none", workers=1)
    assert not (tmp_path / "none").exists()
