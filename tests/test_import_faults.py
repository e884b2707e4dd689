"""Sensor faults found at import, each on the rig twin: a pot's wrap (the hub driven past 180 deg) written in degrees
and in volts, an ADC's rail (a small ``adc_range``), a channel stuck (a stretch of a clean record's column overwritten
with a constant), and a jump no hub makes that is no turn of the pot. Each is said in one ``fault:`` line and in the
manifest; a wrap is unwrapped, a rail or a stuck run masked (the diagnosis compares none of it, the identification
fits around it), a jump cuts the record. The identification's model of a faulty record matches the same record's
without the fault, within what the samples left out cost."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness import spec as specmod
from harness.diagnosis.experiments import load_experiments, split_point
from harness.ident import armax
from harness.ident.calibration import Calibration
from harness.ident.identify import prepare, run_masks, unmasked_stretch
from harness.rig.campaign import run_campaign
from harness.rig.faults import fastest_step_deg
from harness.rig.records import ImportOptions, import_records
from harness.rundir import DataError, Manifest, load_run, read_dataset

KP, KE = 35.5145, -3.3636
CAL = Calibration(Kp=KP, Ke=KE)
ORDER = (3, 2, 2)  # na, nb, nc: the grid's choice on these records (nb + nk <= na)
RATE, SECONDS = 50.0, 10.0


def _campaign(dest: Path, spec: str, experiments: list[dict], daq: dict | None = None) -> dict[str, pd.DataFrame]:
    """A campaign of ``spec``'s rig (no calibration experiments) at RATE Hz: its datasets by name."""
    raw = copy.deepcopy(specmod.load(spec).raw)
    raw["calibration"] = []
    raw["campaign"]["sample_rate"] = RATE
    raw.setdefault("daq", {}).update(daq or {})
    raw["experiment"] = experiments
    run_campaign(specmod.from_dict(raw, f"{spec}.toml"), dest, workers=1)
    return {e["name"]: read_dataset(dest / "data" / f"{e['name']}.parquet") for e in experiments}


@pytest.fixture(scope="module")
def twins(tmp_path_factory, fmus) -> dict[str, pd.DataFrame]:
    """The blind rig (noise on both sensors): ``turning``, a PRBS about 1.5 V that turns the hub round (its pot
    wraps); ``clean`` and ``rail``, one PRBS through a 16-bit ADC over the default range and over 0.8 of the clean
    record's largest pot voltage (theta pinned at the rail); the same noise in both."""
    tmp = tmp_path_factory.mktemp("fault_twins")
    turning = dict(name="turning", signal="prbs", B=0.1, amplitude=1.0, offset=1.5, duration=SECONDS)
    out = _campaign(tmp / "turning", "blind", [turning])
    prbs = [dict(name="prbs", signal="prbs", B=0.2, amplitude=1.0, duration=SECONDS)]
    clean = _campaign(tmp / "clean", "blind", prbs, {"adc_bits": 16})["prbs"]
    top = 0.8 * float(np.max(np.abs(clean["theta_v"])))
    rail = _campaign(tmp / "rail", "blind", prbs, {"adc_bits": 16, "adc_range": top})["prbs"]
    rail.attrs["adc_range"] = top
    return {**out, "clean": clean, "rail": rail}


def _deg_csv(path: Path, t, u, theta, alpha) -> Path:
    pd.DataFrame({"t": t, "u": u, "theta_deg": theta, "alpha_deg": alpha}).to_csv(path, index=False)
    return path


def _reading(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The angles [deg] the twin's sensors read through the calibration: theta wrapped as the pot reads it."""
    return KP * df["theta_v"].to_numpy(), KE * df["alpha_v"].to_numpy()


def _import(files: list[Path], out: Path) -> list[str]:
    """Import ``files`` into ``out``; returns the lines said."""
    said: list[str] = []
    import_records(files, out, ImportOptions(calibration=CAL), note=said.append)
    return said


def _model(run: Path, masked: bool = True) -> armax.ArmaxModel:
    """The ARMAX model of ORDER identified on a run's one record, as the identification prepares it (the import's
    masks left out, or, ``masked`` False, fitted across)."""
    (p,) = prepare(load_run(run), CAL, 0.8, "y", run_masks(run) if masked else None).values()
    return armax.estimate(p.u_d, p.y_f, *ORDER, Ts=p.Ts)


def _fit_on(model: armax.ArmaxModel, run: Path) -> float:
    """The model's fit [%] (simulation, MATLAB compare's) on a run's one record."""
    (p,) = prepare(load_run(run), CAL, 0.8, "y").values()
    return armax.compare(model, p.u_d, p.y_f)


def _faults(run: Path) -> list[dict]:
    return [f for e in Manifest.load(run).experiments for f in e.faults or []]


def test_a_wrap_in_degrees_and_in_volts_is_said_and_unwrapped(twins, tmp_path):
    df = twins["turning"]
    t, u = df["t"].to_numpy(), df["u"].to_numpy()
    theta, alpha = _reading(df)
    wraps = int(np.sum(np.abs(np.diff(theta)) > 180.0))
    assert wraps >= 3  # the hub went round
    turns = 360.0 * np.round((df["theta"].to_numpy() - theta) / 360.0)  # the whole turns the truth knows
    clean = _import([_deg_csv(tmp_path / "clean.csv", t, u, theta + turns, alpha)], tmp_path / "clean")
    assert not [m for m in clean if m.startswith("fault: ")] and not _faults(tmp_path / "clean")
    deg = _deg_csv(tmp_path / "deg.csv", t, u, theta, alpha)
    volts = tmp_path / "volts.csv"
    df[["t", "u", "theta_v", "alpha_v"]].to_csv(volts, index=False)
    reference = _model(tmp_path / "clean")
    for path in (deg, volts):
        run = tmp_path / path.stem
        said = [m for m in _import([path], run) if m.startswith("fault: ")]
        faults = _faults(run)
        assert len(faults) == wraps and {f["kind"] for f in faults} == {"wrap"}
        assert said == [f["line"] for f in faults]  # each said in one line, as the manifest has it
        assert all(f"fault: {path.stem}: theta wrap at " in m and "unwrapped by one turn" in m for m in said)
        assert ("V) in one sample" in said[0]) == (path is volts)
        data = read_dataset(run / "data" / f"{path.stem}.parquet")
        np.testing.assert_allclose(data["theta"], theta + turns, atol=1e-9)  # unwrapped as the truth's turns say
        model = _model(run)
        np.testing.assert_allclose(np.r_[model.A, model.B, model.C], np.r_[reference.A, reference.B, reference.C],
                                   rtol=1e-6, atol=1e-9)  # fmt: skip


def test_a_wrap_through_a_calibration_that_does_not_give_the_pots_span_cuts_the_record(twins, tmp_path):
    """A pot of 35.5 deg/V read as 30 deg/V: its wraps are 298 deg, no turn: the record is cut at each, not fitted
    across, and its parts long enough for two folds kept."""
    volts = tmp_path / "volts.csv"
    twins["turning"][["t", "u", "theta_v", "alpha_v"]].to_csv(volts, index=False)
    said: list[str] = []
    import_records([volts], tmp_path / "run", ImportOptions(calibration=Calibration(Kp=30.0, Ke=KE)), note=said.append)
    faults = _faults(tmp_path / "run")
    lines = sorted({f["line"] for f in faults if f["kind"] == "jump"})
    assert lines == sorted(m for m in said if m.startswith("fault: ")) and len(lines) >= 3
    assert all("and no turn of the pot" in m and "cut there into" in m for m in lines)
    for e in Manifest.load(tmp_path / "run").experiments:
        theta = read_dataset(tmp_path / "run" / "data" / f"{e.name}.parquet")["theta"].to_numpy()
        assert e.name.startswith("volts_") and np.max(np.abs(np.diff(theta))) < fastest_step_deg(1.0 / RATE, 2.5)


def test_a_rail_is_masked_left_out_and_identified_as_without_it(twins, tmp_path):
    clean, rail = twins["clean"], twins["rail"]
    top = rail.attrs["adc_range"]
    pinned = np.flatnonzero(np.abs(rail["theta_v"].to_numpy()) >= top)
    assert pinned.size >= 10  # the hub went beyond the ADC's range
    t, u = clean["t"].to_numpy(), clean["u"].to_numpy()
    _import([_deg_csv(tmp_path / "clean.csv", t, u, *_reading(clean))], tmp_path / "clean")
    reference = _fit_on(_model(tmp_path / "clean"), tmp_path / "clean")
    deg = _deg_csv(tmp_path / "rail.csv", t, u, *_reading(rail))
    volts = tmp_path / "rail_v.csv"
    rail[["t", "u", "theta_v", "alpha_v"]].to_csv(volts, index=False)
    for path in (deg, volts):
        run = tmp_path / path.stem
        said = [m for m in _import([path], run) if m.startswith("fault: ")]
        faults = _faults(run)
        assert {(f["channel"], f["kind"]) for f in faults} == {("theta", "rail")}, said
        assert said == [f["line"] for f in faults] and all("masked" in m for m in said)
        (entry,) = Manifest.load(run).experiments
        spans = entry.masked["theta"]
        np.testing.assert_array_equal(np.concatenate([np.arange(a, b) for a, b in spans]), pinned)
        assert sum(f["samples"] for f in faults) == pinned.size
        data = read_dataset(run / "data" / f"{path.stem}.parquet")
        assert len(data) == len(rail)  # masked, not deleted
        (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
        assert not x.valid["theta"][pinned].any() and x.valid["alpha"].all()  # the diagnosis compares none of them
        fitted, across = (_fit_on(_model(run, masked), tmp_path / "clean") for masked in (True, False))
        # measured on the clean record: 91.6 % for its own model, 90.8 % for the rail record's (identified on its
        # longest stretch without the rail), 84.9 % for the rail record's fitted across the rail
        assert fitted > reference - 3.0 and fitted > across + 2.0, (reference, fitted, across)


@pytest.mark.parametrize("channel", ["theta", "alpha"])
def test_a_stuck_channel_is_masked_and_identified_as_without_it(twins, tmp_path, channel):
    clean = twins["clean"]
    t, u = clean["t"].to_numpy(), clean["u"].to_numpy()
    theta, alpha = _reading(clean)
    _import([_deg_csv(tmp_path / "clean.csv", t, u, theta, alpha)], tmp_path / "clean")
    reference = _fit_on(_model(tmp_path / "clean"), tmp_path / "clean")
    a, b = 300, 340
    cols = {"theta": theta.copy(), "alpha": alpha.copy()}
    cols[channel][a:b] = cols[channel][a]  # the channel stops changing while the rig moves on
    said = [m for m in _import([_deg_csv(tmp_path / "stuck.csv", t, u, **cols)], tmp_path / "stuck") if "fault" in m]
    faults = _faults(tmp_path / "stuck")
    assert [(f["channel"], f["kind"], f["row"], f["samples"]) for f in faults] == [(channel, "stuck", a, b - a)]
    assert said == [faults[0]["line"]] and f"{b - a} samples (0.8 s) held at" in said[0]
    (entry,) = Manifest.load(tmp_path / "stuck").experiments
    assert entry.masked == {channel: [[a, b]]}
    fitted, across = (_fit_on(_model(tmp_path / "stuck", masked), tmp_path / "clean") for masked in (True, False))
    # measured on the clean record: 91.6 % for its own model, 90.9 % for the stuck record's (theta or alpha stuck),
    # 89.9 % (theta) and 88.9 % (alpha) fitted across the stuck run
    assert fitted > reference - 3.0 and fitted > across, (reference, fitted, across)


def test_a_jump_that_is_no_turn_cuts_the_record(tmp_path):
    n = 400
    t, u, theta, alpha = _sine_record(n)
    limit = fastest_step_deg(1.0 / RATE, 1.0)
    jumped = theta + np.where(np.arange(n) >= 150, 2.0 * limit, 0.0)  # an offset no hub makes in a sample
    said = _import([_deg_csv(tmp_path / "rec.csv", t, u, jumped, alpha)], tmp_path / "run")
    (line,) = [m for m in said if m.startswith("fault: ")]
    assert line.startswith("fault: rec: theta jump at 3 s (row 150): a jump of +") and "kept rec_1" in line
    m = Manifest.load(tmp_path / "run")
    assert [(e.name, e.n) for e in m.experiments] == [("rec_1", 150), ("rec_2", 250)]
    assert all(e.faults and e.faults[0]["line"] == line for e in m.experiments)
    np.testing.assert_allclose(read_dataset(tmp_path / "run" / "data" / "rec_2.parquet")["theta"], jumped[150:])
    short = theta + np.where(np.arange(n) >= 350, 2.0 * limit, 0.0)  # its second part too short: dropped
    said = _import([_deg_csv(tmp_path / "short.csv", t, u, short, alpha)], tmp_path / "short")
    assert any("1 shorter than 100 samples dropped" in s for s in said)
    assert [e.name for e in Manifest.load(tmp_path / "short").experiments] == ["short_1"]
    every = theta + 2.0 * limit * (np.arange(n) // 90)  # no part long enough: refused, in one line
    with pytest.raises(DataError, match=r"^every.csv: fault: every: theta jump at 1.8 s .* nothing left to import$"):
        _import([_deg_csv(tmp_path / "every.csv", t, u, every, alpha)], tmp_path / "every")
    assert not (tmp_path / "every").exists()


def test_no_fault_in_the_lab_rigs_clean_records(tmp_path, fmus):
    """The lab rig (friction, a 12-bit ADC, noise): its quantised readings hold still at rest and at the ends of
    each swing, which are no fault; only its pot's wraps are said."""
    lab = [dict(e, duration=8.0) for e in specmod.load("lab").raw["experiment"] if e["signal"] in ("prbs", "square")]
    data = _campaign(tmp_path / "lab", "lab", lab)
    files = []
    for name, df in data.items():
        files.append(_deg_csv(tmp_path / f"{name}.csv", df["t"], df["u"], *_reading(df)))
        df[["t", "u", "theta_v", "alpha_v"]].to_csv(tmp_path / f"{name}_v.csv", index=False)
        files.append(tmp_path / f"{name}_v.csv")
    said = _import(files, tmp_path / "run")
    assert {f["kind"] for f in _faults(tmp_path / "run")} <= {"wrap"}, [m for m in said if "fault" in m]


def test_the_command_line_says_each_fault_in_one_line(twins, tmp_path):
    clean = twins["clean"]
    theta, alpha = _reading(clean)
    alpha[200:260] = alpha[200]
    path = _deg_csv(tmp_path / "rec.csv", clean["t"], clean["u"], theta, alpha)
    r = subprocess.run([sys.executable, "-m", "harness.cli", "import", str(path), "--out", str(tmp_path / "run"),
                        "--kp", str(KP), "--ke", str(KE)], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr
    lines = [x for x in r.stderr.splitlines() if x.startswith("fault: ")]
    assert lines == [f["line"] for f in _faults(tmp_path / "run")] and len(lines) == 1
    assert lines[0].startswith("fault: rec: alpha stuck at 4 s (row 200): 60 samples (1.2 s) held at ")


def _sine_record(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A synthetic record at RATE: t [s], a +-1 V square command, the hub swinging 20 deg at 0.4 Hz and the link at
    rest, both with 0.05 deg of noise."""
    t = np.arange(n) / RATE
    u = np.where(np.sin(2 * np.pi * 0.5 * t) >= 0, 1.0, -1.0)
    theta = 20.0 * np.sin(2 * np.pi * 0.4 * t) + np.random.default_rng(1).normal(0, 0.05, n)
    alpha = np.random.default_rng(2).normal(0, 0.05, n)
    return t, u, theta, alpha


def test_masked_samples_are_left_out_by_the_identification_and_the_diagnosis(tmp_path):
    """Samples masked in a run's manifest (``masked``: a channel pinned at a rail or stuck) are left out: the
    identification fits the longest stretch without any in the channels it reads, the diagnosis compares none."""
    n = 400
    t, u, theta, alpha = _sine_record(n)
    path = tmp_path / "rec.csv"
    pd.DataFrame({"t": t, "u": u, "theta_deg": theta, "alpha_deg": alpha}).to_csv(path, index=False)
    run = tmp_path / "run"
    import_records([path], run, ImportOptions(calibration=CAL))
    assert run_masks(run) == {}
    m = Manifest.load(run)
    m.experiments[0].masked = {"theta": [[120, 150], [300, 310]]}
    m.write(run)
    assert run_masks(run) == {"rec": {"theta": [[120, 150], [300, 310]]}}
    assert unmasked_stretch(n, [[120, 150], [300, 310]]) == (150, 300)
    for output, size in (("y", 150), ("theta", 150), ("alpha", n)):  # alpha reads no masked sample
        (p,) = prepare(load_run(run), CAL, 0.8, output, run_masks(run)).values()
        assert p.u.size == size
        np.testing.assert_array_equal(p.u, u[150 : 150 + size] if size < n else u)
    (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
    assert np.flatnonzero(~x.valid["theta"]).tolist() == [*range(120, 150), *range(300, 310)]
    assert x.valid["alpha"].all()


def test_a_masked_stretch_is_never_a_quiet_point(tmp_path):
    """A sensor held still by its fault is not the rig at rest: the diagnosis cuts a lone record elsewhere, and reads
    the gauge's rest elsewhere (measured on the twin: a stuck alpha had been taken for the link's rest, the replay's
    gauge offset set from it, the held-out gap before any fit 0.0319 against the clean record's 0.0155; now 0.0170,
    alpha's residual 0.0882 deg RMS against 0.0883)."""
    n = 400
    t, u, theta, alpha = _sine_record(n)
    alpha[170:230] = alpha[170]
    theta[170:230] = theta[170]
    path = tmp_path / "rec.csv"
    pd.DataFrame({"t": t, "u": u, "theta_deg": theta, "alpha_deg": alpha}).to_csv(path, index=False)
    run = tmp_path / "run"
    import_records([path], run, ImportOptions(calibration=CAL))
    assert Manifest.load(run).experiments[0].masked == {"theta": [[170, 230]], "alpha": [[170, 230]]}  # found stuck
    (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
    assert x.faulty is not None and np.flatnonzero(x.faulty).tolist() == list(range(170, 230))
    assert not 170 <= split_point(x) < 230 and x.alpha_rest != alpha[170]
    m = Manifest.load(run)
    m.experiments[0].masked = None
    m.write(run)
    (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
    assert x.faulty is None and 170 <= split_point(x) < 230  # not masked, the still stretch is the quietest
