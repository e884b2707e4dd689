"""Stream a run directory to Rerun (rerun-sdk 0.41): ``run.rrd`` by default, plus a spawned or remote viewer.

Every view of the blueprint shows data as soon as the recording opens: series over time live on the ``time``
timeline (the time panel's), everything else is static. Plots that are not over time (Bode, residual
correlations, the cross-fit heat map) are drawn in 2D views with their own axes, grid and tick labels, and the
axis units in the view names. Rerun's 2D views point y down, so values are drawn at -y.

Entity tree (all logged from the run directory alone, via :func:`harness.render.load.load_results`):

- ``overview`` (markdown: what the run holds, the tabs); the blueprint opens on it
- ``data/<experiment>/{u,theta,alpha}``: every experiment as measured (command [V], angles [deg] through the
  run's calibration); timeline ``time`` [s]
- ``datasets/<name>/measured``, ``.../simulated`` (identification domain y_f [deg/sample], selected model),
  ``.../command`` (u [V]), ``.../tip/measured``, ``.../tip/simulated`` (tip angle [deg]); timeline ``time`` [s]
- ``crossfit/matrix`` (Tensor, dims model x dataset, fit [%]), ``crossfit/heatmap`` (the report's heat map, a PNG:
  models and datasets by name, each value readable on its cell), ``crossfit/table`` (markdown, at full width)
- ``models/selected/pz/{poles,zeros,unit_circle,axes}`` (z-plane, model with integrator)
- ``bode/magnitude/<model>``, ``bode/phase/<model>`` (2D line strips: x = log10 f [Hz], y = magnitude / 20 dB or
  phase / 90 deg) and ``bode/{magnitude,phase}/axes``
- ``resid/acf/<dataset>``, ``resid/ccf/<dataset>`` (2D line strips over the lag), ``resid/{acf,ccf}/bounds``
  (99 %), ``resid/{acf,ccf}/axes``; ``resid/summary`` (markdown)
- ``diagnosis/gap`` (2D bars per experiment, named, as given and with the effects: :func:`log_bars`),
  ``diagnosis/waterfall`` (the held-out gap stage by stage, named), ``diagnosis/summary`` (markdown),
  ``diagnosis/replays/<experiment>/<channel>/{record,given,recalibrated,effects}`` (the replays against the record,
  [deg] over ``time``)
- ``diagnosis/force/time/<record>/{force,upper,lower}`` (the likelihood engine's missing force [N m] and its +-2
  standard deviation band over ``time``) and ``diagnosis/force/speed/<record>`` (2D points: the force against the
  hub's speed [deg/s]), ``diagnosis/force/speed/axes``, ``diagnosis/force/where`` (markdown: where the linear
  fit's residuals are not white): when ``diagnose --engine likelihood`` wrote force_picture.parquet
  (:mod:`harness.render.force`)

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
from numpy.typing import ArrayLike

from ..diagnosis.replays import STAGES
from ..ident import lti
from ..rundir import Manifest, to_plain
from . import figures
from .analysis import (
    RESID_LAGS,
    bode_curves,
    bode_grid,
    record_angles,
    replay_fits,
    residual_tests,
    tip_from_filtered,
)
from .gap_text import diagnosis_markdown, gap_rows
from .load import RunResults, load_results
from .report import holds, title
from .rrd import make_stable
from .tables import crossfit_table

__all__ = ["APPLICATION_ID", "bar_bounds", "log_bars", "log_run", "recording_id", "write_recording"]

APPLICATION_ID = "flexjoint"
N_BODE = 400
DB_PER_UNIT = 20.0  # Bode magnitude: one 2D unit per 20 dB (a decade of gain, as one unit is a decade of f)
DEG_PER_UNIT = 90.0  # Bode phase: one 2D unit per 90 deg
LAG_WIDTH = 10.0  # residual plots: the lag axis spans 10 units
CORR_HEIGHT = 4.0  # residual plots: a correlation of 1 is 4 units high
FORCE_WIDTH = 10.0  # the force against the hub's speed: the speeds span 10 units
FORCE_HEIGHT = 4.0  # and the forces 4
MIN_BAR = 0.01  # 2D bar charts: half the thickness of a bar of (about) zero
BAR_HEIGHT = 4.0  # 2D bar charts: the tallest bar is 4 units high, a category 1 unit wide

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
def _xy(x: ArrayLike, y: ArrayLike) -> np.ndarray:
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


def _log_crossfit(rec: rr.RecordingStream, res: RunResults) -> bool:
    """The matrix as a Tensor, the report's heat map (models and datasets by name, each value in a colour that
    reads on its cell) as a PNG image, and the table; False when there is no cross-fit."""
    cf = res.crossfit
    if cf is None or cf.empty:
        return False
    values = cf.to_numpy(dtype=float)
    finite = values[np.isfinite(values)]
    lo, hi = (float(np.floor(finite.min())), float(np.ceil(finite.max()))) if finite.size else (0.0, 100.0)
    hi = hi if hi > lo else lo + 1.0
    # colour map over the fits actually present (e.g. 86-98 %), not 0-max, or every cell looks the same
    rec.log("crossfit/matrix", rr.Tensor(values, dim_names=("model", "dataset"), value_range=(lo, hi)), static=True)
    png = figures.crossfit_png(cf)
    rec.log("crossfit/heatmap", rr.EncodedImage(contents=png, media_type="image/png"), static=True)
    legend = ", ".join(f"{j + 1} = `{c}`" for j, c in enumerate(cf.columns))
    _markdown(
        rec,
        "crossfit/table",
        [
            "### Cross-fit fit [%]",
            "",
            "Model (row) simulated on dataset (column). Datasets are numbered 1..n in this table as in report.md: "
            f"{legend}. The heat map names them; the tensor view holds the same matrix (rows in this order).",
            "",
            *crossfit_table(res),
            "",
            f"Source: {res.crossfit_source}.",
        ],
    )
    return True


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


def log_bars(
    rec: rr.RecordingStream,
    path: str,
    categories: list[str],
    series: list[tuple[str, np.ndarray, list[int]]],
    values: bool = True,
) -> rrb.VisualBounds2D:
    """A bar chart in 2D with named categories: per category one bar per series (``name``, values, colour) side by
    side, the category names under the slots (on two staggered rows when there are many), the value axis ticked on
    the left, each bar's value over it (``values``); ``path/<series name>`` the bars (line strips as wide as their
    slot, their round ends kept within the bar), ``path/<series name>/values`` the values."""
    n, k = len(categories), len(series)
    width = 0.8 / k
    r = 0.5 * width
    top = max((float(np.nanmax(v)) for _, v, _ in series if np.isfinite(v).any()), default=1.0) or 1.0
    scale = BAR_HEIGHT / top  # the tallest bar BAR_HEIGHT units high
    for j, (name, v, color) in enumerate(series):
        h = np.nan_to_num(np.asarray(v, dtype=float)) * scale
        xc = np.arange(n) + 0.1 + (j + 0.5) * width
        strips, radii = [], []
        for x, y in zip(xc, h, strict=True):
            if y >= 2 * r:  # upright, its round ends (r past each point) kept within 0..y
                strips.append(_xy([x, x], [r, y - r]))
                radii.append(r)
            else:  # lower than wide: lying, as wide as the slot
                half = max(0.5 * y, MIN_BAR)
                strips.append(_xy([x - r + half, x + r - half], [half, half]))
                radii.append(half)
        rec.log(f"{path}/{_part(name)}", rr.LineStrips2D(strips, colors=[color], radii=radii), static=True)
        if values:
            at = _xy(xc, h + 0.04 * BAR_HEIGHT)
            rec.log(f"{path}/{_part(name)}/values", rr.Points2D(at, radii=0.001, colors=[color],
                    labels=[f"{x:.3f}" for x in v], show_labels=True), static=True)  # fmt: skip
    step = 10.0 ** math.floor(math.log10(top / 2))
    step = step * 5 if top / step > 10 else step * 2 if top / step > 5 else step
    yticks = [(y * scale, f"{y:g}") for y in _ticks(0.0, top, step) if y <= top * 1.05]
    _log_axes(rec, f"{path}/axes", [(i + 0.5, "") for i in range(n)], yticks, (0.0, float(n)), (0.0, BAR_HEIGHT))
    stagger = n > 5
    pos = [(i + 0.5, -(0.06 + (0.08 if stagger and i % 2 else 0.0)) * BAR_HEIGHT) for i in range(n)]
    rec.log(f"{path}/categories", rr.Points2D(_xy(*np.array(pos).T), radii=0.001, colors=[_BLACK],
            labels=categories, show_labels=True), static=True)  # fmt: skip
    return bar_bounds(n)


def bar_bounds(n: int) -> rrb.VisualBounds2D:
    """The bounds that frame a :func:`log_bars` chart of ``n`` categories (as :func:`_log_axes` frames its plot,
    with room for two rows of category names)."""
    pad_x, pad_y = 0.04 * n, 0.06 * BAR_HEIGHT
    return rrb.VisualBounds2D(x_range=[-3 * pad_x, n + pad_x], y_range=[-BAR_HEIGHT - 2 * pad_y, 5 * pad_y])


def _log_diagnosis(rec: rr.RecordingStream, res: RunResults) -> dict[str, rrb.VisualBounds2D]:
    d = res.diagnosis
    if d is None:
        return {}
    bounds = {}
    rows = gap_rows(d)
    lines = ["### Sim-to-real gap diagnosis", ""]
    if rows:
        before = np.array([r[1] for r in rows])
        after = np.array([r[2] for r in rows])
        series = [("simulation as given", before, _RED), ("recalibrated, with the effects", after, _BLUE)]
        names = [r[0].split(" (")[0] for r in rows]  # the experiment; its fold is in the summary
        bounds["gap"] = log_bars(rec, "diagnosis/gap", names, series, values=len(rows) <= 6)
        lines += ["Gap per experiment (gap = 1 - fit/100): the simulation as given red (left), recalibrated with the "
                  "effects blue (right).", ""]  # fmt: skip
    steps = d.waterfall()
    if len(steps) > 1:
        gaps = np.array([g for _, g, _ in steps])
        bounds["waterfall"] = log_bars(rec, "diagnosis/waterfall", [s[0] for s in steps],
                                        [("held-out gap", gaps, _ORANGE)])  # fmt: skip
    lines += diagnosis_markdown(d)
    _markdown(rec, "diagnosis/summary", lines)
    return bounds


def _log_replays(rec: rr.RecordingStream, res: RunResults) -> None:
    """Each experiment's replays against its record, per channel, over ``time``:
    ``diagnosis/replays/<experiment>/<channel>/{record,given,recalibrated,effects}``."""
    colors = {"record": _BLACK, "given": _ORANGE, "recalibrated": [44, 160, 44], "effects": _BLUE}
    for name, rp in res.replays.items():
        t = rr.TimeColumn("time", duration=rp.t)
        fits = replay_fits(rp)
        for ch in ("theta", "alpha"):
            base = f"diagnosis/replays/{_part(name)}/{ch}"
            _style(rec, f"{base}/record", f"record {ch} [deg]", colors["record"], 2.0)
            _series(rec, f"{base}/record", t, rp.record[ch])
            for stage, label in STAGES.items():
                _style(rec, f"{base}/{stage}", f"{label} (fit {fits[stage]:.1f} %)", colors[stage])
                _series(rec, f"{base}/{stage}", t, rp.sim[stage][ch])


def _step(span: float) -> float:
    """A tick step of 1, 2 or 5 times a power of ten, about a quarter of ``span`` (> 0)."""
    step = 10.0 ** math.floor(math.log10(span / 2))
    return step * 5 if span / step > 10 else step * 2 if span / step > 5 else step


def _log_force(rec: rr.RecordingStream, res: RunResults) -> rrb.VisualBounds2D | None:
    """The likelihood engine's missing force per record: over ``time`` with its +-2 sd band
    (``diagnosis/force/time/<record>/{force,upper,lower}``), and against the hub's speed as 2D points
    (``diagnosis/force/speed/<record>``, x the speed, y the force, scaled to :data:`FORCE_WIDTH` by
    :data:`FORCE_HEIGHT`); returns the scatter's bounds (None: no force picture)."""
    if not res.force:
        return None
    speed = np.concatenate([tr.speed for tr in res.force])
    force = np.concatenate([tr.force for tr in res.force])
    smax = float(np.nanmax(np.abs(speed), initial=0.0)) or 1.0
    fmax = float(np.nanmax(np.abs(force), initial=0.0)) or 1.0
    sx, sy = 0.5 * FORCE_WIDTH / smax, 0.5 * FORCE_HEIGHT / fmax  # 2D units per deg/s, per N m
    for i, tr in enumerate(res.force):
        color = _PALETTE[i % len(_PALETTE)]
        base = f"diagnosis/force/time/{_part(tr.name)}"
        t = rr.TimeColumn("time", duration=tr.t)
        _style(rec, f"{base}/force", f"{tr.name}: missing force [N m]", color, 1.5)
        _series(rec, f"{base}/force", t, tr.force)
        for side, sign in (("upper", 1.0), ("lower", -1.0)):
            _style(rec, f"{base}/{side}", f"{tr.name}: {side} 2 sd", color, 0.5)
            _series(rec, f"{base}/{side}", t, tr.force + sign * 2.0 * tr.force_sd)
        rec.log(f"diagnosis/force/speed/{_part(tr.name)}", rr.Points2D(_xy(tr.speed * sx, tr.force * sy),
                radii=0.02, colors=[color]), static=True)  # fmt: skip
    ds, df = _step(2.0 * smax), _step(2.0 * fmax)
    xticks = [(x * sx, f"{x:g}") for x in _ticks(-smax, smax, ds) if abs(x) <= smax]
    yticks = [(y * sy, f"{y:g}") for y in _ticks(-fmax, fmax, df) if abs(y) <= fmax]
    half_w, half_h = 0.5 * FORCE_WIDTH, 0.5 * FORCE_HEIGHT
    if res.not_white:
        _markdown(rec, "diagnosis/force/where", ["Where the linear fit's residuals are not white (octave bands, "
                                                 "stretches of time; each at 1 %):", "",
                                                 *(f"- {x}" for x in res.not_white)])  # fmt: skip
    return _log_axes(rec, "diagnosis/force/speed/axes", xticks, yticks, (-half_w, half_w), (-half_h, half_h))


def _log_data(rec: rr.RecordingStream, res: RunResults) -> None:
    """Every experiment's data as measured over ``time``: ``data/<experiment>/{u,theta,alpha}``."""
    for name, df in res.records.items():
        t_s = df["t"].to_numpy(dtype=float)
        t = rr.TimeColumn("time", duration=t_s - t_s[0])
        theta, alpha, unit = record_angles(res, name)
        base = f"data/{_part(name)}"
        for ch, y, label, color in (("u", df["u"].to_numpy(dtype=float), "command u [V]", _BLUE),
                                    ("theta", theta, f"theta [{unit}]", _BLACK),
                                    ("alpha", alpha, f"alpha [{unit}]", [44, 160, 44])):  # fmt: skip
            _style(rec, f"{base}/{ch}", label, color)
            _series(rec, f"{base}/{ch}", t, y)


def _log_overview(rec: rr.RecordingStream, res: RunResults) -> None:
    m = res.manifest
    lines = [
        f"### {title(res)}",
        "",
        f"- holds: {holds(res)}",
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
    if res.missing_force is not None:
        verdict = res.missing_force.words()
        lines.append(f"- missing force (likelihood engine): **{verdict}**; its tab draws it against time and hub speed")
    lines += [
        "",
        "Tabs: data (each experiment as measured), datasets (identification domain, measured vs the selected",
        "model), cross-fit (heat map, table, tensor), model (pole-zero map, Bode over log10 f), residuals",
        "(correlations over the lag), diagnosis (gaps, stages and summary), replays (each experiment re-simulated",
        "as given, recalibrated and with the effects, against the record); the ones this run directory has data",
        "for. The full numbers are in report.md and the JSON files.",
    ]
    _markdown(rec, "overview", lines)


def _log_all(rec: rr.RecordingStream, res: RunResults) -> dict[str, rrb.VisualBounds2D]:
    """Log everything; returns the 2D views' bounds by plot name."""
    rec.send_recording_name(title(res).replace("`", ""))
    _log_overview(rec, res)
    _log_data(rec, res)
    _log_datasets(rec, res)
    bounds: dict[str, rrb.VisualBounds2D] = {}
    if _log_crossfit(rec, res):
        bounds["heatmap"] = rrb.VisualBounds2D()  # the image framed as logged
    _log_pz(rec, res)
    bounds.update({f"bode_{k}": v for k, v in _log_bode(rec, res).items()})
    bounds.update({f"resid_{k}": v for k, v in _log_resid(rec, res).items()})
    bounds.update({f"diagnosis_{k}": v for k, v in _log_diagnosis(rec, res).items()})
    force = _log_force(rec, res)
    if force is not None:
        bounds["force_speed"] = force
    _log_replays(rec, res)
    return bounds


# ----------------------------------------------------------------------------------------------- blueprint
def _data_tab(res: RunResults) -> Any:
    """Each experiment as measured: command, theta, alpha over time, one tab per experiment."""
    per = []
    for name in res.records:
        o = f"data/{_part(name)}"
        unit = "deg" if res.calibration is not None else "V"
        per.append(rrb.Vertical(
            rrb.TimeSeriesView(origin=f"{o}/u", name=f"{name}: command u [V] vs t [s]"),
            rrb.TimeSeriesView(origin=f"{o}/theta", name=f"{name}: theta [{unit}] vs t [s]"),
            rrb.TimeSeriesView(origin=f"{o}/alpha", name=f"{name}: alpha [{unit}] vs t [s]"),
            name=name,
        ))  # fmt: skip
    return rrb.Tabs(*per, name="data")


def _datasets_tab(res: RunResults) -> Any:
    """The identification datasets: y_f measured (and simulated by the selected model), tip angle, command."""
    per = []
    for name in res.prepared:
        o = f"datasets/{_part(name)}"
        shown = ["$origin/measured", "$origin/simulated"] if name in res.simulated else ["$origin/measured"]
        per.append(rrb.Vertical(
            rrb.TimeSeriesView(origin=o, contents=shown, name=f"{name}: y_f [deg/sample] vs t [s]"),
            rrb.TimeSeriesView(origin=f"{o}/tip", name=f"{name}: tip angle [deg] vs t [s]"),
            rrb.TimeSeriesView(origin=o, contents=["$origin/command"], name=f"{name}: command u [V] vs t [s]"),
            row_shares=[2.0, 2.0, 1.0],
            name=name,
        ))  # fmt: skip
    return rrb.Tabs(*per, name="datasets")


def _model_tab(res: RunResults, bounds: dict[str, rrb.VisualBounds2D]) -> Any:
    views: list[Any] = []
    if res.selected is not None:
        views.append(
            rrb.Spatial2DView(
                origin="models/selected/pz",
                name="pole-zero map of the selected model: Re z (right) vs Im z (up)",
                visual_bounds=rrb.VisualBounds2D(x_range=[-1.5, 1.5], y_range=[-1.5, 1.5]),
            )
        )
    views.append(
        rrb.Vertical(
            rrb.Spatial2DView(origin="bode/magnitude", name="Bode magnitude [dB] vs log10 f [Hz]",
                              visual_bounds=bounds.get("bode_magnitude")),
            rrb.Spatial2DView(origin="bode/phase", name="Bode phase [deg] vs log10 f [Hz]",
                              visual_bounds=bounds.get("bode_phase")),
        )
    )  # fmt: skip
    return rrb.Horizontal(*views, name="model")


def _diagnosis_tab(res: RunResults, bounds: dict[str, rrb.VisualBounds2D]) -> Any:
    bars: list[Any] = []
    if "diagnosis_gap" in bounds:
        bars.append(
            rrb.Spatial2DView(
                origin="diagnosis/gap",
                visual_bounds=bounds["diagnosis_gap"],
                name="gap per experiment: as given (red) / recalibrated with the effects (blue)",
            )
        )
    if "diagnosis_waterfall" in bounds:
        bars.append(rrb.Spatial2DView(origin="diagnosis/waterfall", visual_bounds=bounds["diagnosis_waterfall"],
                                      name="held-out gap by stage (gap = 1 - fit/100)"))  # fmt: skip
    summary = rrb.TextDocumentView(origin="diagnosis/summary", name="summary")
    if not bars:
        return summary
    return rrb.Tabs(summary, rrb.Horizontal(*bars, name="gaps"), name="diagnosis")  # the summary's tables at full width


def _force_tab(bounds: dict[str, rrb.VisualBounds2D], res: RunResults) -> Any:
    """The missing force: over time with its band, and against the hub's speed; where the residuals are not white,
    when they are not somewhere."""
    where = [rrb.TextDocumentView(origin="diagnosis/force/where", name="where not white")] if res.not_white else []
    return rrb.Vertical(
        rrb.TimeSeriesView(origin="diagnosis/force/time", name="missing force [N m] vs t [s], +-2 sd band"),
        rrb.Spatial2DView(origin="diagnosis/force/speed", visual_bounds=bounds["force_speed"],
                          name="missing force [N m] (up) vs hub speed [deg/s] (right)"),
        *where,
        name="missing force",
    )  # fmt: skip


def _replays_tab(res: RunResults) -> Any:
    """Per experiment: theta and alpha of the record and the replays (as given, recalibrated, with the effects)."""
    per = []
    for name in res.replays:
        o = f"diagnosis/replays/{_part(name)}"
        per.append(rrb.Vertical(
            rrb.TimeSeriesView(origin=f"{o}/theta", name=f"{name}: theta [deg] vs t [s], record and replays"),
            rrb.TimeSeriesView(origin=f"{o}/alpha", name=f"{name}: alpha [deg] vs t [s], record and replays"),
            name=name,
        ))  # fmt: skip
    return rrb.Tabs(*per, name="replays")


def _blueprint(res: RunResults, bounds: dict[str, rrb.VisualBounds2D], active: int = 0) -> rrb.Blueprint:
    """The tabs this run has data for, the overview first and active (``active``: another tab's index); tables at
    full width."""
    tabs: list[Any] = [rrb.TextDocumentView(origin="overview", name="overview")]
    if res.records:
        tabs.append(_data_tab(res))
    if res.prepared:
        tabs.append(_datasets_tab(res))
    if "heatmap" in bounds:
        tabs.append(
            rrb.Vertical(
                rrb.Horizontal(
                    rrb.Spatial2DView(origin="crossfit/heatmap", name="cross-fit [%]: model (row) on dataset (column)"),
                    rrb.TensorView(origin="crossfit/matrix", name="cross-fit tensor (model x dataset)"),
                    column_shares=[3.0, 1.0],
                ),
                rrb.TextDocumentView(origin="crossfit/table", name="cross-fit table"),
                row_shares=[3.0, 2.0],
                name="cross-fit",
            )
        )
    if res.models:
        tabs.append(_model_tab(res, bounds))
    if "resid_acf" in bounds:
        tabs.append(
            rrb.Vertical(
                rrb.Spatial2DView(origin="resid/acf", name="residual autocorrelation r_ee vs lag [samples]",
                                  visual_bounds=bounds["resid_acf"]),
                rrb.Spatial2DView(origin="resid/ccf", name="residual-input cross-correlation r_eu vs lag [samples]",
                                  visual_bounds=bounds["resid_ccf"]),
                rrb.TextDocumentView(origin="resid/summary", name="residual tests"),
                name="residuals",
            )
        )  # fmt: skip
    if res.diagnosis is not None:
        tabs.append(_diagnosis_tab(res, bounds))
    if "force_speed" in bounds:
        tabs.append(_force_tab(bounds, res))
    if res.replays:
        tabs.append(_replays_tab(res))
    return rrb.Blueprint(
        rrb.Tabs(*tabs, active_tab=min(active, len(tabs) - 1)),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="time", state="collapsed"),
    )


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
    """Log a run directory to Rerun: to a recording file, and live to a viewer when asked.

    One recording, application id ``flexjoint``, recording id from the manifest's spec hash; the blueprint that
    lays it out travels with it.

    Parameters
    ----------
    run : Path
        The run directory.
    rrd : Path, optional
        The recording to write (atomically); default ``<run>/run.rrd``.
    spawn : bool
        Also stream to a newly spawned viewer.
    connect : str, optional
        Also stream to a running viewer (``rerun+http://127.0.0.1:9876/proxy``).
    results : RunResults, optional
        The run already loaded, shared with the report.

    Returns
    -------
    Path or None
        The ``.rrd`` file written.
    """
    if connect is not None:
        _check_url(connect)
    res = results if results is not None else load_results(Path(run))
    out = Path(rrd) if rrd is not None else res.paths.recording
    _write_rrd(res, out)
    if spawn or connect is not None:
        _stream_live(res, spawn, connect)
    return out
