"""Acceptance gate: does the selected model meet the spec's fit thresholds on every dataset and on average?

The thresholds come from the spec's ``[accept]`` table (``min_fit`` per dataset, ``min_average_fit``), as
recorded in the run's manifest or given explicitly. Fits are the cross-fit row of the selected model
(``crossfit.csv``, computed through the exported FMU) or, before the cross-fit, its cross-validation fits in
``models/selected.json``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from ..rundir import DataError, Manifest, check_fresh
from ..spec import ACCEPT_DEFAULTS, check_percent


@dataclass
class Verdict:
    """Outcome of the gate: ``passed`` and the failing cells as human-readable strings."""

    passed: bool
    fits: dict[str, float]
    average: float
    thresholds: dict[str, float]
    source: str
    failures: list[str] = field(default_factory=list)


def thresholds_of(run: Path, override: dict[str, Any] | None = None) -> dict[str, float]:
    """``[accept]`` thresholds of the run's spec (defaults where absent), with ``override`` on top."""
    th = dict(ACCEPT_DEFAULTS)
    th.update((Manifest.load(run).spec or {}).get("accept", {}))
    for k, v in (override or {}).items():
        th[k] = check_percent(f"--{k.replace('_', '-')}", v)
    return {k: check_percent(f"[accept].{k}", v) for k, v in th.items()}


def selected_fits(run: Path) -> tuple[dict[str, float], str]:
    """Per-dataset fits [%] of the selected model and where they were read from."""
    run = Path(run)
    cf = run / "crossfit.csv"
    if cf.exists():
        df = pd.read_csv(cf, index_col="model")
        if "selected" in df.index:
            row = df.loc["selected"].drop(labels=["average"], errors="ignore")
            return {k: float(v) for k, v in row.items()}, "crossfit.csv (exported FMU)"
    sel = run / "models" / "selected.json"
    if sel.exists():
        rec = json.loads(sel.read_text())
        return {k: (math.nan if v is None else float(v)) for k, v in rec["cv"].items()}, "models/selected.json"
    raise DataError(f"{run}: no selected model (run `flexjoint identify {run}` first)")


def judge(fits: Mapping[str, float], thresholds: Mapping[str, float], source: str = "") -> Verdict:
    """The rule, on per-dataset fits [%]: every fit >= ``min_fit`` and their mean >= ``min_average_fit``.
    Unstable (NaN) fits fail, and so does an empty set of fits."""
    th = {k: float(v) for k, v in thresholds.items()}
    fits = dict(fits)
    failures = [
        f"{name}: {'unstable' if math.isnan(v) else f'{v:.2f} %'} < {th['min_fit']:g} %"
        for name, v in fits.items()
        if not v >= th["min_fit"]
    ]
    avg = sum(fits.values()) / len(fits) if fits else math.nan
    if not avg >= th["min_average_fit"]:
        failures.append(f"average: {avg:.2f} % < {th['min_average_fit']:g} %")
    return Verdict(not failures, fits, avg, th, source, failures)


def accept(run: Path, override: dict[str, Any] | None = None) -> Verdict:
    """The acceptance gate: does a run's selected model meet the fit thresholds?

    Parameters
    ----------
    run : Path
        An identified run directory.
    override : dict, optional
        ``{"min_fit": ..., "min_average_fit": ...}`` [%] instead of the spec's ``[accept]`` values.

    Returns
    -------
    Verdict
        ``passed``, the fits, their average, the thresholds, where the fits were read, and the failing cells.

    Raises
    ------
    harness.DataError
        No selected model, or models or a cross-fit made from other data than the run holds.
    """
    thresholds = thresholds_of(run, override)  # first: a malformed manifest is said before a missing model
    fits, source = selected_fits(run)
    check_fresh(run, ("models", "crossfit.csv") if source.startswith("crossfit.csv") else ("models",))
    return judge(fits, thresholds, source)
