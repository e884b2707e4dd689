"""Monte Carlo over rig tolerances (``flexjoint sweep``): does the identification still pass on every rig?

``run_sweep(spec, ["plant.Ks=normal(1.3,0.05)", ...], n, seed, out)`` draws ``n`` rigs, runs each rig's campaign
(its calibration and identification experiments; analysis experiments such as the multisine are skipped),
calibrates it from its own calibration experiments, then either identifies it with the spec's ``[identify]``
grid (``orders`` fixes one (na, nb, nc): the lean tolerance study of a selected model structure) or scores a
given model (``models/<m>.json``) on it, and applies the spec's ``[accept]`` thresholds to the per-dataset fits.

Sampling: a Latin hypercube (default, ``scipy.stats.qmc.LatinHypercube``) or a scrambled Sobol sequence
(``sampler="sobol"``; keep ``n`` a power of 2 for its balance) of ``n`` points in [0, 1)^d, each coordinate
mapped through the inverse CDF of its parameter's distribution:

- ``normal(mu, sigma)``: Gaussian, mean mu, standard deviation sigma (unbounded);
- ``uniform(lo, hi)``: uniform on [lo, hi];
- ``lognormal(median, s)``: log(x) ~ normal(log(median), s), so s is about the relative spread (x > 0);
- ``triangular(lo, mode, hi)``: triangular on [lo, hi] with its peak at mode.

Integer FMU parameters are rounded to the nearest integer. Every rig is driven by the spec's own commands (the
same PRBS realisations, as a lab reuses its excitation files) and gets its own measurement-noise seed
(``daq.seed``, derived from ``seed`` and the rig's index): rigs differ in their build and in their noise, not in
the test they are put through.

Fits [%] are MATLAB ``compare`` fits in the identification domain (see :mod:`harness.ident.identify`): with the grid,
the selected model's cross-validation fit on each dataset; with a given model, that model's fit on each dataset
of the rig (its own preprocessing, the rig's calibration). A rig passes when every dataset's fit >= ``min_fit``
and their mean >= ``min_average_fit`` (``harness.ident.accept``'s rule; an unstable model or a rig with no stable
causal model fails).

Summary statistics:

- pass rate k/n with the Wilson score 95 % interval (``scipy.stats.binomtest(...).proportion_ci``);
- sensitivity of the mean fit to each varied parameter, ranked by its first-order index S1, the share of the
  mean fit's variance explained by that parameter alone: the correlation ratio Var(E[fit | x_i]) / Var(fit)
  (McKay's index for Latin-hypercube samples), estimated from the sweep's own rigs by sorting them on x_i into
  B = round(sqrt(n)) equal-count bins, and adjusted for the bias of B bin means (eta^2_adj = 1 - (1 - eta^2)
  (n - 1) / (n - B), floored at 0). It holds for responses that are not monotone, such as a given model's fit
  that peaks at the nominal parameter value. Alongside: standardised rank regression coefficients (SRRC: least
  squares of the standardised ranks of the mean fit on those of the parameters) give the direction of a
  monotone effect, with the rank regression's R^2, and Spearman rank correlations. A failed rig's missing fit
  counts as the worst fit in every index.

Outputs (written by the client only): ``sweep.parquet`` (one row per rig), ``sweep.json`` (configuration and
summary, byte-stable), ``sweep.timing.json`` (wall time), ``report.md``, ``figures/sweep_*.png`` and the Rerun
recording ``sweep.rrd``.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
import time
import uuid
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import rerun as rr
import rerun.blueprint as rrb
from matplotlib.ticker import MaxNLocator
from scipy import stats
from scipy.stats import binomtest, qmc, rankdata, spearmanr

from . import spec as specmod
from .executor import Executor, FmuBytes, fmu_bytes
from .fmu.build import build_all
from .fmu.modeldesc import source_model
from .ident import armax
from .ident.accept import judge
from .ident.calibration import calibrate
from .ident.identify import load_model, prepare, run_grid
from .render.figures import new_figure, save_figure
from .render.viewer import bar_bounds, log_bars, write_recording
from .rig.campaign import simulate_spec, versions
from .rundir import DataError, ExperimentEntry, RunDir, atomic_write_bytes, atomic_write_text, write_json

__all__ = [
    "DISTRIBUTIONS",
    "Vary",
    "draw",
    "first_order",
    "parse_vary",
    "pass_interval",
    "report_sweep",
    "run_sweep",
    "sensitivity",
]

Progress = Callable[[str], None]

# distribution -> its parameters, in order
DISTRIBUTIONS: dict[str, tuple[str, ...]] = {
    "normal": ("mu", "sigma"),
    "uniform": ("lo", "hi"),
    "lognormal": ("median", "s"),
    "triangular": ("lo", "mode", "hi"),
}
SAMPLERS = ("lhs", "sobol")
_MODELS = {"plant": "flexjoint", "daq": "daq"}
_VARY_RE = re.compile(r"^\s*([A-Za-z_]\w*)\.([A-Za-z_]\w*)\s*=\s*([A-Za-z_]\w*)\s*\((.*)\)\s*$")


# ----------------------------------------------------------------------------------------------- distributions
@dataclass(frozen=True)
class Vary:
    """One varied rig parameter: ``table.name`` (FMI name in ``[plant]`` or ``[daq]``), distribution and its
    parameters (see the module docstring)."""

    table: str
    name: str
    dist: str
    args: tuple[float, ...]
    integer: bool = False

    @property
    def key(self) -> str:
        return f"{self.table}.{self.name}"

    @property
    def law(self) -> str:
        """The distribution as written, e.g. ``normal(1.3, 0.05)``."""
        return f"{self.dist}({', '.join(f'{a:g}' for a in self.args)})"

    def __str__(self) -> str:
        return f"{self.key}={self.law}"

    def ppf(self, u: np.ndarray) -> np.ndarray:
        """Inverse CDF at probabilities ``u`` in (0, 1)."""

        a = self.args
        if self.dist == "normal":
            x = stats.norm.ppf(u, loc=a[0], scale=a[1])
        elif self.dist == "uniform":
            x = a[0] + (a[1] - a[0]) * u
        elif self.dist == "lognormal":
            x = a[0] * np.exp(a[1] * stats.norm.ppf(u))
        else:
            lo, mode, hi = a
            x = stats.triang.ppf(u, (mode - lo) / (hi - lo), loc=lo, scale=hi - lo)
        x = np.asarray(x, dtype=float)
        return np.round(x) if self.integer else x

    def bounds(self) -> tuple[float, float]:
        """Support of the distribution [lo, hi] (infinite ends for normal; (0, inf) for lognormal)."""
        if self.dist == "normal":
            return -math.inf, math.inf
        if self.dist == "lognormal":
            return 0.0, math.inf
        return self.args[0], self.args[-1]


def parse_vary(text: str) -> Vary:
    """Parse ``table.name=dist(a,b[,c])`` (e.g. ``plant.Ks=normal(1.3,0.05)``); errors name what is valid."""
    m = _VARY_RE.match(text)
    if not m:
        raise specmod.SpecError(f"--vary {text!r}: expected table.name=dist(args), e.g. plant.Ks=normal(1.3,0.05)")
    table, name, dist, argtext = m.groups()
    if table not in _MODELS:
        raise specmod.SpecError(f"--vary {text!r}: table must be plant or daq")
    params = specmod.fmu_parameters(_MODELS[table])
    if name not in params:
        raise specmod.SpecError(f"--vary {text!r}: unknown {table} parameter {name!r}; valid: {', '.join(params)}")
    if (table, name) == ("daq", "seed"):
        raise specmod.SpecError(f"--vary {text!r}: each rig's noise seed is drawn from --seed, not varied")
    if params[name][0] == "Boolean":
        raise specmod.SpecError(f"--vary {text!r}: {table}.{name} is a Boolean and cannot be drawn")
    if dist not in DISTRIBUTIONS:
        raise specmod.SpecError(f"--vary {text!r}: unknown distribution {dist!r}; valid: {', '.join(DISTRIBUTIONS)}")
    want = DISTRIBUTIONS[dist]
    try:
        args = tuple(float(a) for a in argtext.split(",")) if argtext.strip() else ()
    except ValueError:
        raise specmod.SpecError(f"--vary {text!r}: arguments must be numbers") from None
    if len(args) != len(want) or not all(math.isfinite(a) for a in args):
        raise specmod.SpecError(f"--vary {text!r}: {dist} takes {len(want)} finite numbers ({', '.join(want)})")
    ok = {
        "normal": args[-1] > 0,
        "lognormal": len(args) == 2 and args[0] > 0 and args[1] > 0,
        "uniform": args[0] < args[-1],
        "triangular": len(args) == 3 and args[0] <= args[1] <= args[2] and args[0] < args[2],
    }[dist]
    if not ok:
        rule = {
            "normal": "sigma > 0",
            "lognormal": "median > 0 and s > 0",
            "uniform": "lo < hi",
            "triangular": "lo <= mode <= hi and lo < hi",
        }[dist]
        raise specmod.SpecError(f"--vary {text!r}: {dist} needs {rule}")
    return Vary(table, name, dist, args, params[name][0] == "Integer")


def draw(varies: Sequence[Vary], n: int, seed: int, sampler: str = "lhs") -> pd.DataFrame:
    """``n`` rigs: one column per varied parameter (``table.name``), one row per rig, from a Latin hypercube
    (``lhs``) or scrambled Sobol (``sobol``) design seeded with ``seed``, mapped through each inverse CDF."""

    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive number of rigs, got {n!r}")
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
    keys = [v.key for v in varies]
    if len(set(keys)) != len(keys):
        raise ValueError(f"a parameter is varied twice: {', '.join(sorted({k for k in keys if keys.count(k) > 1}))}")
    if not varies:
        raise ValueError("nothing to vary: give at least one --vary table.name=dist(...)")
    rng = np.random.default_rng(seed)
    d = len(varies)
    if sampler == "lhs":
        u = qmc.LatinHypercube(d, seed=rng).random(n)
    else:
        with warnings.catch_warnings():  # n not a power of 2: documented, the balance is then approximate
            warnings.simplefilter("ignore", UserWarning)
            u = qmc.Sobol(d, scramble=True, seed=rng).random(n)
    u = np.clip(u, 1e-12, 1.0 - 1e-12)  # inverse CDFs are infinite at 0 and 1
    return pd.DataFrame({v.key: v.ppf(u[:, j]) for j, v in enumerate(varies)})


def rig_seed(seed: int, i: int) -> int:
    """Noise seed (``daq.seed``) of rig ``i`` of a sweep seeded with ``seed`` (a 31-bit integer)."""
    return int(np.random.SeedSequence([int(seed), int(i)]).generate_state(1)[0] % (2**31 - 1))


# ----------------------------------------------------------------------------------------------- one rig (a task)
@dataclass(frozen=True)
class Plan:
    """What every rig task shares: the base spec, the identification settings or the model record to score,
    and the built FMUs."""

    spec: specmod.Spec
    identify: specmod.IdentifySettings
    model: dict[str, Any] | None
    fmus: Mapping[str, FmuBytes]


def rig_spec(base: specmod.Spec, params: Mapping[str, float], seed: int) -> specmod.Spec:
    """The base spec with one rig's parameters (``{"plant.Ks": 1.31, ...}``) and noise seed (``daq.seed``),
    validated; the analysis experiments are dropped (a sweep only identifies)."""
    raw = copy.deepcopy(base.raw)
    for key, value in params.items():
        table, name = _split_key(key)
        kind = specmod.fmu_parameters(_MODELS[table])[name][0]
        raw.setdefault(table, {})[name] = int(value) if kind == "Integer" else float(value)
    raw.setdefault("daq", {})["seed"] = int(seed)
    raw["experiment"] = [e for e in raw.get("experiment", []) if e.get("role", "identification") == "identification"]
    return specmod.from_dict(raw, base.path)


def run_rig(item: tuple[int, dict[str, float], int], plan: Plan) -> dict[str, Any]:
    """One rig, start to finish, as one task: campaign (serially, on this worker's rig), calibration,
    identification or scoring of the given model; returns numbers only (the client writes every file)."""

    i, params, seed = item
    spec = rig_spec(plan.spec, params, seed)
    data = simulate_spec(spec, plan.fmus, workers=1)
    # calibrated from the simulated columns in memory, as calibrate_run would from this campaign's run directory
    cal = calibrate([ExperimentEntry(name=e.name, role=e.role, signal=e.signal) for e in spec.calibration], data)
    ident = {e.name: pd.DataFrame(data[e.name]) for e in spec.experiments}
    row: dict[str, Any] = {"rig": i, "noise_seed": seed, **params}
    row.update(Kp=cal.Kp, Ke=cal.Ke, dead_zone_v=cal.dead_zone_v)
    names = list(ident)
    if plan.model is not None:
        m = armax.ArmaxModel.from_dict(plan.model)
        pre = plan.model.get("preprocessing") or {}
        prepared = prepare(ident, cal, float(pre.get("af", 0.8)), str(pre.get("output", "y")))
        ic = str(pre.get("ic", "z"))
        fits = {n: armax.compare(m, prepared[n].u_d, prepared[n].y_f, ic=ic) for n in names}
        orders, source, error = (m.na, m.nb, m.nc, m.nk), str(plan.model.get("name", "model")), ""
    else:
        prepared = prepare(ident, cal, float(plan.identify["af"]), str(plan.identify["output"]))
        try:
            res = run_grid(prepared, plan.identify, workers=1)
        except ValueError as exc:  # no stable causal model on this rig: a failing rig, not a failed sweep
            fits, orders, source, error = dict.fromkeys(names, math.nan), (-1, -1, -1, -1), "", str(exc)
        else:
            sel = res.grid.loc[res.selected]
            fits = {n: float(sel[f"cv_{n}"]) for n in names}
            orders = (int(sel.na), int(sel.nb), int(sel.nc), int(sel.nk))
            source, error = str(sel.dataset), ""
    row.update(na=orders[0], nb=orders[1], nc=orders[2], nk=orders[3], model_from=source, error=error)
    row.update({f"fit_{n}": float(fits[n]) for n in names})
    return row


# ----------------------------------------------------------------------------------------------- statistics
def pass_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a pass rate k/n."""

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def first_order(x: np.ndarray, y: np.ndarray, bins: int) -> float:
    """Bias-adjusted correlation ratio of ``y`` on ``x`` with ``bins`` equal-count bins of sorted ``x`` (see the
    module docstring); NaN when y does not vary or there are too few rigs for the bins."""
    n = y.size
    sst = float(np.sum((y - y.mean()) ** 2))
    if sst == 0.0 or n <= bins or bins < 2:
        return math.nan
    groups = np.array_split(np.argsort(x, kind="stable"), bins)
    ssb = sum(g.size * (float(y[g].mean()) - float(y.mean())) ** 2 for g in groups)
    return max(0.0, 1.0 - (1.0 - ssb / sst) * (n - 1) / (n - bins))


def sensitivity(x: pd.DataFrame, y: np.ndarray) -> dict[str, Any]:
    """First-order index S1 (ranking), SRRC and Spearman correlation of ``y`` (NaN = worst) on each column of
    ``x``; see the module docstring."""

    y = np.asarray(y, dtype=float)
    finite = np.isfinite(y)
    yv = np.where(finite, y, np.min(y[finite]) if finite.any() else 0.0)  # a failed rig: the worst fit
    n, d = x.shape
    bins = max(2, int(round(math.sqrt(n))))
    ry = rankdata(np.where(finite, y, -np.inf))
    rx = np.column_stack([rankdata(x[c].to_numpy()) for c in x.columns]) if d else np.empty((n, 0))
    sx, sy = rx.std(axis=0), ry.std()
    live = sx > 0
    srrc = np.full(d, math.nan)
    r2 = math.nan
    if sy > 0 and live.any() and n >= int(live.sum()) + 2:
        zx = (rx[:, live] - rx[:, live].mean(axis=0)) / sx[live]
        zy = (ry - ry.mean()) / sy
        beta = np.linalg.lstsq(zx, zy, rcond=None)[0]
        srrc[live] = beta
        r2 = float(1.0 - np.sum((zy - zx @ beta) ** 2) / np.sum(zy**2))
    rows = []
    for j, c in enumerate(x.columns):
        rho = float(spearmanr(rx[:, j], ry)[0]) if live[j] and sy > 0 else math.nan
        s1 = first_order(x[c].to_numpy(dtype=float), yv, bins) if live[j] else math.nan
        rows.append({"param": c, "s1": s1, "srrc": float(srrc[j]), "spearman": rho})

    def order(r: dict[str, Any]) -> tuple[float, float, str]:
        s1, b = r["s1"], r["srrc"]
        return (-s1 if math.isfinite(s1) else 1.0, -abs(b) if math.isfinite(b) else 0.0, r["param"])

    rows.sort(key=order)
    for rank, r in enumerate(rows, 1):
        r["rank"] = rank
    return {
        "target": "fit_mean",
        "method": f"first-order index S1: bias-adjusted correlation ratio of the mean fit on each parameter "
        f"({bins} equal-count bins); SRRC and Spearman rank correlations alongside; failed rigs count as the "
        "worst fit",
        "bins": bins,
        "r2_rank": r2,
        "ranking": rows,
    }


def _stats(v: np.ndarray) -> dict[str, float]:
    f = v[np.isfinite(v)]
    if not f.size:
        return {"n": 0}
    q = np.percentile(f, [5, 50, 95])
    std = float(f.std(ddof=1)) if f.size > 1 else 0.0
    return {
        "n": int(f.size),
        "mean": float(f.mean()),
        "std": std,
        "min": float(f.min()),
        "p05": float(q[0]),
        "median": float(q[1]),
        "p95": float(q[2]),
        "max": float(f.max()),
    }


def summarise(table: pd.DataFrame, varies: Sequence[Vary], thresholds: Mapping[str, float]) -> dict[str, Any]:
    """Pass rate with its interval, fit statistics, failures per dataset and the sensitivity ranking."""
    n = len(table)
    k = int(table["passed"].sum())
    lo, hi = pass_interval(k, n)
    fit_cols = [c for c in table.columns if c.startswith("fit_") and c not in ("fit_mean", "fit_min")]
    below = {c[4:]: int((~(table[c] >= thresholds["min_fit"])).sum()) for c in fit_cols}
    params = {}
    for v in varies:
        col = table[v.key].to_numpy(dtype=float)
        params[v.key] = {"distribution": v.law, **_stats(col)}
    return {
        "pass": {
            "passed": k,
            "n": n,
            "rate": k / n,
            "ci95": [lo, hi],
            "method": "Wilson score interval, 95 %",
        },
        "fit_mean": _stats(table["fit_mean"].to_numpy(dtype=float)),
        "fit_min": _stats(table["fit_min"].to_numpy(dtype=float)),
        "below_min_fit_by_dataset": below,
        "rigs_without_model": int((table["error"] != "").sum()),
        "parameters": params,
        "sensitivity": sensitivity(table[[v.key for v in varies]], table["fit_mean"].to_numpy(dtype=float)),
    }


# ----------------------------------------------------------------------------------------------- outputs
def _write_parquet(path: Path, table: pd.DataFrame) -> None:
    sink = pa.BufferOutputStream()
    t = pa.Table.from_pandas(table, preserve_index=False)
    t = t.replace_schema_metadata(None)  # no pandas metadata blob: plain columns, stable bytes
    pq.write_table(t, sink, compression="zstd", write_statistics=False, store_schema=False)
    atomic_write_bytes(path, sink.getvalue().to_pybytes())


def param_label(key: str) -> str:
    """``plant.Ks`` -> "plant.Ks [N.m/rad]": the varied parameter with the unit its FMU declares (none: as is)."""
    table, _, name = key.partition(".")
    try:
        unit = source_model(_MODELS[table]).parameters()[name].unit if table in _MODELS else ""
    except (FileNotFoundError, KeyError):
        unit = ""
    return f"{key} [{unit}]" if unit else key


def write_figures(out: Path, table: pd.DataFrame, summary: dict[str, Any], th: Mapping[str, float]) -> list[str]:
    """``figures/sweep_fit.png`` (mean-fit histogram), ``sweep_scatter.png`` (mean fit against each varied
    parameter, pass/fail coloured), ``sweep_sensitivity.png`` (S1 bars); returns their relative paths. Each with
    a title, axes with units, whole rigs on a count axis."""

    figs = RunDir(out).figures
    ok = table["passed"].to_numpy(bool)
    fm = table["fit_mean"].to_numpy(float)
    n = len(table)
    fig = new_figure(7, 4)
    ax = fig.subplots()
    f = fm[np.isfinite(fm)]
    ax.hist(f, bins=max(5, min(40, int(np.sqrt(max(f.size, 1))) * 2)), color="#4a7ab5")
    ax.axvline(th["min_average_fit"], color="#d62728", ls="--", label=f"min_average_fit {th['min_average_fit']:g} %")
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("mean fit over the identification datasets [%]")
    ax.set_ylabel("rigs [count]")
    no_model = n - f.size
    extra = f"; {no_model} without a model, not shown" if no_model else ""
    ax.set_title(f"mean fit of {n} rigs: {int(ok.sum())} pass{extra}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, figs / "sweep_fit.png")

    keys = list(summary["parameters"])
    fig = new_figure(4.5 * len(keys), 4)
    axes = np.atleast_1d(fig.subplots(1, len(keys)))
    for ax, key in zip(axes, keys, strict=True):
        x = table[key].to_numpy(float)
        ax.scatter(x[ok], fm[ok], s=12, c="#2ca02c", label="pass")
        ax.scatter(x[~ok], np.where(np.isfinite(fm[~ok]), fm[~ok], np.nan), s=12, c="#d62728", label="fail")
        ax.axhline(th["min_average_fit"], color="#999999", ls="--", lw=0.8, label="min_average_fit")
        ax.set_xlabel(param_label(key))
        ax.set_ylabel("mean fit [%]")
        ax.set_title(f"mean fit against {key}")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, figs / "sweep_scatter.png")

    rank = summary["sensitivity"]["ranking"]
    fig = new_figure(7, 0.6 * len(rank) + 1.6)
    ax = fig.subplots()
    vals = [r["s1"] if math.isfinite(r["s1"]) else 0.0 for r in rank]
    names = [param_label(r["param"]) + ("" if math.isfinite(r["s1"]) else " (S1 undefined)") for r in rank]
    ax.barh(names[::-1], vals[::-1], color="#4a7ab5")
    ax.set_xlabel("first-order sensitivity index S1 of the mean fit [1]")
    ax.set_title("which varied parameter explains the spread of the mean fit")
    ax.set_xlim(0, max(1.0, max(vals, default=0.0)))
    fig.tight_layout()
    save_figure(fig, figs / "sweep_sensitivity.png")
    return ["figures/sweep_fit.png", "figures/sweep_scatter.png", "figures/sweep_sensitivity.png"]


def _num(x: Any, fmt: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def report_markdown(doc: dict[str, Any], figures: Sequence[str]) -> str:
    """The sweep's ``report.md``."""
    s, p = doc["summary"], doc["summary"]["pass"]
    th = doc["thresholds"]
    how = (
        f"the given model `{doc['model']['name']}` (ARMAX{tuple(doc['model']['orders'])}) scored on every rig"
        if doc["model"]
        else f"identified on every rig with the spec's grid (na {doc['identify']['na']}, nb {doc['identify']['nb']},"
        f" nc {doc['identify']['nc']}, nk {doc['identify']['nk']})"
    )
    lines = [
        f"# Tolerance sweep: {doc['spec']['name']}",
        "",
        f"{doc['n']} rigs drawn by {doc['sampler']} (seed {doc['seed']}); model: {how}. A rig passes when every "
        f"identification dataset fits >= {th['min_fit']:g} % and their mean >= {th['min_average_fit']:g} %.",
        "",
        f"**Pass rate: {p['passed']}/{p['n']} = {100 * p['rate']:.1f} %** "
        f"(95 % Wilson interval {100 * p['ci95'][0]:.1f}-{100 * p['ci95'][1]:.1f} %).",
        "",
        "| parameter | distribution | min | median | max |",
        "|---|---|---|---|---|",
    ]
    for key, st in s["parameters"].items():
        cells = [_num(st.get(k), ".4g") for k in ("min", "median", "max")]
        lines.append(f"| `{key}` | {st['distribution']} | {' | '.join(cells)} |")
    fm = s["fit_mean"]
    lines += [
        "",
        f"Mean fit [%]: mean {_num(fm.get('mean'))}, 5th percentile {_num(fm.get('p05'))}, median "
        f"{_num(fm.get('median'))}, min {_num(fm.get('min'))}. Rigs without a stable causal model: "
        f"{s['rigs_without_model']}.",
        "",
        "Rigs below min_fit, by dataset: " + ", ".join(f"{k} {v}" for k, v in s["below_min_fit_by_dataset"].items()),
        "",
        "## Sensitivity of the mean fit",
        "",
        f"{s['sensitivity']['method']}; rank regression R^2 = {_num(s['sensitivity']['r2_rank'], '.3f')}.",
        "",
        "| rank | parameter | S1 | SRRC | Spearman |",
        "|---|---|---|---|---|",
    ]
    for r in s["sensitivity"]["ranking"]:
        cells = [_num(r["s1"], ".3f"), _num(r["srrc"], "+.3f"), _num(r["spearman"], "+.3f")]
        lines.append(f"| {r['rank']} | `{r['param']}` | {' | '.join(cells)} |")
    lines += ["", "## Figures", ""] + [f"![{Path(f).stem}]({f})" for f in figures]
    lines += ["", "Data: `sweep.parquet` (one row per rig), summary: `sweep.json`, Rerun: `sweep.rrd`.", ""]
    return "\n".join(lines)


def write_rrd(out: Path, table: pd.DataFrame, doc: dict[str, Any], markdown: str, path: Path | None = None) -> Path:
    """``sweep.rrd`` (by the viewer's writer, :func:`harness.render.viewer.write_recording`): per-rig series on the
    ``rig`` timeline, mean fit against each parameter on that parameter's own timeline, the sensitivity bars and
    the report, with its blueprint."""

    key = hashlib.sha256(json.dumps({k: doc[k] for k in ("spec", "vary", "n", "seed")}, sort_keys=True).encode())
    rig = rr.TimeColumn("rig", sequence=table["rig"].to_numpy(np.int64))
    ok = table["passed"].to_numpy(bool)
    fm = table["fit_mean"].to_numpy(float)
    keys = [v["key"] for v in doc["vary"]]
    rank = doc["summary"]["sensitivity"]["ranking"]
    s1 = np.array([r["s1"] if math.isfinite(r["s1"]) else 0.0 for r in rank])
    bounds = bar_bounds(len(rank))
    scatter_tabs = []
    for key_ in keys:
        scatter_tabs.append(rrb.TimeSeriesView(origin=f"scatter/{rr.escape_entity_path_part(key_)}", name=key_))
    blueprint = rrb.Blueprint(
        rrb.Tabs(
            rrb.TextDocumentView(origin="report", name="report"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="rigs/fit", name="fits per rig [%]"),
                rrb.TimeSeriesView(origin="rigs/params", name="drawn parameters"),
                name="rigs",
            ),
            rrb.Tabs(*scatter_tabs, name="fit vs parameter"),
            rrb.Spatial2DView(origin="sensitivity", name="first-order index S1 [1] (ranked)", visual_bounds=bounds),
        ),
        rrb.TimePanel(timeline="rig"),
    )

    def log(rec: rr.RecordingStream) -> None:
        rec.send_recording_name(f"flexjoint sweep {doc['spec']['name']}")
        text = "\n".join(x for x in markdown.splitlines() if not x.startswith("!["))  # no broken image links
        rec.log("report", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        series = (("mean", fm, [40, 90, 220]), ("min", table["fit_min"].to_numpy(float), [230, 120, 20]))
        for name, values, color in series:
            rec.log(f"rigs/fit/{name}", rr.SeriesLines(colors=[color], names=[f"{name} fit"]), static=True)
            rec.send_columns(f"rigs/fit/{name}", indexes=[rig], columns=rr.Scalars.columns(scalars=values))
        passed = rr.SeriesPoints(colors=[[44, 160, 44]], names=["passed (100) / failed (0)"])
        rec.log("rigs/fit/passed", passed, static=True)
        rec.send_columns("rigs/fit/passed", indexes=[rig], columns=rr.Scalars.columns(scalars=100.0 * ok))
        for key_ in keys:
            part = rr.escape_entity_path_part(key_)
            x = table[key_].to_numpy(float)
            rec.send_columns(f"rigs/params/{part}", indexes=[rig], columns=rr.Scalars.columns(scalars=x))
            scale = 10.0 ** (6 - math.floor(math.log10(max(float(np.max(np.abs(x))), 1e-300))))
            tl = f"{key_} [x{scale:.0e}]"
            for label, mask, color in (("pass", ok, [44, 160, 44]), ("fail", ~ok, [214, 39, 40])):
                if not mask.any():
                    continue
                p = f"scatter/{part}/{label}"
                rec.log(p, rr.SeriesPoints(colors=[color], names=[f"{label}: mean fit [%]"]), static=True)
                idx = rr.TimeColumn(tl, sequence=np.round(x[mask] * scale).astype(np.int64))
                vals = np.where(np.isfinite(fm[mask]), fm[mask], 0.0)
                rec.send_columns(p, indexes=[idx], columns=rr.Scalars.columns(scalars=vals))
        log_bars(rec, "sensitivity", [r["param"] for r in rank], [("S1", s1, [74, 122, 181])])

    rec_id = str(uuid.UUID(hex=key.hexdigest()[:32]))
    return write_recording(path or out / "sweep.rrd", rec_id, log, blueprint=blueprint)


def _split_key(key: str) -> tuple[str, str]:
    """``table.name`` -> (table, name)."""
    table, _, name = key.partition(".")
    return table, name


# ----------------------------------------------------------------------------------------------- the sweep
def parse_orders(text: str | Sequence[int] | None) -> tuple[int, int, int] | None:
    """``"na,nb,nc"`` (or a sequence) -> (na, nb, nc); None stays None."""
    if text is None:
        return None
    parts = text.split(",") if isinstance(text, str) else list(text)
    try:
        o = tuple(int(p) for p in parts)
    except ValueError:
        raise ValueError(f"--orders {text!r}: expected three integers na,nb,nc") from None
    if len(o) != 3 or min(o) < 0:
        raise ValueError(f"--orders {text!r}: expected three non-negative integers na,nb,nc")
    return o[0], o[1], o[2]


def run_sweep(
    spec: specmod.Spec | str | Path,
    vary: Sequence[str | Vary],
    n: int,
    seed: int = 0,
    out: Path = Path("sweep"),
    *,
    model: Path | None = None,
    orders: str | Sequence[int] | None = None,
    sampler: str = "lhs",
    workers: int | None = None,
    scheduler: str | None = None,
    progress: Progress | None = None,
    rrd: bool = True,
) -> dict[str, Any]:
    """Monte Carlo over rig tolerances: draw ``n`` rigs, run and judge each as a task, write the outputs.

    Parameters
    ----------
    spec : Spec, str or Path
        The base campaign.
    vary : sequence of str or Vary
        The parameters drawn: ``"plant.Ks=normal(1.3,0.05)"``; ``normal(mu,sigma)``, ``uniform(lo,hi)``,
        ``lognormal(median,s)``, ``triangular(lo,mode,hi)``.
    n : int
        Number of rigs.
    seed : int
        Seed of the draws and of each rig's noise.
    out : Path
        The directory to write: ``sweep.parquet`` (one row per rig), ``sweep.json``, ``report.md``, ``figures/``,
        ``sweep.rrd``.
    model : Path, optional
        Score this ``models/<m>.json`` on every rig instead of identifying each.
    orders : str or sequence of int, optional
        Identify one order ``na,nb,nc`` per rig instead of the spec's grid.
    sampler : {"lhs", "sobol"}
        Latin hypercube or Sobol points.
    workers, scheduler : optional
        Where to run (:class:`harness.Executor`).
    progress : callable, optional
        Called with one line of text per rig.
    rrd : bool
        Write ``sweep.rrd``.

    Returns
    -------
    dict
        The ``sweep.json`` document (pass rate with its 95 % Wilson interval, parameters ranked by sensitivity,
        thresholds, draws) plus ``wall_s``.
    """

    t0 = time.perf_counter()
    base = spec if isinstance(spec, specmod.Spec) else specmod.load(spec)
    varies = [v if isinstance(v, Vary) else parse_vary(v) for v in vary]
    fixed = parse_orders(orders)
    record = None
    if model is not None:
        if not Path(model).is_file():
            raise FileNotFoundError(f"model {model} not found")
        m, record = load_model(Path(model))
        if not math.isclose(m.Ts, base.Ts, rel_tol=1e-9):
            raise ValueError(f"model {model} has Ts = {m.Ts:g} s but the spec samples at {base.Ts:g} s")
        if fixed is not None:
            raise ValueError("--orders fixes the orders of the identification; it does not apply to --model")
    ident = base.identify.copy()
    if fixed is not None:
        ident["na"], ident["nb"], ident["nc"] = fixed
    if RunDir(out).manifest.exists():
        raise FileExistsError(f"--out {out} holds a run: the sweep's report.md and figures/ would replace its own; "
                              "give another --out")  # fmt: skip
    draws = draw(varies, n, seed, sampler)
    seeds = [rig_seed(seed, i) for i in range(n)]
    rig_spec(base, draws.iloc[0].to_dict(), seeds[0])  # a bad parameter value fails here, before any task
    fmus = {k: fmu_bytes(v) for k, v in build_all().items()}
    plan = Plan(base, ident, record, fmus)
    items = [(i, {k: float(v) for k, v in draws.iloc[i].items()}, seeds[i]) for i in range(n)]
    with Executor(workers, scheduler, progress) as ex:
        rows = ex.map(run_rig, items, plan, desc="rig", labels=[str(i) for i in range(n)])
    table = pd.DataFrame(rows)
    for v in varies:  # integer parameters stay integers in the table
        if v.integer:
            table[v.key] = table[v.key].astype(np.int64)
    fit_cols = [c for c in table.columns if c.startswith("fit_")]
    th = {k: float(base.accept[k]) for k in ("min_fit", "min_average_fit")}
    fits = table[fit_cols].to_numpy(dtype=float)
    with np.errstate(invalid="ignore"):
        table["fit_mean"] = fits.mean(axis=1)
        table["fit_min"] = fits.min(axis=1)
    table["passed"] = [judge(dict(zip(fit_cols, map(float, f), strict=True)), th).passed for f in fits]

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(table, varies, th)
    doc = {
        "kind": "sweep",
        "spec": {"name": base.name, "file": Path(base.path).name, "sha256": base.sha256()},
        "vary": [{"key": v.key, "distribution": v.dist, "args": list(v.args), "integer": v.integer} for v in varies],
        "n": n,
        "seed": seed,
        "sampler": {"lhs": "Latin hypercube", "sobol": "scrambled Sobol"}[sampler],
        "identify": None if record else {k: ident[k] for k in ("na", "nb", "nc", "nk", "af", "output", "ic")},
        "model": None
        if record is None
        else {"name": record.get("name"), "file": str(model), "orders": [record[k] for k in ("na", "nb", "nc", "nk")]},
        "thresholds": th,
        "fmus": {k: {"file": v.name, "sha256": v.sha256} for k, v in fmus.items()},
        "versions": versions(),
        "summary": summary,
    }
    _write_parquet(out / "sweep.parquet", table)
    write_json(out / "sweep.json", doc)
    _write_report(out, table, doc, rrd)
    wall = time.perf_counter() - t0
    write_json(out / "sweep.timing.json", {"wall_s": wall, "workers": workers, "scheduler": scheduler})
    return {**doc, "wall_s": wall}


def _write_report(out: Path, table: pd.DataFrame, doc: dict[str, Any], rrd: bool | Path) -> Path | None:
    """``report.md`` and ``figures/`` of a sweep, and its recording (``sweep.rrd``, or the path ``rrd``; none when
    False); returns the recording's path."""
    figures = write_figures(out, table, doc["summary"], doc["thresholds"])
    markdown = report_markdown(doc, figures)
    atomic_write_text(RunDir(out).report, markdown)
    if rrd is False:
        return None
    return write_rrd(out, table, doc, markdown, None if rrd is True else Path(rrd))


def report_sweep(out: Path, rrd: Path | None = None) -> tuple[Path, Path]:
    """Write a sweep directory's report again from its ``sweep.json`` and ``sweep.parquet`` (``flexjoint report``
    on a sweep): report.md, figures/ and the recording (``sweep.rrd`` unless ``rrd``); returns (report, recording)."""
    out = Path(out)
    for f in ("sweep.json", "sweep.parquet"):
        if not (out / f).is_file():
            raise DataError(f"{out}: not a sweep directory (no {f})")
    try:
        doc = json.loads((out / "sweep.json").read_text())
        table = pq.read_table(out / "sweep.parquet").to_pandas()
    except (json.JSONDecodeError, OSError, pa.ArrowException) as exc:
        raise DataError(f"{out}: sweep.json or sweep.parquet unreadable ({exc})") from None
    varies = [Vary(*_split_key(v["key"]), v["distribution"], tuple(v["args"]), v["integer"]) for v in doc["vary"]]
    doc["summary"] = summarise(table, varies, doc["thresholds"])  # the same numbers, in the order they were made
    recording = _write_report(out, table, doc, rrd or True)
    assert recording is not None
    return RunDir(out).report, recording
