"""harness.ident.crossfit on a small synthetic run directory made from a known ARMAX system."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.signal import lfilter

from benchmarks.problems import demo_system
from harness.ident import armax as ax
from harness.ident import crossfit as cf
from harness.ident.calibration import Calibration
from harness.ident.identify import prepare
from harness.rundir import load_run, write_dataset, write_json

TS, N, AF = 0.02, 700, 0.8
KP, KE, GAUGE_OFFSET = 35.5145, -3.3636, 0.05
DATASETS = {"prbs_a": (0.1, 1), "prbs_b": (0.2, 2), "square": (None, 3)}
ORDERS = {"prbs_a": (4, 3, 4), "prbs_b": (4, 2, 3), "square": (5, 3, 4)}


def _command(p_switch: float | None, seed: int) -> np.ndarray:
    """PRBS (switching probability p_switch) or a 0.4 Hz square wave, 1 V amplitude, 0.2 V offset."""
    k = np.arange(N)
    if p_switch is None:
        return 0.2 + np.where(np.sin(2 * np.pi * 0.4 * k * TS) >= 0, 1.0, -1.0)
    rng = np.random.default_rng(seed)
    return 0.2 + np.where(np.cumsum(rng.random(N) < p_switch) % 2 == 0, 1.0, -1.0)


def _write_run(run: Path) -> None:
    """DAQ-volt datasets whose filtered tip angle is the demo ARMAX system driven by the detrended command."""
    true = demo_system(TS)
    experiments = []
    for name, (p_switch, seed) in DATASETS.items():
        u = _command(p_switch, seed)
        e = 0.01 * np.random.default_rng(100 + seed).standard_normal(N)
        y_f = ax.generate(true, u - u.mean(), e)
        y = 20.0 + lfilter([1.0, -AF], [1.0 - AF, -(1.0 - AF)], y_f)  # H^-1: integrator + inverse low-pass
        alpha = 1.5 * np.sin(2 * np.pi * 3.0 * np.arange(N) * TS)  # deflection [deg]
        theta = y - alpha
        cols = {
            "t": np.arange(N) * TS,
            "u": u,
            "theta_v": ((theta + 180.0) % 360.0 - 180.0) / KP,  # the pot wraps at +-180 deg
            "alpha_v": alpha / KE + GAUGE_OFFSET,
            "theta": theta,
            "alpha": alpha,
        }
        write_dataset(run / "data" / f"{name}.parquet", cols)
        experiments.append({"name": name, "role": "identification", "signal": "prbs", "n": N, "seed": seed})
    write_json(
        run / "manifest.json",
        {"kind": "import", "seed": 0, "sample_rate": 1 / TS, "experiments": experiments},
    )
    cal = Calibration(Kp=KP, Ke=KE, gauge_offset_v=GAUGE_OFFSET, source={"test": "by hand"})
    cal.to_json(run / "calibration.json")
    prepared = prepare(load_run(run), cal, AF, "y")
    records = {}
    for name, p in prepared.items():
        m = ax.estimate(p.u_d, p.y_f, *ORDERS[name], 1, Ts=p.Ts)
        cv = {d: ax.compare(m, q.u_d, q.y_f, ic="z") for d, q in prepared.items()}
        records[name] = {
            "name": name,
            "dataset": name,
            **m.to_dict(),
            "fit_own": cv[name],
            "cv": cv,
            "cv_mean": float(np.mean(list(cv.values()))),
            "preprocessing": {"af": AF, "output": "y", "detrend": "constant", "initial": "rest", "ic": "z"},
            "selected": False,
            "selection_rule": "test: prbs_b by hand",
        }
    records["selected"] = {**records["prbs_b"], "name": "selected", "selected": True}
    for name, rec in records.items():
        write_json(run / "models" / f"{name}.json", rec)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("run")
    _write_run(path)
    return path


def test_crossfit_matrix_from_fmus_equals_python(run):
    seen: list[str] = []
    df = cf.crossfit_run(run, progress=seen.append)
    names = list(DATASETS)
    assert seen == [*names, "selected"]
    assert list(df.index) == [*names, "selected"] and list(df.columns) == [*names, "average"]
    recs = {n: json.loads((run / "models" / f"{n}.json").read_text()) for n in df.index}
    prepared = prepare(load_run(run), Calibration.from_json(run / "calibration.json"), AF, "y")
    for n in df.index:
        m = ax.ArmaxModel.from_dict(recs[n])
        for d in names:
            assert abs(df.loc[n, d] - ax.compare(m, prepared[d].u_d, prepared[d].y_f, ic="z")) < 1e-6
            assert df.loc[n, d] == pytest.approx(recs[n]["cv"][d], abs=1e-6)
    for d in names:  # diagonal: each model's fit on its own dataset
        assert df.loc[d, d] == pytest.approx(recs[d]["fit_own"], abs=1e-6)
    assert df.loc["selected", names].tolist() == df.loc["prbs_b", names].tolist()
    assert np.allclose(df["average"], df[names].mean(axis=1), rtol=0, atol=1e-12)
    assert 0 <= df.attrs["max_abs_diff"] < 1e-6
    assert df[names].to_numpy().min() > 80.0  # the models explain the data
    csv = pd.read_csv(run / "crossfit.csv")
    assert list(csv.columns) == ["model", *names, "average"]
    assert np.allclose(csv[names].to_numpy(), df[names].to_numpy(), atol=1e-6)


def test_csv_bytes_and_fmus_stable_and_stale_fmus_reexported(run):
    cf.crossfit_run(run)
    first = (run / "crossfit.csv").read_bytes()
    stamps = {p.name: p.stat().st_mtime_ns for p in (run / "models").glob("*.fmu")}
    assert len(stamps) == 4
    df = cf.crossfit_run(run)
    assert (run / "crossfit.csv").read_bytes() == first
    assert {p.name: p.stat().st_mtime_ns for p in (run / "models").glob("*.fmu")} == stamps
    assert {p.stem for p in (run / "models").glob("*.fmu")} == {*DATASETS, "selected"}

    # replace the selected model: its FMU is stale and must be re-exported, the row must follow
    sel = run / "models" / "selected.json"
    old = sel.read_text()
    rec = json.loads((run / "models" / "square.json").read_text())
    try:
        write_json(sel, {**rec, "name": "selected", "selected": True})
        df2 = cf.crossfit_run(run)
        assert df2.loc["selected"].tolist() == df2.loc["square"].tolist()
        assert df2.loc["selected"].tolist() != df.loc["selected"].tolist()
    finally:
        sel.write_text(old)
        cf.crossfit_run(run)
    assert (run / "crossfit.csv").read_bytes() == first


def test_unstable_model_gets_an_empty_row_and_no_fmu(run, lab1_model):
    bad = run / "models" / "zz_lab1_rounded.json"
    write_json(bad, {"name": "zz_lab1_rounded", **lab1_model.to_dict(), "preprocessing": {"af": AF, "output": "y"}})
    try:
        df = cf.crossfit_run(run)
        assert df.index[-1] == "zz_lab1_rounded"
        assert df.loc["zz_lab1_rounded"].isna().all()
        assert not (run / "models" / "zz_lab1_rounded.fmu").exists()
        last = (run / "crossfit.csv").read_text().splitlines()[-1]
        assert last == "zz_lab1_rounded" + "," * 4
    finally:
        bad.unlink()
        cf.crossfit_run(run)


def test_disagreement_between_fmu_and_python_is_reported(run, monkeypatch):
    real = ax.compare
    monkeypatch.setattr(ax, "compare", lambda *a, **k: real(*a, **k) + 2e-3)
    with pytest.raises(cf.CrossfitMismatch, match=r"differ by up to 0\.002 fit points"):
        cf.crossfit_run(run)


def test_sample_time_mismatch_is_one_clear_error(run):
    rec = json.loads((run / "models" / "prbs_a.json").read_text())
    m = ax.ArmaxModel.from_dict({**rec, "Ts": 0.01})
    prepared = prepare(load_run(run), Calibration.from_json(run / "calibration.json"), AF, "y")
    with pytest.raises(ValueError, match="has Ts = 0.01 s but dataset prbs_a is sampled at 0.02 s"):
        cf.score_models({"x": (m, None)}, {"x": prepared})
    assert not math.isnan(ax.compare(m, prepared["prbs_a"].u_d, prepared["prbs_a"].y_f))
