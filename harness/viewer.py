"""Stream a run directory to Rerun (rerun-sdk 0.41): ``run.rrd`` by default, plus a spawned or remote viewer.

Entity tree (all logged from the run directory alone, via :func:`harness.report.load_results`):

- ``datasets/<name>/measured``, ``.../simulated`` (identification domain y_f [deg/sample], selected model),
  ``.../command`` (u [V]), ``.../tip/measured``, ``.../tip/simulated`` (tip angle [deg]); timeline ``time``
  [s]
- ``crossfit/matrix`` (Tensor, dims model x dataset, fit [%]) and ``crossfit/table`` (markdown)
- ``models/selected/pz/{poles,zeros,unit_circle}`` (z-plane, model with integrator)
- ``bode/magnitude/<model>`` [dB], ``bode/phase/<model>`` [deg]: timeline ``frequency_mHz`` (sequence, mHz)
- ``resid/acf/<dataset>``, ``resid/ccf/<dataset>`` and ``resid/{acf,ccf}/bound_{upper,lower}`` (99 %):
  timeline ``lag`` (sequence, samples); ``resid/summary`` (markdown)
- ``diagnosis/gap_before``, ``diagnosis/gap_after`` (bar charts), ``diagnosis/summary`` (markdown)
- ``overview`` (markdown)

Time series use one ``send_columns`` call per entity. Plots over frequency or lag use their own timelines:
select ``frequency_mHz`` or ``lag`` in the time panel to see the Bode and residual tabs.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import tempfile
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from . import armax
from .report import (
    RunResults,
    bode,
    crossfit_table,
    diagnosis_markdown,
    gap_rows,
    load_results,
    pole_zero,
    tip_from_filtered,
)

__all__ = ["APPLICATION_ID", "log_run", "recording_id"]

APPLICATION_ID = "flexjoint"
RESID_LAGS = 25
N_BODE = 500

_BLACK = [30, 30, 30]
_ORANGE = [230, 120, 20]
_GREY = [150, 150, 150]
_RED = [220, 40, 40]
_BLUE = [40, 90, 220]


def recording_id(manifest: dict[str, Any]) -> str:
    """Stable recording id (UUID form) from the manifest's spec hash, or from its data sources for imports."""
    key = manifest.get("spec_sha256")
    if not key:
        basis = manifest.get("sources") or manifest.get("experiments") or manifest
        key = hashlib.sha256(json.dumps(basis, sort_keys=True, default=str).encode()).hexdigest()
    return str(uuid.UUID(hex=hashlib.sha256(str(key).encode()).hexdigest()[:32]))


def _part(name: str) -> str:
    return rr.escape_entity_path_part(str(name))


def _series(rec: rr.RecordingStream, path: str, timeline: rr.TimeColumn, values: np.ndarray) -> None:
    cols = rr.Scalars.columns(scalars=np.asarray(values, dtype=float))
    rec.send_columns(path, indexes=[timeline], columns=cols)


def _style(rec: rr.RecordingStream, path: str, name: str, color: list[int], width: float = 1.0) -> None:
    rec.log(path, rr.SeriesLines(colors=[color], names=[name], widths=[width]), static=True)


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


def _log_crossfit(rec: rr.RecordingStream, res: RunResults) -> None:
    cf = res.crossfit
    if cf is None or cf.empty:
        return
    values = cf.to_numpy(dtype=float)
    finite = values[np.isfinite(values)]
    # colour map over the fits actually present (e.g. 86-98 %), not 0-max, or every cell looks the same
    span = (float(np.floor(finite.min())), float(np.ceil(finite.max()))) if finite.size else None
    tensor = rr.Tensor(values, dim_names=("model", "dataset"), value_range=span)
    rec.log("crossfit/matrix", tensor, static=True)
    text = "\n".join(
        [
            "### Cross-fit [%]",
            "",
            "Rows: " + ", ".join(f"{i} = `{n}`" for i, n in enumerate(cf.index)) + " (tensor index).",
            "",
            *crossfit_table(res),
            "",
            f"Source: {res.crossfit_source}.",
        ]
    )
    rec.log("crossfit/table", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)


def _log_pz(rec: rr.RecordingStream, res: RunResults) -> None:
    if res.selected is None:
        return
    poles, zeros = pole_zero(res.selected[0], res.af)
    base = "models/selected/pz"
    rec.log(
        f"{base}/poles",
        rr.Points2D(np.c_[poles.real, poles.imag], colors=[_RED], radii=0.025, labels=["x"] * poles.size),
        static=True,
    )
    rec.log(
        f"{base}/zeros",
        rr.Points2D(np.c_[zeros.real, zeros.imag], colors=[_BLUE], radii=0.025, labels=["o"] * zeros.size),
        static=True,
    )
    th = np.linspace(0.0, 2.0 * math.pi, 241)
    circle = rr.LineStrips2D([np.c_[np.cos(th), np.sin(th)]], colors=[_GREY])
    rec.log(f"{base}/unit_circle", circle, static=True)
    axes = [[[-1.2, 0.0], [1.2, 0.0]], [[0.0, -1.2], [0.0, 1.2]]]
    rec.log(f"{base}/axes", rr.LineStrips2D(axes, colors=[[210, 210, 210]], radii=0.003), static=True)


def _log_bode(rec: rr.RecordingStream, res: RunResults) -> None:
    if not res.models:
        return
    Ts = res.sample_time
    nyq = 0.5 / Ts
    mhz = np.unique(np.round(np.arange(1, N_BODE) * nyq / N_BODE * 1000.0).astype(np.int64))
    mhz = mhz[mhz > 0]
    f = mhz / 1000.0
    timeline = rr.TimeColumn("frequency_mHz", sequence=mhz)
    for name, (m, _) in res.models.items():
        mag, ph = bode(m, res.af, f)
        color, width = (_BLUE, 2.0) if name == "selected" else (_GREY, 1.0)
        for kind, vals, unit in (("magnitude", mag, "dB"), ("phase", ph, "deg")):
            path = f"bode/{kind}/{_part(name)}"
            _style(rec, path, f"{name} [{unit}]", color, width)
            _series(rec, path, timeline, vals)


def _log_resid(rec: rr.RecordingStream, res: RunResults) -> None:
    if res.selected is None or not res.prepared:
        return
    m = res.selected[0]
    rows = [
        "| dataset | acf lags outside | white | ccf lags outside | independent |",
        "|---|---|---|---|---|",
    ]
    bound = 0.0
    lags = RESID_LAGS
    for name, p in res.prepared.items():
        lags = min(RESID_LAGS, p.y_f.size // 2 - 1)
        rt = armax.resid(m, p.u_d, p.y_f, lags=lags)
        bound = max(bound, rt.bound)
        lag = rr.TimeColumn("lag", sequence=np.arange(rt.acf.size))
        _series(rec, f"resid/acf/{_part(name)}", lag, rt.acf)
        _series(rec, f"resid/ccf/{_part(name)}", rr.TimeColumn("lag", sequence=rt.lags_ccf), rt.ccf)
        rows.append(
            f"| {name} | {rt.n_out_acf}/{rt.lags} | {'yes' if rt.white else 'no'} | "
            f"{rt.n_out_ccf}/{rt.lags_ccf.size} | {'yes' if rt.independent else 'no'} |"
        )
    for kind, k in (("acf", np.arange(lags + 1)), ("ccf", np.arange(-lags, lags + 1))):
        for side, sign in (("upper", 1.0), ("lower", -1.0)):
            path = f"resid/{kind}/bound_{side}"
            _style(rec, path, f"99 % bound ({side})", _RED)
            _series(rec, path, rr.TimeColumn("lag", sequence=k), np.full(k.size, sign * bound))
    text = "\n".join(
        [
            "### Residual tests of the selected model",
            "",
            f"99 % bound 2.58/sqrt(N) = {bound:.4f} (widest over datasets).",
            "",
            *rows,
        ]
    )
    rec.log("resid/summary", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)


def _log_diagnosis(rec: rr.RecordingStream, res: RunResults) -> None:
    d = res.diagnosis
    if d is None:
        return
    rows = gap_rows(d)
    if rows:
        x = np.arange(len(rows), dtype=float)
        before = np.array([r[1] for r in rows])
        after = np.array([r[2] for r in rows])
        rec.log("diagnosis/gap_before", rr.BarChart(before, abscissa=x, color=_RED), static=True)
        rec.log("diagnosis/gap_after", rr.BarChart(after, abscissa=x, color=_BLUE), static=True)
    lines = ["### Sim-to-real gap diagnosis", ""]
    if rows:
        legend = ", ".join(f"{i} = {r[0]}" for i, r in enumerate(rows))
        lines += [f"Bars (red before, blue after) by index: {legend}", ""]
    lines += diagnosis_markdown(d)
    doc = rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN)
    rec.log("diagnosis/summary", doc, static=True)


def _log_overview(rec: rr.RecordingStream, res: RunResults) -> None:
    m = res.manifest
    lines = [
        "### flexjoint run",
        "",
        f"- kind: {m.get('kind', '-')}",
        f"- spec sha256: `{m.get('spec_sha256', '-')}`",
        f"- sample rate: {m.get('sample_rate', '-')} Hz",
        f"- identification datasets: {', '.join(res.prepared) or '-'}",
    ]
    if res.selected is not None:
        r = res.selected[1]
        orders = f"({r['na']},{r['nb']},{r['nc']},{r['nk']})"
        lines.append(f"- selected ARMAX (na,nb,nc,nk) = {orders}, trained on `{r.get('dataset')}`")
    lines += [
        "",
        "Series over time use the `time` timeline. The Bode tab uses `frequency_mHz` and the residual",
        "tab uses `lag`: pick that timeline in the time panel to see them.",
    ]
    rec.log("overview", rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN), static=True)


def _log_all(rec: rr.RecordingStream, res: RunResults) -> None:
    spec = res.manifest.get("spec") or {}
    name = (spec.get("campaign") or {}).get("name") if isinstance(spec, dict) else None
    rec.send_recording_name(f"flexjoint {name or res.run.name}")
    _log_overview(rec, res)
    _log_datasets(rec, res)
    _log_crossfit(rec, res)
    _log_pz(rec, res)
    _log_bode(rec, res)
    _log_resid(rec, res)
    _log_diagnosis(rec, res)


# ----------------------------------------------------------------------------------------------- blueprint
def _blueprint(res: RunResults) -> rrb.Blueprint:
    tabs: list[Any] = [rrb.TextDocumentView(origin="overview", name="overview")]
    if res.prepared:
        per = []
        for name in res.prepared:
            o = f"datasets/{_part(name)}"
            per.append(
                rrb.Vertical(
                    rrb.TimeSeriesView(
                        origin=o, contents=["$origin/measured", "$origin/simulated"], name=f"{name}: y_f"
                    ),
                    rrb.TimeSeriesView(origin=f"{o}/tip", name=f"{name}: tip angle [deg]"),
                    rrb.TimeSeriesView(origin=o, contents=["$origin/command"], name=f"{name}: command [V]"),
                    row_shares=[2.0, 2.0, 1.0],
                    name=name,
                )
            )
        tabs.append(rrb.Tabs(*per, name="datasets"))
    if res.crossfit is not None and not res.crossfit.empty:
        tabs.append(
            rrb.Horizontal(
                rrb.TensorView(origin="crossfit/matrix", name="cross-fit matrix"),
                rrb.TextDocumentView(origin="crossfit/table", name="cross-fit table"),
                name="cross-fit",
            )
        )
    if res.models:
        tabs.append(
            rrb.Horizontal(
                rrb.Spatial2DView(
                    origin="models/selected/pz",
                    name="pole-zero (selected, with integrator)",
                    visual_bounds=rrb.VisualBounds2D(x_range=[-1.5, 1.5], y_range=[-1.5, 1.5]),
                ),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="bode/magnitude", name="Bode magnitude [dB] vs f [mHz]"),
                    rrb.TimeSeriesView(origin="bode/phase", name="Bode phase [deg] vs f [mHz]"),
                ),
                name="model",
            )
        )
    if res.selected is not None and res.prepared:
        tabs.append(
            rrb.Vertical(
                rrb.TimeSeriesView(origin="resid/acf", name="residual autocorrelation vs lag"),
                rrb.TimeSeriesView(origin="resid/ccf", name="residual-input cross-correlation vs lag"),
                rrb.TextDocumentView(origin="resid/summary", name="residual tests"),
                name="residuals",
            )
        )
    if res.diagnosis is not None:
        gaps = ["$origin/gap_before", "$origin/gap_after"]
        tabs.append(
            rrb.Horizontal(
                rrb.BarChartView(origin="diagnosis", contents=gaps, name="gap before / after"),
                rrb.TextDocumentView(origin="diagnosis/summary", name="diagnosis"),
                name="diagnosis",
            )
        )
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


def _write_rrd(res: RunResults, rrd: Path, blueprint: rrb.Blueprint) -> None:
    """Log everything into a temp file next to ``rrd`` and rename it into place; no half file on error."""
    rrd.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=rrd.parent, prefix=f".{rrd.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(tmp_name)
    rec = None
    try:
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(res.manifest))
        rec.set_sinks(rr.FileSink(str(tmp)), default_blueprint=blueprint)
        _log_all(rec, res)
        rec.flush()
        rec.disconnect()  # closes the file sink and writes the RRD footer
        rec = None
        os.chmod(tmp, 0o644)  # mkstemp made it 0600
        os.replace(tmp, rrd)
    except BaseException:
        if rec is not None:
            with contextlib.suppress(Exception):  # best effort: the original error matters
                rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise


def _stream_live(res: RunResults, blueprint: rrb.Blueprint, spawn: bool, connect: str | None) -> None:
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(res.manifest))
    where = connect or "a spawned viewer"
    try:
        if spawn:
            rec.spawn(default_blueprint=blueprint)
        else:
            rec.connect_grpc(connect, default_blueprint=blueprint)
        _log_all(rec, res)
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
) -> Path | None:
    """Log a run directory to Rerun: always to ``rrd`` (default ``<run>/run.rrd``, written atomically), and
    live to a spawned viewer (``spawn=True``) or a running one (``connect`` = gRPC URL such as
    ``rerun+http://127.0.0.1:9876/proxy``). One recording, application id ``flexjoint``, recording id from
    the manifest's spec hash; the blueprint travels with it. Returns the path of the ``.rrd`` file.
    """
    if connect is not None:
        _check_url(connect)
    res = load_results(Path(run))
    out = Path(rrd) if rrd is not None else res.run / "run.rrd"
    blueprint = _blueprint(res)
    _write_rrd(res, out, blueprint)
    if spawn or connect is not None:
        _stream_live(res, blueprint, spawn, connect)
    return out
