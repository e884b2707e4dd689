"""The report's matplotlib figures, each drawn from data computed elsewhere (:mod:`harness.render.analysis`,
:mod:`harness.ident.lti`) and written as PNG.

Figures are drawn with matplotlib's Agg canvas (no pyplot, no global backend change) at a fixed dpi and with
no software/date metadata, so the same data give the same bytes on the same library versions.
"""

from __future__ import annotations

import io
import math
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..ident import armax, lti
from ..ident.preprocess import filter_response
from ..rundir import atomic_write_bytes
from .analysis import MIN_COHERENCE, MeasuredFRF
from .tables import fmt

__all__ = [
    "DPI",
    "PZ_VIEW_MAX",
    "TimePanel",
    "bode",
    "crossfit_figure",
    "crossfit_png",
    "diagnosis_bars",
    "filter_responses",
    "fixed_layout",
    "gap_waterfall",
    "new_figure",
    "png_bytes",
    "pole_zero",
    "residual_correlations",
    "save_figure",
    "square_response",
    "experiment_data",
    "replay",
    "time_response",
]

DPI = 100
PZ_VIEW_MAX = 2.5  # half-width of the pole-zero plot; farther roots are listed on it instead


def new_figure(w: float, h: float) -> Figure:
    """A matplotlib figure of w x h inches at the report's DPI, drawn without pyplot (no GUI, thread-safe)."""
    fig = Figure(figsize=(w, h), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def fixed_layout(fig: Figure, hspace: float = 0.3) -> None:
    """Fixed margins for the report's many stacked time plots (9 in wide): a third of ``tight_layout``'s cost, which
    draws every tick label once more to measure it."""
    fig.subplots_adjust(left=0.09, right=0.98, top=0.94, bottom=0.08, hspace=hspace)


def png_bytes(fig: Figure) -> bytes:
    """``fig`` as PNG bytes, without a timestamp or software tag (the same bytes on a re-run)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None})
    return buf.getvalue()


def save_figure(fig: Figure, path: Path) -> None:
    """Write ``fig`` as PNG atomically (:func:`png_bytes`)."""
    atomic_write_bytes(path, png_bytes(fig))


FigureJob = tuple[Callable[..., None], tuple, dict]


def figure_png(job: FigureJob) -> bytes:
    """The PNG bytes that ``fn(*args, path, **kwargs)`` saves (``job`` = (fn, args, kwargs)): a figure drawn where
    it runs (a worker that shares no files with the client) and written by the caller."""
    fn, args, kwargs = job
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "figure.png"
        fn(*args, path, **kwargs)
        return path.read_bytes()


def filter_responses(afs: tuple[float, ...], af_used: float, f_hz: np.ndarray, Ts: float, path: Path) -> None:
    """Magnitude [dB] and phase [deg] of H(z) for each af in ``afs`` over ``f_hz`` [Hz]."""
    fig = new_figure(7, 5)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    for af in afs:
        mag, ph = filter_response(af, f_hz, Ts)
        lw = 2.0 if af == af_used else 1.0
        ax_m.semilogx(f_hz, 20 * np.log10(mag), lw=lw, label=f"af = {af:g}" + (" (used)" if af == af_used else ""))
        ax_p.semilogx(f_hz, np.degrees(ph), lw=lw)
    ax_m.set_ylabel("magnitude [dB]")
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_m.set_title(f"H(z) = (1-af)(z-1)/(z-af), Ts = {Ts:g} s")
    ax_m.legend()
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def bode(
    curves: Mapping[str, lti.BodeData],
    selected_label: str,
    measured: MeasuredFRF | None,
    path: Path,
) -> None:
    """Bode of G = B/A / H(z) (u [V] -> tip angle [deg]): the per-dataset models grey, ``curves["selected"]``
    blue, and the measured (nonparametric) response as dots."""
    fig = new_figure(7, 5.5)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    for name, d in curves.items():
        if name != "selected":
            ax_m.semilogx(d.f_hz, d.mag_db, color="0.7", lw=0.8)
            ax_p.semilogx(d.f_hz, d.phase_deg, color="0.7", lw=0.8)
    sel = curves["selected"]
    ax_m.semilogx(sel.f_hz, sel.mag_db, color="C0", lw=2, label=f"selected {selected_label}")
    ax_p.semilogx(sel.f_hz, sel.phase_deg, color="C0", lw=2)
    ax_m.plot([], [], color="0.7", label="per-dataset models")
    if measured is not None:
        near = float(np.interp(measured.f_hz[0], sel.f_hz, sel.phase_deg))
        label = f"measured on {measured.dataset} (H1, coherence >= {MIN_COHERENCE:g})"
        ax_m.semilogx(measured.f_hz, measured.mag_db, ".", color="k", ms=3, label=label)
        ax_p.semilogx(measured.f_hz, measured.phase_deg(near), ".", color="k", ms=3)
    ax_m.set_ylabel("magnitude [dB]")
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_m.set_title("Bode of G = B/A / H(z): command u [V] to tip angle y [deg]")
    ax_m.legend(fontsize=8)
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def pole_zero(poles: np.ndarray, zeros: np.ndarray, path: Path) -> None:
    """z-plane map with the unit circle; roots beyond PZ_VIEW_MAX are listed on the plot."""
    fig = new_figure(5.5, 5.5)
    ax = fig.subplots()
    th = np.linspace(0, 2 * math.pi, 361)
    ax.plot(np.cos(th), np.sin(th), color="0.5", lw=0.8)
    ax.axhline(0, color="0.8", lw=0.6)
    ax.axvline(0, color="0.8", lw=0.6)
    ax.plot(poles.real, poles.imag, "x", color="C3", ms=9, mew=2, label=f"poles ({poles.size})")
    ax.plot(zeros.real, zeros.imag, "o", mfc="none", color="C0", ms=8, mew=1.5, label=f"zeros ({zeros.size})")
    both = np.concatenate([poles, zeros])
    lim = float(np.clip(1.1 * np.max(np.abs(both), initial=1.0), 1.3, PZ_VIEW_MAX))
    far = [
        f"{kind} at {fmt(x.real, 2)}{x.imag:+.2f}j"
        for kind, xs in (("pole", poles), ("zero", zeros))
        for x in xs
        if abs(x.real) > lim or abs(x.imag) > lim
    ]
    if far:
        ax.text(0.98, 0.02, "off view: " + ", ".join(far), transform=ax.transAxes, ha="right", fontsize=8)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("Re z")
    ax.set_ylabel("Im z")
    ax.set_title("pole-zero map of the selected model (with integrator)")
    ax.legend(loc="upper left")
    fig.tight_layout()
    save_figure(fig, path)


@dataclass(frozen=True)
class TimePanel:
    """One dataset's panel: time t [s], measured and simulated y_f [deg/sample] (simulated None without a
    model), and the zoom window (t0, t1) [s]."""

    name: str
    t: np.ndarray
    measured: np.ndarray
    simulated: np.ndarray | None
    zoom: tuple[float, float]


def time_response(pnl: TimePanel, zoom_s: float, path: Path) -> None:
    """One dataset: the whole record (measured, and with a model simulated and the residual) and, under it, the
    zoom window where the residual is largest, so that measurement and simulation can be told apart."""
    fig = new_figure(9, 6)
    top, zoom = fig.subplots(2, 1)
    for ax in (top, zoom):
        ax.plot(pnl.t, pnl.measured, color="k", lw=0.9, label="measured")
        if pnl.simulated is not None:
            ax.plot(pnl.t, pnl.simulated, color="C1", lw=0.9, label="simulated (selected model)")
            ax.plot(pnl.t, pnl.measured - pnl.simulated, color="C3", lw=0.7, label="residual")
        ax.set_ylabel("y_f [deg/sample]")
        ax.grid(True, alpha=0.3)
    fit = f": fit {fmt(armax.fit_percent(pnl.measured, pnl.simulated))} %" if pnl.simulated is not None else ""
    top.set_title(f"{pnl.name}{fit} (filtered tip-angle difference y_f)")
    top.set_xlabel("t [s]")
    top.axvspan(*pnl.zoom, color="C0", alpha=0.12)
    zoom.set_xlim(*pnl.zoom)
    what = "largest residual" if pnl.simulated is not None else "first"
    zoom.set_xlabel(f"t [s] (zoom: the {what} {zoom_s:g} s, shaded above)")
    top.legend(fontsize=8, loc="upper right")
    fixed_layout(fig)
    save_figure(fig, path)


def experiment_data(
    name: str,
    t: np.ndarray,
    u: np.ndarray,
    theta: np.ndarray,
    alpha: np.ndarray,
    unit: str,
    path: Path,
    ref: np.ndarray | None = None,
) -> None:
    """One experiment's data as recorded (MATLAB's ``plot(data)``): command u [V], shaft angle theta and link
    deflection alpha [``unit``] over t [s]; a closed-loop record's reference ``ref`` [deg] dashed over theta."""
    fig = new_figure(9, 6)
    axes = fig.subplots(3, 1, sharex=True)
    for ax, y, label, color in (
        (axes[0], u, "command u [V]", "k"),
        (axes[1], theta, f"theta [{unit}]", "C0"),
        (axes[2], alpha, f"alpha [{unit}]", "C2"),
    ):
        ax.plot(t, y, color=color, lw=0.8)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    if ref is not None:
        axes[1].plot(t, ref, color="0.45", lw=0.9, ls="--", label="reference [deg]")
        axes[1].plot([], [], color="C0", lw=0.8, label="theta")
        axes[1].legend(fontsize=8, loc="upper right")
    axes[0].set_title(f"{name}: the data (command, shaft angle, link deflection)")
    axes[2].set_xlabel("t [s]")
    fixed_layout(fig)
    save_figure(fig, path)


def replay(
    name: str,
    t: np.ndarray,
    record: Mapping[str, np.ndarray],
    sims: Mapping[str, Mapping[str, np.ndarray]],
    labels: Mapping[str, str],
    fits: Mapping[str, float],
    zoom: tuple[float, float],
    path: Path,
) -> None:
    """One experiment's replays against its record, per channel (theta, alpha [deg] over t [s]): each stage of
    ``sims`` ({stage: {channel: [deg]}}, labelled ``labels[stage]`` with its fit ``fits[stage]`` [%]) in its own
    colour, the record black over them, the last stage's residual under them; the whole record on the left, the
    window ``zoom`` (t0, t1) [s] on the right (shaded on the left)."""
    colors = ("C1", "C2", "C0", "C4")
    fig = new_figure(13, 7)
    grid = fig.subplots(3, 2, sharex="col", sharey="row", height_ratios=[2, 2, 1], width_ratios=[3, 2])
    last = list(sims)[-1]
    for col in (0, 1):
        ax_th, ax_al, ax_e = grid[:, col]
        for ax, ch in ((ax_th, "theta"), (ax_al, "alpha")):
            for (stage, sim), color in zip(sims.items(), colors, strict=False):
                ax.plot(t, sim[ch], color=color, lw=0.9, label=f"{labels[stage]} (fit {fmt(fits[stage], 1)} %)")
            ax.plot(t, record[ch], color="k", lw=0.8, label="record", zorder=5)
            ax.grid(True, alpha=0.3)
        for ch, color in (("theta", "C0"), ("alpha", "C2")):
            ax_e.plot(t, record[ch] - sims[last][ch], color=color, lw=0.7, label=ch)
        ax_e.grid(True, alpha=0.3)
    for row, label in enumerate(("theta [deg]", "alpha [deg]", "residual [deg]")):
        grid[row, 0].set_ylabel(label)
        grid[row, 0].axvspan(*zoom, color="0.5", alpha=0.12)
    grid[2, 0].set_xlabel("t [s]")
    grid[2, 1].set_xlabel("t [s] (zoom: where the simulation as given misses most)")
    grid[2, 1].set_xlim(*zoom)
    grid[2, 0].legend(fontsize=7, loc="upper right", title=f"record - {labels[last]}", title_fontsize=7)
    grid[0, 0].set_title(f"{name}: the diagnosis's replays against the record")
    grid[0, 1].set_title(f"{zoom[0]:.1f}-{zoom[1]:.1f} s")
    grid[0, 1].legend(fontsize=7, loc="best")
    fig.subplots_adjust(left=0.06, right=0.99, top=0.94, bottom=0.08, hspace=0.3, wspace=0.06)
    save_figure(fig, path)


def square_response(t: np.ndarray, u: np.ndarray, y: np.ndarray, title: str, path: Path) -> None:
    """Command u [V] and tip angle y [deg] over t [s]."""
    fig = new_figure(7, 4)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t, u, color="k", lw=1)
    ax1.set_ylabel("u [V]")
    ax2.plot(t, y, color="C0", lw=1.2)
    ax2.set_ylabel("tip angle y [deg]")
    ax2.set_xlabel("t [s]")
    ax1.set_title(title)
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def residual_correlations(rt: armax.ResidTest, title: str, path: Path) -> None:
    """Autocorrelation of the residual and its cross-correlation with the input, with the 99 % bound."""
    fig = new_figure(7, 5)
    ax1, ax2 = fig.subplots(2, 1)
    lags = np.arange(rt.acf.size)
    ax1.vlines(lags, 0, rt.acf, color="C0")
    ax1.plot(lags, rt.acf, "o", color="C0", ms=3)
    ax2.vlines(rt.lags_ccf, 0, rt.ccf, color="C2")
    ax2.plot(rt.lags_ccf, rt.ccf, "o", color="C2", ms=3)
    for ax, x in ((ax1, lags), (ax2, rt.lags_ccf)):
        ax.fill_between(x, -rt.bound, rt.bound, color="C3", alpha=0.15, label="99 % bound")
        ax.axhline(0, color="0.5", lw=0.6)
    ax1.set_title(title, fontsize=10)
    ax1.set_ylabel("r_ee(k) / r_ee(0)")
    ax1.set_xlabel("lag k [samples]")
    ax2.set_ylabel("r_eu(k), normalised")
    ax2.set_xlabel("lag k [samples]")
    ax1.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


_CROSSFIT_PNG: dict[str, bytes] = {}  # the last heat map drawn, by its matrix (as CSV)


def crossfit_png(cf: pd.DataFrame) -> bytes:
    """The cross-fit heat map (:func:`crossfit_figure`) as PNG bytes, drawn once per matrix in a process: the report
    and the recording show the same figure."""
    key = cf.to_csv()
    if key not in _CROSSFIT_PNG:
        png = png_bytes(crossfit_figure(cf))
        _CROSSFIT_PNG.clear()
        _CROSSFIT_PNG[key] = png
    return _CROSSFIT_PNG[key]


def crossfit_figure(cf: pd.DataFrame) -> Figure:
    """Heat map of the cross-fit matrix [%] (model rows, dataset columns, by name), each value written in black
    or white, whichever reads on its cell's colour."""
    vals = cf.to_numpy(dtype=float)
    fig = new_figure(2.6 + 0.9 * vals.shape[1], 2.2 + 0.5 * vals.shape[0])
    ax = fig.subplots()
    shown = np.where(np.isfinite(vals), vals, np.nan)
    im = ax.imshow(shown, cmap="viridis", aspect="auto")
    ax.set_xticks(range(vals.shape[1]), [str(c) for c in cf.columns], rotation=35, ha="right")
    ax.set_yticks(range(vals.shape[0]), list(cf.index))
    ax.set_xlabel("dataset the model is simulated on")
    ax.set_ylabel("model (fitted on dataset)")
    for i in range(vals.shape[0]):
        for j in range(vals.shape[1]):
            r, g, b, _ = im.cmap(im.norm(vals[i, j])) if np.isfinite(vals[i, j]) else (1.0, 1.0, 1.0, 1.0)
            dark = 0.299 * r + 0.587 * g + 0.114 * b < 0.5
            ax.text(j, i, fmt(vals[i, j], 1), ha="center", va="center", fontsize=8, color="w" if dark else "k")
    fig.colorbar(im, ax=ax, label="fit [%]")
    ax.set_title("cross-fit [%]: each model (row) simulated on each dataset (column)")
    fig.tight_layout()
    return fig


def diagnosis_bars(rows: list[tuple[str, float, float]], path: Path) -> None:
    """Gap per experiment (label, before, after) as paired bars."""
    fig = new_figure(max(5.0, 0.9 * len(rows) + 2), 4)
    ax = fig.subplots()
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r[1] for r in rows], 0.4, label="simulation as given")
    ax.bar(x + 0.2, [r[2] for r in rows], 0.4, label="recalibrated, with the effects")
    ax.set_xticks(x, [r[0] for r in rows], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("gap [1] = 1 - fit [%] / 100")
    ax.set_xlabel("experiment")
    ax.set_title("sim-to-real gap per experiment")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def gap_waterfall(rows: list[tuple[str, float, float]], noise: float, path: Path) -> None:
    """The held-out gap stage by stage (stage, gap after it, closed [%]): the first bar is the gap before, each
    next one floats from the previous gap to the gap after its stage (green when it closes, red when it reopens)
    and is labelled with the change, the last bar is the final gap; the noise floor dashed."""
    fig = new_figure(max(6.0, 1.1 * len(rows) + 2), 4.5)
    ax = fig.subplots()
    prev = rows[0][1]
    ax.bar(0, prev, 0.6, color="C0")
    ax.text(0, prev, f"{prev:.4f}", ha="center", va="bottom", fontsize=8)
    for i, (_, g, _) in enumerate(rows[1:], 1):
        lo, hi = min(prev, g), max(prev, g)
        ax.bar(i, max(hi - lo, 1e-4 * rows[0][1]), 0.6, bottom=lo, color="C2" if g <= prev else "C3")
        ax.plot([i - 1.3, i + 0.3], [prev, prev], color="0.5", lw=0.6)
        ax.text(i, hi, f"{g - prev:+.4f}", ha="center", va="bottom", fontsize=8)
        prev = g
    ax.bar(len(rows), prev, 0.6, color="C0")
    ax.text(len(rows), prev, f"{prev:.4f}", ha="center", va="bottom", fontsize=8)
    if math.isfinite(noise):
        ax.axhline(noise, color="k", ls="--", lw=0.8, label=f"noise floor {noise:.4f}")
        ax.legend(fontsize=8)
    labels = [r[0] for r in rows] + ["final"]
    ax.set_xticks(np.arange(len(labels)), labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("held-out gap [1] = 1 - fit [%] / 100")
    ax.set_xlabel("stage")
    ax.set_title("gap waterfall: the simulation as given, recalibration, then each effect")
    ax.set_ylim(0, 1.12 * rows[0][1])
    fig.tight_layout()
    save_figure(fig, path)
