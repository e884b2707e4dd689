"""The cross-fit matrix: every identified model, exported as an FMU, run by fmpy on every dataset.

Row i, column j: MATLAB ``compare`` fit [%] (zero initial state, ic="z") of model i simulated on dataset j,
in the identification domain: input the detrended command u_d [V] of dataset j, output scored against its
y_f = H(z) y (``harness.ident.identify.prepare`` with the model's preprocessing af and output). The exported FMUs
carry u_offset = 0, so the detrended command goes in and one FMU serves every dataset. The same matrix is
computed by the Python simulation (``harness.ident.armax.compare``); the two must agree to ``TOLERANCE`` fit points.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..rundir import atomic_write_text, check_fresh, load_run, record_inputs
from . import armax
from .calibration import load_calibration
from .export import ModelFMU, export_model, model_records
from .identify import PreparedExperiment, prepare, run_masks

__all__ = ["TOLERANCE", "CrossfitMismatch", "CrossfitResult", "crossfit_run", "format_csv", "score_models"]

TOLERANCE = 1e-6  # largest allowed |fit(FMU) - fit(Python)| [fit points]


class CrossfitMismatch(RuntimeError):
    """The FMU and the Python simulation disagree by more than TOLERANCE."""


@dataclass
class CrossfitResult:
    """Fit [%] matrices (index: model, columns: datasets) from the FMUs and from Python, and their largest
    absolute difference [fit points] (NaN entries, unstable models, must be NaN in both)."""

    fmu: pd.DataFrame
    python: pd.DataFrame
    max_abs_diff: float


def _order(records: dict[str, dict[str, Any]], datasets: list[str]) -> list[str]:
    """Per-dataset models in dataset order, then ``selected``, then any other model by name."""
    first = [n for n in datasets if n in records]
    last = ["selected"] if "selected" in records else []
    return first + last + sorted(set(records) - set(first) - set(last))


def _preprocessing(rec: dict[str, Any], name: str) -> tuple[float, str]:
    pre = rec.get("preprocessing") or {}
    try:
        return float(pre["af"]), str(pre.get("output", "y"))
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"models/{name}.json: missing preprocessing.af") from None


def score_models(
    models: dict[str, tuple[armax.ArmaxModel, Path | None]],
    prepared: dict[str, dict[str, PreparedExperiment]],
    progress: Callable[[str], None] | None = None,
) -> CrossfitResult:
    """Score every model on every dataset through its FMU and through Python.

    ``models``: name -> (model, FMU path or None for a model that has no FMU, i.e. an unstable one);
    ``prepared``: name -> that model's {dataset: PreparedExperiment} (its own preprocessing). Raises CrossfitMismatch
    when the two matrices differ by more than TOLERANCE, ValueError when a dataset's sample time is not the
    model's.
    """
    rows_fmu: dict[str, dict[str, float]] = {}
    rows_py: dict[str, dict[str, float]] = {}
    for name, (model, fmu) in models.items():
        data = prepared[name]
        for ds, p in data.items():
            if not math.isclose(p.Ts, model.Ts, rel_tol=1e-6):
                msg = f"model {name} has Ts = {model.Ts:g} s but dataset {ds} is sampled at {p.Ts:g} s"
                raise ValueError(msg)
        rows_py[name] = {ds: armax.compare(model, p.u_d, p.y_f, ic="z") for ds, p in data.items()}
        if fmu is None:
            rows_fmu[name] = {ds: math.nan for ds in data}
        else:
            with ModelFMU(fmu) as runner:
                fits = {ds: armax.fit_percent(p.y_f, runner.run(p.u_d)["y_f"]) for ds, p in data.items()}
            rows_fmu[name] = fits
        if progress:
            progress(name)
    fmu_df = pd.DataFrame.from_dict(rows_fmu, orient="index")
    py_df = pd.DataFrame.from_dict(rows_py, orient="index")
    fmu_df.index.name = py_df.index.name = "model"
    a, b = fmu_df.to_numpy(float), py_df.to_numpy(float)
    if not np.array_equal(np.isnan(a), np.isnan(b)):
        i, j = np.argwhere(np.isnan(a) != np.isnan(b))[0]
        raise CrossfitMismatch(
            f"model {fmu_df.index[i]} on {fmu_df.columns[j]}: FMU fit {a[i, j]} but Python fit {b[i, j]}"
        )
    diff = np.where(np.isnan(a), 0.0, np.abs(a - b))
    worst = float(diff.max()) if diff.size else 0.0
    if worst > TOLERANCE:
        i, j = np.unravel_index(int(np.argmax(diff)), diff.shape)
        raise CrossfitMismatch(
            f"FMU and Python fits differ by up to {worst:.3g} fit points (> {TOLERANCE:g}): "
            f"model {fmu_df.index[i]} on dataset {fmu_df.columns[j]}"
        )
    return CrossfitResult(fmu_df, py_df, worst)


def format_csv(matrix: pd.DataFrame) -> str:
    """``crossfit.csv`` text: column ``model``, the datasets, then ``average`` (row mean; empty when a row has
    a NaN); fits with 6 decimals, NaN as an empty field."""
    df = matrix.copy()
    df["average"] = df.mean(axis=1, skipna=False)
    df.index.name = "model"
    return df.to_csv(float_format="%.6f", lineterminator="\n")


def crossfit_run(run: Path, progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Run every model of a run, as its FMU through fmpy, on every identification dataset.

    Each ``models/<name>.fmu`` is exported when missing or stale; ``crossfit.csv`` is written atomically.

    Parameters
    ----------
    run : Path
        An identified run directory.
    progress : callable, optional
        Called with one line of text per model.

    Returns
    -------
    pandas.DataFrame
        Fit [%] of model i (index ``model``) on dataset j (columns), then ``average``;
        ``attrs["max_abs_diff"]`` is the largest difference to the Python-side simulation [fit points].

    Raises
    ------
    harness.DataError
        Models identified from other data than the run holds.
    """
    run = Path(run)
    check_fresh(run, ("models",))
    datasets = load_run(run, role="identification")
    records = model_records(run)
    cal = load_calibration(run)
    cache: dict[tuple[float, str], dict[str, PreparedExperiment]] = {}
    models: dict[str, tuple[armax.ArmaxModel, Path | None]] = {}
    prepared: dict[str, dict[str, PreparedExperiment]] = {}
    for name in _order(records, list(datasets)):
        rec = records[name]
        key = _preprocessing(rec, name)
        if key not in cache:
            cache[key] = prepare(datasets, cal, key[0], key[1], run_masks(run))
        prepared[name] = cache[key]
        model = armax.ArmaxModel.from_dict(rec)
        path = run / "models" / f"{name}.fmu"
        if model.stable:
            models[name] = (model, export_model(rec, path))
        else:  # no fit for an unstable model (NaN row); remove a stale FMU
            path.unlink(missing_ok=True)
            models[name] = (model, None)
    res = score_models(models, prepared, progress)
    atomic_write_text(run / "crossfit.csv", format_csv(res.fmu))
    record_inputs(run, "crossfit.csv")
    out = res.fmu.copy()
    out["average"] = out.mean(axis=1, skipna=False)
    out.attrs["max_abs_diff"] = res.max_abs_diff
    return out
