"""A prediction's (and a design's) files, report.md, figures and recording, each from what its directory holds.

``write_prediction(pred, out)`` writes ``prediction.json`` (:meth:`harness.prediction.Prediction.to_json`),
``prediction.parquet`` (t, ref and the median and 95 % band of theta, alpha [deg] and u [V] per sample, and the
record's where there is one) and ``prediction.members.parquet`` (per member its parameter draw and pooled metrics),
then :func:`report_prediction`: ``report.md``, ``figures/prediction_traces.png`` (the bands over the record),
``figures/prediction_metrics.png`` (each metric's members, band, the record's value and the spec's limit) and
``prediction.rrd``. A design directory also holds ``design.json``, whose gains, margins and search the report adds.
"""

from __future__ import annotations

import hashlib
import json
import math
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import rerun as rr
import rerun.blueprint as rrb

from ..design import Design, controller_toml, twin_spec
from ..rundir import DataError, atomic_write_bytes, atomic_write_text, write_dataset, write_json
from ..ssp import ssp_bytes
from ..twin import Twin
from .figures import new_figure, save_figure
from .tables import fmt_any
from .viewer import write_recording

__all__ = ["FILES", "report_prediction", "write_design", "write_prediction"]

FILES = {"json": "prediction.json", "traces": "prediction.parquet", "members": "prediction.members.parquet"}
FIGURES = ("prediction_traces.png", "prediction_metrics.png")
CHANNELS = {"theta": "theta [deg]", "alpha": "alpha [deg]", "u": "u [V]"}
LABELS = {
    "overshoot_pct": "overshoot [%]",
    "settling_s": "settling [s]",
    "stop_error_deg": "stopping error [deg]",
    "peak_alpha_deg": "peak deflection [deg]",
    "peak_u_v": "peak command [V]",
    "ring_alpha_deg": "alpha ringing, RMS [deg]",
    "ring_hz": "ringing frequency [Hz]",
    "stop_error_up_deg": "stopping error, steps up [deg]",
    "stop_error_down_deg": "stopping error, steps down [deg]",
}
SHOWN = ("overshoot_pct", "settling_s", "stop_error_deg", "peak_alpha_deg", "peak_u_v", "ring_alpha_deg")


def write_prediction(pred: Any, out: Path, rrd: bool = True) -> Path:
    """A prediction's files into a directory, each written atomically, then its report.

    Parameters
    ----------
    pred : Prediction
        What :func:`harness.predict_loop` returned.
    out : Path
        The directory: prediction.json, prediction.parquet, prediction.members.parquet, then
        (:func:`report_prediction`) report.md, figures/ and prediction.rrd.
    rrd : bool
        Write the Rerun recording too.

    Returns
    -------
    Path
        The report (``out/report.md``).
    """
    out = Path(out)
    write_json(out / FILES["json"], pred.to_json())
    cols: dict[str, np.ndarray] = {"t": pred.reference.t, "ref": pred.reference.ref_deg}
    for c, (lo, med, hi) in pred.bands.items():
        cols |= {f"{c}_lo": lo, f"{c}_median": med, f"{c}_hi": hi}
    if pred.record is not None:
        m = pred.reference.ref_deg.size
        for c in CHANNELS:
            v = np.full(m, np.nan)
            rec = getattr(pred.record, c)[:m]
            v[: rec.size] = rec
            cols[f"{c}_record"] = v
    write_dataset(out / FILES["traces"], cols)
    members: dict[str, np.ndarray] = {"member": np.arange(pred.n, dtype=float)}
    names = sorted({k for d in pred.draws for k in d})
    members |= {k: np.array([d.get(k, math.nan) for d in pred.draws], dtype=float) for k in names}
    members |= {k: np.asarray(v, dtype=float) for k, v in pred.values.items()}
    write_dataset(out / FILES["members"], members)
    return report_prediction(out, rrd=rrd)


def write_design(d: Design, twin: Twin, out: Path, rrd: bool = True) -> Path:
    """A design's files into a directory, each written atomically, then its prediction's.

    Parameters
    ----------
    d : Design
        What :func:`harness.design_controller` returned.
    twin : Twin
        The rig it was designed on (the loop's SSP runs it).
    out : Path
        The directory: design.json, controller.toml (a ``[controller]`` table for a spec), loop.ssp (the twin under
        the controller tracking the reference, as SSP 1.0: ``flexjoint ssp``'s archive), then the prediction's
        (:func:`write_prediction`; its report.md shows the design).
    rrd : bool
        Write the Rerun recording too.

    Returns
    -------
    Path
        The report (``out/report.md``).
    """
    ref = d.prediction.reference
    spec = twin_spec(twin, d.controller, ref, d.prediction.seed)
    ssp = ssp_bytes(spec, "loop", "closed", None if ref.signal else ref.ref_deg)
    out = Path(out)
    write_json(out / "design.json", d.to_json())
    note = (
        f"{d.method} designed by flexjoint design on {twin.name} for {ref.label}\n(design.json: its specs and margins)"
    )
    atomic_write_text(out / "controller.toml", controller_toml(d.controller, note))
    atomic_write_bytes(out / "loop.ssp", ssp)
    return write_prediction(d.prediction, out, rrd=rrd)


def _load(out: Path) -> tuple[dict[str, Any], pd.DataFrame, pd.DataFrame, dict[str, Any] | None]:
    paths = {k: Path(out) / v for k, v in FILES.items()}
    missing = [p.name for p in paths.values() if not p.is_file()]
    if missing:
        raise DataError(f"{out}: {', '.join(missing)} missing (run `flexjoint predict` or `flexjoint design` again)")
    doc = json.loads(paths["json"].read_text(encoding="utf-8"))
    design = Path(out) / "design.json"
    return (doc, pd.read_parquet(paths["traces"]), pd.read_parquet(paths["members"]),
            json.loads(design.read_text(encoding="utf-8")) if design.is_file() else None)  # fmt: skip


def _traces_figure(traces: pd.DataFrame, path: Path, title: str) -> None:
    fig = new_figure(9.0, 7.5)
    axes = fig.subplots(3, 1, sharex=True)
    t = traces["t"].to_numpy()
    for ax, (c, label) in zip(axes, CHANNELS.items(), strict=True):
        ax.fill_between(t, traces[f"{c}_lo"], traces[f"{c}_hi"], color="tab:blue", alpha=0.25, lw=0, label="95 % band")
        ax.plot(t, traces[f"{c}_median"], color="tab:blue", lw=1.0, label="median")
        if f"{c}_record" in traces:
            ax.plot(t, traces[f"{c}_record"], color="k", lw=0.8, label="record")
        if c == "theta":
            ax.plot(t, traces["ref"], color="tab:gray", lw=0.8, ls="--", label="reference")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=4)
    axes[0].set_title(title, fontsize=10)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    save_figure(fig, path)


def _metrics_figure(doc: dict[str, Any], members: pd.DataFrame, path: Path) -> None:
    fig = new_figure(9.0, 5.5)
    axes = fig.subplots(2, 3).ravel()
    specs = doc.get("specs") or {}
    for ax, m in zip(axes, SHOWN, strict=True):
        v = members[m].to_numpy(float) if m in members else np.array([])
        v = v[np.isfinite(v)]
        b = doc["metrics"][m]
        if v.size:
            ax.hist(v, bins=min(30, max(5, v.size // 5)), color="tab:blue", alpha=0.5)
        for key, style in (("lo", ":"), ("median", "-"), ("hi", ":")):
            if b.get(key) is not None and math.isfinite(b[key]):
                ax.axvline(b[key], color="tab:blue", ls=style, lw=1.0)
        if b.get("measured") is not None:
            ax.axvline(b["measured"], color="k", lw=1.5, label="record")
        if m in specs:
            ax.axvline(specs[m]["limit"], color="tab:red", lw=1.5, label="spec")
        ax.set_title(LABELS[m], fontsize=9)
        ax.tick_params(labelsize=8)
    fig.suptitle(
        f"{doc['n']} members: median (solid), 95 % band (dotted); record (black), spec limit (red)", fontsize=9
    )
    fig.tight_layout()
    save_figure(fig, path)


def _num(x: Any) -> str:
    """A number to 4 significant digits; "—" for JSON's null (infinite, or no ringing: the report's footnote)."""
    return fmt_any(float(x)) if isinstance(x, (int, float)) else "—" if x is None else str(x)


def markdown(doc: dict[str, Any], design: dict[str, Any] | None) -> str:
    """report.md of a prediction (and its design)."""
    lines = []
    if design is not None:
        lines += [f"# Design: {design['method']} on {design['rig']}", ""]
        verdict = "every spec met" if design["passed"] else "NOT every spec met"
        lines += [f"{verdict} on the rig as predicted ({doc['n']} members). Searched {design['searched']} candidates"
                  + (" (weights given)" if not design["searched"] else "") + f"; chosen: `{design['parameters']}`.",
                  ""]  # fmt: skip
        lin = design["linear"]
        lines += [f"Linear loop: disk margin {lin['disk_margin']:.3g} (gain margin {lin['gain_margin_db']:.3g} dB, "
                  f"phase margin {lin['phase_margin_deg']:.3g} deg; balanced, at the plant's input).", ""]  # fmt: skip
        lines += ["Controller (`controller.toml`, a `[controller]` table for a spec; `loop.ssp` the loop as SSP 1.0):",
                  "", f"`{json.dumps(design['gains'])[:400]}`", ""]  # fmt: skip
        if design.get("rounds"):
            lines += ["| round | targets | chosen | predicted worst |", "|---|---|---|---|"]
            for i, r in enumerate(design["rounds"], 1):
                tg = ", ".join(f"{LABELS[k]} {_num(v)}" for k, v in r["targets"].items())
                pr = ", ".join(f"{LABELS[k]} {_num(v)}" for k, v in r["predicted"].items())
                lines.append(f"| {i} | {tg} | `{r['parameters']}` | {pr} |")
            lines.append("")
    lines += [f"# Prediction: {doc['controller']['kind']} on {doc['rig']}", ""]
    lines += [f"Reference: {doc['reference']}, at {doc['sample_rate']:g} Hz; {doc['n']} members (seed {doc['seed']}), "
              f"band {doc['band']}; settling band {doc['band_pct']:g} % of the step; diverged: {doc['diverged']}.",
              ""]  # fmt: skip
    if doc.get("record"):
        lines += [f"Record: `{doc['record']}`."]
        if doc.get("fit_pct"):
            lines += [f"Fit of the median to the record: theta {_num(doc['fit_pct']['theta'])} %, alpha "
                      f"{_num(doc['fit_pct']['alpha'])} %."]  # fmt: skip
        lines.append("")
    has_meas = any(b.get("measured") is not None for b in doc["metrics"].values())
    head = "| metric | median | 95 % band |" + (" measured | inside |" if has_meas else "")
    lines += [head, "|---|---|---|" + ("---|---|" if has_meas else "")]
    for m, b in doc["metrics"].items():
        row = f"| {LABELS.get(m, m)} | {_num(b['median'])} | {_num(b['lo'])} .. {_num(b['hi'])} |"
        if has_meas:
            meas = b.get("measured")
            inside = meas is not None and b["lo"] is not None and b["hi"] is not None and b["lo"] <= meas <= b["hi"]
            row += f" {_num(meas)} | {'—' if meas is None else 'yes' if inside else 'no'} |"
        lines.append(row)
    lines += ["", "—: infinite (a loop that diverged, a step that never settled), or none (no ringing, no step that "
              "way).", ""]  # fmt: skip
    if doc.get("specs"):
        lines += ["| spec | predicted (band's end) | met |", "|---|---|---|"]
        for v in doc["specs"].values():
            lines.append(f"| {v['spec']} | {_num(v['predicted'])} | {'yes' if v['met'] else '**no**'} |")
        lines.append("")
    lines += [f"![traces](figures/{FIGURES[0]})", "", f"![metrics](figures/{FIGURES[1]})", "", "Definitions:", ""]
    lines += [f"- `{k}`: {v}" for k, v in doc["definitions"].items()]
    return "\n".join(lines) + "\n"


def report_prediction(out: Path, rrd: bool | Path = True) -> Path:
    """report.md, figures and (``rrd``: True its own prediction.rrd, or a path) the recording of the prediction in
    ``out``, from its files. Returns report.md."""
    out = Path(out)
    doc, traces, members, design = _load(out)
    text = markdown(doc, design)
    title = f"{doc['controller']['kind']} on {doc['rig']}: median and 95 % band of {doc['n']} members"
    _traces_figure(traces, out / "figures" / FIGURES[0], title)
    _metrics_figure(doc, members, out / "figures" / FIGURES[1])
    atomic_write_text(out / "report.md", text)
    if rrd:
        write_rrd(out, doc, traces, text, None if rrd is True else Path(rrd))
    return out / "report.md"


def write_rrd(out: Path, doc: dict[str, Any], traces: pd.DataFrame, text: str, path: Path | None = None) -> Path:
    """prediction.rrd: the bands, median, record and reference per channel (``send_columns``) and the report."""
    key = hashlib.sha256(json.dumps({k: doc[k] for k in ("rig", "controller", "n", "seed")}, sort_keys=True).encode())
    t = rr.TimeColumn("time", duration=traces["t"].to_numpy(float))
    blueprint = rrb.Blueprint(
        rrb.Tabs(
            rrb.Vertical(
                *(rrb.TimeSeriesView(origin=f"loop/{c}", name=f"{label} vs t [s]") for c, label in CHANNELS.items()),
                name="loop",
            ),  # fmt: skip
            rrb.TextDocumentView(origin="report", name="report"),
        )
    )
    colors = {"lo": [120, 160, 220], "median": [31, 119, 180], "hi": [120, 160, 220], "record": [0, 0, 0]}

    def log(rec: rr.RecordingStream) -> None:
        rec.send_recording_name(f"flexjoint prediction {doc['rig']}")
        body = "\n".join(x for x in text.splitlines() if not x.startswith("!["))
        rec.log("report", rr.TextDocument(body, media_type=rr.MediaType.MARKDOWN), static=True)
        for c in CHANNELS:
            for part, color in colors.items():
                col = f"{c}_{part}"
                if col not in traces:
                    continue
                path_ = f"loop/{c}/{part}"
                rec.log(path_, rr.SeriesLines(colors=[color], names=[part]), static=True)
                v = traces[col].to_numpy(float)
                rec.send_columns(path_, indexes=[t], columns=rr.Scalars.columns(scalars=v))
        rec.log("loop/theta/ref", rr.SeriesLines(colors=[[150, 150, 150]], names=["reference"]), static=True)
        rec.send_columns("loop/theta/ref", indexes=[t], columns=rr.Scalars.columns(scalars=traces["ref"].to_numpy()))

    rec_id = str(uuid.UUID(hex=key.hexdigest()[:32]))
    return write_recording(path or out / "prediction.rrd", rec_id, log, blueprint=blueprint)
