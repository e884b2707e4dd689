"""Campaigns on the rig twin: run layout, byte-for-byte reproducibility, overrides, and the lab's calibration
numbers recovered from the twin's own calibration experiments."""

import json
import shutil

import numpy as np
import pytest

from harness import spec as specmod
from harness.fmu.plant import PlantParams, dead_zone_voltage
from harness.pipeline import calibrate_run
from harness.rig.campaign import run_campaign, simulate_spec
from harness.rundir import load_run, read_dataset


@pytest.fixture(scope="module")
def lab_run(tmp_path_factory, lab_campaign):
    """A copy of the session's lab campaign (calibrate_run writes into it)."""
    out = tmp_path_factory.mktemp("lab") / "run"
    shutil.copytree(lab_campaign, out)
    return out


def test_run_directory_layout_and_manifest(lab_run):
    m = json.loads((lab_run / "manifest.json").read_text())
    spec = specmod.load("lab")
    assert m["spec_sha256"] == spec.sha256() and m["seed"] == 1
    assert set(m["fmus"]) == {"flexjoint", "daq"} and all(len(v["sha256"]) == 64 for v in m["fmus"].values())
    assert {"numpy", "fmpy", "harness"} <= set(m["versions"])
    names = [e["name"] for e in m["experiments"]]
    assert names == [e.name for e in spec.all_experiments()]
    data = load_run(lab_run)
    assert len(data) == 9
    for df in data.values():
        assert list(df.columns) == ["t", "u", "theta_v", "alpha_v", "theta", "alpha"]
        assert len(df) == 3000 and df["t"].iloc[1] == pytest.approx(0.02)
    # 12-bit ADC over +-10 V: every measured voltage sits on the LSB lattice
    lsb = 20.0 / 2**12
    v = data["prbs_b010"]["theta_v"].to_numpy()
    np.testing.assert_allclose(v / lsb, np.round(v / lsb), atol=1e-9)


def test_same_spec_gives_the_same_bytes(tmp_path, fmus):
    spec = specmod.load("lab")
    short = specmod.from_dict({**spec.raw, "calibration": [], "experiment": spec.raw["experiment"][:2]}, spec.path)
    a, b = tmp_path / "a", tmp_path / "b"
    run_campaign(short, a, fmus=fmus, workers=1)
    run_campaign(short, b, fmus=fmus, workers=2)  # process pool must not change a byte
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f


def test_override_changes_the_rig(fmus):
    base = specmod.load("lab")
    exp = [base.experiment("square_040")]
    ref = simulate_spec(base, fmus, exp, workers=1)["square_040"]
    sat = simulate_spec(specmod.load("lab", ["plant.amp_limit=1.0"]), fmus, exp, workers=1)["square_040"]
    # a 1 V amplifier limit on a 1.5 V square: the shaft covers clearly less angle
    travel = lambda d: np.ptp(d["theta"])  # noqa: E731
    assert travel(sat) < 0.8 * travel(ref)


def test_lab_calibration_recovers_the_twin_within_one_percent(lab_run):
    cal = calibrate_run(lab_run)
    spec = specmod.load("lab")
    true_kp, true_ke = 35.5145, -3.3636  # the daq FMU's pot_gain and gauge_gain (spec leaves the defaults)
    true_dz = dead_zone_voltage(PlantParams(coulomb_torque=spec.plant["coulomb_torque"]))
    assert cal.Kp == pytest.approx(true_kp, rel=0.01)
    assert cal.Ke == pytest.approx(true_ke, rel=0.01)
    assert cal.dead_zone_v == pytest.approx(true_dz, rel=0.01)
    # the seed's span formula over-reads Kp because of the pot's 8 deg dead band: 360/352
    assert cal.source["Kp"]["Kp_span_formula"] == pytest.approx(true_kp * 360 / 352, rel=0.003)
    assert json.loads((lab_run / "calibration.json").read_text())["Kp"] == cal.Kp


def test_comb_on_the_twin_reads_the_comb_angles(lab_run):
    df = read_dataset(lab_run / "data" / "comb.parquet")
    held = np.isfinite(df["comb_angle"].to_numpy())
    # hub clamped: the shaft does not move, and the settled true deflection equals the comb angle
    assert np.ptp(df["theta"]) == 0.0
    settled = held & np.r_[False, np.diff(held.astype(int)) == 0]
    err = (df["alpha"] - df["comb_angle"])[settled]
    assert np.max(np.abs(err)) < 0.05 * np.max(np.abs(df["comb_angle"]))
