"""Closed-loop records imported as they are: the reference as role ref, the controller given or identified (with its
R^2), an encoder theta; and each kind of bad input as one line."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import scipy.io

from harness.diagnosis.blindtest import campaign_spec
from harness.diagnosis.experiments import load_experiments
from harness.fmu.build import build_all
from harness.ident.calibration import load_calibration
from harness.rig.campaign import simulate_spec
from harness.rig.controller import R2_MIN, Controller, identify_controller, law, parse_controller
from harness.rig.records import ImportOptions, import_records, record_files
from harness.rundir import DataError, Manifest, RunDir, read_dataset

K = [9.231, -18.769, 1.203, -0.041]  # specs/blind_closed.toml


@pytest.fixture(scope="module")
def closed_csv(tmp_path_factory):
    """A closed-loop record as a lab exports it: time, command, angles in degrees, the reference (4 s at 500 Hz)."""
    d = tmp_path_factory.mktemp("closed")
    spec = campaign_spec(True, ["campaign.seed=3"], "closed")
    df = simulate_spec(spec, build_all(), experiments=spec.experiments[1:2], workers=1)[spec.experiments[1].name]
    kp, ke = 35.5145, -3.3636
    rec = pd.DataFrame(
        {
            "time": df["t"],
            "Vm": df["u"],
            "theta_deg": kp * df["theta_v"],  # what the lab's DAQ read, in its calibration
            "alpha_deg": ke * df["alpha_v"],
            "theta_ref_deg": df["ref"],
        }
    )
    path = d / "square.csv"
    rec.to_csv(path, index=False)
    return path, rec


def test_reference_becomes_ref_and_the_controller_is_identified(closed_csv, tmp_path):
    path, rec = closed_csv
    notes: list[str] = []
    import_records([path], tmp_path / "imp", ImportOptions(columns={"theta_ref_deg": "ref"}), note=notes.append)
    e = Manifest.load(tmp_path / "imp").experiments[0]
    assert e.loop == "closed" and e.controller["source"] == "identified"
    assert e.controller["kind"] == "state_feedback" and e.controller["r2"] > 0.999
    np.testing.assert_allclose(e.controller["K"], K, rtol=0.02, atol=0.01)  # the spec's gains
    assert e.controller["cutoff"] == 15.0  # the spec's velocity filter, chosen by R^2
    df = read_dataset(RunDir(tmp_path / "imp").dataset("square"))
    np.testing.assert_allclose(df["ref"], rec["theta_ref_deg"], rtol=0, atol=1e-12)
    assert any("controller identified from the record: state_feedback" in n for n in notes)
    # the diagnosis replays it in closed loop, and says why
    sim = campaign_spec(True, [], "closed")
    x = load_experiments(tmp_path / "imp", load_calibration(tmp_path / "imp"), sim, 10.0)["square"]
    assert x.replay == "closed" and "identified, R^2 1.000" in x.replay_reason


def test_given_controller_and_a_command_no_controller_explains(closed_csv, tmp_path):
    path, rec = closed_csv
    given = parse_controller("state_feedback:K=9.231,-18.769,1.203,-0.041;cutoff=15;u_limit=10")
    assert given == Controller(K=K, cutoff=15.0, u_limit=10.0, source="given")
    import_records([path], tmp_path / "a", ImportOptions(columns={"theta_ref_deg": "ref"}, controller=given))
    assert Manifest.load(tmp_path / "a").experiments[0].controller == given.to_dict()
    # a command that is not the controller's: R^2 below R2_MIN, said, and replayed by multiple shooting
    noisy = rec.assign(Vm=np.random.default_rng(1).normal(0.0, 2.0, len(rec)))
    noisy.to_csv(tmp_path / "noisy.csv", index=False)
    notes: list[str] = []
    import_records([tmp_path / "noisy.csv"], tmp_path / "b", ImportOptions(columns={"theta_ref_deg": "ref"}),
                   note=notes.append)  # fmt: skip
    c = Manifest.load(tmp_path / "b").experiments[0].controller
    assert c["r2"] < 0.05 < R2_MIN
    assert any("does not explain the logged command" in n for n in notes)
    sim = campaign_spec(True, [], "closed")
    x = load_experiments(tmp_path / "b", load_calibration(tmp_path / "b"), sim, 10.0)["noisy"]
    assert x.replay == "shooting" and "explains too little" in x.replay_reason


def test_identify_controller_recovers_a_pid_and_its_clamp():
    Ts, n = 1e-3, 6000
    t = np.arange(n) * Ts
    rng = np.random.default_rng(2)
    ref = np.radians(np.where(t % 2.0 < 1.0, 20.0, -20.0))
    theta = np.radians(18.0 * np.sin(2 * np.pi * 0.5 * t) + 0.02 * rng.standard_normal(n))
    alpha = np.radians(2.0 * np.sin(2 * np.pi * 7.0 * t))
    pid = Controller(kind="pid", kp=6.0, ki=3.0, kd=0.3, cutoff=50.0)
    c = identify_controller(ref, theta, alpha, law(pid, ref, theta, alpha, Ts), Ts, kind="pid")
    assert (c.kp, c.ki, c.kd, c.cutoff, c.u_limit) == pytest.approx((6.0, 3.0, 0.3, 50.0, 0.0), rel=1e-6, abs=1e-9)
    assert c.r2 == pytest.approx(1.0, abs=1e-9) and c.source == "identified"
    # a reference logged 7 samples ahead of the command that used it (the other lab's logger): found
    late = Controller(kind="pid", kp=6.0, ki=3.0, kd=0.3, cutoff=50.0, ref_delay=7)
    c = identify_controller(ref, theta, alpha, law(late, ref, theta, alpha, Ts), Ts, kind="pid")
    assert (c.ref_delay, c.kp, c.r2) == (7, pytest.approx(6.0, rel=1e-3), pytest.approx(1.0, abs=1e-6))
    # a PD that hits its clamp (the other lab's kind): the clamped samples are left out of the fit
    pd_ = Controller(kind="pid", kp=15.0, kd=0.3, cutoff=25.0, u_limit=4.0)
    u = law(pd_, ref, theta, alpha, Ts)
    assert 0.05 < np.mean(np.abs(u) == 4.0) < 0.9
    c = identify_controller(ref, theta, alpha, u, Ts, kind="pid")
    assert (c.kp, c.ki, c.kd, c.cutoff, c.u_limit) == pytest.approx((15.0, 0.0, 0.3, 25.0, 4.0), rel=1e-6, abs=1e-9)


def test_encoder_theta(closed_csv, tmp_path):
    path, rec = closed_csv
    counts = np.round(rec["theta_deg"] / 360.0 * 4096)
    rec.assign(theta_counts=counts).drop(columns="theta_deg").to_csv(tmp_path / "enc.csv", index=False)
    opts = ImportOptions(columns={"theta_ref_deg": "ref"}, counts_per_rev=4096)
    import_records([tmp_path / "enc.csv"], tmp_path / "e", opts)
    e = Manifest.load(tmp_path / "e").experiments[0]
    assert (e.theta_sensor, e.counts_per_rev, e.lattice_deg["theta"]) == ("encoder", 4096.0, 360.0 / 4096)
    sim = campaign_spec(True, [], "closed")
    x = load_experiments(tmp_path / "e", load_calibration(tmp_path / "e"), sim, 10.0)["enc"]
    assert x.encoder and x.daq["theta_sensor"] == 1 and x.daq["encoder_counts"] == 4096.0
    assert x.valid["theta"].all()  # no pot dead band to mask
    with pytest.raises(DataError, match="an encoder theta needs --counts-per-rev"):
        import_records([path], tmp_path / "f", ImportOptions(theta_sensor="encoder"))


@pytest.mark.parametrize(
    "text, msg",
    [
        ("lqr:K=1,2,3,4", r"expected KIND:NAME=VALUE;\.\.\. with KIND one of state_feedback, pid"),
        ("pid:kp=1;gain=2", r"'gain' is not a pid setting; valid: kp, ki, kd, cutoff, u_limit, ref_delay, alpha_bias"),
        ("pid:kp=x", r"kp='x' is not a number"),
        ("state_feedback:K=1,2", r"controller K must have 4 gains"),
    ],
)
def test_bad_controller_is_one_line(text, msg):
    with pytest.raises(ValueError, match=msg) as e:
        parse_controller(text)
    assert "\n" not in str(e.value)


def test_bad_reference_is_one_line(closed_csv, tmp_path):
    path, rec = closed_csv
    bad = rec.copy()
    bad.loc[100, "theta_ref_deg"] = np.nan
    bad.to_csv(tmp_path / "nan.csv", index=False)
    with pytest.raises(DataError, match=r"column 'theta_ref_deg' \(ref\) has 1 NaN/missing/non-numeric value"):
        import_records([tmp_path / "nan.csv"], tmp_path / "x", ImportOptions(columns={"theta_ref_deg": "ref"}))
    assert not (tmp_path / "x").exists()
    with pytest.raises(DataError, match=r"--columns names 'setpoint_deg', not in the file"):
        import_records([path], tmp_path / "x", ImportOptions(columns={"setpoint_deg": "ref"}))


def _to_file_blocks(rec: pd.DataFrame, d, counts_per_rev: int = 4096) -> dict[str, np.ndarray]:
    """The record as a QUARC model saves it: one To File block per scope, each a .mat matrix of its own time column
    then its signals (here N x k, as a lab's script leaves them after loading: data_vm = [t, Vm], data_theta = [t,
    theta_ref, theta] with theta on the encoder's counts, data_alpha = [t, alpha], angles in degrees)."""
    step = 360.0 / counts_per_rev
    blocks = {
        "data_vm": np.column_stack([rec["time"], rec["Vm"]]),
        "data_theta": np.column_stack([rec["time"], rec["theta_ref_deg"], step * np.round(rec["theta_deg"] / step)]),
        "data_alpha": np.column_stack([rec["time"], rec["alpha_deg"]]),
    }
    for name, m in blocks.items():
        scipy.io.savemat(d / f"{name}.mat", {name: m})
    return blocks


QUARC_COLUMNS = {"data_vm:0": "t", "data_vm:1": "u", "data_theta:1": "ref", "data_theta:2": "theta",
                 "data_alpha:1": "alpha"}  # fmt: skip
QUARC_OPTS = ImportOptions(columns=QUARC_COLUMNS, units={"theta": "deg", "alpha": "deg", "ref": "deg"},
                           theta_sensor="encoder", counts_per_rev=4096)  # fmt: skip


def test_a_record_in_several_files_is_one_record(closed_csv, tmp_path):
    """A QUARC capture (three .mat files, each with its own time column) imports as the one record it is: the same
    dataset as the same columns in one CSV, its files and their sha256 in the manifest, named as asked."""
    _, rec = closed_csv
    blocks = _to_file_blocks(rec, tmp_path)
    parts = "+".join(str(tmp_path / f"{n}.mat") for n in blocks)
    notes: list[str] = []
    import_records([f"square={parts}"], tmp_path / "q", QUARC_OPTS, note=notes.append)
    one = pd.DataFrame({"t": blocks["data_vm"][:, 0], "u": blocks["data_vm"][:, 1], "ref": blocks["data_theta"][:, 1],
                        "theta": blocks["data_theta"][:, 2], "alpha": blocks["data_alpha"][:, 1]})  # fmt: skip
    one.to_csv(tmp_path / "square.csv", index=False)
    csv_opts = replace(QUARC_OPTS, columns={"ref": "ref"})
    import_records([tmp_path / "square.csv"], tmp_path / "c", csv_opts)
    joined, single = (read_dataset(RunDir(tmp_path / r).dataset("square")) for r in ("q", "c"))
    pd.testing.assert_frame_equal(joined, single, check_exact=True)
    m = Manifest.load(tmp_path / "q")
    src = m.sources["square"]
    assert src["file"] == "data_vm.mat+data_theta.mat+data_alpha.mat"
    assert src["sha256"].split("+") == [
        hashlib.sha256((tmp_path / f"{n}.mat").read_bytes()).hexdigest() for n in blocks
    ]
    e = m.experiments[0]
    assert e.loop == "closed" and e.controller["r2"] > 0.99 and e.theta_sensor == "encoder"
    # unnamed, the record takes the files' common stem; the command line says it the same way
    columns = ",".join(f"{k}={v}" for k, v in QUARC_COLUMNS.items())
    cmd = ["--columns", columns, "--units", "theta=deg,alpha=deg,ref=deg", "--theta-sensor", "encoder",
           "--counts-per-rev", "4096"]  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "harness", "import", parts, "--out", str(tmp_path / "u"), *cmd],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0 and "imported 1 dataset(s)" in r.stdout, r.stderr
    assert [x.name for x in Manifest.load(tmp_path / "u").experiments] == ["data"]
    assert record_files(parts)[0] == "data" and record_files(tmp_path / "square.csv") == (
        "square",
        [tmp_path / "square.csv"],
    )


def test_files_that_are_not_one_record_are_one_line(closed_csv, tmp_path):
    _, rec = closed_csv
    blocks = _to_file_blocks(rec, tmp_path)
    parts = [tmp_path / f"{n}.mat" for n in blocks]
    short = blocks["data_alpha"][:-5]
    scipy.io.savemat(tmp_path / "short_alpha.mat", {"data_alpha": short})
    late = blocks["data_alpha"].copy()
    late[300:, 0] += 0.001  # another clock from row 300 on
    scipy.io.savemat(tmp_path / "late_alpha.mat", {"data_alpha": late})
    cases = [
        (f"{parts[0]}+{parts[1]}+{tmp_path / 'short_alpha.mat'}", r"must have as many rows \(data_vm.mat 2000, "
         r"data_theta.mat 2000, short_alpha.mat 1995\)"),
        (f"{parts[0]}+{parts[1]}+{tmp_path / 'late_alpha.mat'}", r"data_vm.mat and late_alpha.mat: their time "
         r"columns differ from row 300 on"),
        (f"{parts[0]}+{tmp_path / 'missing.mat'}", r"missing.mat: no such file \(in the record"),
        (f"{parts[0]}+{parts[0]}", "the same file name twice in one record"),
    ]  # fmt: skip
    for arg, msg in cases:
        with pytest.raises(DataError, match=msg) as err:
            import_records([arg], tmp_path / "x", QUARC_OPTS)
        assert "\n" not in str(err.value) and not (tmp_path / "x").exists()
    with pytest.raises(DataError, match=r"no header: 7 numeric columns .* e.g. --columns data_vm:0=t,data_vm:1=u"):
        import_records(["+".join(map(str, parts))], tmp_path / "x", ImportOptions())
