"""Real closed-loop records nobody here made (tests/fixtures/real/, provenance in its README), imported as recorded
and diagnosed against their own lab sheet (specs/cu_flexible_arm.toml)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from shared_runs import CU, CU_IMPORT, QUANSER, QUANSER_COLUMNS, QUANSER_IMPORT, perturbed_copy

from harness import spec as specmod
from harness.diagnosis.diagnose import diagnose_run
from harness.diagnosis.experiments import load_experiments
from harness.diagnosis.gauge import gauge_delay
from harness.diagnosis.result import Diagnosis
from harness.diagnosis.simulation import fmu_value
from harness.ident.calibration import load_calibration
from harness.rig.controller import command_r2
from harness.rig.records import import_records
from harness.rundir import Manifest


@pytest.fixture(scope="module")
def cu_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cu") / "run"
    notes: list[str] = []
    import_records(CU, out, CU_IMPORT, note=notes.append)
    return out, notes


def test_cu_records_import_closed_loop_with_the_labs_controller(cu_run):
    run, notes = cu_run
    m = Manifest.load(run)
    assert m.sample_rate == 1000.0 and [e.n for e in m.experiments] == [10000, 10000]
    for e in m.experiments:
        c = e.controller
        assert e.loop == "closed" and c["source"] == "identified" and c["kind"] == "state_feedback"
        assert c["r2"] > 0.95 and c["ref_delay"] == 7 and c["cutoff"] == 25.0  # the log leads the command 7 ms
        # the lab logged K1 7.778 V/rad, |K2| 1.667 V/m x 0.45 m, K3 1.333 V s/rad, K4 1.333 V s/m x 0.45 m
        np.testing.assert_allclose(c["K"][:3], [7.778, 0.750, 1.333], rtol=0.15)
        assert -0.6 < c["K"][3] < -0.3  # the tip-rate gain: the log's 0.6 V s/rad, with the record's own filter
        assert -4.5 < c["alpha_bias"] < -3.5  # the gauge read ~4 deg at rest (negated): zeroed, kept for the controller
        assert e.lattice_deg["theta"] == pytest.approx(np.degrees(0.001))  # printed to 0.001 rad
    assert sum("alpha zeroed" in n for n in notes) == 2


def test_cu_lab_sheets_controller_is_the_law_the_records_logged(cu_run):
    """The spec's controller is the lab's law in the harness's convention: the log's deflection is the negated alpha,
    so its K2 (-1.667 V/m) and K4 (1.333 V s/m) enter x L with their signs turned. With the log's signs kept, the law
    explained R^2 0.33 of the logged command."""
    run, _ = cu_run
    sheet = specmod.load("cu_flexible_arm")
    cal = load_calibration(run)
    for x in load_experiments(run, cal, sheet, fmu_value({}, "daq", "adc_range"), "auto").values():
        law = replace(sheet.controller, alpha_bias=x.controller["alpha_bias"])  # the record's gauge zero
        r2 = command_r2(law, np.radians(x.ref), np.radians(x.theta), np.radians(x.alpha), x.u, x.Ts)
        assert r2 > 0.94


def test_cu_records_gauge_reads_59_ms_behind_the_hub(cu_run):
    """alpha from theta through the link: the records' gauge reads 59 ms late on both records (each alone 58-60),
    the link's clamped frequency 1.70 Hz (the sheet says 1.8); the Quanser record's gauge is on time."""
    run, _ = cu_run
    xs = load_experiments(run, load_calibration(run), specmod.load("cu_flexible_arm"), 10.0)
    g = gauge_delay(xs)
    assert g.samples == 59 and g.seconds == 0.059 and g.link_hz == pytest.approx(1.70, abs=0.02)
    assert g.fit_none_pct == pytest.approx(56.0, abs=0.5) and g.fit_pct == pytest.approx(83.1, abs=0.5)
    for name in xs:
        assert 58 <= gauge_delay({name: xs[name]}).samples <= 60


def test_cu_records_diagnosed_against_their_lab_sheet(cu_run):
    """Closed-loop replay through the identified controller, the gauge read 59 ms late as the records show, each
    record's gauge offset and the command offset fitted, the rig identified in what the data determine under the lab
    sheet's priors: held-out fit 66.0 % as given -> 86.6 % recalibrated, alpha 52.2 -> 81.9 %, nothing held by a
    wall (before the sensors were fitted: 64.3 -> 83.6 %, alpha 77.7 %). Then a drive limit of 0.78 V (the logged
    command reaches 5.53 V) closes half the score left: 90.4 %, alpha 86.8 % (81.1 % before), and with it the hub's
    inertia and the drive's time constant return to the sheet's (Jeq 0.00217 kg m^2, the sheet 0.002). Each record
    fitted alone with it agrees with the other within their intervals on every parameter, and theta's gain is the
    sheet's."""
    from harness.cli import diagnosis_summary
    from harness.render.gap_text import diagnosis_markdown

    run, _ = cu_run
    d = diagnose_run(run, "cu_flexible_arm", workers=1)
    assert {r["replay"] for r in d.replays.values()} == {"closed"}
    assert d.folds.A != d.folds.B
    assert d.calibration.gauge_delay_s == 0.059
    said = "the gauge reads 59 ms (59 samples) behind the hub angle: alpha from theta through a 1.7 Hz link fits"
    summary = diagnosis_summary(d)
    assert f"  data: {said}" in summary
    # the link's damping is not determined: its finding gives its interval, once; the summary shows the five
    # parameters that moved most, the others (this one) in diagnosis.json
    assert "link damping ratio is not determined by these data" in d.parameters["plant.zeta_link"].finding
    assert "plant.zeta_link" not in summary and "  and 7 more (see diagnosis.json)" in summary
    assert all(line.count("95 % interval") <= 1 for line in summary.splitlines())
    assert "sensors, each record's gauge offset: flexibleArm_test_3 " in summary
    assert "behaviour, each record's step metrics inside the replays' 95 % band: flexibleArm_test_3 " in summary
    paragraphs = "\n".join(diagnosis_markdown(d)).replace("\n\n", "\0").replace("\n", " ").split("\0")  # lines joined
    assert any(p.startswith(f"Gauge timing (every replay reads it so): {said}") for p in paragraphs)
    dec = d.gap.decomposition
    assert 100 * (1 - dec.before) < 67.0 and 100 * (1 - dec.after_recalibration) > 86.0
    assert dec.channels["after_recalibration"]["alpha"] > 81.0
    assert d.noise_floor.fit_pct < 100.0  # the records' 0.001 steps are in the floor
    assert not [k for k, p in d.parameters.items() if p.at_bound]
    assert not [k for k, p in d.parameters.items() if p.folds_disagree]
    for fitted, lo, hi in d.parameters["plant.Ks"].folds:  # recalibrated alone: 1.63 N m/rad, the sheet 2.24
        assert 1.58 < lo <= fitted <= hi < 1.70
    assert d.parameters["plant.u_offset"].ci95[1] < 0.0  # a command offset of -0.05 V, its interval short of 0
    # the drive's limit, against the record's own range; the rig it leaves is the sheet's
    (sat,) = d.effects
    assert sat.effect == "saturation" and 0.7 < sat.params["plant.amp_limit"] < 0.9
    assert "the logged command reaches 5.53 V" in sat.against_record
    assert 100 * (1 - dec.after_effects) >= 89.0 and dec.channels["after_effects"]["alpha"] >= 85.0
    assert dec.gap_channel() == "alpha" and d.verdict in ("unexplained", "saturation")  # it closes half the score
    assert 45.0 < d.gap.explained_pct < 55.0
    assert d.parameters["plant.Jeq"].fitted == pytest.approx(0.002, rel=0.2)
    assert d.parameters["rig.drive_tau"].fitted == pytest.approx(d.parameters["rig.drive_tau"].nominal, rel=0.2)
    assert d.parameters["plant.Ks"].fitted == pytest.approx(2.09, rel=0.03)
    assert {k for k, p in d.parameters.items() if p.records} >= {"rig.drive_gain", "plant.Ks", "sensor.theta_gain"}
    assert not [k for k, p in d.parameters.items() if p.records_apart] and not d.caveats
    assert d.parameters["sensor.theta_gain"].fitted == pytest.approx(1.0, abs=0.01)
    header = "| each record alone (flexibleArm_test_3 / flexibleArm_test_4) |"
    assert any(line.startswith("| parameter |") and line.endswith(header) for line in diagnosis_markdown(d))


def _quanser_halves(tmp: Path) -> list[Path]:
    """The Quanser record cut at 2.5 s into two files, each with its reference (as a lab saves two runs)."""
    rec = pd.read_csv(QUANSER[0], dtype=str).merge(pd.read_csv(QUANSER[1], dtype=str), on="t")
    n = len(rec) // 2
    out = [tmp / "first.csv", tmp / "second.csv"]
    for path, part in zip(out, (rec.iloc[:n], rec.iloc[n:]), strict=True):
        part.to_csv(path, index=False)
    return out


def test_quanser_record_diagnosed_against_the_datasheet(quanser_run):
    """The manual's Quanser figures, on the record itself: closed-loop replay through the identified LQR (R^2
    0.980), held-out fit 85.0 % as given -> 90.6 % recalibrated (the rig identified in its combos under the
    datasheet's priors, the gauge's offset and the command offset with it, without derivatives: the controller acts
    on the encoder's counts; 91.3 % before those were fitted, from one grid start) -> 93.6 % with the effects, Ks
    above the datasheet's 1.3, no linear parameter at a bound; the
    encoder's and the gauge's lattices (0.0879, 0.00848 deg) found from the values and in the noise floor."""
    (e,) = Manifest.load(quanser_run).experiments
    assert e.controller["r2"] == pytest.approx(0.980, abs=0.005) and e.loop == "closed"
    assert e.lattice_deg["theta"] == 360.0 / 4096
    assert e.lattice_deg["alpha"] == pytest.approx(0.008478, rel=1e-3)
    d = Diagnosis.load(quanser_run)
    dec = d.gap.decomposition
    assert 100 * (1 - dec.before) == pytest.approx(85.0, abs=0.1)
    assert 100 * (1 - dec.after_recalibration) >= 90.0 and 100 * (1 - dec.after_effects) >= 91.0
    assert 1.04 <= d.parameters["plant.Ks"].fitted <= 1.7
    assert not [k for k, p in d.parameters.items() if p.at_bound]
    assert 99.0 < d.noise_floor.fit_pct < 99.2
    # per channel: theta fits as given, alpha holds the gap (measured 93.5 / 79.8 % -> 96.5 / 88.2 %)
    by = dec.channels
    assert by["before"]["theta"] > 93.0 and by["before"]["alpha"] < 81.0 and dec.gap_channel() == "alpha"
    for stage, gap in (("before", dec.before), ("after_recalibration", dec.after_recalibration)):
        # both channels move in both halves: the pooled mean squared gap is the channels' mean
        pooled = np.mean([(1 - by[stage][c] / 100) ** 2 for c in ("theta", "alpha")])
        assert pooled == pytest.approx(gap**2, rel=1e-6)


@pytest.mark.parametrize("draw", [1, 3])
def test_the_quanser_record_perturbed_at_1e_12_gives_the_same_verdict(quanser_run, tmp_path, draw):
    """The Quanser record's last digits changed as another CPU's rounding changes them: the same verdict and
    effects, and the drive gain inside the first fit's 95 % interval (with numpy's AVX-512 loops, draw 3 added a
    friction and its drive gain fell outside; with the numerics pinned it holds)."""
    first = Diagnosis.load(quanser_run)
    run = perturbed_copy(quanser_run, tmp_path / "run", draw)
    again = diagnose_run(run, "nominal", tmp_path / "again", workers=1, force=True)
    assert again.verdict == first.verdict and sorted(again.effect_names) == sorted(first.effect_names)
    lo, hi = first.parameters["rig.drive_gain"].ci95
    assert lo <= again.parameters["rig.drive_gain"].fitted <= hi


@pytest.fixture(scope="module")
def quanser_halves(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("halves")
    halves = replace(QUANSER_IMPORT, columns={"t": "t", **QUANSER_COLUMNS})
    import_records(_quanser_halves(tmp), tmp / "run", halves)
    return diagnose_run(tmp / "run", "nominal", tmp / "diag", workers=1)


@pytest.mark.xdist_group("quanser_halves")  # one process diagnoses the halves
def test_the_quanser_halves_each_fitted_alone_are_one_rig(quanser_halves):
    """The second half starts mid-motion; its replay starts from its measured state, the hub's and the link's rates
    from the widest cubic that still fits (noise averages out; a 20 ms one read the hub's rate off by more than the
    rig's own). Each half recalibrated alone, on its fold's fit window or on its whole length, fitted without
    derivatives (its controller acts on the encoder's counts, a staircase in the parameters): drive gain 1.609 and
    1.636 rad/(V s), within each other's intervals on every parameter (by least squares they came out apart on the
    drive, Ks and the gauge gain): one rig, and no caveat says otherwise."""
    d = quanser_halves
    gain = d.parameters["rig.drive_gain"]
    (a, lo_a, hi_a), (b, lo_b, hi_b) = gain.records.values()
    assert lo_a <= b <= hi_a and lo_b <= a <= hi_b
    assert not [k for k, p in d.parameters.items() if p.records_apart or p.folds_disagree] and not d.caveats
    assert d.verdict == "unexplained"


@pytest.mark.xdist_group("quanser_halves")  # one process diagnoses the halves
def test_quanser_record_in_two_files_fits_as_the_whole_record(quanser_halves):
    """The record imported as its two halves: the second file starts mid-motion (hub at -2.9 rad/s), and its replay
    starts from its measured state, the controller's velocity filter too (87.5 % from rest); held out 84.8 % as given,
    91.4 % recalibrated (the whole record 85.0 -> 91.3 %), Ks 1.41-1.50 on each half."""
    d = quanser_halves
    dec = d.gap.decomposition
    assert 100 * (1 - dec.before) > 84.0 and 100 * (1 - dec.after_recalibration) >= 91.0
    for fitted, _, _ in d.parameters["plant.Ks"].folds:
        assert 1.04 <= fitted <= 1.56


@pytest.mark.xdist_group("quanser_halves")  # one process diagnoses the halves
@pytest.mark.xfail(
    strict=True,
    reason=(
        "issue 34 open: the halves' folds fit the inertia ratio at 0.508 and 0.473, each half alone at 0.436 and "
        "0.479, but their joint fit (Powell's search on the encoder's staircase, from the folds' combined values) "
        "ends at 0.399, a hub inertia of 0.00152 kg m^2 against the whole record's 0.0020 recalibrated (0.00239 "
        "with its second mode); the search spends its 281 evaluations, and three times as many from its end take the "
        "ratio only to 0.413"
    ),
)
def test_quanser_record_in_two_files_is_the_same_rig(quanser_halves):
    """The two halves' own recalibrations, each also started from the other's, land in one basin (from its own grid
    point alone the second stopped at a drive gain of 1.78 rad/(V s)), and the hub inertia they imply together is
    near the whole record's (0.00216 against 0.00219 kg m^2)."""
    d = quanser_halves
    assert d.parameters["plant.Jeq"].fitted == pytest.approx(0.00219, rel=0.1)  # the whole record's
    assert 100 * (1 - d.gap.decomposition.after_recalibration) >= 91.0
    (a, _, _), (b, _, _) = d.parameters["rig.drive_gain"].folds
    assert max(a, b) < 1.01 * min(a, b)


def test_a_units_records_each_fitted_alone_beside_the_joint_fit(tmp_path):
    """Three records of one unit (test_3 cut in two files, and test_4): each recalibrated alone, from the grid and
    from the joint fit, so its own fit is the joint parameters' on it or better, but for what its priors trade
    (measured 83.9 / 88.7 / 82.70 % alone, 83.9 / 87.7 / 82.71 % jointly); every fitted parameter per record; the
    summary says both."""
    from harness.cli import diagnosis_summary

    lines = CU[0].read_text().splitlines(keepends=True)
    half = (len(lines) + 1) // 2
    files = [tmp_path / "test_3a.txt", tmp_path / "test_3b.txt", CU[1]]
    files[0].write_text("".join(lines[:half]))
    files[1].write_text("".join(lines[:1] + lines[half:]))
    import_records(files, tmp_path / "run", CU_IMPORT)
    d = diagnose_run(tmp_path / "run", "cu_flexible_arm", workers=1)
    names = ["test_3a", "test_3b", "flexibleArm_test_4"]
    assert list(d.gap.records) == names
    for r in d.gap.records.values():
        assert r["own"] >= r["joint"] - 0.05 and r["joint"] > 82.0
    fitted = [k for k, p in d.parameters.items() if p.records]
    assert {"rig.drive_gain", "rig.drive_tau", "plant.Ks", "sensor.alpha_gauge_gain"} <= set(fitted)
    for k in fitted:
        for v, lo, hi in d.parameters[k].records.values():
            assert lo <= v <= hi
    assert "each record's fit, recalibrated alone -> with the joint parameters: test_3a" in " ".join(
        diagnosis_summary(d).split()
    )
    # the second half of test_3 is not one rig with the others: its drive is faster and slower to answer (measured
    # 3.33 [3.03-3.64] rad/(V s) against test_4's 2.61 [2.33-2.92]), and a caveat says so, with the drive limit
    assert ("test_3b", "flexibleArm_test_4") in d.parameters["rig.drive_gain"].records_apart
    (apart,) = [c for c in d.caveats if "exclude each other" in c]
    assert "drive gain" in apart and "the linear model with saturation does not describe" in apart
