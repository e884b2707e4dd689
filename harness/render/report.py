"""``report.md`` and ``figures/*.png`` of a run directory, written from the run directory alone.

Also the loader of a run's results (:func:`load_results`) shared with :mod:`harness.render.viewer`: datasets in the
identification domain (detrended command u_d [V], filtered difference y_f = H(z) y [deg/sample] of the tip
angle y [deg]), the identified models, grid, cross-fit matrix, diagnosis and doubled-rate check.

Figures are drawn with matplotlib's Agg canvas (no pyplot, no global backend change) at a fixed dpi and with
no software/date metadata, so the same run directory gives the same bytes on the same library versions.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.signal import coherence, csd, lfilter, welch

from ..ident import armax, lti
from ..ident.calibration import SEED_CALIBRATION, Calibration
from ..ident.identify import Prepared, prepare
from ..ident.preprocess import filter_response
from ..rundir import DataError, atomic_write_bytes, load_manifest, load_run
from ..spec import IDENTIFY_DEFAULTS

__all__ = [
    "DPI",
    "SEED_CALIBRATION",
    "RunResults",
    "bode",
    "crossfit_table",
    "diagnosis_markdown",
    "fold_roles",
    "gap_rows",
    "load_results",
    "pole_zero",
    "tip_from_filtered",
    "waterfall",
    "write_report",
]

DPI = 100
FILTER_AFS = (0.6, 0.8, 0.9)
RESID_LAGS = 25
GRID_COLUMNS = ("dataset", "na", "nb", "nc", "nk", "causal", "stable", "fit")
PZ_VIEW_MAX = 2.5  # half-width of the pole-zero plot; farther roots are listed on it instead
SQUARE_HZ, SQUARE_V, SQUARE_PERIODS = 0.4, 1.0, 3  # square-wave test input of the selected model
ZOOM_S = 4.0  # s: the zoom window of the time-response panels, where the residual is largest
MIN_COHERENCE = 0.8  # measured FRF points shown on the Bode plot where the coherence u -> y_f reaches this


# ----------------------------------------------------------------------------------------------- loading
@dataclass
class RunResults:
    """What a run directory holds, loaded once.

    ``prepared``: identification datasets (u_d [V], y_f [deg/sample], y [deg], u [V], Ts [s]), manifest order;
    ``models``: name -> (ArmaxModel, JSON record) for ``models/<dataset>.json`` and ``models/selected.json``;
    ``simulated``: dataset -> y_f simulated by the selected model (ic of its preprocessing record);
    ``crossfit``: models x datasets fit [%] (no average column), ``crossfit_source`` where it came from.
    """

    run: Path
    manifest: dict[str, Any]
    calibration: Calibration | None = None
    calibration_file: dict[str, Any] | None = None
    prepared: dict[str, Prepared] = field(default_factory=dict)
    models: dict[str, tuple[armax.ArmaxModel, dict[str, Any]]] = field(default_factory=dict)
    simulated: dict[str, np.ndarray] = field(default_factory=dict)
    grid: pd.DataFrame | None = None
    crossfit: pd.DataFrame | None = None
    crossfit_csv_average: pd.Series | None = None
    crossfit_source: str = ""
    diagnosis: dict[str, Any] | None = None
    doubled_rate: dict[str, Any] | None = None
    af: float = float(IDENTIFY_DEFAULTS["af"])
    ic: str = str(IDENTIFY_DEFAULTS["ic"])

    @property
    def selected(self) -> tuple[armax.ArmaxModel, dict[str, Any]] | None:
        """The selected model and its record, or None before identification."""
        return self.models.get("selected")

    @property
    def sample_time(self) -> float:
        """Sampling period Ts [s]: from the data, else the manifest's sample_rate, else 1 s."""
        if self.prepared:
            return next(iter(self.prepared.values())).Ts
        rate = self.manifest.get("sample_rate")
        return 1.0 / float(rate) if rate else 1.0


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


CalPair = tuple[Calibration | None, dict[str, Any] | None]


def _calibration(run: Path, record: dict[str, Any] | None) -> CalPair:
    """The calibration the models were fitted with (model record), else ``calibration.json``."""
    raw = _read_json(run / "calibration.json")
    file_cal = None
    if raw is not None:
        file_cal = Calibration.from_json(run / "calibration.json")
    if record and isinstance(record.get("calibration"), dict):
        c = record["calibration"]
        base = file_cal or Calibration(Kp=c["Kp"], Ke=c["Ke"])
        return (
            Calibration(
                Kp=c.get("Kp", base.Kp),
                Ke=c.get("Ke", base.Ke),
                gauge_offset_v=c.get("gauge_offset_v", base.gauge_offset_v),
                pot_offset_v=c.get("pot_offset_v", base.pot_offset_v),
                dead_zone_v=base.dead_zone_v,
            ),
            raw,
        )
    return file_cal, raw


def load_results(run: Path) -> RunResults:
    """Load everything :func:`write_report` and :func:`harness.render.viewer.log_run` need from a run directory."""
    run = Path(run)
    if not run.is_dir():
        raise DataError(f"{run}: no such run directory")
    res = RunResults(run=run, manifest=load_manifest(run))
    exps = res.manifest.get("experiments", [])
    names = [e["name"] for e in exps if e.get("role", "identification") == "identification"]
    for name in [*names, "selected"]:
        p = run / "models" / f"{name}.json"
        rec = _read_json(p)
        if rec is not None:
            try:
                res.models[name] = (armax.ArmaxModel.from_dict(rec), rec)
            except ValueError as exc:
                raise ValueError(f"{p}: {exc}") from None
    sel = res.models.get("selected")
    sel_rec = sel[1] if sel else None
    if sel_rec:
        pre = sel_rec.get("preprocessing", {})
        res.af = float(pre.get("af", res.af))
        res.ic = str(pre.get("ic", res.ic))
    res.calibration, res.calibration_file = _calibration(run, sel_rec)
    if names and res.calibration is not None:
        output = str((sel_rec or {}).get("preprocessing", {}).get("output", "y"))
        res.prepared = prepare(load_run(run, role="identification"), res.calibration, res.af, output)
    if sel is not None:
        model = sel[0]
        for name, p in res.prepared.items():
            if model.stable:
                res.simulated[name] = armax.simulate(model, p.u_d, p.y_f, res.ic)
    if (run / "grid.csv").exists():
        res.grid = pd.read_csv(run / "grid.csv")
        missing = [c for c in GRID_COLUMNS if c not in res.grid.columns]
        if missing:
            raise ValueError(f"{run / 'grid.csv'}: missing column(s) {', '.join(missing)}")
    _load_crossfit(res)
    res.diagnosis = _read_json(run / "diagnosis.json")
    res.doubled_rate = _read_json(run / "doubled_rate.json")
    return res


def _load_crossfit(res: RunResults) -> None:
    path = res.run / "crossfit.csv"
    if path.exists():
        df = pd.read_csv(path)
        if "model" not in df.columns:
            raise ValueError(f"{path}: first column must be 'model', got {list(df.columns)[:1]}")
        df = df.set_index("model")
        df.index = df.index.astype(str)
        if "average" in df.columns:
            res.crossfit_csv_average = df.pop("average").astype(float)
        res.crossfit = df.astype(float)
        res.crossfit_source = "crossfit.csv"
        return
    rows = {}
    for name, (_, rec) in res.models.items():
        if isinstance(rec.get("cv"), dict) and rec["cv"]:
            rows[name] = {k: (math.nan if v is None else float(v)) for k, v in rec["cv"].items()}
    if rows:
        res.crossfit = pd.DataFrame.from_dict(rows, orient="index")
        res.crossfit.index.name = "model"
        res.crossfit_source = "models/*.json cv (Python-side simulation; crossfit.csv not written yet)"


# ----------------------------------------------------------------------------------------------- model views
def pole_zero(model: armax.ArmaxModel, af: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(poles, zeros) in the z-plane of G = B/A / H(z) (``lti.with_integrator``), zeros at 0 included."""
    g = lti.with_integrator(model, af)
    return lti.poles(g), lti.zeros(g)


def bode(model: armax.ArmaxModel, af: float | None, f_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Magnitude [dB] and unwrapped phase [deg] of G = B/A / H(z) (u [V] -> tip angle [deg]) at f_hz [Hz]."""
    d = lti.bode_data(lti.with_integrator(model, af), f_hz)
    return d.mag_db, d.phase_deg


def tip_from_filtered(y_f: np.ndarray, af: float, y0: float = 0.0) -> np.ndarray:
    """Invert H(z): the angle [deg] whose filtered difference is ``y_f``, starting at rest at ``y0`` [deg]."""
    return y0 + lfilter([1.0, -af], [1.0 - af, -(1.0 - af)], np.asarray(y_f, dtype=float))


def measured_frf(res: RunResults, dataset: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Nonparametric frequency response u [V] -> tip angle y [deg] of one dataset: the H1 estimate (Welch,
    Hann, 50 % overlap) of u_d -> y_f divided by H(z), at the frequencies [Hz] where the coherence reaches
    MIN_COHERENCE; None when the dataset is absent or too short."""
    p = res.prepared.get(dataset)
    if p is None or p.y_f.size < 64:
        return None
    fs = 1.0 / p.Ts
    nper = min(256, p.y_f.size // 4)
    f, puu = welch(p.u_d, fs=fs, nperseg=nper)
    _, puy = csd(p.u_d, p.y_f, fs=fs, nperseg=nper)
    _, coh = coherence(p.u_d, p.y_f, fs=fs, nperseg=nper)
    keep = (f > 0) & (puu > 0) & (coh >= MIN_COHERENCE)
    if not keep.any():
        return None
    z = np.exp(1j * 2 * np.pi * f[keep] * p.Ts)
    h = (1 - res.af) * (z - 1) / (z - res.af)
    return f[keep], (puy[keep] / puu[keep]) / h


def _bode_grid(Ts: float, n: int = 300) -> np.ndarray:
    """Log-spaced frequencies [Hz] from 0.01 Hz (or 1e-3 of Nyquist) up to 0.999 Nyquist."""
    nyq = 0.5 / Ts
    return np.logspace(math.log10(min(0.01, 1e-3 * nyq)), math.log10(0.999 * nyq), n)


# ----------------------------------------------------------------------------------------------- formatting
def _fmt(x: Any, nd: int = 2) -> str:
    if x is None:
        return "—"
    if isinstance(x, bool | np.bool_):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(v):
        return "—"
    s = f"{v:.{nd}f}"
    return s[1:] if s.startswith("-") and float(s) == 0.0 else s  # no "-0.00"


def _fmt_any(x: Any) -> str:
    """Compact rendering of a JSON value for a table cell (floats to 4 significant digits)."""
    if isinstance(x, float):
        return "—" if not math.isfinite(x) else f"{x:.4g}"
    if isinstance(x, dict):
        return ", ".join(
            f"{k}={{{_fmt_any(v)}}}" if isinstance(v, dict) else f"{k}={_fmt_any(v)}" for k, v in x.items()
        )
    if isinstance(x, list):
        return "[" + ", ".join(_fmt_any(v) for v in x) + "]"
    return "—" if x is None else str(x)


def _vec(x: np.ndarray) -> str:
    return np.array2string(np.asarray(x, dtype=float), precision=6, max_line_width=100, suppress_small=False)


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows]
    return out


def _orders(rec: dict[str, Any]) -> str:
    return f"({rec['na']},{rec['nb']},{rec['nc']},{rec['nk']})"


# ----------------------------------------------------------------------------------------------- figures
def new_figure(w: float, h: float) -> Figure:
    """A matplotlib figure of w x h inches at the report's DPI, drawn without pyplot (no GUI, thread-safe)."""
    fig = Figure(figsize=(w, h), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: Path) -> None:
    """Write ``fig`` as PNG atomically, without a timestamp or software tag (the same bytes on a re-run)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None})
    atomic_write_bytes(path, buf.getvalue())


def _fig_filter(res: RunResults, path: Path) -> None:
    Ts = res.sample_time
    f = _bode_grid(Ts)
    fig = new_figure(7, 5)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    for af in FILTER_AFS:
        mag, ph = filter_response(af, f, Ts)
        ax_m.semilogx(f, 20 * np.log10(mag), label=f"af = {af:g}")
        ax_p.semilogx(f, np.degrees(ph))
    ax_m.set_ylabel("magnitude [dB]")
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_m.set_title(f"H(z) = (1-af)(z-1)/(z-af), Ts = {Ts:g} s")
    ax_m.legend()
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def _fig_bode(res: RunResults, path: Path) -> None:
    Ts = res.sample_time
    f = _bode_grid(Ts)
    fig = new_figure(7, 5.5)
    ax_m, ax_p = fig.subplots(2, 1, sharex=True)
    for name, (m, _) in res.models.items():
        if name == "selected":
            continue
        mag, ph = bode(m, res.af, f)
        ax_m.semilogx(f, mag, color="0.7", lw=0.8)
        ax_p.semilogx(f, ph, color="0.7", lw=0.8)
    m, rec = res.models["selected"]
    mag, ph = bode(m, res.af, f)
    ax_m.semilogx(f, mag, color="C0", lw=2, label=f"selected {_orders(rec)}")
    ax_p.semilogx(f, ph, color="C0", lw=2)
    ax_m.plot([], [], color="0.7", label="per-dataset models")
    meas = measured_frf(res, str(rec.get("dataset", "")))
    if meas is not None:
        fm, gm = meas
        pm = np.degrees(np.unwrap(np.angle(gm)))
        pm += 360.0 * np.round((np.interp(fm[0], f, ph) - pm[0]) / 360.0)  # the model's branch of the phase
        label = f"measured on {rec.get('dataset')} (H1, coherence >= {MIN_COHERENCE:g})"
        ax_m.semilogx(fm, 20 * np.log10(np.abs(gm)), ".", color="k", ms=3, label=label)
        ax_p.semilogx(fm, pm, ".", color="k", ms=3)
    ax_m.set_ylabel("magnitude [dB]")
    ax_p.set_ylabel("phase [deg]")
    ax_p.set_xlabel("frequency [Hz]")
    ax_m.set_title("Bode of G = B/A / H(z): command u [V] to tip angle y [deg]")
    ax_m.legend()
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


def _fig_pz(res: RunResults, path: Path) -> None:
    poles, zeros = pole_zero(res.models["selected"][0], res.af)
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
        f"{kind} at {_fmt(x.real, 2)}{x.imag:+.2f}j"
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


def _zoom(t: np.ndarray, r: np.ndarray, width: float) -> tuple[float, float]:
    """The ``width`` s window [t0, t1] where the residual ``r`` has the most energy."""
    n = max(2, min(t.size, int(round(width / (t[1] - t[0])))))
    energy = np.convolve(r**2, np.ones(n), "valid")
    k = int(np.argmax(energy))
    return float(t[k]), float(t[k + n - 1])


def _fig_time(res: RunResults, path: Path) -> None:
    """Per dataset: the whole record (measured, simulated, residual) and, under it, a ZOOM_S window where the
    residual is largest, so that measurement and simulation can be told apart."""
    names = list(res.prepared)
    ncol = 3 if len(names) > 4 else min(2, len(names))
    nrow = math.ceil(len(names) / ncol)
    fig = new_figure(4.2 * ncol, 4.2 * nrow)
    grid = fig.subplots(2 * nrow, ncol, squeeze=False)
    for i, name in enumerate(names):
        top, zoom = grid[2 * (i // ncol), i % ncol], grid[2 * (i // ncol) + 1, i % ncol]
        p = res.prepared[name]
        t = np.arange(p.y_f.size) * p.Ts
        sim = res.simulated.get(name)
        for ax in (top, zoom):
            ax.plot(t, p.y_f, color="k", lw=0.8, label="measured")
            if sim is not None:
                ax.plot(t, sim, color="C1", lw=0.8, label="simulated")
                ax.plot(t, p.y_f - sim, color="C3", lw=0.6, label="residual")
            ax.tick_params(labelsize=7)
            ax.set_ylabel("y_f [deg/sample]", fontsize=7)
        if sim is not None:
            top.set_title(f"{name}: fit {_fmt(armax.fit_percent(p.y_f, sim))} %", fontsize=9)
            t0, t1 = _zoom(t, p.y_f - sim, ZOOM_S)
        else:
            top.set_title(name, fontsize=9)
            t0, t1 = 0.0, min(ZOOM_S, float(t[-1]))
        top.axvspan(t0, t1, color="C0", alpha=0.12)
        zoom.set_xlim(t0, t1)
        zoom.set_xlabel(f"t [s] (zoom: largest residual over {ZOOM_S:g} s)", fontsize=7)
    for i in range(len(names), nrow * ncol):
        grid[2 * (i // ncol), i % ncol].set_visible(False)
        grid[2 * (i // ncol) + 1, i % ncol].set_visible(False)
    grid[0, 0].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def _fig_square(res: RunResults, path: Path) -> tuple[float, float]:
    g = lti.with_integrator(res.models["selected"][0], res.af)
    t, u, y = lti.square_response(g, SQUARE_HZ, SQUARE_V, SQUARE_PERIODS / SQUARE_HZ)
    fig = new_figure(7, 4)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t, u, color="k", lw=1)
    ax1.set_ylabel("u [V]")
    ax2.plot(t, y, color="C0", lw=1.2)
    ax2.set_ylabel("tip angle y [deg]")
    ax2.set_xlabel("t [s]")
    ax1.set_title(f"square-wave response of G = B/A / H(z) ({SQUARE_V:g} V, {SQUARE_HZ:g} Hz)")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    return float(np.min(y)), float(np.max(y))


def _fig_resid(rt: armax.ResidTest, title: str, path: Path) -> None:
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
    ax1.set_xlabel("lag k")
    ax2.set_ylabel("r_eu(k), normalised")
    ax2.set_xlabel("lag k")
    ax1.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def _fig_crossfit(cf: pd.DataFrame, path: Path) -> None:
    vals = cf.to_numpy(dtype=float)
    fig = new_figure(1.2 + 0.75 * vals.shape[1], 1.0 + 0.45 * vals.shape[0])
    ax = fig.subplots()
    im = ax.imshow(np.where(np.isfinite(vals), vals, np.nan), cmap="viridis", aspect="auto")
    ax.set_xticks(range(vals.shape[1]), [str(i + 1) for i in range(vals.shape[1])])
    ax.set_yticks(range(vals.shape[0]), list(cf.index))
    ax.set_xlabel("dataset")
    for i in range(vals.shape[0]):
        for j in range(vals.shape[1]):
            ax.text(j, i, _fmt(vals[i, j], 1), ha="center", va="center", fontsize=7, color="w")
    fig.colorbar(im, ax=ax, label="fit [%]")
    ax.set_title("cross-fit: model (row) on dataset (column)")
    fig.tight_layout()
    save_figure(fig, path)


# ----------------------------------------------------------------------------------------------- diagnosis
VERDICT_MEANING = {
    "none": "no gap beyond the measurement noise: the simulation explains the rig",
    "quantization": "no gap beyond the measurement noise, but every sample sits on an ADC lattice: the rig's "
    "converter quantises (found by this signature in the data, not by closing a gap)",
    "unexplained": "the candidate effects together do not close enough of the gap beyond noise; the gap has a "
    "cause outside the library (the partial candidates are listed with their honest shrink)",
}
STAGE_LABELS = {"before": "simulation as given", "after_recalibration": "after recalibration"}


def _exp_gap(entry: Any) -> float:
    """Gap of one experiment from its per-channel fit [%]: sqrt(mean over channels of (1 - fit/100)^2)."""
    fit = entry.get("fit_pct") if isinstance(entry, dict) else entry
    vals = [_num(v) for v in fit.values()] if isinstance(fit, dict) else [_num(fit)]
    vals = [v for v in vals if math.isfinite(v)]
    return math.sqrt(sum((1.0 - v / 100.0) ** 2 for v in vals) / len(vals)) if vals else math.nan


def _gap_experiments(diag: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    gap = diag.get("gap")
    if not isinstance(gap, dict):
        return {}, {}
    b, a = gap.get("before"), gap.get("after")
    eb = b.get("experiments") if isinstance(b, dict) else None
    ea = a.get("experiments") if isinstance(a, dict) else None
    return (eb, ea) if isinstance(eb, dict) and isinstance(ea, dict) else ({}, {})


def gap_rows(diag: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(label, gap before, gap after) from ``diagnosis.json``: per experiment when ``gap.before/after`` hold
    ``experiments`` (gap = sqrt(mean over channels of (1 - fit/100)^2), the diagnoser's definition), else
    per effect from its ``gap_before``/``gap_after``."""
    eb, ea = _gap_experiments(diag)
    if eb:
        return [(name, _exp_gap(eb[name]), _exp_gap(ea.get(name))) for name in eb]
    return [
        (str(e.get("effect", "?")), _num(e.get("gap_before")), _num(e.get("gap_after")))
        for e in diag.get("effects", []) or []
        if isinstance(e, dict) and ("gap_before" in e or "gap_after" in e)
    ]


def fold_roles(diag: dict[str, Any]) -> dict[str, str]:
    """Experiment -> its fold of the diagnoser's 2-fold cross-fit (``folds`` {"A": [...], "B": [...]}):
    "fold A" (parameters fitted on B score it), "fold B", or "A and B" for a lone experiment."""
    folds = diag.get("folds")
    roles: dict[str, str] = {}
    if isinstance(folds, dict):
        for k in ("A", "B"):
            for name in folds.get(k) or []:
                roles[str(name)] = "A and B" if name in roles else f"fold {k}"
    return roles


def waterfall(diag: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(stage, gap after it, share of the excess gap it closed [%]) from ``gap.decomposition``, starting with
    ("simulation as given", gap before, nan); empty when the diagnosis has no decomposition."""
    dec = (diag.get("gap") or {}).get("decomposition")
    if not isinstance(dec, dict) or not math.isfinite(_num(dec.get("before"))):
        return []
    rows = [("simulation as given", _num(dec["before"]), math.nan)]
    for s in dec.get("steps") or []:
        if isinstance(s, dict):
            rows.append((str(s.get("stage", "?")), _num(s.get("gap_after")), _num(s.get("closed_pct"))))
    return rows


def _channels(entry: Any) -> str:
    fit = entry.get("fit_pct") if isinstance(entry, dict) else entry
    if isinstance(fit, dict):
        return ", ".join(f"{k} {_fmt(v)}" for k, v in fit.items())
    return _fmt(fit)


def _params_text(params: Any) -> str:
    if not isinstance(params, dict) or not params:
        return "—"
    return ", ".join(f"{k} = {_fmt_any(v)}" for k, v in params.items())


def _verdict_lines(diag: dict[str, Any]) -> list[str]:
    verdict = str(diag.get("verdict", "—"))
    lines = [f"Verdict: **{verdict}**", ""]
    effects = [e for e in diag.get("effects", []) or [] if isinstance(e, dict)]
    if verdict in VERDICT_MEANING:
        lines += [f"`{verdict}`: {VERDICT_MEANING[verdict]}.", ""]
    elif len(effects) == 1:
        share = _fmt((diag.get("gap") or {}).get("explained_pct"), 1)
        lines += [f"The only effect found; modelled, it closes {share} % of the gap beyond noise on held-out data.", ""]
    elif effects:
        first = str(effects[0].get("effect"))
        why = "" if first == verdict else f" (`{first}` was added first, because it closed most of the gap alone)"
        lines += [
            f"{len(effects)} effects found. The verdict is the one whose removal from the final model reopens most of "
            f"the gap (drop-one importance below){why}.",
            "",
        ]
    params = diag.get("parameters")
    findings = [
        str(p["finding"])
        for p in (params.values() if isinstance(params, dict) else [])
        if isinstance(p, dict) and p.get("finding") and "matches" not in str(p["finding"])
    ]
    if findings:
        lines += ["Linear findings: " + "; ".join(findings) + ".", ""]
    return lines


def _effects_lines(diag: dict[str, Any]) -> list[str]:
    effects = [e for e in diag.get("effects", []) or [] if isinstance(e, dict)]
    if not effects:
        return []
    rows = [
        [
            str(e.get("effect", "?")),
            _params_text(e.get("params")),
            _fmt(e.get("importance_pct"), 1),
            _fmt(e.get("gap_before"), 4),
            _fmt(e.get("gap_after"), 4),
            _fmt(e.get("shrink_pct"), 1),
            str(e.get("selected_by", "—")),
        ]
        for e in effects
    ]
    header = ["effect", "fitted parameters", "importance [%]", "gap before", "gap after", "shrink [%]", "found by"]
    lines = ["Effects, in the order they were added (gaps on held-out experiments):", "", *_table(header, rows), ""]
    lines += [
        "Importance: remove each effect alone from the final model and part of the gap reopens; an effect's "
        "importance is its share of what the removals reopen (the verdict is the effect whose removal reopens "
        "most); shrink: how much the gap fell when the effect was added.",
        "",
    ]
    if any("lattice" in str(e.get("selected_by", "")) for e in effects):
        lines += [
            "An effect found by its signature in the data (every sample on the ADC lattice) is added for the record, "
            "not because it closes the gap: quantisation error looks like noise, so its shrink can be negative.",
            "",
        ]
    return lines


def _parameters_lines(diag: dict[str, Any]) -> list[str]:
    params = diag.get("parameters")
    if not isinstance(params, dict) or not params:
        return []
    rows = []
    for name, p in params.items():
        if not isinstance(p, dict):
            continue
        ci = p.get("ci95")
        ci_text = f"{_fmt_any(ci[0])} .. {_fmt_any(ci[1])}" if isinstance(ci, list) and len(ci) == 2 else "—"
        rows.append(
            [
                str(name),
                str(p.get("unit", "—")),
                _fmt_any(p.get("nominal")),
                _fmt_any(p.get("fitted")),
                ci_text,
                _fmt(p.get("change_pct"), 1),
                str(p.get("finding", "—")),
            ]
        )
    applied = diag.get("recalibration_applied")
    note = "" if applied is None else (" It was applied." if applied else " It closed too little to be kept.")
    header = ["parameter", "unit", "nominal", "fitted", "95 % CI", "change [%]", "finding"]
    return [
        "Linear parameters of the simulation recalibrated against the data (within physical bounds): a linear "
        f"mismatch is a finding about the rig, not an unmodelled effect.{note}",
        "",
        *_table(header, rows),
        "",
    ]


def _decomposition_lines(diag: dict[str, Any], figure: str | None) -> list[str]:
    rows = waterfall(diag)
    if not rows:
        return []
    dec = diag["gap"]["decomposition"]
    body = [[stage, _fmt(g, 4), _fmt(100.0 * (1.0 - g), 2), _fmt(c, 1)] for stage, g, c in rows]
    noise = _num(dec.get("noise_floor"))
    body.append(["noise floor", _fmt(noise, 4), _fmt(100.0 * (1.0 - noise), 2), "—"])
    lines = [
        "How far the gap shrinks, stage by stage (held-out experiments; fit % = 100 (1 - gap); closed: share of the "
        "excess squared gap above the noise floor that the stage closes):",
        "",
        *_table(["stage", "gap", "fit [%]", "closed [%]"], body),
        "",
    ]
    return [*lines, f"![gap waterfall]({figure})", ""] if figure else lines


def _overall_lines(diag: dict[str, Any]) -> list[str]:
    gap = diag.get("gap")
    if not isinstance(gap, dict):
        return []
    rows = []
    held = gap.get("held_out")
    if isinstance(held, dict):
        gaps = [_fmt(held.get("gap_before"), 4), _fmt(held.get("gap_after"), 4)]
        rows.append(
            [
                "held out (fitted on the other fold)",
                *gaps,
                _fmt(held.get("fit_pct_before")),
                _fmt(held.get("fit_pct_after")),
            ]
        )
    b, a = gap.get("before"), gap.get("after")
    if isinstance(b, dict) and isinstance(a, dict) and "gap" in b:
        rows.append(
            [
                "all experiments, final parameters",
                _fmt(b.get("gap"), 4),
                _fmt(a.get("gap"), 4),
                _fmt(b.get("fit_pct")),
                _fmt(a.get("fit_pct")),
            ]
        )
    if not rows:
        return []
    lines = [*_table(["gap", "before", "after", "fit before [%]", "fit after [%]"], rows), ""]
    if "shrink_pct" in gap:
        shrink = _fmt(gap.get("shrink_pct"), 1)
        lines += [f"Held-out shrink {shrink} % (in sample {_fmt(gap.get('shrink_pct_in_sample'), 1)} %).", ""]
    return lines


def _experiments_lines(diag: dict[str, Any]) -> list[str]:
    eb, ea = _gap_experiments(diag)
    if not eb:
        return []
    roles = fold_roles(diag)
    rows = [
        [
            name,
            roles.get(name, "—"),
            _channels(eb[name]),
            _channels(ea.get(name)),
            _fmt(_exp_gap(eb[name]), 4),
            _fmt(_exp_gap(ea.get(name)), 4),
        ]
        for name in eb
    ]
    header = ["experiment", "fold", "fit before [%]", "fit after [%]", "gap before", "gap after"]
    return [
        "Per experiment (2-fold cross-fit: what is fitted on one fold is scored on the other, so every experiment "
        "is held out once; 'after' here uses the final parameters):",
        "",
        *_table(header, rows),
        "",
    ]


def _candidates_lines(diag: dict[str, Any]) -> list[str]:
    cands = [c for c in diag.get("candidates", []) or [] if isinstance(c, dict)]
    if not cands:
        return []
    rows = [
        [
            str(c.get("effect", "?")),
            _params_text(c.get("params")),
            _fmt(c.get("held_out_share_pct"), 1),
            _fmt(c.get("shrink_pct"), 1),
            str(c.get("note", "")) or "—",
        ]
        for c in cands
    ]
    header = ["candidate", "fitted parameters", "closes [%] of the excess", "shrink [%]", "note"]
    return ["Candidates, each alone on the first round (held out):", "", *_table(header, rows), ""]


def _where_stages(where: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(label, where-dict) per stage: {"before": ..., "after_recalibration": ...}, or today's flat structure."""
    staged = [(STAGE_LABELS[k], where[k]) for k in STAGE_LABELS if isinstance(where.get(k), dict)]
    return staged or [("simulation as given", where)]


def _where_cells(s: dict[str, Any]) -> list[str]:
    """Dominant band, amplitude regime, events and headline of one channel's pooled where-summary."""
    fr = s.get("frequency") or {}
    band = fr.get("dominant_band")
    band_text = f"{band} ({_fmt(100.0 * _num(fr.get('dominant_share')), 0)} %)" if band else "—"
    regime = str((s.get("amplitude") or {}).get("regime", "—"))
    ev = s.get("events") or {}
    conc = [k for k in ("reversals", "wraps") if isinstance(ev.get(k), dict) and ev[k].get("concentrates")]
    return [band_text, regime, ", ".join(conc) or "none", str(s.get("headline", "—"))]


def _where_lines(diag: dict[str, Any]) -> list[str]:
    where = diag.get("where")
    if not isinstance(where, dict) or not where:
        return []
    if "skipped" in where:
        return [f"Where the gap is: not analysed ({where['skipped']}).", ""]
    rows = []
    for label, w in _where_stages(where):
        for ch in ("theta", "alpha"):
            s = w.get(ch)
            if isinstance(s, dict) and s:
                rows.append([label, ch, *_where_cells(s)])
    lines = []
    if rows:
        header = ["residual of", "channel", "dominant band", "amplitude", "concentrates at", "finding"]
        lines += ["Where the gap is (pooled over experiments; per experiment in `diagnosis.json`):", ""]
        lines += [*_table(header, rows), ""]
    masked = where.get("masked")
    if isinstance(masked, dict) and masked:
        share = ", ".join(f"{k} {_fmt(100.0 * _num(v), 1)} %" for k, v in masked.items())
        lines += [f"Samples masked as invalid (pot dead band, ADC clipping) and left out of every gap: {share}.", ""]
    return lines


def diagnosis_markdown(diag: dict[str, Any], waterfall_figure: str | None = None) -> list[str]:
    """Markdown lines summarising ``diagnosis.json`` for a person: verdict and what it means, recalibrated
    parameters, effects with their importance, the gap stage by stage (with ``waterfall_figure`` when given),
    overall and per-experiment gaps with the folds, first-round candidates, noise floor and where the gap is.
    Absent parts are skipped; nothing is printed as a raw dictionary."""
    lines = _verdict_lines(diag)
    lines += _parameters_lines(diag)
    lines += _effects_lines(diag)
    lines += _decomposition_lines(diag, waterfall_figure)
    lines += _overall_lines(diag)
    lines += _experiments_lines(diag)
    lines += _candidates_lines(diag)
    noise = diag.get("noise_floor")
    if isinstance(noise, dict) and "gap" in noise:
        parts = [f"gap {_fmt(noise.get('gap'), 4)} (fit {_fmt(noise.get('fit_pct'))} %)"]
        for ch in ("theta", "alpha"):
            if f"{ch}_deg" in noise:
                parts.append(f"{ch} {_fmt_any(noise[f'{ch}_deg'])} deg rms")
        how = f", {noise['method']}" if isinstance(noise.get("method"), str) else ""
        lines += [f"Noise floor (from the data{how}): " + ", ".join(parts) + ".", ""]
    lines += _where_lines(diag)
    return lines


def _same(a: float, b: float, tol: float = 0.005) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _fig_diagnosis(rows: list[tuple[str, float, float]], path: Path) -> None:
    fig = new_figure(max(5.0, 0.9 * len(rows) + 2), 4)
    ax = fig.subplots()
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r[1] for r in rows], 0.4, label="gap before")
    ax.bar(x + 0.2, [r[2] for r in rows], 0.4, label="gap after")
    ax.set_xticks(x, [r[0] for r in rows], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("gap")
    ax.set_title("sim-to-real gap per experiment before / after modelling the effects")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def _fig_waterfall(rows: list[tuple[str, float, float]], noise: float, path: Path) -> None:
    """The held-out gap stage by stage: the first bar is the gap before, each next one floats from the previous
    gap to the gap after its stage (green when it closes, red when it reopens), the noise floor dashed."""
    fig = new_figure(max(5.0, 1.1 * len(rows) + 2), 4)
    ax = fig.subplots()
    prev = rows[0][1]
    ax.bar(0, prev, 0.6, color="C0")
    for i, (_, g, _) in enumerate(rows[1:], 1):
        lo, hi = min(prev, g), max(prev, g)
        ax.bar(i, hi - lo, 0.6, bottom=lo, color="C2" if g <= prev else "C3")
        ax.plot([i - 1.3, i + 0.3], [prev, prev], color="0.5", lw=0.6)
        prev = g
    ax.bar(len(rows), prev, 0.6, color="C0")
    if math.isfinite(noise):
        ax.axhline(noise, color="k", ls="--", lw=0.8, label=f"noise floor {noise:.4f}")
        ax.legend(fontsize=8)
    labels = [r[0] for r in rows] + ["final"]
    ax.set_xticks(np.arange(len(labels)), labels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("held-out gap (fit % = 100 (1 - gap))")
    ax.set_title("gap waterfall: recalibration, then each effect")
    fig.tight_layout()
    save_figure(fig, path)


# ----------------------------------------------------------------------------------------------- sections
def _section_header(res: RunResults) -> list[str]:
    m = res.manifest
    spec = m.get("spec", {}) or {}
    camp = (spec.get("campaign", {}) or {}) if isinstance(spec, dict) else {}
    name = camp.get("name", m.get("spec_file", ""))
    lines = [f"# flexjoint run report: {name or res.run.name}", ""]
    rows = [
        ["kind", str(m.get("kind", "—"))],
        ["spec sha256", f"`{m['spec_sha256']}`" if m.get("spec_sha256") else ""],
        ["random seed", _fmt_any(m.get("seed")) if m.get("seed") is not None else ""],
        ["sample rate [Hz]", _fmt_any(m.get("sample_rate"))],
        ["experiments", str(len(m.get("experiments", [])))],
        ["identification datasets", ", ".join(res.prepared) or "—"],
    ]
    rows = [r for r in rows if r[1]]
    for k, v in sorted((m.get("versions") or {}).items()):
        rows.append([f"version {k}", str(v)])
    lines += [*_table(["item", "value"], rows), ""]
    sources = m.get("sources")
    if m.get("kind") == "import" and isinstance(sources, dict) and sources:
        units = {e.get("name"): e.get("units", {}) for e in m.get("experiments", []) if isinstance(e, dict)}
        body = [
            [
                name,
                f"`{src.get('file', '?')}`",
                str(src.get("format", "—")),
                ", ".join(f"{k} {units[name][k]}" for k in ("t", "u", "theta", "alpha") if k in units.get(name, {}))
                or "—",
                "; ".join(src.get("notes") or []) or "—",
            ]
            for name, src in sources.items()
            if isinstance(src, dict)
        ]
        lines += ["Imported records:", "", *_table(["dataset", "file", "format", "units", "notes"], body), ""]
    return lines


def _section_calibration(res: RunResults) -> list[str]:
    lines = ["## Calibration", ""]
    cal = res.calibration
    if cal is None:
        return [*lines, "No `calibration.json` in this run.", ""]
    rows = []
    for key, label, unit in (("Kp", "Kp", "deg/V"), ("Ke", "Ke", "deg/V"), ("dead_zone_v", "dead zone", "V")):
        v = float(getattr(cal, key))
        s = SEED_CALIBRATION[key]
        diff = 100.0 * (v - s) / abs(s) if math.isfinite(v) else math.nan
        rows.append([label, unit, _fmt(v, 4), _fmt(s, 4), _fmt(diff, 2)])
    rows.append(["gauge offset", "V", _fmt(cal.gauge_offset_v, 4), "—", "—"])
    rows.append(["pot offset", "V", _fmt(cal.pot_offset_v, 4), "—", "—"])
    lines += _table(["quantity", "unit", "this run", "lab 1", "difference [%]"], rows)
    src = (res.calibration_file or {}).get("source") or {}
    methods = [f"- {k}: {v['method']}" for k, v in src.items() if isinstance(v, dict) and "method" in v]
    if methods:
        lines += ["", "Methods:", "", *methods]
    return [*lines, ""]


def _section_filter(res: RunResults, figdir: Path) -> list[str]:
    _fig_filter(res, figdir / "filter_response.png")
    Ts = res.sample_time
    rows = []
    for af in FILTER_AFS:
        fc = -math.log(af) / (2 * math.pi * Ts)
        rows.append([f"{af:g}", _fmt(fc, 3), _fmt(2 * (1 - af) / (1 + af), 4)])
    return [
        "## Preprocessing filter",
        "",
        f"H(z) = (1 - af)(z - 1)/(z - af): differentiation and low-pass in one; af = {res.af:g} used here.",
        "",
        *_table(["af", "pole frequency -ln(af)/(2 pi Ts) [Hz]", "gain at Nyquist"], rows),
        "",
        "![filter responses](figures/filter_response.png)",
        "",
    ]


def _threshold(res: RunResults) -> float:
    spec = res.manifest.get("spec") or {}
    ident = spec.get("identify", {}) if isinstance(spec, dict) else {}
    return float(ident.get("fit_threshold", IDENTIFY_DEFAULTS["fit_threshold"]))


def _section_grid(res: RunResults) -> list[str]:
    lines = ["## ARMAX grid and selection", ""]
    g = res.grid
    if g is not None and len(g):
        thr = _threshold(res)
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
        lines += _table(["grid", "count"], rows) + [""]
    else:
        lines += ["No `grid.csv` in this run.", ""]
    sel = res.selected
    if sel is None:
        return [*lines, "No selected model (`models/selected.json`) yet.", ""]
    m, rec = sel
    lines += [
        f"Selected model: ARMAX (na, nb, nc, nk) = {_orders(rec)}, trained on `{rec.get('dataset', '?')}`, "
        f"fit on own dataset {_fmt(rec.get('fit_own'))} %, "
        f"mean cross-validation fit {_fmt(rec.get('cv_mean'))} %.",
        "",
        f"Selection rule: {rec.get('selection_rule', '—')}",
        "",
    ]
    per = [(n, r) for n, (_, r) in res.models.items() if n != "selected"]
    if per:
        rows = [[n, _orders(r), _fmt(r.get("fit_own")), _fmt(r.get("cv_mean"))] for n, r in per]
        lines += ["Model chosen per dataset (by the selection rule; the highest fit of each is in `grid.csv`):", ""]
        lines += _table(["dataset", "(na,nb,nc,nk)", "fit own [%]", "mean CV fit [%]"], rows) + [""]
    lines += [
        "Coefficients (full precision in `models/selected.json`):",
        "",
        "```",
        f"A = {_vec(m.A)}",
        f"B = {_vec(m.B)}",
        f"C = {_vec(m.C)}",
        "```",
        "",
    ]
    return lines + _estimates_lines(res, m, rec)


def _estimates_lines(res: RunResults, m: armax.ArmaxModel, rec: dict[str, Any]) -> list[str]:
    """Free parameters with their standard deviations (from ``cov``) and the information criteria of the selected
    model on its training dataset, as MATLAB's ``present``/``fpe``/``aic`` give them."""
    names = [f"a{i}" for i in range(1, m.na + 1)]
    names += [f"b{i}" for i in range(m.nk, m.nk + m.nb)] + [f"c{i}" for i in range(1, m.nc + 1)]
    values = np.concatenate([m.A[1:], m.B[m.nk :], m.C[1:]])
    std = m.std
    if std.size != len(names) or values.size != len(names) or not np.isfinite(std).any():
        return []  # no covariance recorded
    rows = [[n, f"{v:.6g}", f"{sd:.3g}", _fmt(100.0 * sd / abs(v), 1) if v else "—"] for n, v, sd in
            zip(names, values, std, strict=True)]  # fmt: skip
    lines = [
        "Free parameters of the selected model with one standard deviation (square root of the covariance "
        "diagonal in the model JSON):",
        "",
        *_table(["parameter", "estimate", "std", "std [% of estimate]"], rows),
        "",
    ]
    p = res.prepared.get(str(rec.get("dataset")))
    V = _num(m.loss)
    if p is not None and math.isfinite(V) and V > 0:
        N, d = p.y_f.size, m.n_params
        fpe = V * (1 + d / N) / (1 - d / N) if N > d else math.nan
        aic = N * math.log(V) + 2 * d
        lines += [
            f"On `{rec.get('dataset')}` (N = {N}, d = {d} parameters): loss V = {V:.6g}, FPE = V (1 + d/N)/(1 - d/N) = "
            f"{fpe:.6g}, AIC = N ln V + 2 d = {aic:.2f}.",
            "",
        ]
    return lines


def crossfit_table(res: RunResults) -> list[str]:
    """Markdown lines of the cross-fit table shaped like seed 000's table 2: models (rows) x datasets
    (numbered columns) + ``Average``, computed as the row mean (never copied), then a dataset legend."""
    cf = res.crossfit
    if cf is None or cf.empty:
        return ["No cross-fit results yet."]
    cols = list(cf.columns)
    avg = cf.to_numpy(dtype=float).mean(axis=1)
    header = ["Models/Data Sets", *[str(j + 1) for j in range(len(cols))], "Average"]
    rows = []
    for i, name in enumerate(cf.index):
        rec = res.models.get(name, (None, None))[1]
        label = f"{name} {_orders(rec)}" if rec else name
        rows.append([label, *[_fmt(v) for v in cf.iloc[i].to_numpy(dtype=float)], _fmt(avg[i])])
    return [
        *_table(header, rows),
        "",
        "Datasets: " + ", ".join(f"{j + 1} = `{c}`" for j, c in enumerate(cols)) + ".",
    ]


def _section_crossfit(res: RunResults, figdir: Path) -> list[str]:
    lines = ["## Cross-fit matrix", ""]
    cf = res.crossfit
    if cf is None or cf.empty:
        return [*lines, "No cross-fit results yet.", ""]
    lines += [
        f"Fit [%] of each model (row) simulated on each dataset (column); source: {res.crossfit_source}.",
        "",
    ]
    lines += [*crossfit_table(res), ""]
    if res.crossfit_csv_average is not None:
        avg = cf.to_numpy(dtype=float).mean(axis=1)
        bad = [
            f"`{n}` ({_fmt(res.crossfit_csv_average.get(n))} in the file, {_fmt(a)} computed)"
            for n, a in zip(cf.index, avg, strict=True)
            if not _same(float(res.crossfit_csv_average.get(n, math.nan)), float(a))
        ]
        if bad:
            lines += [
                "Averages in `crossfit.csv` that are not the mean of their row: " + "; ".join(bad) + ".",
                "",
            ]
    _fig_crossfit(cf, figdir / "crossfit.png")
    return [*lines, "![cross-fit matrix](figures/crossfit.png)", ""]


def _section_model(res: RunResults, figdir: Path) -> list[str]:
    if res.selected is None:
        return []
    m, _ = res.selected
    _fig_bode(res, figdir / "bode_selected.png")
    _fig_pz(res, figdir / "pz_selected.png")
    lo, hi = _fig_square(res, figdir / "square_response.png")
    g = lti.with_integrator(m, res.af)
    poles, zeros = pole_zero(m, res.af)
    num = np.asarray(g.num[0][0], dtype=float)
    den = np.asarray(g.den[0][0], dtype=float)
    ss = lti.companion_ss(g)
    rows = [[_fmt(p.real, 4), _fmt(p.imag, 4), _fmt(abs(p), 4)] for p in poles]
    zrows = [[_fmt(z.real, 4), _fmt(z.imag, 4), _fmt(abs(z), 4)] for z in zeros]
    nmp = int(np.sum(np.abs(zeros) > 1.0))
    return [
        "## Selected model with the integrator",
        "",
        f"G(z) = B/A / H(z) with H(z) = (1 - af)(z - 1)/(z - af), af = {res.af:g}: the command u [V] to the",
        "tip angle y [deg] (`harness.ident.lti.with_integrator`). Coefficients in descending powers of z:",
        "",
        "```",
        f"num = {_vec(num)}",
        f"den = {_vec(den)}",
        "```",
        "",
        "Companion-form state space x(k+1) = A x(k) + B u(k), y(k) = C x(k) + D u(k) (seed eq. 10),",
        "B = e1, A with ones on the subdiagonal and first row:",
        "",
        "```",
        f"A[0, :] = {_vec(np.asarray(ss.A)[0])}",
        f"C       = {_vec(np.asarray(ss.C)[0])}",
        f"D       = {_vec(np.asarray(ss.D)[0])}",
        "```",
        "",
        f"{poles.size} poles, {zeros.size} zeros ({nmp} outside the unit circle: non-minimum phase).",
        "",
        "Poles:",
        "",
        *_table(["Re", "Im", "modulus"], rows),
        "",
        "Zeros:",
        "",
        *_table(["Re", "Im", "modulus"], zrows),
        "",
        "Bode plot with the measured (nonparametric, H1) response of the selected model's dataset where its "
        f"coherence reaches {MIN_COHERENCE:g}:",
        "",
        "![Bode](figures/bode_selected.png)",
        "",
        "![pole-zero map](figures/pz_selected.png)",
        "",
        f"Square-wave response ({SQUARE_V:g} V, {SQUARE_HZ:g} Hz, {SQUARE_PERIODS} periods, from rest): "
        f"tip angle from {_fmt(lo, 3)} to {_fmt(hi, 3)} deg.",
        "",
        "![square-wave response](figures/square_response.png)",
        "",
    ]


def _section_time(res: RunResults, figdir: Path) -> list[str]:
    if not res.prepared:
        return []
    _fig_time(res, figdir / "time_responses.png")
    lines = ["## Time responses per dataset", ""]
    if res.simulated:
        rows = []
        for name, p in res.prepared.items():
            y = res.simulated.get(name)
            rows.append([name, _fmt(armax.fit_percent(p.y_f, y)) if y is not None else "—"])
        lines += [
            f"Selected model simulated (ic = '{res.ic}') on every dataset, identification domain y_f:",
            "",
        ]
        lines += _table(["dataset", "fit [%]"], rows) + [""]
    lines += [
        f"Each panel: the whole record with the residual (red), and under it the {ZOOM_S:g} s where the residual is "
        "largest (shaded above).",
        "",
    ]
    return [*lines, "![time responses](figures/time_responses.png)", ""]


def _section_resid(res: RunResults, figdir: Path) -> list[str]:
    if res.selected is None or not res.prepared:
        return []
    m, rec = res.selected
    rows = []
    own = rec.get("dataset") if rec.get("dataset") in res.prepared else next(iter(res.prepared))
    own_test = None
    for name, p in res.prepared.items():
        rt = armax.resid(m, p.u_d, p.y_f, lags=min(RESID_LAGS, p.y_f.size // 2 - 1))
        if name == own:
            own_test = rt
        rows.append(
            [
                name,
                f"{rt.n_out_acf}/{rt.lags} (allowed {rt.allowed_acf})",
                _fmt(rt.white),
                f"{rt.n_out_ccf}/{rt.lags_ccf.size} (allowed {rt.allowed_ccf})",
                _fmt(rt.independent),
            ]
        )
    assert own_test is not None
    _fig_resid(own_test, f"residuals of the selected model on {own}", figdir / "residuals.png")
    coloured = [r[0] for r in rows if r[2] == "no"]
    verdict = (
        f"The residuals are not white on {len(coloured)} of {len(rows)} datasets: the noise model C misses part of "
        "the disturbance (or the dynamics are undermodelled); the fit thresholds of `flexjoint accept` do not test "
        "this."
        if coloured
        else "The residuals are white on every dataset."
    )
    return [
        "## Residual tests",
        "",
        f"One-step prediction errors of the selected model; 99 % bound 2.58/sqrt(N) = "
        f"{_fmt(own_test.bound, 4)} on `{own}`.",
        "",
        *_table(["dataset", "acf lags outside", "white", "ccf lags outside", "independent"], rows),
        "",
        verdict,
        "",
        "![residual correlations](figures/residuals.png)",
        "",
    ]


def _section_doubled(res: RunResults) -> list[str]:
    d = res.doubled_rate
    if d is None:
        return []
    rows = [[str(k), _fmt_any(v)] for k, v in d.items()]
    return ["## Doubled sampling rate check", "", *_table(["item", "value"], rows), ""]


def _section_diagnosis(res: RunResults, figdir: Path) -> list[str]:
    d = res.diagnosis
    if d is None:
        return []
    steps = waterfall(d)
    fig = None
    if len(steps) > 1:
        noise = _num(d["gap"]["decomposition"].get("noise_floor"))
        _fig_waterfall(steps, noise, figdir / "gap_waterfall.png")
        fig = "figures/gap_waterfall.png"
    sim = d.get("sim_spec")
    lines = ["## Sim-to-real gap diagnosis", ""]
    if sim:
        lines += [f"The data of this run against the simulation `{sim}`; every number is in `diagnosis.json`.", ""]
    lines += diagnosis_markdown(d, fig)
    rows = [r for r in gap_rows(d) if math.isfinite(r[1]) or math.isfinite(r[2])]
    if rows:
        roles = fold_roles(d)
        rows = [(f"{r[0]} ({roles[r[0]]})" if r[0] in roles else r[0], r[1], r[2]) for r in rows]
        _fig_diagnosis(rows, figdir / "diagnosis.png")
        lines += ["![gap per experiment](figures/diagnosis.png)", ""]
    return lines


# ----------------------------------------------------------------------------------------------- entry point
def write_report(run: Path) -> Path:
    """Write ``<run>/report.md`` and ``<run>/figures/*.png`` from the run directory alone; returns report.md.

    Any run directory (a campaign, an import, identified or not, diagnosed or not): each section is written from
    what the directory holds and skipped (or one line) when it has nothing for it. Sections: run header (with the
    imported records' formats and units), calibration vs lab 1, preprocessing filter (af = 0.6, 0.8, 0.9), grid
    summary and selection, cross-fit table (averages computed), selected model with integrator (Bode, pole-zero,
    square wave), time responses, residual tests, doubled-rate check and the diagnosis (verdict and what it
    means, recalibrated parameters, effects with their drop-one importance, gap waterfall, folds, where).
    Every file is written atomically (temp file + rename).
    """
    res = load_results(run)
    figdir = res.run / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    lines = _section_header(res)
    lines += _section_calibration(res)
    lines += _section_filter(res, figdir)
    lines += _section_grid(res)
    lines += _section_crossfit(res, figdir)
    lines += _section_model(res, figdir)
    lines += _section_time(res, figdir)
    lines += _section_resid(res, figdir)
    lines += _section_doubled(res)
    lines += _section_diagnosis(res, figdir)
    out = res.run / "report.md"
    atomic_write_bytes(out, ("\n".join(lines).rstrip() + "\n").encode())
    return out
