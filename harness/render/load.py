"""The results of a run directory, loaded once for :mod:`harness.render.report` and :mod:`harness.render.viewer`.

Datasets in the identification domain (detrended command u_d [V], filtered difference y_f = H(z) y [deg/sample] of
the tip angle y [deg]), the identified models with the selected model's simulation of every dataset, grid,
cross-fit matrix, diagnosis and doubled-rate check. Every path comes from :class:`harness.rundir.RunDir`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..diagnosis.replays import Replay, read_replays
from ..diagnosis.result import Diagnosis
from ..ident import armax
from ..ident.calibration import Calibration
from ..ident.identify import PreparedExperiment, prepare
from ..likelihood.force import ForceTrace, MissingForce
from ..likelihood.traces import read_traces
from ..likelihood.whiteness import Where
from ..rundir import DataError, Manifest, RunDir, load_run, stale_artefacts
from ..spec import IDENTIFY_DEFAULTS

__all__ = ["GRID_COLUMNS", "RunResults", "load_results"]

GRID_COLUMNS = ("dataset", "na", "nb", "nc", "nk", "causal", "stable", "fit")
MISSING_FORCE = ("shape", "size", "unit", "dead_band_v", "samples_near_zero")  # what is shown of likelihood.json's


@dataclass
class RunResults:
    """What a run directory holds, loaded once.

    ``prepared``: identification datasets (u_d [V], y_f [deg/sample], y [deg], u [V], Ts [s]), manifest order;
    ``models``: name -> (ArmaxModel, JSON record) for ``models/<dataset>.json`` and ``models/selected.json``;
    ``simulated``: dataset -> y_f simulated by the selected model (ic of its preprocessing record);
    ``crossfit``: models x datasets fit [%] (no average column), ``crossfit_source`` where it came from;
    ``records``: every experiment's dataset (all roles, manifest order); ``replays``: the diagnosis's replays beside
    the record per experiment (:mod:`harness.diagnosis.replays`); ``missing_force``: the likelihood engine's verdict
    (likelihood.json's ``missing_force``) and ``force`` the smoothed force per record it was read from
    (force_picture.parquet, :mod:`harness.likelihood.traces`), and ``not_white``, where its residuals are not white
    (likelihood.json's ``where``: "record channel: bands, stretches"), beside a diagnosis when ``diagnose --engine
    likelihood`` wrote them. A directory that ``flexjoint diagnose --out``
    wrote holds a diagnosis only: its manifest is then a stand-in of kind "diagnosis" with no experiments.
    ``stale``: the artefacts left out because they were made from other inputs than the directory holds
    (:func:`harness.rundir.stale_artefacts`: artefact -> the line that says so).
    """

    run: Path
    manifest: Manifest
    calibration: Calibration | None = None
    calibration_file: dict[str, Any] | None = None
    prepared: dict[str, PreparedExperiment] = field(default_factory=dict)
    models: dict[str, tuple[armax.ArmaxModel, dict[str, Any]]] = field(default_factory=dict)
    simulated: dict[str, np.ndarray] = field(default_factory=dict)
    grid: pd.DataFrame | None = None
    crossfit: pd.DataFrame | None = None
    crossfit_csv_average: pd.Series | None = None
    crossfit_source: str = ""
    diagnosis: Diagnosis | None = None
    doubled_rate: dict[str, Any] | None = None
    records: dict[str, pd.DataFrame] = field(default_factory=dict)
    replays: dict[str, Replay] = field(default_factory=dict)
    missing_force: MissingForce | None = None
    force: tuple[ForceTrace, ...] = ()
    not_white: tuple[str, ...] = ()
    af: float = float(IDENTIFY_DEFAULTS["af"])
    ic: str = str(IDENTIFY_DEFAULTS["ic"])
    stale: dict[str, str] = field(default_factory=dict)

    @property
    def paths(self) -> RunDir:
        """The run-directory layout."""
        return RunDir(self.run)

    @property
    def selected(self) -> tuple[armax.ArmaxModel, dict[str, Any]] | None:
        """The selected model and its record, or None before identification."""
        return self.models.get("selected")

    @property
    def sample_time(self) -> float:
        """Sampling period Ts [s]: from the data, else the manifest's sample_rate, else 1 s."""
        if self.prepared:
            return next(iter(self.prepared.values())).Ts
        rate = self.manifest.sample_rate
        return 1.0 / float(rate) if rate else 1.0

    @property
    def fit_threshold(self) -> float:
        """The identification's fit threshold [%] on the own dataset (from the recorded spec, else the default)."""
        ident = (self.manifest.spec or {}).get("identify", {})
        return float(ident.get("fit_threshold", IDENTIFY_DEFAULTS["fit_threshold"]))


def _read_json(path: Path) -> dict[str, Any] | None:
    if not path.exists():
        return None
    try:
        obj = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a JSON object")
    return obj


def _calibration(paths: RunDir, record: dict[str, Any] | None) -> tuple[Calibration | None, dict[str, Any] | None]:
    """The calibration the models were fitted with (model record), else ``calibration.json``; and that file."""
    raw = _read_json(paths.calibration)
    file_cal = Calibration.from_json(paths.calibration) if raw is not None else None
    if record and isinstance(record.get("calibration"), dict):
        c = record["calibration"]
        base = file_cal or Calibration(Kp=c["Kp"], Ke=c["Ke"])
        cal = Calibration(
            Kp=c.get("Kp", base.Kp),
            Ke=c.get("Ke", base.Ke),
            gauge_offset_v=c.get("gauge_offset_v", base.gauge_offset_v),
            pot_offset_v=c.get("pot_offset_v", base.pot_offset_v),
            dead_zone_v=base.dead_zone_v,
        )
        return cal, raw
    return file_cal, raw


def load_results(run: Path) -> RunResults:
    """Load everything the report and the viewer need from a run directory (any stage: campaign, import,
    identified, diagnosed)."""
    run = Path(run)
    if not run.is_dir():
        raise DataError(f"{run}: no such run directory")
    paths = RunDir(run)
    if not paths.manifest.exists() and paths.diagnosis.exists():  # what `flexjoint diagnose --out` wrote
        manifest = Manifest(kind="diagnosis", experiments=[], sample_rate=None)
    else:
        manifest = Manifest.load(run)
    res = RunResults(run=run, manifest=manifest, stale=stale_artefacts(run) if paths.manifest.exists() else {})
    if manifest.experiments:
        res.records = load_run(run, role=None)
    names = [e.name for e in res.manifest.entries("identification")]
    for name in [*names, "selected"] if "models" not in res.stale else []:
        p = paths.model(name)
        rec = _read_json(p)
        if rec is not None:
            try:
                res.models[name] = (armax.ArmaxModel.from_dict(rec), rec)
            except ValueError as exc:
                raise ValueError(f"{p}: {exc}") from None
    sel = res.models.get("selected")
    sel_rec = sel[1] if sel else None
    pre = (sel_rec or {}).get("preprocessing", {})
    res.af = float(pre.get("af", res.af))
    res.ic = str(pre.get("ic", res.ic))
    if "calibration.json" not in res.stale or sel_rec is not None:
        res.calibration, res.calibration_file = _calibration(paths, sel_rec)
    if names and res.calibration is not None:
        output = str(pre.get("output", "y"))
        res.prepared = prepare({n: res.records[n] for n in names}, res.calibration, res.af, output)
    if sel is not None and sel[0].stable:
        for name, prep in res.prepared.items():
            res.simulated[name] = armax.simulate(sel[0], prep.u_d, prep.y_f, res.ic)
    if paths.grid.exists() and "grid.csv" not in res.stale:
        res.grid = pd.read_csv(paths.grid)
        missing = [c for c in GRID_COLUMNS if c not in res.grid.columns]
        if missing:
            raise ValueError(f"{paths.grid}: missing column(s) {', '.join(missing)}")
    _load_crossfit(res)
    fresh = paths.diagnosis.exists() and "diagnosis.json" not in res.stale
    res.diagnosis = Diagnosis.load(paths.diagnosis) if fresh else None
    if res.diagnosis is not None and paths.diagnosis_replays.exists():
        res.replays = read_replays(paths.diagnosis_replays)
    likelihood = _read_json(paths.likelihood) if res.diagnosis is not None else None
    if likelihood is not None and paths.force_traces.exists():
        res.missing_force, res.force = _verdict(paths.likelihood, likelihood), read_traces(paths.force_traces)
        res.not_white = tuple(f"{r} {c}: {w}" for r, chans in likelihood.get("where", {}).items()
                              for c, doc in chans.items() if (w := Where.from_json(doc).words()))  # fmt: skip
    res.doubled_rate = _read_json(paths.doubled_rate) if "doubled_rate.json" not in res.stale else None
    return res


def _verdict(path: Path, doc: dict[str, Any]) -> MissingForce:
    """likelihood.json's ``missing_force`` with the fields the report and the recording show; one line when not."""
    mf = doc.get("missing_force")
    missing = [k for k in MISSING_FORCE if k not in mf] if isinstance(mf, dict) else list(MISSING_FORCE)
    if missing or not isinstance(mf, dict):
        raise DataError(f"{path}: missing_force lacks {', '.join(missing)} (re-run diagnose --engine likelihood)")
    return MissingForce.from_json(mf)


def _load_crossfit(res: RunResults) -> None:
    path = res.paths.crossfit
    if path.exists() and "crossfit.csv" not in res.stale:
        df = pd.read_csv(path)
        if "model" not in df.columns:
            raise ValueError(f"{path}: first column must be 'model', got {list(df.columns)[:1]}")
        df = df.set_index("model")
        df.index = df.index.astype(str)
        if "average" in df.columns:
            res.crossfit_csv_average = df.pop("average").astype(float)
        res.crossfit = df.astype(float)
        res.crossfit_source = "crossfit.csv (the exported FMUs)"
        return
    rows = {}
    for name, (_, rec) in res.models.items():
        if isinstance(rec.get("cv"), dict) and rec["cv"]:
            rows[name] = {k: (math.nan if v is None else float(v)) for k, v in rec["cv"].items()}
    if rows:
        res.crossfit = pd.DataFrame.from_dict(rows, orient="index")
        res.crossfit.index.name = "model"
        res.crossfit_source = "the models' cross-validation in Python (crossfit.csv not written yet)"
