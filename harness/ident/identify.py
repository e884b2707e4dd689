"""The identification campaign of lab 1: ARMAX order grid per dataset, threshold, cross-validation on every
dataset, and the selection of the simplest model near the best average.

Domain: the model maps the detrended command u_d [V] to y_f = H(z) y, the differentiated and low-pass filtered
tip angle y [deg] (``harness.ident.preprocess``), with its mean removed too; fits are MATLAB ``compare`` fits in percent
on that pair. Lab 1 detrended only the input, reasoning that differentiation detrends the output; it does
not when the command has a nonzero mean (PRBS B = 0.05 at 60 s averages ~0.3 V here), and the constant velocity
that mean produces is then an error no model of u_d can fit, so both sides are detrended.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import pandas as pd

from .. import spec as specmod
from ..executor import Executor
from ..rundir import (
    DataError,
    Manifest,
    atomic_write_text,
    load_run,
    record_inputs,
    recorded_spec,
    stale_artefacts,
    write_json,
)
from ..spec import IdentifySettings
from . import armax
from .calibration import Calibration, alpha_deg, calibrate_run, load_calibration, theta_deg, tip_deg
from .gridfit import PreparedExperiment, cross_validate, fit_slice
from .preprocess import preprocess


def output_angle(df: pd.DataFrame, cal: Calibration, output: str = "y") -> np.ndarray:
    """The identified angle [deg] from DAQ volts: ``y`` tip = theta + alpha, ``theta`` shaft, ``alpha`` deflection."""
    if output == "y":
        return tip_deg(df["theta_v"].to_numpy(), df["alpha_v"].to_numpy(), cal)
    if output == "theta":
        return theta_deg(df["theta_v"].to_numpy(), cal)
    if output == "alpha":
        return alpha_deg(df["alpha_v"].to_numpy(), cal)
    raise ValueError(f"identify.output must be y, theta or alpha, got {output!r}")


OUTPUT_CHANNELS = {"y": ("theta", "alpha"), "theta": ("theta",), "alpha": ("alpha",)}  # the sensors an output reads


def run_masks(run: Path) -> dict[str, dict[str, list[list[int]]]]:
    """The samples an import masked per dataset and channel, [first, end) ranges (the manifest's ``masked``: a
    channel pinned at a rail or stuck, :mod:`harness.rig.faults`); empty for a run without any."""
    return {e.name: e.masked for e in Manifest.load(run).experiments if e.masked}


def unmasked_stretch(n: int, spans: Sequence[Sequence[int]]) -> tuple[int, int]:
    """The longest stretch [first, end) of ``n`` samples that holds none of the masked ranges ``spans``."""
    bad = np.zeros(n, dtype=bool)
    for a, b in spans:
        bad[int(a) : int(b)] = True
    edges = np.flatnonzero(np.diff(np.r_[1, bad.astype(int), 1]))  # starts and ends of the unmasked runs
    if not edges.size:
        return 0, 0
    runs = list(zip(edges[0::2], edges[1::2], strict=True))
    a, b = max(runs, key=lambda r: (r[1] - r[0], -r[0]))
    return int(a), int(b)


def prepare(
    datasets: dict[str, pd.DataFrame],
    cal: Calibration,
    af: float = 0.8,
    output: str = "y",
    masked: Mapping[str, Mapping[str, Sequence[Sequence[int]]]] | None = None,
) -> dict[str, PreparedExperiment]:
    """Convert a run's volts to the output angle and apply lab 1's preprocessing to every dataset.

    The command is detrended; the angle [deg] is differentiated and low-passed by H(z) = (1 - af)(z - 1)/(z - af),
    which removes the integrator. A dataset with masked samples in a channel the output reads (``masked``:
    :func:`run_masks`) is identified on its longest stretch without any (:func:`unmasked_stretch`): an ARMAX model
    fits a stretch of contiguous samples, and none is fitted across a fault.

    Parameters
    ----------
    datasets : dict of str to pandas.DataFrame
        The datasets (:func:`harness.load_run`).
    cal : Calibration
        Kp, Ke and the offsets that convert the DAQ's volts to degrees.
    af : float
        The filter's pole.
    output : {"y", "theta", "alpha"}
        The identified angle: the tip (theta + alpha), the shaft, or the deflection.
    masked : mapping, optional
        Dataset -> channel -> masked [first, end) sample ranges.

    Returns
    -------
    dict of str to PreparedExperiment
        Per dataset: ``u_d`` [V], ``y_f`` [deg/sample], the angle itself, the raw command and ``Ts``.
    """
    out = {}
    for name, df in datasets.items():
        spans = [r for c in OUTPUT_CHANNELS.get(output, ()) for r in (masked or {}).get(name, {}).get(c, [])]
        if spans:
            a, b = unmasked_stretch(len(df), spans)
            df = df.iloc[a:b]
        y = output_angle(df, cal, output)
        u = df["u"].to_numpy(dtype=float)
        u_d, y_f = preprocess(u, y, af, "constant", initial="rest")
        offset = float(np.mean(y_f))
        Ts = float(np.median(np.diff(df["t"].to_numpy())))
        out[name] = PreparedExperiment(name, u_d, y_f - offset, y, u, Ts, offset)
    return out


def _orders(spec_identify: IdentifySettings) -> list[tuple[int, int, int]]:
    def rng(key: str, v: int | list[int]) -> range:
        lo, hi = (v, v) if isinstance(v, int) else (int(v[0]), int(v[1]))
        if lo < 0 or hi < lo:
            raise ValueError(f"identify.{key} must be an integer or [lo, hi] with 0 <= lo <= hi, got {v!r}")
        return range(lo, hi + 1)

    s = spec_identify
    return [(na, nb, nc) for na in rng("na", s["na"]) for nb in rng("nb", s["nb"]) for nc in rng("nc", s["nc"])]


T = TypeVar("T")


def slices_per_dataset(n_datasets: int, n_workers: int, n_orders: int) -> int:
    """Into how many tasks each dataset's grid is cut: the fewest that give every worker as many tasks (the lab's 9
    datasets on 2 workers: 2, 18 tasks of ~0.7 s instead of 9 of ~1.4 s, where one worker fits 5 datasets and the
    other waits for it); 1 serially; at most one order per task."""
    return max(1, min(n_workers // math.gcd(n_datasets, n_workers), n_orders))


def deal(n: int, k: int) -> list[int]:
    """The slice each of ``n`` orders goes to, dealt back and forth over ``k`` slices (0, 1, .., k-1, k-1, .., 1, 0,
    0, 1, ..): slices of like cost where the cost grows along the grid. Every k-th order instead gave the lab's second
    slice every even nc, 13 % more work (0.59 s against 0.67 s), and a map in order hands every dataset's second slice
    to the same worker."""
    return [i % k if (i // k) % 2 == 0 else k - 1 - i % k for i in range(n)]


def _slices(items: list[T], k: int) -> list[list[T]]:
    """``items`` dealt into ``k`` slices (:func:`deal`)."""
    slot = deal(len(items), k)
    return [[o for o, s in zip(items, slot, strict=True) if s == j] for j in range(k)]


def _undeal(parts: list[list[T]]) -> list[T]:
    """What the slices of :func:`_slices` gave, item by item, back in the order of the items."""
    rows = [iter(p) for p in parts]
    return [next(rows[s]) for s in deal(sum(len(p) for p in parts), len(parts))]


@dataclass
class GridResult:
    """The grid (one row per fitted order and dataset), the models by row index, and the selection."""

    grid: pd.DataFrame
    models: dict[int, armax.ArmaxModel]
    best: dict[str, int]  # dataset -> row index of that dataset's best model
    selected: int
    rule: str
    datasets: list[str] = field(default_factory=list)


def _select(grid: pd.DataFrame, rows: pd.Index, tolerance: float) -> tuple[int, str]:
    """Simplest model (fewest na+nb+nc, then highest mean) within ``tolerance`` points of the best mean CV fit."""
    cand = grid.loc[rows]
    cand = cand[np.isfinite(cand["cv_mean"])]
    if cand.empty:
        raise ValueError("no stable causal model to select from")
    best = float(cand["cv_mean"].max())
    near = cand[cand["cv_mean"] >= best - tolerance]
    pick = near.sort_values(["n_params", "cv_mean"], ascending=[True, False], kind="stable").index[0]
    rule = (
        f"simplest model (fewest na+nb+nc, ties by higher mean) whose mean cross-validation fit is within "
        f"{tolerance:g} fit points of the best mean ({best:.2f} %)"
    )
    return int(pick), rule


def run_grid(
    prepared: dict[str, PreparedExperiment],
    spec_identify: IdentifySettings,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
    scheduler: str | None = None,
) -> GridResult:
    """Fit the order grid on every dataset, keep causal models above the threshold, cross-validate, select.

    Each dataset's grid, cut into slices of the orders, is tasks of a :class:`harness.Executor`; the rows come
    back in the grid's order however it was cut.

    Parameters
    ----------
    prepared : dict of str to PreparedExperiment
        The identification datasets (:func:`prepare`).
    spec_identify : IdentifySettings
        The spec's ``[identify]`` table: order ranges, nk, threshold, tolerance, initial state.
    workers, scheduler : optional
        Where to run (:class:`harness.Executor`).
    progress : callable, optional
        Called with one line of text per finished task.

    Returns
    -------
    GridResult
        Every order on every dataset (``grid``), the models, each dataset's best, the selected one and the rule
        that selected it.
    """
    orders = _orders(spec_identify)
    nk, ic = int(spec_identify["nk"]), str(spec_identify["ic"])
    threshold, tol = float(spec_identify["fit_threshold"]), float(spec_identify["tolerance"])
    rows: list[dict[str, Any]] = []
    names = list(prepared)
    # tasks of a dataset and a slice of the orders (:func:`deal`: slices of like cost) on the executor, as many per
    # worker (BLAS at one thread per worker: the fits are N x <= 19 regressions); then the cross-validation of the
    # survivors, a slice of them per worker
    with Executor(workers, scheduler, progress) as ex:
        k = slices_per_dataset(len(prepared), ex.n_workers, len(orders))
        tasks = [(p, part) for p in prepared.values() for part in _slices(orders, k)]
        labels = [f"{n} {j + 1}/{k}" if k > 1 else n for n in prepared for j in range(k)]
        res = ex.map(fit_slice, tasks, nk, ic, labels=labels)
        for i in range(len(prepared)):
            rows.extend(_undeal(res[i * k : (i + 1) * k]))
        models = {i: armax.ArmaxModel.from_dict(r.pop("model")) for i, r in enumerate(rows) if r["model"] is not None}
        for r in rows:
            r.pop("model", None)
        grid = pd.DataFrame(rows)
        grid["survivor"] = grid["causal"] & grid["stable"] & (grid["fit"] >= threshold)
        # a dataset with nothing above the threshold keeps its best stable causal fit (flagged by survivor=False)
        fallback = {}
        for n in names:
            if not (grid["survivor"] & (grid["dataset"] == n)).any():
                ok = grid.index[(grid["dataset"] == n) & grid["causal"] & grid["stable"]]
                if len(ok) == 0:
                    raise ValueError(f"dataset {n}: no stable causal ARMAX model in the grid")
                fallback[n] = int(grid.loc[ok, "fit"].idxmax())
        checked = sorted({*np.flatnonzero(grid["survivor"].to_numpy()).tolist(), *fallback.values()})
        parts = _slices(checked, max(1, min(ex.n_workers, len(checked))))
        fits = ex.map(cross_validate, [[models[i] for i in part] for part in parts], prepared, ic, quiet=True)
    cv = np.full((len(grid), len(names)), np.nan)
    cv[checked] = _undeal(fits)
    grid["cv_mean"] = cv.mean(axis=1)
    for j, n in enumerate(names):
        grid[f"cv_{n}"] = cv[:, j]
    best = {
        n: fallback[n]
        if n in fallback
        else _select(grid, grid.index[(grid["dataset"] == n) & grid["survivor"]], tol)[0]
        for n in names
    }
    survivors = grid.index[grid["survivor"]]
    selected, rule = _select(grid, survivors if len(survivors) else pd.Index(list(best.values())), tol)
    return GridResult(grid, models, best, selected, rule, names)


def model_record(
    res: GridResult, i: int, name: str, spec_identify: IdentifySettings, cal: Calibration
) -> dict[str, Any]:
    """The JSON written to ``models/<name>.json``."""
    row = res.grid.loc[i]
    m = res.models[i]
    return {
        "name": name,
        "dataset": str(row["dataset"]),
        **m.to_dict(),
        "fit_own": float(row["fit"]),
        "cv": {n: float(row[f"cv_{n}"]) for n in res.datasets},
        "cv_mean": float(row["cv_mean"]),
        "survivor": bool(row["survivor"]),
        "preprocessing": {
            "af": float(spec_identify["af"]),
            "output": str(spec_identify["output"]),
            "detrend": "constant (input and filtered output)",
            "initial": "rest",
            "ic": str(spec_identify["ic"]),
        },
        "calibration": {"Kp": cal.Kp, "Ke": cal.Ke, "gauge_offset_v": cal.gauge_offset_v},
        "selected": i == res.selected,
        "selection_rule": res.rule,
    }


def write_grid(res: GridResult, run: Path, spec_identify: IdentifySettings, cal: Calibration) -> dict[str, Path]:
    """Write ``grid.csv`` and ``models/<dataset>.json`` + ``models/selected.json``; returns model paths by name."""

    run = Path(run)
    atomic_write_text(run / "grid.csv", res.grid.to_csv(index=False, float_format="%.6f"))
    paths = {}
    for name, i in [*res.best.items(), ("selected", res.selected)]:
        paths[name] = run / "models" / f"{name}.json"
        write_json(paths[name], model_record(res, i, name, spec_identify, cal))
    record_inputs(run, "grid.csv")
    record_inputs(run, "models")
    return paths


def load_model(path: Path) -> tuple[armax.ArmaxModel, dict[str, Any]]:
    """Read ``models/<name>.json`` back: the model and its full record."""

    rec = json.loads(Path(path).read_text())
    return armax.ArmaxModel.from_dict(rec), rec


def identify_run(
    run: Path, identify: Mapping[str, Any] | None = None, progress: Callable[[str], None] | None = None
) -> tuple[GridResult, dict[str, PreparedExperiment], Calibration, IdentifySettings]:
    """Grid, cross-validation and selection on a run's identification datasets; writes grid.csv and models/. A
    calibration.json made from other data than the run holds is made again from its calibration experiments.

    Parameters
    ----------
    run : Path
        The run directory (a campaign or an import).
    identify : mapping, optional
        Overrides of the spec's ``[identify]`` table (``na``, ``nb``, ``nc`` ranges, ``af``, ...).
    progress : callable, optional
        Called with one line of text per finished grid task.

    Returns
    -------
    grid : GridResult
        The order grid, the best model per dataset, the selected one and the rule that chose it.
    prepared : dict of str to PreparedExperiment
        Each identification dataset detrended and filtered as identified.
    calibration : Calibration
        Kp, Ke and the dead zone the angles were read with.
    identify : IdentifySettings
        The ``[identify]`` settings used.
    """

    run = Path(run)
    spec = recorded_spec(run)
    ident = cast(IdentifySettings, {**(spec.identify if spec else specmod.IDENTIFY_DEFAULTS), **(identify or {})})
    stale = stale_artefacts(run).get("calibration.json")
    if stale and not Manifest.load(run).entries("calibration"):
        raise DataError(stale.replace("re-run flexjoint identify", "import the records again"))
    cal = calibrate_run(run) if stale else load_calibration(run)
    prepared = prepare(load_run(run), cal, float(ident["af"]), str(ident["output"]), run_masks(run))
    res = run_grid(prepared, ident, progress=progress)
    write_grid(res, run, ident, cal)
    return res, prepared, cal, ident
