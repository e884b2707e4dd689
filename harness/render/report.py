"""``report.md`` and ``figures/*.png`` of a run directory, written from the run directory alone, for a person:
each section has a table or a figure a lab report would have; the full detail stays in the JSON and CSV files.

The run is loaded by :mod:`harness.render.load`, the numbers are computed by :mod:`harness.render.analysis` and
:mod:`harness.ident`, the figures drawn by :mod:`harness.render.figures`, the diagnosis worded by
:mod:`harness.render.gap_text`. A line of prose is at most 200 characters (:func:`harness.render.tables.wrap_prose`
cuts longer ones at their sentences); the report keeps the facts, the manual the explanations.
"""

from __future__ import annotations

import contextvars
import math
import re
import threading
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ..diagnosis.replays import STAGES
from ..executor import Executor, in_session
from ..ident import armax, lti
from ..ident.calibration import LAB1_CALIBRATION
from ..ident.preprocess import filter_response
from ..rundir import atomic_write_bytes
from ..spec import SPEC_DIR
from . import figures
from .analysis import (
    MIN_COHERENCE,
    best_per_dataset,
    bode_curves,
    bode_grid,
    estimates,
    measured_frf,
    record_angles,
    replay_fits,
    residual_tests,
    zoom_window,
)
from .force import force_markdown
from .gap_text import diagnosis_markdown, gap_rows, manual
from .load import RunResults, load_results
from .tables import crossfit_table, fmt, fmt_any, orders, table, vec, wrap_prose

__all__ = ["PendingReport", "begin_report", "figure_name", "holds", "spec_overrides", "title", "write_report"]

FILTER_AFS = (0.6, 0.8, 0.9)
SQUARE_HZ, SQUARE_V, SQUARE_PERIODS = 0.4, 1.0, 3  # square-wave test input of the selected model
ZOOM_S = 4.0  # s: the zoom window of the time-response panels, where the residual is largest
DOUBLED_RATE_LABELS = {
    "experiment": "experiment",
    "sample_rate_hz": "sample rate [Hz]",
    "orders": "orders (na, nb, nc, nk)",
    "fit_model_50hz_as_is": "fit of the selected model applied as is [%]",
    "fit_reidentified_100hz": "fit of the same orders re-identified at this rate [%]",
    "gain_ratio_as_is": "static gain of the model as is / re-identified",
    "skipped": "skipped",
}


Drawings = list[tuple[figures.FigureJob, Path]]  # the report's figures to draw: (job, file), drawn by draw()


def _same(a: float, b: float, tol: float = 0.005) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


# ----------------------------------------------------------------------------------------------- sections
def figure_name(prefix: str, name: str) -> str:
    """``figures/<prefix>_<name>.png`` with any character of ``name`` a file name should not carry replaced."""
    return f"figures/{prefix}_{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}.png"


def spec_overrides(res: RunResults) -> list[str]:
    """``table.name=value`` where the spec a campaign ran differs from the bundled spec file it names (its
    ``--set`` overrides); [] for imports, for specs that are not bundled, and when there is no difference."""
    m = res.manifest
    path = SPEC_DIR / (m.spec_file or "")
    if m.kind != "campaign" or not m.spec or not m.spec_file or not path.is_file():
        return []
    try:
        base = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return []
    out = []
    for tab, ran in sorted(m.spec.items()):
        if not isinstance(ran, dict):
            continue
        sheet = base.get(tab)
        given = sheet if isinstance(sheet, dict) else {}
        out += [f"{tab}.{k}={v}" for k, v in sorted(ran.items()) if not isinstance(v, dict) and given.get(k) != v]
    return out


def holds(res: RunResults) -> str:
    """What the directory holds, in the pipeline's words: "simulated campaign: data, calibrated, identified, ..."."""
    p = res.paths
    have = [
        ("data", bool(res.records)),
        ("calibrated", p.calibration.exists()),
        ("identified", res.selected is not None),
        ("cross-fitted", p.crossfit.exists()),
        ("diagnosed", res.diagnosis is not None),
    ]
    source = {"campaign": "simulated campaign", "import": "imported records"}.get(res.manifest.kind, res.manifest.kind)
    return f"{source}: " + ", ".join(k for k, ok in have if ok) if any(ok for _, ok in have) else source


def title(res: RunResults) -> str:
    """The report's title: the spec's name and its overrides, or what a diagnosis compared."""
    m = res.manifest
    if m.kind == "diagnosis" and res.diagnosis is not None:
        d = res.diagnosis
        return f"flexjoint diagnosis: `{d.real}` against `{d.sim_spec}`"
    name = ((m.spec or {}).get("campaign") or {}).get("name", m.spec_file or "") or res.run.name
    over = spec_overrides(res)
    return f"flexjoint run report: {name}" + (f" (--set {', --set '.join(over)})" if over else "")


def _section_header(res: RunResults) -> list[str]:
    m = res.manifest
    lines = [f"# {title(res)}", ""]
    versions = ", ".join(f"{k} {v}" for k, v in sorted((m.versions or {}).items()))
    rows = [
        ["holds", holds(res)],
        ["spec", f"`{m.spec_file}`" if m.spec_file else ""],
        ["overrides (`--set`)", ", ".join(f"`{o}`" for o in spec_overrides(res))],
        ["spec sha256", f"`{m.spec_sha256}`" if m.spec_sha256 else ""],
        ["random seed", fmt_any(m.seed) if m.seed is not None else ""],
        ["sample rate [Hz]", fmt_any(m.sample_rate) if m.sample_rate is not None else ""],
        ["experiments", str(len(m.experiments)) if m.experiments else ""],
        ["identification datasets", ", ".join(res.prepared)],
        ["versions", versions],
    ]
    if m.kind == "diagnosis" and res.diagnosis is not None:
        d = res.diagnosis
        rows += [["real run", f"`{d.real}` (relative to this directory)"], ["simulation", f"`{d.sim_spec}`"]]
    lines += [*table(["item", "value"], [r for r in rows if r[1]]), ""]
    if res.stale:
        lines += ["Left out of this report, made from other inputs than the directory holds:", ""]
        lines += [f"- {why}" for why in res.stale.values()] + [""]
    if m.removed:
        lines += [f"Replaced an earlier run here (`--force`), removing: {', '.join(f'`{r}`' for r in m.removed)}.", ""]
    sources = m.sources
    if m.kind == "import" and sources:
        units = {e.name: e.units or {} for e in m.experiments}
        body = [
            [
                ds,
                f"`{src.get('file', '?')}`",
                str(src.get("format", "—")),
                ", ".join(f"{k} {units[ds][k]}" for k in ("t", "u", "theta", "alpha") if k in units.get(ds, {})) or "—",
                "; ".join(src.get("notes") or []) or "—",
            ]
            for ds, src in sources.items()
            if isinstance(src, dict)
        ]
        lines += ["Imported records:", "", *table(["dataset", "file", "format", "units", "notes"], body), ""]
    return lines


def _section_data(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    """Every experiment's data as measured (command, shaft angle, deflection over time), one figure each."""
    if not res.records:
        return []
    rows, links = [], []
    for e in res.manifest.experiments:
        df = res.records.get(e.name)
        if df is None:
            continue
        t = df["t"].to_numpy(dtype=float)
        theta, alpha, unit = record_angles(res, e.name)
        link = figure_name("data", e.name)
        ref = df["ref"].to_numpy(dtype=float) if "ref" in df.columns and unit == "deg" else None
        u = df["u"].to_numpy(dtype=float)
        job: figures.FigureJob = (figures.experiment_data, (e.name, t - t[0], u, theta, alpha, unit), {"ref": ref})
        drawings.append((job, figdir / Path(link).name))
        rows.append([e.name, e.role, e.signal or "—", str(t.size), fmt(float(t[-1] - t[0]), 2)])
        links += [f"![data of {e.name}]({link})", ""]
    how = "through the run's calibration" if res.calibration is not None else "in volts (no calibration yet)"
    return [
        "## Data",
        "",
        f"Each experiment as measured: command u [V], shaft angle theta and link deflection alpha {how}.",
        "",
        *table(["experiment", "role", "signal", "samples", "duration [s]"], rows),
        "",
        *links,
    ]


def _section_calibration(res: RunResults) -> list[str]:
    lines = ["## Calibration", ""]
    cal = res.calibration
    if cal is None:
        return [*lines, res.stale.get("calibration.json", "No `calibration.json` in this run."), ""]
    rows = []
    for key, label, unit in (("Kp", "Kp", "deg/V"), ("Ke", "Ke", "deg/V"), ("dead_zone_v", "dead zone", "V")):
        v = float(getattr(cal, key))
        ref = LAB1_CALIBRATION[key]
        diff = 100.0 * (v - ref) / abs(ref) if math.isfinite(v) else math.nan
        rows.append([label, unit, fmt(v, 4), fmt(ref, 4), fmt(diff, 2)])
    rows.append(["gauge offset", "V", fmt(cal.gauge_offset_v, 4), "—", "—"])
    rows.append(["pot offset", "V", fmt(cal.pot_offset_v, 4), "—", "—"])
    lines += table(["quantity", "unit", "this run", "lab 1", "difference [%]"], rows)
    src = (res.calibration_file or {}).get("source") or {}
    methods = [f"- {k}: {v['method']}" for k, v in src.items() if isinstance(v, dict) and "method" in v]
    if methods:
        lines += ["", "Methods:", "", *methods]
    return [*lines, ""]


def _section_filter(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    Ts = res.sample_time
    drawings.append(((figures.filter_responses, (FILTER_AFS, res.af, bode_grid(Ts), Ts), {}),
                     figdir / "filter_response.png"))  # fmt: skip
    rows = []
    for af in FILTER_AFS:
        fc = -math.log(af) / (2 * math.pi * Ts)
        rows.append([f"{af:g}", fmt(fc, 3), fmt(float(filter_response(af, [0.5 / Ts], Ts)[0][0]), 4)])
    return [
        "## Preprocessing filter",
        "",
        f"H(z) = (1 - af)(z - 1)/(z - af): differentiation and low-pass in one; af = {res.af:g} used here.",
        "",
        *table(["af", "pole frequency -ln(af)/(2 pi Ts) [Hz]", "gain at Nyquist"], rows),
        "",
        "![filter responses](figures/filter_response.png)",
        "",
    ]


def _grid_counts(res: RunResults, g: pd.DataFrame) -> list[str]:
    thr = res.fit_threshold
    causal = g["causal"].astype(bool)
    stable = g["stable"].astype(bool) & causal
    above = stable & (pd.to_numeric(g["fit"], errors="coerce") >= thr)
    survivors = g["survivor"].astype(bool) if "survivor" in g else above
    rows = [
        ["order combinations x datasets", str(len(g))],
        ["datasets", str(g["dataset"].nunique())],
        ["causal (nb + nk <= na), fitted", str(int(causal.sum()))],
        ["stable", str(int(stable.sum()))],
        [f"fit >= {thr:g} % on own dataset", str(int(above.sum()))],
        ["survivors (cross-validated on all datasets)", str(int(survivors.sum()))],
    ]
    return [*table(["grid", "count"], rows), ""]


def _per_dataset_lines(res: RunResults) -> list[str]:
    """Per dataset: the best model of grid.csv by mean cross-validation fit and the one the selection rule chose
    (the simplest within the tolerance of that best)."""
    per = {n: r for n, (_, r) in res.models.items() if n != "selected"}
    if not per:
        return []
    best = best_per_dataset(res.grid) if res.grid is not None else pd.DataFrame()
    rows = []
    for n, r in per.items():
        b = best.loc[n] if n in best.index else None
        best_cells = [orders(b), fmt(b["fit"]), fmt(b["cv_mean"])] if b is not None else ["—", "—", "—"]
        rows.append([n, *best_cells, orders(r), fmt(r.get("fit_own")), fmt(r.get("cv_mean"))])
    header = [
        "dataset",
        "best by CV: orders",
        "fit own [%]",
        "mean CV fit [%]",
        "selected: orders",
        "fit own [%]",
        "mean CV fit [%]",
    ]
    return [
        "Per dataset, the best model of the grid by mean cross-validation (CV) fit over all datasets, and the one "
        "the selection rule keeps:",
        "",
        *table(header, rows),
        "",
    ]


def _estimates_lines(res: RunResults, m: armax.ArmaxModel, rec: dict) -> list[str]:
    """Free parameters with their standard deviations (from ``cov``) and the information criteria of the model on
    its training dataset, as MATLAB's ``present``/``fpe``/``aic`` give them."""
    p = res.prepared.get(str(rec.get("dataset")))
    est = estimates(m, p.y_f.size if p is not None else 0)
    if est is None:
        return []
    rows = [
        [n, f"{v:.6g}", f"{sd:.3g}", fmt(100.0 * sd / abs(v), 1) if v else "—"]
        for n, v, sd in zip(est.names, est.values, est.std, strict=True)
    ]
    lines = [
        "Free parameters of the selected model with one standard deviation (square root of the covariance "
        "diagonal in the model JSON):",
        "",
        *table(["parameter", "estimate", "std", "std [% of estimate]"], rows),
        "",
    ]
    if math.isfinite(est.fpe):
        d = len(est.names)
        lines += [
            *table(
                ["dataset", "N", "d", "loss V", "FPE = V (1 + d/N)/(1 - d/N)", "AIC = N ln V + 2 d"],
                [[str(rec.get("dataset")), str(est.N), str(d), f"{est.loss:.6g}", f"{est.fpe:.6g}", f"{est.aic:.2f}"]],
            ),
            "",
        ]
    return lines


def _section_grid(res: RunResults) -> list[str]:
    lines = ["## ARMAX grid and selection", ""]
    if res.grid is not None and len(res.grid):
        lines += _grid_counts(res, res.grid)
    else:
        lines += ["No `grid.csv` in this run.", ""]
    sel = res.selected
    if sel is None:
        return [*lines, "No selected model (`models/selected.json`) yet.", ""]
    m, rec = sel
    lines += [
        f"Selected model: ARMAX (na, nb, nc, nk) = {orders(rec)}, trained on `{rec.get('dataset', '?')}`, "
        f"fit on own dataset {fmt(rec.get('fit_own'))} %, mean cross-validation fit {fmt(rec.get('cv_mean'))} %.",
        "",
        f"Selection rule: {rec.get('selection_rule', '—')}.",
        "",
        *_per_dataset_lines(res),
        "Coefficients (full precision in `models/selected.json`):",
        "",
        "```",
        f"A = {vec(m.A)}",
        f"B = {vec(m.B)}",
        f"C = {vec(m.C)}",
        "```",
        "",
    ]
    return lines + _estimates_lines(res, m, rec)


def _section_crossfit(res: RunResults, figdir: Path) -> list[str]:
    lines = ["## Cross-fit matrix", ""]
    cf = res.crossfit
    if cf is None or cf.empty:
        return [*lines, "No cross-fit results yet.", ""]
    lines += [f"Fit [%] of each model (row) simulated on each dataset (column), from {res.crossfit_source}.", ""]
    lines += [*crossfit_table(res), ""]
    if res.crossfit_csv_average is not None:
        avg = cf.to_numpy(dtype=float).mean(axis=1)
        bad = [
            f"`{n}` ({fmt(res.crossfit_csv_average.get(n))} in the file, {fmt(a)} computed)"
            for n, a in zip(cf.index, avg, strict=True)
            if not _same(float(res.crossfit_csv_average.get(n, math.nan)), float(a))
        ]
        if bad:
            lines += ["Averages in `crossfit.csv` that are not the mean of their row: " + "; ".join(bad) + ".", ""]
    atomic_write_bytes(figdir / "crossfit.png", figures.crossfit_png(cf))  # drawn here: the recording shows it too
    return [*lines, "![cross-fit matrix](figures/crossfit.png)", ""]


def _roots_rows(xs: np.ndarray) -> list[list[str]]:
    return [[fmt(x.real, 4), fmt(x.imag, 4), fmt(abs(x), 4)] for x in xs]


def _section_model(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    if res.selected is None:
        return []
    m, rec = res.selected
    g = lti.with_integrator(m, res.af)
    poles, zeros = lti.poles(g), lti.zeros(g)
    own = res.prepared.get(str(rec.get("dataset")))
    meas = measured_frf(own, res.af) if own is not None else None
    curves = bode_curves(res, bode_grid(res.sample_time))
    drawings.append(((figures.bode, (curves, orders(rec), meas), {}), figdir / "bode_selected.png"))
    drawings.append(((figures.pole_zero, (poles, zeros), {}), figdir / "pz_selected.png"))
    t, u, y = lti.square_response(g, SQUARE_HZ, SQUARE_V, SQUARE_PERIODS / SQUARE_HZ)
    title = f"square-wave response of G = B/A / H(z) ({SQUARE_V:g} V, {SQUARE_HZ:g} Hz)"
    drawings.append(((figures.square_response, (t, u, y, title), {}), figdir / "square_response.png"))
    ss = lti.companion_ss(g)
    nmp = int(np.sum(np.abs(zeros) > 1.0))
    measured = (
        f"Bode plot with the measured (nonparametric, H1 Welch) response of `{meas.dataset}` at the "
        f"{meas.f_hz.size} frequencies where its coherence reaches {MIN_COHERENCE:g}:"
        if meas is not None
        else f"Bode plot (no frequency of the training dataset reaches a coherence of {MIN_COHERENCE:g}):"
    )
    return [
        "## Selected model with the integrator",
        "",
        f"G(z) = B/A / H(z) with H(z) = (1 - af)(z - 1)/(z - af), af = {res.af:g}: the command u [V] to the",
        "tip angle y [deg] (`harness.ident.lti.with_integrator`). Coefficients in descending powers of z:",
        "",
        "```",
        f"num = {vec(np.asarray(g.num[0][0], dtype=float))}",
        f"den = {vec(np.asarray(g.den[0][0], dtype=float))}",
        "```",
        "",
        "Companion-form state space x(k+1) = A x(k) + B u(k), y(k) = C x(k) + D u(k) (lab 1 eq. 10),",
        "B = e1, A with ones on the subdiagonal and first row:",
        "",
        "```",
        f"A[0, :] = {vec(np.asarray(ss.A)[0])}",
        f"C       = {vec(np.asarray(ss.C)[0])}",
        f"D       = {vec(np.asarray(ss.D)[0])}",
        "```",
        "",
        f"{poles.size} poles, {zeros.size} zeros ({nmp} outside the unit circle: non-minimum phase).",
        "",
        *table(["pole Re", "Im", "modulus"], _roots_rows(poles)),
        "",
        *table(["zero Re", "Im", "modulus"], _roots_rows(zeros)),
        "",
        measured,
        "",
        "![Bode](figures/bode_selected.png)",
        "",
        "![pole-zero map](figures/pz_selected.png)",
        "",
        f"Square-wave response ({SQUARE_V:g} V, {SQUARE_HZ:g} Hz, {SQUARE_PERIODS} periods, from rest): "
        f"tip angle from {fmt(float(np.min(y)), 3)} to {fmt(float(np.max(y)), 3)} deg.",
        "",
        "![square-wave response](figures/square_response.png)",
        "",
    ]


def _section_time(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    if not res.prepared:
        return []
    panels = []
    for name, p in res.prepared.items():
        t = np.arange(p.y_f.size) * p.Ts
        sim = res.simulated.get(name)
        zoom = zoom_window(t, p.y_f - sim, ZOOM_S) if sim is not None else (0.0, min(ZOOM_S, float(t[-1])))
        panels.append(figures.TimePanel(name, t, p.y_f, sim, zoom))
    lines = ["## Time responses per dataset", ""]
    if res.simulated:
        rows = [
            [
                pnl.name,
                fmt(armax.fit_percent(pnl.measured, pnl.simulated)),
                fmt(float(np.sqrt(np.mean((pnl.measured - pnl.simulated) ** 2))), 4),
                f"{pnl.zoom[0]:.1f}-{pnl.zoom[1]:.1f}",
            ]
            for pnl in panels
            if pnl.simulated is not None
        ]
        lines += [f"Selected model simulated (ic = '{res.ic}') on every dataset, identification domain y_f:", ""]
        lines += table(["dataset", "fit [%]", "residual rms [deg/sample]", "zoom window [s]"], rows) + [""]
        lines += [
            "Each figure: the whole record, measured (black), simulated (orange) and the residual (red), and under "
            f"it the {ZOOM_S:g} s where the residual is largest (shaded above).",
            "",
        ]
    else:
        lines += [
            "No identified model yet: each figure shows the measured y_f (the filtered difference of the tip angle, "
            f"identification domain), the whole record and its first {ZOOM_S:g} s.",
            "",
        ]
    for pnl in panels:
        link = figure_name("time", pnl.name)
        drawings.append(((figures.time_response, (pnl, ZOOM_S), {}), figdir / Path(link).name))
        lines += [f"![time response of {pnl.name}]({link})", ""]
    return lines


def _section_resid(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    tests = residual_tests(res)
    if not tests:
        return []
    rec = res.selected[1] if res.selected else {}
    own = str(rec["dataset"]) if rec.get("dataset") in tests else next(iter(tests))
    acf = {(rt.lags, rt.allowed_acf) for rt in tests.values()}
    ccf = {(rt.lags_ccf.size, rt.allowed_ccf) for rt in tests.values()}
    rows = [  # the lags and how many may lie outside in the header where every dataset has the same
        [
            name,
            f"{rt.n_out_acf}" + (f"/{rt.lags} (allowed {rt.allowed_acf})" if len(acf) > 1 else ""),
            fmt(rt.white),
            f"{rt.n_out_ccf}" + (f"/{rt.lags_ccf.size} (allowed {rt.allowed_ccf})" if len(ccf) > 1 else ""),
            fmt(rt.independent),
        ]
        for name, rt in tests.items()
    ]
    of_acf = f" of {next(iter(acf))[0]} (allowed {next(iter(acf))[1]})" if len(acf) == 1 else ""
    of_ccf = f" of {next(iter(ccf))[0]} (allowed {next(iter(ccf))[1]})" if len(ccf) == 1 else ""
    job: figures.FigureJob = (
        figures.residual_correlations,
        (tests[own], f"residuals of the selected model on {own}"),
        {},
    )
    drawings.append((job, figdir / "residuals.png"))
    coloured = sum(not rt.white for rt in tests.values())
    dependent = sum(not rt.independent for rt in tests.values())
    verdict = (
        f"The residuals are not white on {coloured} of {len(tests)} datasets and not independent of the input on "
        f"{dependent}: the noise model C misses part of the disturbance, or the dynamics are undermodelled."
        if coloured or dependent
        else "The residuals are white and independent of the input on every dataset."
    )
    return [
        "## Residual tests",
        "",
        f"One-step prediction errors of the selected model; 99 % bound 2.58/sqrt(N) = {fmt(tests[own].bound, 4)} "
        f"on `{own}`.",
        "",
        *table(["dataset", f"acf lags outside{of_acf}", "white", f"ccf lags outside{of_ccf}", "independent"], rows),
        "",
        verdict + " Acceptance (`flexjoint accept`) gates on the fit only; it does not test the residuals.",
        "",
        "![residual correlations](figures/residuals.png)",
        "",
    ]


def _section_doubled(res: RunResults) -> list[str]:
    d = res.doubled_rate
    if d is None:
        return []
    rows = [[DOUBLED_RATE_LABELS.get(k, k.replace("_", " ")), fmt_any(v)] for k, v in d.items()]
    return [
        "## Doubled sampling rate check",
        "",
        "One experiment simulated again at twice the sample rate (lab 1, section 3.4): a discrete model is tied to "
        "its sample time, so the selected model applied sample by sample misjudges the input's effect, while the "
        "same orders re-identified at the new rate fit again.",
        "",
        *table(["quantity", "value"], rows),
        "",
    ]


def _section_diagnosis(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    d = res.diagnosis
    if d is None:
        return []
    job: figures.FigureJob = (figures.gap_waterfall, (d.waterfall(), d.gap.decomposition.noise_floor), {})
    drawings.append((job, figdir / "gap_waterfall.png"))
    lines = ["## Sim-to-real gap diagnosis", ""]
    lines += [
        f"The data of this run against the simulation `{d.sim_spec}`; every number is in `diagnosis.json` "
        f"(how to read them: {manual('reading-the-report')}).",
        "",
    ]
    lines += diagnosis_markdown(d, "figures/gap_waterfall.png")
    rows = gap_rows(d)
    if rows:
        drawings.append(((figures.diagnosis_bars, (rows,), {}), figdir / "diagnosis.png"))
        lines += ["![gap per experiment](figures/diagnosis.png)", ""]
    return lines + _force_lines(res) + _replay_lines(res, figdir, drawings)


def _force_lines(res: RunResults) -> list[str]:
    """The likelihood engine's missing force (when ``diagnose --engine likelihood`` wrote it): its shape, size and
    samples at rest, its figure (drawn by diagnose, beside report.md) linked; where the residuals are not white."""
    mf = res.missing_force
    if mf is None:
        return []
    png = res.paths.force_figure
    lines = force_markdown(mf, res.force, png.name if png.exists() else None)
    if res.not_white:
        shown = [f"- {x}" for x in res.not_white[:8]] + ([f"- and {len(res.not_white) - 8} more (`likelihood.json`)"]
                                                          if len(res.not_white) > 8 else [])  # fmt: skip
        lines += ["Where the linear fit's residuals are not white (octave bands, stretches of time; each at 1 %):", "",
                  *shown, ""]  # fmt: skip
    return lines


def _replay_lines(res: RunResults, figdir: Path, drawings: Drawings) -> list[str]:
    """Each experiment's replays (as given, recalibrated, with the effects) against its record, per channel."""
    if not res.replays:
        return []
    fits = {name: replay_fits(rp) for name, rp in res.replays.items()}
    body = [[name, *(fmt(f[s], 1) for s in STAGES)] for name, f in fits.items()]
    lines = [
        "### Replays against the record",
        "",
        "Every experiment re-simulated as the diagnosis replayed it (`diagnosis.replays.parquet`): as given, "
        "recalibrated (recalibration alone) and with the effects found (the final parameters), against the record; "
        "fit [%] pooled over theta and alpha:",
        "",
        *table(["experiment", *(f"{label} [%]" for label in STAGES.values())], body),
        "",
    ]
    for name, rp in res.replays.items():
        link = figure_name("replay", name)
        miss = np.nan_to_num(rp.record["theta"] - rp.sim["given"]["theta"])  # where the simulation as given misses
        zoom = zoom_window(rp.t, miss, ZOOM_S)
        job: figures.FigureJob = (figures.replay, (name, rp.t, rp.record, rp.sim, dict(STAGES), fits[name], zoom), {})
        drawings.append((job, figdir / Path(link).name))
        lines += [f"![replays of {name}]({link})", ""]
    return lines


def draw(drawings: Drawings) -> Callable[[], None]:
    """Draw the figures ``drawings`` (jobs of :func:`harness.render.figures.figure_png`, each with its file); returns
    ``wait()``, which returns when they are written. Over the command's cluster where one runs (``flexjoint run``: a
    figure a task, the last drawings first: the replays, the largest, then down to the data, the smallest), drawn
    while the caller goes on (the recording); else here, at once (a report alone does not start a cluster for its
    figures)."""
    if not drawings or not in_session():
        for (fn, args, kwargs), path in drawings:
            fn(*args, path, **kwargs)
        return lambda: None
    jobs = [job for job, _ in drawings[::-1]]
    paths = [path for _, path in drawings[::-1]]
    drawn: dict[str, Any] = {}

    def remote() -> None:
        try:
            drawn["pngs"] = Executor().map(figures.figure_png, jobs, desc="report figures", quiet=True)
        except BaseException as e:  # raised again by wait(), in the caller's thread
            drawn["error"] = e

    thread = threading.Thread(target=contextvars.copy_context().run, args=(remote,), daemon=True)
    thread.start()

    def wait() -> None:
        thread.join()
        if "error" in drawn:
            raise drawn["error"]
        for png, path in zip(drawn["pngs"], paths, strict=True):
            atomic_write_bytes(path, png)

    return wait


# ----------------------------------------------------------------------------------------------- entry point
@dataclass(frozen=True)
class PendingReport:
    """A report whose text is written and whose figures are being drawn (:func:`begin_report`): :meth:`write` waits
    for them and writes report.md."""

    path: Path  # report.md
    figdir: Path
    text: str
    wait: Callable[[], None]

    def write(self) -> Path:
        """Wait for the figures, remove those of an earlier report that this one does not link, write report.md
        (atomically); returns its path."""
        self.wait()
        linked = {Path(x).name for x in re.findall(r"!\[[^\]]*\]\(figures/([^)]+)\)", self.text)}
        for old in self.figdir.glob("*.png"):
            if old.name not in linked:
                old.unlink()
        atomic_write_bytes(self.path, self.text.encode())
        return self.path


def begin_report(run: Path, results: RunResults | None = None) -> PendingReport:
    """The report of a run directory (:func:`write_report`) with its figures drawn over the command's cluster while
    the caller goes on (``flexjoint run`` writes the recording meanwhile), or here, at once, outside a session;
    :meth:`PendingReport.write` finishes it."""
    res = results if results is not None else load_results(run)
    figdir = res.paths.figures
    figdir.mkdir(parents=True, exist_ok=True)
    lines = _section_header(res)
    drawings: Drawings = []
    if res.manifest.kind != "diagnosis":
        lines += _section_data(res, figdir, drawings)
        lines += _section_calibration(res)
        lines += _section_filter(res, figdir, drawings)
        lines += _section_grid(res)
        lines += _section_crossfit(res, figdir)
        lines += _section_model(res, figdir, drawings)
        lines += _section_time(res, figdir, drawings)
        lines += _section_resid(res, figdir, drawings)
        lines += _section_doubled(res)
    lines += _section_diagnosis(res, figdir, drawings)
    text = "\n".join(wrap_prose(lines)).rstrip() + "\n"  # no line of prose over MAX_LINE characters
    return PendingReport(res.paths.report, figdir, text, draw(drawings))


def write_report(run: Path, results: RunResults | None = None) -> Path:
    """Write ``report.md`` and its figures for a run directory, from the directory alone.

    Any run directory (a campaign, an import, identified or not, diagnosed or not, or the diagnosis alone that
    ``flexjoint diagnose --out`` wrote): each section is written from what the directory holds and skipped (or one
    line) when it has nothing for it. Sections: what the run holds, the data of every experiment, calibration,
    preprocessing filter, grid and selection, cross-fit, the selected model, time responses, residual tests, the
    doubled-rate check, and the diagnosis with its replays against the record. Every file is written atomically;
    a figure of an earlier report that this one does not link is removed.

    Parameters
    ----------
    run : Path
        The directory.
    results : RunResults, optional
        The run already loaded (:func:`harness.render.load.load_results`), shared with the viewer.

    Returns
    -------
    Path
        ``<run>/report.md``.
    """
    return begin_report(run, results).write()
