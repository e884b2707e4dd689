"""Real records in the forms labs keep them (CSV with any separator and decimal comma, .mat v5 and v7.3, Parquet;
volts, degrees, radians, encoder counts, metres of tip deflection; 50 Hz, 500 Hz, 1 kHz) reach the same run
directory, and `diagnose` gives the same numbers as on the equivalent volts CSV. Every fixture is written here
from a short campaign of the rig twin. Hostile inputs end in one line naming what was found."""

from __future__ import annotations

import copy
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import scipy.io
from scipy.linalg import expm

from harness import spec as specmod
from harness.diagnosis.diagnose import diagnose_run
from harness.ident.calibration import Calibration
from harness.rig.campaign import run_campaign
from harness.rig.controller import (
    R2_MIN,
    Controller,
    command_r2,
    identify_controller,
    law,
)
from harness.rig.records import MIN_RECORD_SECONDS, ImportOptions, import_records
from harness.rundir import DataError, Manifest, read_dataset

KP, KE, GAUGE_OFFSET = 35.5145, -3.3636, 0.0125  # the lab's DAQ calibration carried by every import here
CAL = Calibration(Kp=KP, Ke=KE, gauge_offset_v=GAUGE_OFFSET)
LINK = 0.419  # m
CPR = 4096  # encoder counts per revolution
VOLTS = ("t", "u", "theta_v", "alpha_v")


def flexjoint(*args):
    return subprocess.run(
        [sys.executable, "-m", "harness.cli", *map(str, args)], capture_output=True, text=True, timeout=600
    )


def _error_line(r) -> str:
    assert r.returncode == 2, r.stdout + r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in r.stderr, r.stderr
    return lines[0]


def _twin(dest: Path, rate: float, seconds: float, names: tuple[str, ...]) -> dict[str, pd.DataFrame]:
    """A short campaign of the blind rig (no calibration experiments) at ``rate`` Hz; commands small enough that
    the pot never wraps, so a record in angles and its volts carry the same information."""
    raw = copy.deepcopy(specmod.load("blind").raw)
    raw["calibration"] = []
    raw["campaign"]["sample_rate"] = rate
    raw["experiment"] = [dict(e, duration=seconds) for e in raw["experiment"] if e["name"] in names]
    for e in raw["experiment"]:
        if e["signal"] == "chirp":
            e["amplitude"] = 0.8
    run_campaign(specmod.from_dict(raw, "blind.toml"), dest, workers=1)
    out = {n: read_dataset(dest / "data" / f"{n}.parquet")[list(VOLTS)] for n in names}
    for df in out.values():
        assert np.max(np.abs(np.diff(df["theta_v"]))) < 1.0  # no pot wrap
    return out


def _deg(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The angles [deg] the lab's calibration gives for the twin's volts."""
    return KP * df["theta_v"].to_numpy(), KE * (df["alpha_v"].to_numpy() - GAUGE_OFFSET)


def _volts_csv(path: Path, t, u, theta_deg, alpha_deg) -> Path:
    """The equivalent volts CSV of a record in angles: theta_v = theta / Kp, alpha_v = alpha / Ke + offset."""
    df = pd.DataFrame({"t": t, "u": u, "theta_v": theta_deg / KP, "alpha_v": alpha_deg / KE + GAUGE_OFFSET})
    path.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(path, index=False)
    return path


def _import(files: list[Path], out: Path, **kw) -> Path:
    import_records(files, out, ImportOptions(calibration=CAL, **kw))
    return out


@pytest.fixture(scope="module")
def twins(tmp_path_factory, fmus):
    tmp = tmp_path_factory.mktemp("twins")
    return {
        50: _twin(tmp / "r50", 50.0, 8.0, ("prbs_small", "square_small", "chirp_slow")),
        500: _twin(tmp / "r500", 500.0, 2.0, ("prbs_small", "square_small")),
        1000: _twin(tmp / "r1000", 1000.0, 2.0, ("prbs_small", "square_small")),  # 2 s: two folds of 1 s
    }


def _same_data(a: Path, b: Path, names: list[str]) -> None:
    for n in names:
        da, db = (pd.read_parquet(r / "data" / f"{n}.parquet") for r in (a, b))
        assert list(da.columns) == [*VOLTS, "theta", "alpha"] == list(db.columns)
        np.testing.assert_allclose(da.to_numpy(), db.to_numpy(), rtol=1e-12, atol=1e-12)
    assert (
        json.loads((a / "calibration.json").read_text())["Kp"] == json.loads((b / "calibration.json").read_text())["Kp"]
    )


def _differences(a, b, rel: float, path: str = "diagnosis") -> list[str]:
    """Where two diagnoses differ: structure, strings, or numbers beyond ``rel`` (relative; 1e-9 absolute)."""
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{path}: keys {sorted(set(a) ^ set(b))}"]
        return [d for k in a for d in _differences(a[k], b[k], rel, f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: {len(a)} vs {len(b)} items"]
        pairs = enumerate(zip(a, b, strict=True))
        return [d for i, (x, y) in pairs for d in _differences(x, y, rel, f"{path}[{i}]")]
    if isinstance(a, float) and isinstance(b, float):
        return [] if b == pytest.approx(a, rel=rel, abs=1e-9, nan_ok=True) else [f"{path}: {a!r} vs {b!r}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def _same_numbers(a: dict, b: dict) -> None:
    """The same diagnosis: identical structure, verdict, effects and strings; what compares the data with the
    simulation as given (gap before, noise floor, where before) to 1e-9; what passes through the optimisers
    (recalibrated parameters, fitted effects, gaps after) to 1e-3, since inputs equal to the last bit give fits
    that agree to their stopping tolerance (~1e-8 in a parameter) and residual statistics amplify that. A candidate
    that closes nothing of the gap is compared by name only: the data do not determine its size (its cost is flat),
    so where its least squares stops is as arbitrary as its last bit."""
    a, b = _determined(a), _determined(b)
    exact = {"gap": {"before": a["gap"]["before"]}, "noise_floor": a["noise_floor"]}
    where = a.get("where", {})
    exact["where"] = where.get("before", where)
    other = {"gap": {"before": b["gap"]["before"]}, "noise_floor": b["noise_floor"]}
    other["where"] = b.get("where", {}).get("before", b.get("where", {}))
    diffs = _differences(exact, other, 1e-9) + _differences(a, b, 1e-3)
    assert not diffs, f"{len(diffs)} differences, e.g. " + "; ".join(diffs[:8])


def _determined(d: dict) -> dict:
    """``d`` with its search's entries (``candidates``, each of ``rounds``) for candidates that close nothing held out
    reduced to their names, in name order."""

    def entries(items: list) -> list:
        kept = [e if (e.get("held_out_share_pct") or 0.0) > 0 else {"effect": e.get("effect")} for e in items]
        return sorted(kept, key=lambda e: json.dumps(e, sort_keys=True))

    out = {**d, "candidates": entries(d.get("candidates", []))}
    out["rounds"] = [entries(r) for r in d.get("rounds", [])]
    return out


# ----------------------------------------------------------------------------------------------- 50 Hz
@pytest.fixture(scope="module")
def lab50(twins, tmp_path_factory):
    """The 50 Hz twin as a volts CSV and as a CSV of degrees, each imported and diagnosed through the CLI (serially:
    a cluster would only add its start to a suite that keeps the cores busy)."""
    tmp = tmp_path_factory.mktemp("lab50")
    volts, deg = [], []
    for name, df in twins[50].items():
        th, al = _deg(df)
        volts.append(tmp / "volts" / f"{name}.csv")
        volts[-1].parent.mkdir(exist_ok=True)
        df.to_csv(volts[-1], index=False)
        deg.append(tmp / "deg" / f"{name}.csv")
        deg[-1].parent.mkdir(exist_ok=True)
        pd.DataFrame({"time": df["t"], "Vm": df["u"], "theta_deg": th, "alpha [deg]": al}).to_csv(deg[-1], index=False)
    runs = {}
    CAL.to_json(tmp / "lab_calibration.json")
    for kind, files in (("volts", volts), ("deg", deg)):
        r = flexjoint("import", *files, "--out", tmp / f"run_{kind}", "--calibration", tmp / "lab_calibration.json")
        assert r.returncode == 0, r.stderr
        r = flexjoint("diagnose", "--real", tmp / f"run_{kind}", "--workers", "1")
        assert r.returncode == 0, r.stderr
        runs[kind] = tmp / f"run_{kind}"
    return runs


def test_degrees_and_volts_reach_the_same_diagnosis(lab50, twins):
    """`flexjoint diagnose --real` on the import from degrees gives the numbers of the import from volts."""
    names = list(twins[50])
    _same_data(lab50["volts"], lab50["deg"], names)
    da, dd = (json.loads((lab50[k] / "diagnosis.json").read_text()) for k in ("volts", "deg"))
    _same_numbers(da, dd)
    assert da["verdict"] == dd["verdict"] and da["gap"]["before"]["gap"] > 0
    m = Manifest.load(lab50["deg"])
    assert m.kind == "import" and m.sample_rate == 50.0 and m.calibration == "given"
    assert m.experiments[0].units == {"t": "s", "u": "V", "theta": "deg", "alpha": "deg"}
    assert m.experiments[0].columns == {"t": "time", "u": "Vm", "theta": "theta_deg", "alpha": "alpha [deg]"}
    assert m.sources["prbs_small"]["format"] == "CSV, separator ','"


def test_other_formats_at_50_hz_give_the_same_dataset(lab50, twins, tmp_path):
    """Radians in Parquet, a MATLAB v5 struct in degrees, a v7.3 file in radians, a headerless matrix of volts:
    the same run directory as the volts CSV (so the same diagnosis)."""
    names = list(twins[50])
    files = {"parquet": [], "v5": [], "v73": [], "matrix": []}
    for name, df in twins[50].items():
        th, al = _deg(df)
        t, u = df["t"].to_numpy(), df["u"].to_numpy()
        p = tmp_path / "pq" / f"{name}.parquet"
        p.parent.mkdir(exist_ok=True)
        pd.DataFrame({"t": t, "u": u, "theta_rad": np.radians(th), "alpha_rad": np.radians(al)}).to_parquet(p)
        files["parquet"].append(p)
        p = tmp_path / "v5" / f"{name}.mat"
        p.parent.mkdir(exist_ok=True)
        scipy.io.savemat(p, {"rec": {"t": t[:, None], "u": u[:, None], "theta_deg": th, "alpha_deg": al}, "Ts": 0.02})
        files["v5"].append(p)
        v73 = {"t": t, "u": u, "hub": np.radians(th), "tip": np.radians(al)}
        files["v73"].append(_mat73(tmp_path / "v73" / f"{name}.mat", v73))
        p = tmp_path / "matrix" / f"{name}.mat"
        p.parent.mkdir(exist_ok=True)
        scipy.io.savemat(p, {"data": df[list(VOLTS)].to_numpy()})
        files["matrix"].append(p)
    ref = lab50["volts"]
    _same_data(ref, _import(files["parquet"], tmp_path / "a"), names)
    _same_data(ref, _import(files["v5"], tmp_path / "b"), names)
    mapping = {"columns": {"hub": "theta", "tip": "alpha"}, "units": {"theta": "rad", "alpha": "rad"}}
    run = _import(files["v73"], tmp_path / "c", **mapping)
    _same_data(ref, run, names)
    assert Manifest.load(run).sources["prbs_small"]["format"] == "MATLAB v7.3 (HDF5)"
    with pytest.raises(DataError, match=r"no header: 4 numeric columns found .*--columns 0=t,1=u,2=theta_v,3=alpha_v"):
        _import(files["matrix"], tmp_path / "d")
    _same_data(ref, _import(files["matrix"], tmp_path / "d", columns=dict(zip("0123", VOLTS, strict=True))), names)
    assert not (tmp_path / "d" / "report.md").exists()


def _mat73(path: Path, variables: dict[str, np.ndarray]) -> Path:
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 with a 512-byte MATLAB header, column vectors stored as
    1 x N datasets (column-major), MATLAB_class attributes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w", userblock_size=512) as f:
        for k, v in variables.items():
            ds = f.create_dataset(k, data=np.asarray(v, dtype=float)[None, :])
            ds.attrs["MATLAB_class"] = np.bytes_("double")
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as f:
        f.write(header.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02IM")
    return path


# ----------------------------------------------------------------------------------------------- 500 Hz, 1 kHz
@pytest.fixture(scope="module")
def fast_rates(twins, tmp_path_factory):
    """500 Hz: a v7.3 .mat with an encoder's integer counts (360/4096 deg) and radians; 1 kHz: a semicolon CSV with
    decimal commas, time in ms, the tip deflection in metres; each with its equivalent volts CSV; all diagnosed."""
    tmp = tmp_path_factory.mktemp("fast")
    out = {}
    rec, ref = [], []
    for name, df in twins[500].items():
        th, al = _deg(df)
        counts = np.round(th * CPR / 360.0)
        enc = {"t": df["t"], "u": df["u"], "theta_counts": counts, "alpha_rad": np.radians(al)}
        rec.append(_mat73(tmp / "enc" / f"{name}.mat", enc))
        ref.append(_volts_csv(tmp / "v500" / f"{name}.csv", df["t"], df["u"], counts * 360.0 / CPR, al))
    # the angles are the pot rig's on an encoder's lattice: said to be a pot, so both runs are the same rig
    out[500] = (_import(rec, tmp / "enc_run", counts_per_rev=CPR, theta_sensor="pot"), _import(ref, tmp / "v500_run"))
    rec, ref = [], []
    for name, df in twins[1000].items():
        th, al = _deg(df)
        d = LINK * np.tan(np.radians(al))
        p = tmp / "m" / f"{name}.csv"
        p.parent.mkdir(parents=True, exist_ok=True)
        frame = pd.DataFrame({"time": 1000.0 * df["t"], "Vm": df["u"], "theta": th, "tip": d})
        text = frame.to_csv(sep=";", index=False, float_format="%.17g", decimal=",")
        p.write_text(text.replace("time;Vm;theta;tip", "time;Vm;theta;tip\nms;V;deg;m"))
        rec.append(p)
        ref.append(_volts_csv(tmp / "v1000" / f"{name}.csv", df["t"], df["u"], th, al))
    out[1000] = (
        _import(rec, tmp / "m_run", columns={"tip": "alpha"}, link_length=LINK),
        _import(ref, tmp / "v1000_run"),
    )
    diag = {}
    for rate, runs in out.items():
        diag[rate] = [diagnose_run(r, "nominal", workers=1).to_dict() for r in runs]
    return out, diag


@pytest.mark.parametrize("rate", [500, 1000])
def test_fast_records_reach_the_same_diagnosis(fast_rates, twins, rate):
    runs, diag = fast_rates
    rec, ref = runs[rate]
    _same_data(rec, ref, list(twins[rate]))
    a, b = diag[rate]
    if rate == 500:  # the counts record says its angle step (360/4096 deg), which joins its noise floor
        step = 360.0 / CPR
        est = a["noise_floor"]["estimated_deg"]["theta"]
        assert a["noise_floor"]["theta_deg"] ** 2 == pytest.approx(est**2 + step**2 / 12.0, rel=1e-6)
        # the floor moves what is measured against it (shares of the excess gap); the findings do not
        assert (a["verdict"], [e["effect"] for e in a["effects"]]) == (
            b["verdict"],
            [e["effect"] for e in b["effects"]],
        )
        for k, p in a["parameters"].items():
            assert p["fitted"] == pytest.approx(b["parameters"][k]["fitted"], rel=1e-3), k
        assert a["gap"]["before"] == b["gap"]["before"]
    else:
        _same_numbers(b, a)
    m = Manifest.load(rec)
    assert m.sample_rate == float(rate)
    assert read_dataset(rec / "data" / "prbs_small.parquet")["t"].diff().median() == pytest.approx(1.0 / rate)
    e = m.experiments[0]
    if rate == 500:
        assert e.units["theta"] == "counts" and e.lattice_deg == {"theta": 360.0 / CPR}
        assert m.sources["prbs_small"]["format"] == "MATLAB v7.3 (HDF5)"
    else:
        assert e.units == {"t": "ms", "u": "V", "theta": "deg", "alpha": "m"}
        assert m.sources["prbs_small"]["format"] == "CSV, separator ';', decimal comma"
        assert any("read as units: ms, V, deg, m" in n for n in m.sources["prbs_small"]["notes"])


# ----------------------------------------------------------------------------------------------- hostile inputs
def _record(n: int = 200, Ts: float = 0.02) -> pd.DataFrame:
    t = np.arange(n) * Ts
    u = np.where(np.random.default_rng(3).random(n) < 0.5, 1.0, -1.0)  # changes at the sample rate
    return pd.DataFrame({"t": t, "u": u, "theta_v": 0.05 * np.sin(t), "alpha_v": 0.01 * np.cos(3 * t)})


def test_time_in_milliseconds_is_converted_with_a_note(tmp_path):
    df = _record()
    df["t"] = np.arange(len(df)) * 20.0  # ms
    df.to_csv(tmp_path / "ms.csv", index=False)
    r = flexjoint("import", tmp_path / "ms.csv", "--out", tmp_path / "run")
    assert r.returncode == 0, r.stderr
    notes = [x for x in r.stderr.splitlines() if x.startswith("note: ")]
    assert any("sample interval of 20: taken as milliseconds (50 Hz)" in x for x in notes), r.stderr
    assert any("calibration: none given; assumed lab 1's Kp 35.5145 deg/V, Ke -3.3636 deg/V" in x for x in notes)
    assert read_dataset(tmp_path / "run" / "data" / "ms.parquet")["t"].iloc[1] == pytest.approx(0.02)
    cal = json.loads((tmp_path / "run" / "calibration.json").read_text())
    assert cal["Kp"] == 35.5145 and cal["source"]["assumed"] is True
    with pytest.raises(DataError, match=r"time column 't' in s has a sample interval of 20 s \(0.05 Hz\): below 10"):
        _import([tmp_path / "ms.csv"], tmp_path / "r2", units={"t": "s"})
    df["t"] = np.arange(len(df)) * 0.5  # 2 Hz in s or 2 kHz in ms: refused
    df.to_csv(tmp_path / "half.csv", index=False)
    with pytest.raises(DataError, match=r"sample interval of 0.5: 2 Hz in seconds .* or 2e\+03 Hz in milliseconds"):
        _import([tmp_path / "half.csv"], tmp_path / "r3")
    assert not (tmp_path / "r3").exists()


def test_units_row_is_read_and_unknown_second_row_refused(tmp_path):
    df = _record()
    th, al = np.degrees(df["theta_v"]), np.degrees(df["alpha_v"])
    body = pd.DataFrame({"t": df["t"], "u": df["u"], "theta": th, "alpha": al}).to_csv(index=False)
    (tmp_path / "units.csv").write_text(body.replace("t,u,theta,alpha\n", "t,u,theta,alpha\ns,V,deg,rad\n"))
    run = _import([tmp_path / "units.csv"], tmp_path / "run")
    d = read_dataset(run / "data" / "units.parquet")
    np.testing.assert_allclose(d["theta"], th)
    np.testing.assert_allclose(d["alpha"], np.degrees(al))  # the units row says alpha is in rad
    (tmp_path / "two.csv").write_text(body.replace("t,u,theta,alpha\n", "t,u,theta,alpha\ntime,cmd,hub,tip\n"))
    with pytest.raises(DataError, match=r"two.csv: line 2 under the header is neither numbers nor units"):
        _import([tmp_path / "two.csv"], tmp_path / "r2")
    (tmp_path / "nounit.csv").write_text(body)
    with pytest.raises(DataError, match=r"unit of theta \(column 'theta'\) not known; give --units theta=UNIT"):
        _import([tmp_path / "nounit.csv"], tmp_path / "r3")


def test_headerless_writematrix_needs_positions(tmp_path):
    _record().to_csv(tmp_path / "m.csv", index=False, header=False)
    line = _error_line(flexjoint("import", tmp_path / "m.csv", "--out", tmp_path / "run"))
    assert "no header: 4 numeric columns found (first row 0, " in line and "--columns 0=t,1=u,2=theta_v" in line
    _import([tmp_path / "m.csv"], tmp_path / "run", columns={"0": "t", "1": "u", "2": "theta_v", "3": "alpha_v"})
    np.testing.assert_allclose(read_dataset(tmp_path / "run" / "data" / "m.parquet")["u"], _record()["u"])


def test_clock_jitter_small_resampled_large_refused(tmp_path):
    rng = np.random.default_rng(5)
    n, Ts = 500, 0.02
    grid = np.arange(n) * Ts
    t = grid + rng.uniform(-50e-6, 50e-6, n)  # host clock: +-50 us at 50 Hz
    t[0] = 0.0
    df = pd.DataFrame({"t": t, "u": np.sin(2 * t), "theta_v": 0.1 * np.sin(t), "alpha_v": 0.02 * np.cos(5 * t)})
    df.to_csv(tmp_path / "jit.csv", index=False)
    seen: list[str] = []
    import_records([tmp_path / "jit.csv"], tmp_path / "run", ImportOptions(calibration=CAL), seen.append)
    d = read_dataset(tmp_path / "run" / "data" / "jit.parquet")
    np.testing.assert_allclose(np.diff(d["t"]), Ts, rtol=1e-9)
    corr = Manifest.load(tmp_path / "run").experiments[0].jitter_corrected_s
    assert 30e-6 < corr <= 60e-6
    assert any("host-clock jitter up to" in s and "resampled onto the uniform 50 Hz grid" in s for s in seen), seen
    # resampled values are the signals at the grid times (interpolation error of 50 us on a 1 rad/s sine)
    np.testing.assert_allclose(d["theta_v"], 0.1 * np.sin(d["t"]), atol=1e-5)
    df["t"] = grid + rng.uniform(-5e-3, 5e-3, n)  # +-5 ms: not jitter to paper over
    df.to_csv(tmp_path / "bad.csv", index=False)
    line = _error_line(flexjoint("import", tmp_path / "bad.csv", "--out", tmp_path / "r2"))
    assert "non-uniform sampling: time stamps stray up to" in line and "10 % of the 20 ms interval at row" in line


@pytest.mark.parametrize(
    "change, message",
    [
        ({"alpha_v": None}, r"no column for alpha; found t, u, theta_v \(CSV, separator ','\)"),
        ({"u": "nan17"}, r"column 'u' \(u\) has 1 NaN/missing/non-numeric value\(s\), first at row 17 \(line 19\)"),
        ({"u": "text5"}, r"first at row 5 \(line 7\): 'oops'"),
        (
            {"theta_v": "inf"},
            r"column 'theta_v' \(theta\) has 1 infinite/NaN/missing/non-numeric value\(s\), first at "
            r"row 17: inf; CSV",
        ),
        (
            {"alpha_v": "-inf"},
            r"column 'alpha_v' \(alpha\) has 1 infinite/NaN/missing/non-numeric value\(s\), first "
            r"at row 17: -inf; CSV",
        ),
        ({"u": "nan"}, r"column 'u' \(u\) has 1 NaN/missing/non-numeric value\(s\), first at row 17: nan; CSV"),
        ({"u": "inf199"}, r"column 'u' \(u\) has 1 infinite/NaN/missing/non-numeric value\(s\), first at row 199: inf"),
        ({"t": "repeat"}, r"not strictly increasing: row 100 has t = 0 s after 1.98 s"),
        ({"theta_v": "counts"}, r"theta column 'theta_counts' is in encoder counts: give --counts-per-rev"),
        ({"alpha_v": "metres"}, r"alpha column 'alpha_m' is a tip deflection in m: give --link-length"),
    ],
)
def test_hostile_records_refused_without_writing(tmp_path, change, message):
    df = _record()
    ((col, what),) = change.items()
    if what is None:
        df = df.drop(columns=col)
    elif what == "nan17":
        df[col] = df[col].astype(object)
        df.loc[17, col] = ""
    elif what == "text5":
        df[col] = df[col].astype(object)
        df.loc[5, col] = "oops"
    elif what in ("inf", "-inf", "nan", "inf199"):  # a number that is not finite, as the file writes it
        df[col] = df[col].astype(object)
        df.loc[199 if what == "inf199" else 17, col] = what.removesuffix("199")
    elif what == "repeat":
        df["t"] = np.r_[df["t"][:100], df["t"][:100]]
    elif what == "counts":
        df = df.rename(columns={"theta_v": "theta_counts"})
    else:
        df = df.rename(columns={"alpha_v": "alpha_m"})
    df.to_csv(tmp_path / "bad.csv", index=False)
    _record().to_csv(tmp_path / "good.csv", index=False)
    with pytest.raises(DataError, match=message) as exc:
        _import([tmp_path / "good.csv", tmp_path / "bad.csv"], tmp_path / "run")
    assert "\n" not in str(exc.value)
    assert not (tmp_path / "run").exists()


def test_calibration_options(tmp_path):
    _record().to_csv(tmp_path / "a.csv", index=False)
    line = _error_line(flexjoint("import", tmp_path / "a.csv", "--out", tmp_path / "r", "--kp", "35"))
    assert "--kp and --ke go together" in line
    CAL.to_json(tmp_path / "cal.json")
    r = flexjoint("import", tmp_path / "a.csv", "--out", tmp_path / "r", "--calibration", tmp_path / "cal.json")
    assert r.returncode == 0 and "assumed" not in r.stderr, r.stderr
    cal = json.loads((tmp_path / "r" / "calibration.json").read_text())
    assert (cal["Kp"], cal["Ke"], cal["gauge_offset_v"]) == (KP, KE, GAUGE_OFFSET)
    assert Manifest.load(tmp_path / "r").calibration == "given"
    assert not math.isnan(read_dataset(tmp_path / "r" / "data" / "a.parquet")["theta"].iloc[3])


def test_one_file_named_on_the_command_line(tmp_path):
    """``NAME=FILE``: a record of one file named like a record of several (it was read as a file named
    ``x=fine.csv`` and refused as missing)."""
    _record().to_csv(tmp_path / "fine.csv", index=False)
    CAL.to_json(tmp_path / "cal.json")
    r = flexjoint(
        "import", f"x={tmp_path / 'fine.csv'}", "--out", tmp_path / "r", "--calibration", tmp_path / "cal.json"
    )
    assert r.returncode == 0 and "imported 1 dataset(s)" in r.stdout, r.stderr
    m = Manifest.load(tmp_path / "r")
    assert [e.name for e in m.experiments] == ["x"] and sorted(m.sources) == ["x"]
    assert [p.name for p in (tmp_path / "r" / "data").iterdir()] == ["x.parquet"]
    _import([tmp_path / "fine.csv"], tmp_path / "unnamed")
    pd.testing.assert_frame_equal(read_dataset(tmp_path / "r" / "data" / "x.parquet"),
                                  read_dataset(tmp_path / "unnamed" / "data" / "fine.parquet"))  # fmt: skip
    line = _error_line(flexjoint("import", f"x={tmp_path / 'gone.csv'}", "--out", tmp_path / "r2"))
    assert line == f"error: {tmp_path / 'gone.csv'}: no such file (in the record x={tmp_path / 'gone.csv'})"
    line = _error_line(flexjoint("import", f"x={tmp_path / 'fine.csv'}", f"x={tmp_path / 'fine.csv'}", "--out",
                                 tmp_path / "r2"))  # fmt: skip
    assert line.startswith("error: two records named 'x'")
    assert not (tmp_path / "r2").exists()


# ----------------------------------------------------------------------------------------------- closed loop
K_SF = [14.1, -28.1, 1.7, 0.2]  # V/rad, V/rad, V s/rad, V s/rad: a lab's LQR-type state feedback
SF = Controller(K=K_SF, cutoff=25.0, u_limit=5.0)


def _plant(Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """The textbook SRV02 + flexible link (x = theta, alpha, theta_dot, alpha_dot [rad, rad/s]; u [V]), zero-order
    hold at ``Ts`` [s]: an independent closed loop for the controller's law, no FMU."""
    Rm, kt, Kg, eta, Jeq, Beq, Jl, Ks = 2.6, 7.68e-3, 70.0, 0.9 * 0.69, 2.08e-3, 0.004, 3.8e-3, 1.3
    g, b = eta * Kg * kt / Rm, Beq + eta * Kg**2 * kt**2 / Rm
    M = np.zeros((5, 5))
    M[0, 2] = M[1, 3] = 1.0
    M[2, :5] = [0.0, Ks / Jeq, -b / Jeq, 0.0, g / Jeq]
    M[3, :5] = [0.0, -Ks / Jeq - Ks / Jl, b / Jeq, 0.0, -g / Jeq]
    E = expm(M * Ts)
    return E[:4, :4], E[:4, 4]


def _closed_loop(c: Controller, rate: float, seconds: float, offset_deg: float = 0.0, seed: int = 0):
    """A closed-loop record as a lab takes it: a +-30 deg square reference (around ``offset_deg``), theta on a 4096
    count encoder, alpha with 0.02 deg gauge noise, the command computed sample by sample by ``c`` from what was
    measured. Returns t [s], ref, theta, alpha [rad], u [V]."""
    Ts = 1.0 / rate
    n = int(round(seconds * rate))
    Ad, Bd = _plant(Ts)
    t = np.arange(n) * Ts
    ref = np.radians(offset_deg + np.where(t % 2.0 < 1.0, 30.0, -30.0) * (t >= 0.25))
    rng = np.random.default_rng(seed)
    step = 2 * math.pi / CPR
    a = math.exp(-2 * math.pi * c.cutoff * Ts)
    x = np.array([math.radians(offset_deg), 0.0, 0.0, 0.0])
    th, al, u = np.empty(n), np.empty(n), np.empty(n)
    vt = va = integral = 0.0
    for k in range(n):
        th[k] = np.round(x[0] / step) * step
        al[k] = x[1] + math.radians(0.02) * rng.standard_normal()
        if k:
            vt = a * vt + (1 - a) * (th[k] - th[k - 1]) / Ts
            va = a * va + (1 - a) * (al[k] - al[k - 1]) / Ts
        e = ref[k] - th[k]
        if c.kind == "state_feedback":
            raw = c.K[0] * e - c.K[1] * al[k] - c.K[2] * vt - c.K[3] * va
        else:
            raw = c.kp * e + c.ki * integral - c.kd * vt
        u[k] = min(max(raw, -c.u_limit), c.u_limit)
        if u[k] == raw:
            integral += Ts * e
        x = Ad @ x + Bd * u[k]
    return t, ref, th, al, u


@pytest.mark.parametrize("rate", [500, 1000])
def test_identify_controller_recovers_the_law_from_a_noisy_closed_loop_record(rate):
    """A record the law itself made in closed loop (it is :func:`law` to the last bit), then logged with 0.02 V of
    noise and clamped at 5 V, printed to 0.01 V: gains within 1.5 %, the filter, the clamp, R^2 > 0.999 (plain least
    squares that keeps the noisy samples next to the clamp loses half the gains, and its R^2 still passes R2_MIN)."""
    Ts = 1.0 / rate
    t, ref, th, al, u = _closed_loop(SF, rate, 4.0)
    np.testing.assert_allclose(law(SF, ref, th, al, Ts), u, rtol=0, atol=1e-12)
    assert 0.01 < np.mean(np.abs(u) == 5.0) < 0.05  # the steps saturate the command
    rng = np.random.default_rng(1)
    logged = np.round(np.clip(u + 0.02 * rng.standard_normal(u.size), -5.0, 5.0), 2)
    c = identify_controller(ref, th, al, logged, Ts)
    np.testing.assert_allclose(c.K, K_SF, rtol=0.015)
    assert (c.kind, c.cutoff, c.u_limit, c.ref_delay, c.source) == ("state_feedback", 25.0, 5.0, 0, "identified")
    assert 0.999 < c.r2 < 1.0
    # an amplifier's measured output: the noise on top of the clamp, no sample exactly at it
    measured = u + 0.02 * rng.standard_normal(u.size)
    c = identify_controller(ref, th, al, measured, Ts)
    np.testing.assert_allclose(c.K, K_SF, rtol=0.015)
    assert c.u_limit == pytest.approx(5.0, abs=0.01) and c.r2 > 0.999
    # a PID on theta (derivative on the measurement, anti-windup) in the same loop
    pid = Controller(kind="pid", kp=8.0, ki=4.0, kd=0.4, cutoff=50.0, u_limit=5.0)
    t, ref, th, al, u = _closed_loop(pid, rate, 4.0)
    np.testing.assert_allclose(law(pid, ref, th, al, Ts), u, rtol=0, atol=1e-12)
    c = identify_controller(ref, th, al, u + 0.01 * rng.standard_normal(u.size), Ts, kind="pid")
    np.testing.assert_allclose([c.kp, c.ki, c.kd], [8.0, 4.0, 0.4], rtol=0.015)
    assert c.cutoff == 50.0 and c.r2 > 0.999
    # a command that is no controller's: nothing explains it
    noise = rng.normal(0.0, 2.0, u.size)
    for kind in ("state_feedback", "pid"):
        assert identify_controller(ref, th, al, noise, Ts, kind=kind).r2 < 0.05 < R2_MIN


def _closed_frame(rate: float, seconds: float = 4.0, offset_deg: float = 0.0, noise: float = 0.0) -> pd.DataFrame:
    """A closed-loop record in the columns a lab exports: time [s], Vm [V], theta_deg, alpha_deg, theta_ref_deg."""
    t, ref, th, al, u = _closed_loop(SF, rate, seconds, offset_deg)
    u = u + noise * np.random.default_rng(4).standard_normal(u.size)
    return pd.DataFrame(
        {"time": t, "Vm": u, "theta_deg": np.degrees(th), "alpha_deg": np.degrees(al), "theta_ref_deg": np.degrees(ref)}
    )


@pytest.mark.parametrize("rate", [500, 1000])
def test_closed_loop_record_imports_with_its_reference_and_identified_controller(tmp_path, rate):
    """500 Hz with the reference in rad (--units ref=rad), 1 kHz with time in ms and no unit: the dataset's ref is
    the reference in degrees, the experiment closed loop at the record's rate, the controller identified."""
    df = _closed_frame(rate)
    ref_deg = df["theta_ref_deg"].to_numpy()
    if rate == 500:
        df = df.assign(setpoint=np.radians(ref_deg)).drop(columns="theta_ref_deg")
        opts = {"columns": {"setpoint": "ref"}, "units": {"ref": "rad"}}
    else:
        df = df.assign(time=1000.0 * df["time"])
        opts = {"columns": {"theta_ref_deg": "ref"}}
    df.to_csv(tmp_path / "sq.csv", index=False, float_format="%.17g")
    seen: list[str] = []
    import_records([tmp_path / "sq.csv"], tmp_path / "run", ImportOptions(calibration=CAL, **opts), seen.append)
    d = read_dataset(tmp_path / "run" / "data" / "sq.parquet")
    assert list(d.columns) == [*VOLTS, "theta", "alpha", "ref"]
    np.testing.assert_allclose(d["ref"], ref_deg, rtol=1e-12, atol=1e-12)
    assert set(np.round(d["ref"], 9)) == {0.0, 30.0, -30.0}
    np.testing.assert_allclose(d["theta_v"], d["theta"] / KP, rtol=1e-12)  # the importer's convention: theta / Kp
    np.testing.assert_allclose(d["t"].diff().median(), 1.0 / rate, rtol=1e-9)
    m = Manifest.load(tmp_path / "run")
    e = m.experiments[0]
    assert m.sample_rate == float(rate) and e.n == 4 * rate and e.loop == "closed"
    assert e.units["ref"] == ("rad" if rate == 500 else "deg") and e.units["t"] == ("s" if rate == 500 else "ms")
    c = e.controller
    assert (c["kind"], c["source"], c["cutoff"], c["u_limit"], c["ref_delay"]) == ("state_feedback", "identified",
                                                                                     25.0, 5.0, 0)  # fmt: skip
    np.testing.assert_allclose(c["K"], K_SF, rtol=1e-6)  # logged exactly as computed: the law to rounding
    assert c["r2"] > 0.999999
    assert any("controller identified from the record: state_feedback (14.1, -28.1, 1.7, 0.2), velocity filter 25 Hz"
               in s and "output limit 5 V" in s for s in seen), seen  # fmt: skip
    assert not any(s.startswith("warning: ") for s in seen), seen
    if rate == 1000:
        assert any("sample interval of 1: taken as milliseconds (1000 Hz)" in s for s in seen), seen


def test_given_controller_low_r2_warning_and_encoder(tmp_path):
    """Through the command line: a given controller is recorded as given (its R^2 on the record said); a command no
    controller explains is imported with one warning line; an encoder's theta past 180 deg stays unwrapped."""
    df = _closed_frame(500, offset_deg=170.0)  # the hub swings across 180 deg: a pot would wrap, an encoder does not
    df.to_csv(tmp_path / "enc.csv", index=False, float_format="%.17g")
    CAL.to_json(tmp_path / "cal.json")
    spec = "state_feedback:K=14.1,-28.1,1.7,0.2;cutoff=25;u_limit=5"
    r = flexjoint("import", tmp_path / "enc.csv", "--out", tmp_path / "a", "--columns", "theta_ref_deg=ref",
                  "--controller", spec, "--theta-sensor", "encoder", "--counts-per-rev", CPR,
                  "--calibration", tmp_path / "cal.json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "note: enc.csv: the given controller explains R^2 1.000 of the logged command" in r.stderr
    assert "warning" not in r.stderr and "Traceback" not in r.stderr
    e = Manifest.load(tmp_path / "a").experiments[0]
    assert e.controller == Controller(K=K_SF, cutoff=25.0, u_limit=5.0, source="given").to_dict()
    assert e.controller["source"] == "given" and "r2" not in e.controller
    assert (e.loop, e.theta_sensor, e.counts_per_rev) == ("closed", "encoder", 4096.0)
    assert e.lattice_deg["theta"] == 360.0 / CPR
    d = read_dataset(tmp_path / "a" / "data" / "enc.parquet")
    np.testing.assert_allclose(d["theta"], df["theta_deg"], rtol=0, atol=1e-12)
    assert d["theta"].max() > 195.0 and d["theta_v"].max() == pytest.approx(d["theta"].max() / KP)  # > 5 V: no wrap
    np.testing.assert_allclose(d["ref"], df["theta_ref_deg"], rtol=0, atol=1e-12)
    # the same record with a command no controller computed: imported, R^2 recorded, one warning line
    df.assign(Vm=np.random.default_rng(7).normal(0.0, 2.0, len(df))).to_csv(tmp_path / "rnd.csv", index=False)
    r = flexjoint("import", tmp_path / "rnd.csv", "--out", tmp_path / "b", "--calibration", tmp_path / "cal.json")
    assert r.returncode == 0, r.stderr
    warnings = [x for x in r.stderr.splitlines() if x.startswith("warning: ")]
    assert len(warnings) == 1, r.stderr
    assert warnings[0].startswith("warning: rnd.csv: R^2 0.0") and f"< {R2_MIN}" in warnings[0]
    assert "no closed-loop replay" in warnings[0] and "multiple shooting" in warnings[0]
    c = Manifest.load(tmp_path / "b").experiments[0].controller
    assert c["source"] == "identified" and 0.0 <= c["r2"] < 0.05  # the reference found by its name: closed loop
    # a given controller that does not explain the record (a gain's sign flipped): kept, with a warning
    wrong = Controller(K=[14.1, 28.1, 1.7, 0.2], cutoff=25.0, u_limit=5.0, source="given")
    seen: list[str] = []
    import_records([tmp_path / "enc.csv"], tmp_path / "c", ImportOptions(calibration=CAL, controller=wrong),
                   seen.append)  # fmt: skip
    assert Manifest.load(tmp_path / "c").experiments[0].controller == wrong.to_dict()
    r2 = command_r2(wrong, np.radians(df["theta_ref_deg"]), np.radians(df["theta_deg"]), np.radians(df["alpha_deg"]),
                    df["Vm"].to_numpy(), 1 / 500)  # fmt: skip
    assert r2 < R2_MIN
    assert [s for s in seen if s.startswith("warning: ")] == [
        f"warning: enc.csv: the given controller explains R^2 {r2:.3f} < {R2_MIN} of the logged command (gains in "
        "V/rad, V s/rad? their signs?); it is used as given"
    ]


def test_encoder_lattice_and_counts_per_rev_notes(tmp_path):
    """An encoder theta in counts is an encoder by default; one in degrees off the count lattice is said;
    --counts-per-rev alone makes theta an encoder's, and one that describes no channel is refused."""
    df = _closed_frame(500)
    counts = np.round(df["theta_deg"] / 360.0 * CPR)
    df.assign(theta_counts=counts).drop(columns="theta_deg").to_csv(tmp_path / "cnt.csv", index=False)
    _import([tmp_path / "cnt.csv"], tmp_path / "a", counts_per_rev=CPR)
    e = Manifest.load(tmp_path / "a").experiments[0]
    assert (e.theta_sensor, e.counts_per_rev, e.lattice_deg["theta"], e.units["theta"]) == (
        "encoder", 4096.0, 360.0 / CPR, "counts")  # fmt: skip
    np.testing.assert_allclose(read_dataset(tmp_path / "a" / "data" / "cnt.parquet")["theta"], df["theta_deg"],
                               rtol=0, atol=1e-9)  # fmt: skip
    smooth = df.assign(theta_deg=df["theta_deg"].rolling(5, min_periods=1).mean())
    smooth.to_csv(tmp_path / "smooth.csv", index=False)
    seen: list[str] = []
    import_records([tmp_path / "smooth.csv"], tmp_path / "b",
                   ImportOptions(calibration=CAL, theta_sensor="encoder", counts_per_rev=CPR), seen.append)  # fmt: skip
    off = "theta is not on the encoder's 0.0878906 deg steps (up to 0.4 of a step off: filtered or resampled?)"
    assert any(off in s for s in seen), seen
    # --counts-per-rev alone says the encoder: the same record, the same manifest entry
    import_records([tmp_path / "smooth.csv"], tmp_path / "c", ImportOptions(calibration=CAL, counts_per_rev=CPR))
    assert Manifest.load(tmp_path / "c").experiments[0] == Manifest.load(tmp_path / "b").experiments[0]
    # a --counts-per-rev that describes nothing (a pot's volts, or a pot said, with no channel in counts): one line
    volts = df.assign(theta_v=df["theta_deg"] / CAL.Kp).drop(columns="theta_deg")
    volts.to_csv(tmp_path / "volts.csv", index=False)
    for path, sensor, why in ((tmp_path / "volts.csv", None, "theta is in volts, a pot's"),
                              (tmp_path / "smooth.csv", "pot", "--theta-sensor pot")):  # fmt: skip
        with pytest.raises(DataError, match=re.escape(f"--counts-per-rev 4096 describes no channel ({why}, none in")):
            import_records([path], tmp_path / "d", ImportOptions(calibration=CAL, counts_per_rev=CPR,
                                                                 theta_sensor=sensor))  # fmt: skip


def _write_mat(path: Path, df: pd.DataFrame, ref: np.ndarray) -> Path:
    scipy.io.savemat(path, {**{k: df[k].to_numpy() for k in df.columns if k != "theta_ref_deg"}, "theta_ref": ref})
    return path


@pytest.mark.parametrize(
    "case, message",
    [
        (
            "short_1khz",
            r"short.csv: 1500 samples at 1000 Hz \(1.5 s\): too short for two folds; need at least 2000 "
            r"samples \(2 s and 100 samples: 1 s and 50 samples per fold\)",
        ),  # fmt: skip
        ("short_20hz", r"short.csv: 80 samples at 20 Hz \(4 s\): too short for two folds; need at least 100 samples"),
        (
            "ref_shorter",
            r"ref.csv: column 'theta_ref_deg' \(ref\) ends at row 1500: 1500 values for the record's "
            r"2000 rows \(a column of another length\)",
        ),  # fmt: skip
        (
            "ref_nan",
            r"ref.csv: column 'theta_ref_deg' \(ref\) has 1 NaN/missing/non-numeric value\(s\), first at row "
            r"700",
        ),  # fmt: skip
        (
            "ref_mat",
            r"ref.mat: column 'theta_ref' \(ref\) has 1900 samples, the record's other columns 2000: a column "
            r"of another length",
        ),  # fmt: skip
        ("row_long", r"ref.csv: line 121 has 6 fields, the header 5 \(time, Vm, theta_deg, alpha_deg, theta_ref_deg\)"),
        (
            "controller_open",
            r"open.csv: --controller given, but the record has no reference column: map it with "
            r"--columns NAME=ref",
        ),  # fmt: skip
        ("cpr_zero", r"--counts-per-rev 0: must be a number > 0"),
        ("cpr_negative", r"--counts-per-rev -4096: must be a number > 0"),
        ("sensor", r"--theta-sensor 'hall': use pot or encoder"),
    ],
)
def test_bad_closed_loop_input_is_one_line_and_nothing_written(tmp_path, case, message):
    df = _closed_frame(500, seconds=4.0).iloc[:2000]  # 4 s at 500 Hz, the first 2000 samples
    good = tmp_path / "good.csv"
    df.to_csv(good, index=False)
    opts: dict = {"columns": {"theta_ref_deg": "ref"}}
    files = [good]
    if case.startswith("short"):
        rate = 1000 if case == "short_1khz" else 20
        n = 1500 if rate == 1000 else 80
        _closed_frame(rate, seconds=n / rate).to_csv(tmp_path / "short.csv", index=False)
        files.append(tmp_path / "short.csv")
    elif case in ("ref_shorter", "ref_nan"):
        bad = df.copy()
        if case == "ref_shorter":
            bad.loc[1500:, "theta_ref_deg"] = np.nan  # written as empty cells: the column ends early
        else:
            bad.loc[700, "theta_ref_deg"] = np.nan
        bad.to_csv(tmp_path / "ref.csv", index=False)
        files.append(tmp_path / "ref.csv")
    elif case == "ref_mat":
        files.append(_write_mat(tmp_path / "ref.mat", df, df["theta_ref_deg"].to_numpy()[:1900]))
        opts = {"columns": {"theta_ref": "ref"}, "units": {"ref": "deg", "theta": "deg", "alpha": "deg"}}
    elif case == "row_long":
        lines = df.to_csv(index=False).splitlines()
        lines[120] += ",0.5"  # past the 50 lines the separator is sniffed on
        (tmp_path / "ref.csv").write_text("\n".join(lines) + "\n")
        files.append(tmp_path / "ref.csv")
    elif case == "controller_open":
        df.drop(columns="theta_ref_deg").to_csv(tmp_path / "open.csv", index=False)
        files, opts = [tmp_path / "open.csv"], {"controller": SF}
    elif case.startswith("cpr"):
        opts["counts_per_rev"] = 0.0 if case == "cpr_zero" else -4096.0
    else:
        opts["theta_sensor"] = "hall"
    with pytest.raises(DataError, match=message) as exc:
        _import(files, tmp_path / "run", **opts)
    assert "\n" not in str(exc.value)
    assert not (tmp_path / "run").exists()


def test_bad_closed_loop_options_on_the_command_line(tmp_path):
    """Each a single `error:` line, exit 2, nothing written."""
    _closed_frame(500).to_csv(tmp_path / "sq.csv", index=False)
    _closed_frame(1000, seconds=1.5).to_csv(tmp_path / "short.csv", index=False)
    cases = [
        (("--controller", "lqr:K=1,2,3,4"), "expected KIND:NAME=VALUE;... with KIND one of state_feedback, pid"),
        (("--controller", "pid:kp=8;kq=2"), "'kq' is not a pid setting; valid: kp, ki, kd, cutoff, u_limit"),
        (("--counts-per-rev", "-4096"), "--counts-per-rev -4096: must be a number > 0"),
        (("--columns", "theta_ref_deg=ref", "short.csv"), "short.csv: 1500 samples at 1000 Hz (1.5 s): too short"),
    ]
    for args, text in cases:
        files = [tmp_path / a for a in args if a.endswith(".csv")] or [tmp_path / "sq.csv"]
        opts = [a for a in args if not a.endswith(".csv")]
        line = _error_line(flexjoint("import", *files, "--out", tmp_path / "run", *opts))
        assert text in line, line
        assert not (tmp_path / "run").exists()
    assert MIN_RECORD_SECONDS == 2.0
