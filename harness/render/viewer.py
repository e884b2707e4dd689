"""Stream a run directory to Rerun (rerun-sdk 0.41): ``run.rrd`` by default, plus a spawned or remote viewer.

Every view of the blueprint shows data as soon as the recording opens: series over time live on the ``time``
timeline (the time panel's), everything else is static. Plots that are not over time (Bode, residual
correlations, the cross-fit heat map) are drawn in 2D views with their own axes, grid and tick labels, and the
axis units in the view names. Rerun's 2D views point y down, so values are drawn at -y.

Entity tree (all logged from the run directory alone, via :func:`harness.render.load.load_results`):

- ``datasets/<name>/measured``, ``.../simulated`` (identification domain y_f [deg/sample], selected model),
  ``.../command`` (u [V]), ``.../tip/measured``, ``.../tip/simulated`` (tip angle [deg]); timeline ``time`` [s]
- ``crossfit/matrix`` (Tensor, dims model x dataset, fit [%]), ``crossfit/table`` (markdown, datasets
  numbered 1..n as in report.md), ``crossfit/heatmap/{cells,values,rows,columns,scale}`` (2D: coloured cells,
  their values, model and dataset labels, the colour scale)
- ``models/selected/pz/{poles,zeros,unit_circle,axes}`` (z-plane, model with integrator)
- ``bode/magnitude/<model>``, ``bode/phase/<model>`` (2D line strips: x = log10 f [Hz], y = magnitude / 20 dB or
  phase / 90 deg) and ``bode/{magnitude,phase}/axes``
- ``resid/acf/<dataset>``, ``resid/ccf/<dataset>`` (2D line strips over the lag), ``resid/{acf,ccf}/bounds``
  (99 %), ``resid/{acf,ccf}/axes``; ``resid/summary`` (markdown)
- ``diagnosis/gap/before``, ``diagnosis/gap/after`` (bar charts side by side per experiment),
  ``diagnosis/waterfall`` (held-out gap stage by stage), ``diagnosis/summary`` (markdown)
- ``overview`` (markdown)

Time series use one ``send_columns`` call per entity.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import tempfile
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from matplotlib import colormaps

from ..ident import lti
from ..rundir import Manifest, to_plain
from .analysis import RESID_LAGS, bode_curves, bode_grid, residual_tests, tip_from_filtered
from .gap_text import diagnosis_markdown, gap_rows
from .load import RunResults, load_results
from .rrd import make_stable
from .tables import crossfit_table

__all__ = ["APPLICATION_ID", "log_run", "recording_id", "write_recording"]

APPLICATION_ID = "flexjoint"
N_BODE = 400
DB_PER_UNIT = 20.0  # Bode magnitude: one 2D unit per 20 dB (a decade of gain, as one unit is a decade of f)
DEG_PER_UNIT = 90.0  # Bode phase: one 2D unit per 90 deg
LAG_WIDTH = 10.0  # residual plots: the lag axis spans 10 units
CORR_HEIGHT = 4.0  # residual plots: a correlation of 1 is 4 units high
CELL = 8  # cross-fit heat map: pixels per cell

_BLACK = [30, 30, 30]
_ORANGE = [230, 120, 20]
_GREY = [150, 150, 150]
_LIGHT = [215, 215, 215]
_RED = [220, 40, 40]
_BLUE = [40, 90, 220]
_PALETTE = [[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75],
            [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]]  # fmt: skip


def recording_id(manifest: Manifest) -> str:
    """Stable recording id (UUID form) from the manifest's spec hash, or from its data sources for imports."""
    key = manifest.spec_sha256
    if not key:
        basis = to_plain(manifest.sources or manifest.experiments)
        key = hashlib.sha256(json.dumps(basis, sort_keys=True, default=str).encode()).hexdigest()
    return str(uuid.UUID(hex=hashlib.sha256(str(key).encode()).hexdigest()[:32]))


def _part(name: str) -> str:
    return rr.escape_entity_path_part(str(name))


def _series(rec: rr.RecordingStream, path: str, timeline: rr.TimeColumn, values: np.ndarray) -> None:
    cols = rr.Scalars.columns(scalars=np.asarray(values, dtype=float))
    rec.send_columns(path, indexes=[timeline], columns=cols)


def _style(rec: rr.RecordingStream, path: str, name: str, color: list[int], width: float = 1.0) -> None:
    rec.log(path, rr.SeriesLines(colors=[color], names=[name], widths=[width]), static=True)


def _markdown(rec: rr.RecordingStream, path: str, lines: list[str]) -> None:
    rec.log(path, rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)


# ----------------------------------------------------------------------------------------------- 2D plots
def _xy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Plot coordinates -> Rerun 2D positions (y down): (x, -y)."""
    return np.column_stack([np.asarray(x, dtype=float), -np.asarray(y, dtype=float)])


def _log_axes(
    rec: rr.RecordingStream,
    path: str,
    xticks: list[tuple[float, str]],
    yticks: list[tuple[float, str]],
    xlim: tuple[float, float],
    ylim: tuple[float, float],
) -> rrb.VisualBounds2D:
    """Grid lines at the ticks, tick labels left of and below the plot box; returns bounds that frame it."""
    (x0, x1), (y0, y1) = xlim, ylim
    grid = [_xy([x, x], [y0, y1]) for x, _ in xticks] + [_xy([x0, x1], [y, y]) for y, _ in yticks]
    rec.log(f"{path}/grid", rr.LineStrips2D(grid, colors=[_LIGHT], radii=0.01, draw_order=-10.0), static=True)
    pad_x, pad_y = 0.04 * (x1 - x0), 0.06 * (y1 - y0)
    pos = [(x, y0 - pad_y) for x, _ in xticks] + [(x0 - pad_x, y) for y, _ in yticks]
    labels = [t for _, t in xticks] + [t for _, t in yticks]
    rec.log(
        f"{path}/ticks",
        rr.Points2D(_xy(*np.array(pos).T), radii=0.001, colors=[_GREY], labels=labels, show_labels=True),
        static=True,
    )
    return rrb.VisualBounds2D(x_range=[x0 - 3 * pad_x, x1 + pad_x], y_range=[-y1 - pad_y, -y0 + 3 * pad_y])


def _ticks(lo: float, hi: float, step: float) -> list[float]:
    return [k * step for k in range(math.floor(lo / step), math.ceil(hi / step) + 1)]


# ----------------------------------------------------------------------------------------------- logging
def _log_datasets(rec: rr.RecordingStream, res: RunResults) -> None:
    for name, p in res.prepared.items():
        base = f"datasets/{_part(name)}"
        t = rr.TimeColumn("time", duration=np.arange(p.y_f.size) * p.Ts)
        _style(rec, f"{base}/measured", "measured y_f", _BLACK)
        _series(rec, f"{base}/measured", t, p.y_f)
        _style(rec, f"{base}/command", "command u [V]", _BLUE)
        _series(rec, f"{base}/command", t, p.u)
        _style(rec, f"{base}/tip/measured", "measured tip [deg]", _BLACK)
        _series(rec, f"{base}/tip/measured", t, p.y)
        if name in res.simulated:
            ys = res.simulated[name]
            _style(rec, f"{base}/simulated", "simulated y_f", _ORANGE)
            _series(rec, f"{base}/simulated", t, ys)
            _style(rec, f"{base}/tip/simulated", "simulated tip [deg]", _ORANGE)
            _series(rec, f"{base}/tip/simulated", t, tip_from_filtered(ys + p.y_f_offset, res.af, float(p.y[0])))


def _heat_colors(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """RGB uint8 of ``values`` on viridis over [lo, hi]; NaN (an unstable model) light grey."""
    span = hi - lo if hi > lo else 1.0
    rgb = colormaps["viridis"](np.clip((np.nan_to_num(values, nan=lo) - lo) / span, 0.0, 1.0))[..., :3] * 255
    rgb = rgb.astype(np.uint8)
    rgb[~np.isfinite(values)] = _LIGHT
    return rgb


def _log_crossfit(rec: rr.RecordingStream, res: RunResults) -> rrb.VisualBounds2D | None:
    cf = res.crossfit
    if cf is None or cf.empty:
        return None
    values = cf.to_numpy(dtype=float)
    finite = values[np.isfinite(values)]
    lo, hi = (float(np.floor(finite.min())), float(np.ceil(finite.max()))) if finite.size else (0.0, 100.0)
    hi = hi if hi > lo else lo + 1.0
    # colour map over the fits actually present (e.g. 86-98 %), not 0-max, or every cell looks the same
    rec.log("crossfit/matrix", rr.Tensor(values, dim_names=("model", "dataset"), value_range=(lo, hi)), static=True)
    nr, nc = values.shape
    # one image: the matrix (CELL pixels per cell), a blank column, then the colour scale (hi at the top)
    img = np.full((nr * CELL, (nc + 2) * CELL, 3), 255, dtype=np.uint8)
    img[:, : nc * CELL] = np.repeat(np.repeat(_heat_colors(values, lo, hi), CELL, 0), CELL, 1)
    scale = np.linspace(hi, lo, nr * CELL)[:, None]
    img[:, (nc + 1) * CELL :] = np.repeat(_heat_colors(scale, lo, hi), CELL, 1)
    rec.log("crossfit/heatmap/cells", rr.Image(img, magnification_filter="Nearest"), static=True)
    ii, jj = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
    centres = np.column_stack([(jj.ravel() + 0.5) * CELL, (ii.ravel() + 0.5) * CELL])
    text = ["—" if not math.isfinite(v) else f"{v:.1f}" for v in values.ravel()]
    rec.log("crossfit/heatmap/values", rr.Points2D(centres, radii=0.01, colors=[[255, 255, 255]], labels=text,
                                                   show_labels=True), static=True)  # fmt: skip
    rows = [f"{name}" for name in cf.index]
    rec.log("crossfit/heatmap/rows", rr.Points2D(np.column_stack([np.full(nr, -0.2 * CELL), (np.arange(nr) + 0.5) *
            CELL]), radii=0.01, colors=[_BLACK], labels=rows, show_labels=True), static=True)  # fmt: skip
    cols = [f"{j + 1}" for j in range(nc)]
    rec.log("crossfit/heatmap/columns", rr.Points2D(np.column_stack([(np.arange(nc) + 0.5) * CELL, np.full(nc, -0.3 *
            CELL)]), radii=0.01, colors=[_BLACK], labels=cols, show_labels=True), static=True)  # fmt: skip
    ticks = [hi, 0.5 * (lo + hi), lo]
    ys = [0.0, 0.5 * nr * CELL, nr * CELL]
    xs = np.full(3, (nc + 2.3) * CELL)
    rec.log("crossfit/heatmap/scale", rr.Points2D(np.column_stack([xs, ys]), radii=0.01, colors=[_BLACK],
            labels=[f"{v:.0f} %" for v in ticks], show_labels=True), static=True)  # fmt: skip
    legend = ", ".join(f"{j + 1} = `{c}`" for j, c in enumerate(cf.columns))
    _markdown(
        rec,
        "crossfit/table",
        [
            "### Cross-fit fit [%]",
            "",
            "Model (row) simulated on dataset (column). Datasets are numbered 1..n here, in the heat map and in "
            f"report.md: {legend}. The tensor view holds the same matrix (rows in this order). Colour scale "
            f"viridis over {lo:.0f}-{hi:.0f} %.",
            "",
            *crossfit_table(res),
            "",
            f"Source: {res.crossfit_source}.",
        ],
    )
    return rrb.VisualBounds2D(x_range=[-2.5 * CELL, (nc + 3.5) * CELL], y_range=[-1.0 * CELL, (nr + 0.5) * CELL])


def _log_pz(rec: rr.RecordingStream, res: RunResults) -> None:
    if res.selected is None:
        return
    g = lti.with_integrator(res.selected[0], res.af)
    poles, zeros = lti.poles(g), lti.zeros(g)
    base = "models/selected/pz"
    rec.log(
        f"{base}/poles",
        rr.Points2D(_xy(poles.real, poles.imag), colors=[_RED], radii=0.025, labels=["x"] * poles.size),
        static=True,
    )
    rec.log(
        f"{base}/zeros",
        rr.Points2D(_xy(zeros.real, zeros.imag), colors=[_BLUE], radii=0.025, labels=["o"] * zeros.size),
        static=True,
    )
    th = np.linspace(0.0, 2.0 * math.pi, 241)
    rec.log(f"{base}/unit_circle", rr.LineStrips2D([_xy(np.cos(th), np.sin(th))], colors=[_GREY]), static=True)
    axes = [[[-1.2, 0.0], [1.2, 0.0]], [[0.0, -1.2], [0.0, 1.2]]]
    rec.log(f"{base}/axes", rr.LineStrips2D(axes, colors=[_LIGHT], radii=0.003), static=True)
    labels = rr.Points2D([[1.25, 0.0], [0.0, -1.25]], radii=0.001, colors=[_GREY], labels=["Re z", "Im z"])
    rec.log(f"{base}/axis_labels", labels, static=True)


def _log_bode(rec: rr.RecordingStream, res: RunResults) -> dict[str, rrb.VisualBounds2D]:
    if not res.models:
        return {}
    f = bode_grid(res.sample_time, N_BODE)
    x = np.log10(f)
    curves = {name: (d.mag_db, d.phase_deg) for name, d in bode_curves(res, f).items()}
    bounds = {}
    xticks = [(float(k), f"{10.0**k:g} Hz") for k in range(math.ceil(x[0]), math.floor(x[-1]) + 1)]
    for kind, idx, unit, per in (("magnitude", 0, "dB", DB_PER_UNIT), ("phase", 1, "deg", DEG_PER_UNIT)):
        for name, c in curves.items():
            color, width = (_BLUE, 0.02) if name == "selected" else (_GREY, 0.008)
            strip = rr.LineStrips2D([_xy(x, c[idx] / per)], colors=[color], radii=width, labels=[name],
                                    show_labels=name == "selected")  # fmt: skip
            rec.log(f"bode/{kind}/{_part(name)}", strip, static=True)
        ys = np.concatenate([c[idx] for c in curves.values()]) / per
        ys = ys[np.isfinite(ys)]
        y0, y1 = (math.floor(ys.min()), math.ceil(ys.max())) if ys.size else (-1, 1)
        yticks = [(float(v), f"{v * per:g} {unit}") for v in _ticks(y0, y1, 1.0)]
        bounds[kind] = _log_axes(rec, f"bode/{kind}/axes", xticks, yticks, (float(x[0]), float(x[-1])), (y0, y1))
    return bounds


def _log_resid(rec: rr.RecordingStream, res: RunResults) -> dict[str, rrb.VisualBounds2D]:
    tests = residual_tests(res)
    if not tests:
        return {}
    rows = [
        "| dataset | acf lags outside | white | ccf lags outside | independent |",
        "|---|---|---|---|---|",
    ]
    bound = 0.0
    lags = RESID_LAGS
    for i, (name, rt) in enumerate(tests.items()):
        lags = rt.lags
        bound = max(bound, rt.bound)
        color = _PALETTE[i % len(_PALETTE)]
        sx_acf, sx_ccf = LAG_WIDTH / lags, LAG_WIDTH / (2 * lags)
        for kind, k, r, sx in (("acf", np.arange(rt.acf.size), rt.acf, sx_acf), ("ccf", rt.lags_ccf, rt.ccf, sx_ccf)):
            strip = rr.LineStrips2D([_xy(k * sx, r * CORR_HEIGHT)], colors=[color], radii=0.02, labels=[name])
            rec.log(f"resid/{kind}/{_part(name)}", strip, static=True)
        rows.append(
            f"| {name} | {rt.n_out_acf}/{rt.lags} | {'yes' if rt.white else 'no'} | "
            f"{rt.n_out_ccf}/{rt.lags_ccf.size} | {'yes' if rt.independent else 'no'} |"
        )
    bounds = {}
    for kind, k0 in (("acf", 0), ("ccf", -lags)):
        sx = LAG_WIDTH / (lags - k0)
        b = bound * CORR_HEIGHT
        lines = [_xy([k0 * sx, lags * sx], [b, b]), _xy([k0 * sx, lags * sx], [-b, -b])]
        rec.log(f"resid/{kind}/bounds", rr.LineStrips2D(lines, colors=[_RED], radii=0.015,
                labels=["99 % bound", "99 % bound"]), static=True)  # fmt: skip
        step = 5 if lags >= 10 else 1
        xticks = [(k * sx, f"{k}") for k in range(k0, lags + 1) if k % step == 0]
        yticks = [(v * CORR_HEIGHT, f"{v:g}") for v in (-1.0, -0.5, 0.0, 0.5, 1.0)]
        bounds[kind] = _log_axes(rec, f"resid/{kind}/axes", xticks, yticks, (k0 * sx, lags * sx),
                                 (-CORR_HEIGHT, CORR_HEIGHT))  # fmt: skip
    _markdown(
        rec,
        "resid/summary",
        [
            "### Residual tests of the selected model",
            "",
            f"99 % bound 2.58/sqrt(N) = {bound:.4f} (widest over datasets), the red lines of the plots.",
            "",
            *rows,
        ],
    )
    return bounds


def _log_diagnosis(rec: rr.RecordingStream, res: RunResults) -> None:
    d = res.diagnosis
    if d is None:
        return
    rows = gap_rows(d)
    lines = ["### Sim-to-real gap diagnosis", ""]
    if rows:
        x = np.arange(len(rows), dtype=float)
        before = np.array([r[1] for r in rows])
        after = np.array([r[2] for r in rows])
        w = np.full(x.size, 0.4)
        rec.log("diagnosis/gap/before", rr.BarChart(before, abscissa=x - 0.2, widths=w, color=_RED), static=True)
        rec.log("diagnosis/gap/after", rr.BarChart(after, abscissa=x + 0.2, widths=w, color=_BLUE), static=True)
        legend = ", ".join(f"{i} = {r[0]}" for i, r in enumerate(rows))
        lines += [f"Gap per experiment, red (left) before and blue (right) after, by index: {legend}", ""]
    steps = d.waterfall()
    if len(steps) > 1:
        gaps = np.array([g for _, g, _ in steps])
        rec.log("diagnosis/waterfall", rr.BarChart(gaps, color=_ORANGE), static=True)
        lines += ["Held-out gap by stage, by index: " + ", ".join(f"{i} = {s[0]}" for i, s in enumerate(steps)), ""]
    lines += diagnosis_markdown(d)
    _markdown(rec, "diagnosis/summary", lines)


def _log_overview(rec: rr.RecordingStream, res: RunResults) -> None:
    m = res.manifest
    lines = [
        "### flexjoint run",
        "",
        f"- kind: {m.kind}",
        f"- spec sha256: `{m.spec_sha256 or '-'}`",
        f"- sample rate: {'-' if m.sample_rate is None else m.sample_rate} Hz",
        f"- identification datasets: {', '.join(res.prepared) or '-'}",
    ]
    if res.selected is not None:
        r = res.selected[1]
        orders = f"({r['na']},{r['nb']},{r['nc']},{r['nk']})"
        lines.append(f"- selected ARMAX (na,nb,nc,nk) = {orders}, trained on `{r.get('dataset')}`")
    if res.diagnosis is not None:
        lines.append(f"- diagnosis verdict: **{res.diagnosis.verdict}**")
    lines += [
        "",
        "Tabs: datasets (measured vs simulated over time), cross-fit (heat map, table, tensor), model (pole-zero",
        "map, Bode over log10 f), residuals (correlations over the lag), diagnosis (gaps and summary); the ones",
        "this run directory has data for. The full numbers are in report.md and the JSON files.",
    ]
    _markdown(rec, "overview", lines)


def _log_all(rec: rr.RecordingStream, res: RunResults) -> dict[str, rrb.VisualBounds2D]:
    """Log everything; returns the 2D views' bounds by plot name."""
    name = ((res.manifest.spec or {}).get("campaign") or {}).get("name")
    rec.send_recording_name(f"flexjoint {name or res.run.name}")
    _log_overview(rec, res)
    _log_datasets(rec, res)
    bounds: dict[str, rrb.VisualBounds2D] = {}
    heat = _log_crossfit(rec, res)
    if heat is not None:
        bounds["heatmap"] = heat
    _log_pz(rec, res)
    bounds.update({f"bode_{k}": v for k, v in _log_bode(rec, res).items()})
    bounds.update({f"resid_{k}": v for k, v in _log_resid(rec, res).items()})
    _log_diagnosis(rec, res)
    return bounds


# ----------------------------------------------------------------------------------------------- blueprint
def _blueprint(res: RunResults, bounds: dict[str, rrb.VisualBounds2D]) -> rrb.Blueprint:
    tabs: list[Any] = [rrb.TextDocumentView(origin="overview", name="overview")]
    if res.prepared:
        per = []
        for name in res.prepared:
            o = f"datasets/{_part(name)}"
            views = [rrb.TimeSeriesView(origin=f"{o}/tip", name=f"{name}: tip angle [deg] vs t [s]")]
            if name in res.simulated:
                ts = rrb.TimeSeriesView(origin=o, contents=["$origin/measured", "$origin/simulated"],
                                        name=f"{name}: y_f [deg/sample] vs t [s]")  # fmt: skip
            else:
                ts = rrb.TimeSeriesView(
                    origin=o, contents=["$origin/measured"], name=f"{name}: y_f [deg/sample] vs t [s]"
                )
            views.insert(0, ts)
            views.append(
                rrb.TimeSeriesView(origin=o, contents=["$origin/command"], name=f"{name}: command u [V] vs t [s]")
            )
            per.append(rrb.Vertical(*views, row_shares=[2.0, 2.0, 1.0], name=name))
        tabs.append(rrb.Tabs(*per, name="datasets"))
    if "heatmap" in bounds:
        tabs.append(
            rrb.Horizontal(
                rrb.Spatial2DView(
                    origin="crossfit/heatmap",
                    name="cross-fit [%]: model (row) on dataset (column)",
                    visual_bounds=bounds["heatmap"],
                ),  # fmt: skip
                rrb.Vertical(
                    rrb.TextDocumentView(origin="crossfit/table", name="cross-fit table"),
                    rrb.TensorView(origin="crossfit/matrix", name="cross-fit tensor (model x dataset)"),
                    row_shares=[2.0, 1.0],
                ),
                column_shares=[3.0, 2.0],
                name="cross-fit",
            )
        )
    if res.models:
        model_views: list[Any] = []
        if res.selected is not None:
            model_views.append(
                rrb.Spatial2DView(
                    origin="models/selected/pz",
                    name="pole-zero map of the selected model: Re z (right) vs Im z (up)",
                    visual_bounds=rrb.VisualBounds2D(x_range=[-1.5, 1.5], y_range=[-1.5, 1.5]),
                )
            )
        model_views.append(
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="bode/magnitude",
                    name="Bode magnitude [dB] vs log10 f [Hz]",
                    visual_bounds=bounds.get("bode_magnitude"),
                ),  # fmt: skip
                rrb.Spatial2DView(
                    origin="bode/phase", name="Bode phase [deg] vs log10 f [Hz]", visual_bounds=bounds.get("bode_phase")
                ),  # fmt: skip
            )
        )
        tabs.append(rrb.Horizontal(*model_views, name="model"))
    if "resid_acf" in bounds:
        tabs.append(
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="resid/acf",
                    name="residual autocorrelation r_ee vs lag [samples]",
                    visual_bounds=bounds["resid_acf"],
                ),  # fmt: skip
                rrb.Spatial2DView(
                    origin="resid/ccf",
                    name="residual-input cross-correlation r_eu vs lag [samples]",
                    visual_bounds=bounds["resid_ccf"],
                ),  # fmt: skip
                rrb.TextDocumentView(origin="resid/summary", name="residual tests"),
                name="residuals",
            )
        )
    if res.diagnosis is not None:
        bars: list[Any] = []
        if gap_rows(res.diagnosis):
            bars.append(
                rrb.BarChartView(origin="diagnosis/gap", name="gap per experiment: before (red) / after (blue)")
            )
        if len(res.diagnosis.waterfall()) > 1:
            bars.append(rrb.BarChartView(origin="diagnosis/waterfall", name="held-out gap by stage"))
        summary = rrb.TextDocumentView(origin="diagnosis/summary", name="diagnosis")
        tabs.append(rrb.Horizontal(rrb.Vertical(*bars), summary, name="diagnosis") if bars else summary)
    root = rrb.Tabs(*tabs, active_tab=1 if len(tabs) > 1 else 0)
    return rrb.Blueprint(root, rrb.TimePanel(timeline="time"))


# ----------------------------------------------------------------------------------------------- entry point
def _check_url(url: str) -> None:
    try:
        rr.GrpcSink(url)
    except (RuntimeError, ValueError, TypeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        example = "rerun+http://127.0.0.1:9876/proxy"
        raise ValueError(f"invalid viewer URL {url!r} (expected e.g. {example}): {first}") from None


def _log_with_blueprint(rec: rr.RecordingStream, res: RunResults) -> None:
    """Log everything, then the blueprint that lays it out (its 2D views are framed on what was logged)."""
    bounds = _log_all(rec, res)
    rec.send_blueprint(stable_ids(_blueprint(res, bounds)), make_active=True, make_default=True)


def stable_ids(blueprint: rrb.Blueprint) -> rrb.Blueprint:
    """``blueprint`` with every container and view id derived from its place in the layout (Rerun draws them at
    random, and they are entity paths of the blueprint store: the same layout then gives the same recording)."""

    def visit(part: Any, place: str) -> None:
        if isinstance(part, (rrb.Container, rrb.View)):
            part.id = uuid.uuid5(uuid.NAMESPACE_URL, f"flexjoint-blueprint:{place}")
        for i, child in enumerate(getattr(part, "contents", None) or ()):
            if isinstance(child, (rrb.Container, rrb.View)):
                visit(child, f"{place}/{i}")

    visit(blueprint.root_container, "root")
    return blueprint


def write_recording(
    rrd: Path, rec_id: str, log: Callable[[rr.RecordingStream], None], blueprint: rrb.Blueprint | None = None
) -> Path:
    """The one ``.rrd`` writer: a recording (application id :data:`APPLICATION_ID`, recording id ``rec_id``, the
    default ``blueprint`` when given) filled by ``log(rec)`` into a temp file next to ``rrd`` and renamed into
    place; no half file on error. Returns ``rrd``."""
    rrd = Path(rrd)
    rrd.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=rrd.parent, prefix=f".{rrd.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp_name)
    rec = None
    try:
        # no start-time property (the recording's name is logged), chunks cut at the end, not by the clock: the
        # same run gives the same data, and make_stable the same bytes
        rec = rr.RecordingStream(
            APPLICATION_ID, recording_id=rec_id, send_properties=False, batcher_config=rr.ChunkBatcherConfig.NEVER()
        )
        rec.set_sinks(rr.FileSink(str(tmp)), default_blueprint=stable_ids(blueprint) if blueprint else None)
        log(rec)
        rec.flush()
        rec.disconnect()  # closes the file sink and writes the RRD footer
        rec = None
        make_stable(tmp)  # the same bytes for the same logging (harness.render.rrd)
        os.chmod(tmp, 0o644)  # mkstemp made it 0600
        os.replace(tmp, rrd)
    except BaseException:
        if rec is not None:
            with contextlib.suppress(Exception):  # best effort: the original error matters
                rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise
    return rrd


def _write_rrd(res: RunResults, rrd: Path) -> None:
    """Log everything into ``rrd`` (atomically, :func:`write_recording`), the blueprint after the data."""
    write_recording(rrd, recording_id(res.manifest), lambda rec: _log_with_blueprint(rec, res))


def _stream_live(res: RunResults, spawn: bool, connect: str | None) -> None:
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(res.manifest))
    where = connect or "a spawned viewer"
    try:
        if spawn:
            rec.spawn()
        else:
            rec.connect_grpc(connect)
        _log_with_blueprint(rec, res)
        rec.flush(timeout_sec=30.0)
    except (RuntimeError, OSError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"cannot stream to the Rerun viewer at {where}: {first}") from None
    finally:
        rec.disconnect()


def log_run(
    run: Path,
    *,
    rrd: Path | None = None,
    spawn: bool = False,
    connect: str | None = None,
    results: RunResults | None = None,
) -> Path | None:
    """Log a run directory to Rerun: always to ``rrd`` (default ``<run>/run.rrd``, written atomically), and
    live to a spawned viewer (``spawn=True``) or a running one (``connect`` = gRPC URL such as
    ``rerun+http://127.0.0.1:9876/proxy``). One recording, application id ``flexjoint``, recording id from
    the manifest's spec hash; the blueprint travels with it. ``results``: the run already loaded
    (:func:`harness.render.load.load_results`), shared with the report. Returns the path of the ``.rrd`` file.
    """
    if connect is not None:
        _check_url(connect)
    res = results if results is not None else load_results(Path(run))
    out = Path(rrd) if rrd is not None else res.paths.recording
    _write_rrd(res, out)
    if spawn or connect is not None:
        _stream_live(res, spawn, connect)
    return out
