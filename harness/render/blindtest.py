"""The report of a blind test's output directory (``blindtest.json``): ``report.md``, ``figures/blindtest.png`` and
``blindtest.rrd``, for ``flexjoint report`` on what ``flexjoint blindtest --out`` wrote."""

from __future__ import annotations

import hashlib
import json
import math
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..diagnosis.blindtest import SCORE_ROWS, SHEET_ROWS, not_fitted_line, score_share, shown_rows
from ..rundir import DataError, RunDir, atomic_write_text
from . import figures
from .tables import fmt, table
from .viewer import write_recording

__all__ = ["report_blindtest"]


def _cell(share: dict[str, Any]) -> str:
    """ "100 % [44-100] (3/3)", or "—" when no case of the family scores it."""
    if not share["n"]:
        return "—"
    lo, hi = share["ci95"]
    return f"{fmt(share['pct'], 0)} % [{fmt(lo, 0)}-{fmt(hi, 0)}] ({share['k']}/{share['n']})"


def _target_line(name: str, t: dict[str, Any]) -> str:
    """ "- single top-1 >= 90 %: 100.0 % (met)"; a target no case scores is said so, not "met"."""
    name = name.removesuffix(" %")
    got = t.get("got")
    if got is None or (isinstance(got, float) and math.isnan(got)):
        return f"- {name} >= {t['target']:g} %: no case scores it"
    return f"- {name} >= {t['target']:g} %: {fmt(got, 1)} % ({'met' if t['met'] else 'NOT met'})"


def _markdown(doc: dict[str, Any], figure: str) -> str:
    tot = doc["totals"]
    cols = [*tot.get("families", {}), "pooled"]
    rows = [
        [row, *(_cell(score_share(tot["families"][c] if c != "pooled" else tot, row)) for c in cols)]
        for row in shown_rows(tot)
    ]
    cases = [
        [
            str(c["case"]),
            c.get("family", "twin"),
            c["kind"],
            ", ".join(c["truth_effects"]) or "none",
            c["score"].get("verdict", "—"),
            ", ".join(f"{k} = {v:.4g}" for k, v in (c["score"].get("fitted") or {}).items()) or "—",
            fmt(c["score"].get("shrink_pct"), 1),
        ]
        for c in doc["cases"]
    ]
    lines = [
        f"# Blind test: {doc['n']} cases (seed {doc['seed']}{', quick' if doc.get('quick') else ''})",
        "",
        f"The diagnoser against rigs with hidden effects, spec `{doc['spec']}`, families: "
        f"{', '.join(doc['families'])}. Each share with its 95 % Wilson interval and count.",
        "",
        *table(["score", *cols], rows),
        "",
        "Targets (pooled):",
        "",
        *(_target_line(k, v) for k, v in tot["targets"].items()),
        "",
        f"![blind-test scores]({figure})",
        "",
        "## Cases",
        "",
        *table(["case", "family", "kind", "hidden effects", "verdict", "fitted", "shrink [%]"], cases),
        "",
        *_sheet_section(doc),
        *_design_section(doc),
    ]
    lines += [f"Skipped: {why}." for why in doc.get("skipped") or []]
    return "\n".join(lines).rstrip() + "\n"


def _sheet_error(case: dict[str, Any], row: str) -> str:
    """A wrong-sheet row's error [%] with "ok" within 10 %, "not fitted" (no row), or "kept" at the sheet's value."""
    sc = case["score"]
    err = sc["sheet_errors"][row]
    if err is None:
        return "not fitted"
    text = f"{fmt(100.0 * err, 1)}{' ok' if sc['sheet_ok'][row] else ''}"
    return f"{text} (kept)" if sc["sheet_status"][row] == "kept" else text


def _sheet_section(doc: dict[str, Any]) -> list[str]:
    """The wrong_sheet rigs: how far each sheet was off (the rig's value / the sheet's), the diagnosis's error on each
    sheet quantity [%], and the drive the plant rows imply (not scored); nothing without such rigs."""
    cases = [c for c in doc["cases"] if c.get("sheet_truth") and "sheet_errors" in c["score"]]
    if not cases:
        return []
    short = {"rig.drive_gain": "K", "rig.drive_tau": "tau", "plant.Ks": "Ks", "daq.gauge_gain": "gauge"}
    rows = [
        [
            str(c["case"]),
            ", ".join(c["truth_effects"]) or "none",
            " ".join(f"{short[k]} x{c['sheet_factors'][k]:.2f}" for k in short),
            *(_sheet_error(c, r) for r in SHEET_ROWS),
            " / ".join(fmt(100.0 * c["score"]["sheet_implied_errors"][r], 1) for r in SHEET_ROWS[:2]),
            c["score"].get("verdict", "—"),
        ]
        for c in cases
    ]
    line = not_fitted_line(doc["totals"])
    return [
        "## Wrong sheet",
        "",
        "Each rig off its sheet (the rig's value / the sheet's; gauge: the DAQ's gauge gain, the data converted with "
        "the sheet's, so the data read 1 / that of the true deflection: the truth of `sensor.alpha_gauge_gain`). "
        "The diagnosis's error on each [%], ok within 10 %; the drive's gain and time constant its fitted plant "
        "parameters imply beside them (not scored).",
        "",
        *table(["case", "hidden effect", "sheet off by", *SHEET_ROWS, "implied K / tau [%]", "verdict"], rows),
        "",
        *([line, ""] if line else []),
    ]


def _design_section(doc: dict[str, Any]) -> list[str]:
    """The design family's rigs: the identified and the sheet design on the true rig (each spec met or not), and the
    true rig's metrics under the identified design against its predicted band; nothing without such rigs."""
    cases = [c for c in doc["cases"] if "design" in c["score"]]
    if not cases:
        return []
    d0 = doc["totals"]["design"]
    metrics = list(cases[0]["score"]["design"]["band_hits"])
    rows = []
    for c in cases:
        ds = c["score"]["design"]
        cells = []
        for m in metrics:
            lo, _, hi = ds["predicted"][m]
            mark = "" if ds["band_hits"][m] else " **out**"
            cells.append(f"{fmt(ds['true_identified'][m], 3)} [{fmt(lo, 3)}-{fmt(hi, 3)}]{mark}")
        rows.append([str(c["case"]), ", ".join(c["truth_effects"]) or "none",
                     "yes" if ds["identified_met"] else "no", "yes" if ds["sheet_met"] else "no", *cells])  # fmt: skip
    return [
        "## Design",
        "",
        f"Each rig logged under an {d0['method']} designed on its sheet to `{d0['specs']}`, diagnosed; an "
        f"{d0['method']} designed to the same specs on the identified twin; both run on the true rig. Specs met on the "
        "true rig by each; the true rig's metrics under the identified design with its predicted 95 % band.",
        "",
        *table(["case", "hidden effect", "identified meets", "sheet meets", *metrics], rows),
        "",
    ]


def _figure(doc: dict[str, Any], path: Path) -> None:
    """Each score per family as a bar [%] with its 95 % interval, the rows of :func:`shown_rows`."""
    tot = doc["totals"]
    fams = [*tot.get("families", {}), "pooled"]
    rows = shown_rows(tot)
    fig = figures.new_figure(9, 0.55 * len(rows) * max(1, len(fams)) / 2 + 2.0)
    ax = fig.subplots()
    h = 0.8 / len(fams)
    y = np.arange(len(rows))
    for j, fam in enumerate(fams):
        scores = tot["families"][fam] if fam != "pooled" else tot
        shares = [score_share(scores, row) for row in rows]
        pct = np.array([s["pct"] if s["n"] else np.nan for s in shares], dtype=float)
        lo = np.array([s["ci95"][0] if s["n"] else np.nan for s in shares], dtype=float)
        hi = np.array([s["ci95"][1] if s["n"] else np.nan for s in shares], dtype=float)
        yy = y - 0.4 + (j + 0.5) * h
        ax.barh(yy, np.nan_to_num(pct), h, label=fam, color=f"C{j}")
        ax.errorbar(pct, yy, xerr=[pct - lo, hi - pct], fmt="none", ecolor="k", elinewidth=0.8, capsize=2)
        for i, row in enumerate(rows):  # a sheet quantity the diagnosis has no row for: said, not a bare 0 %
            where = SCORE_ROWS[row]
            missing = scores["wrong_sheet"]["rows"][where[2]]["not_fitted"] if where[1:2] == ("rows",) else 0
            if missing:
                box = {"facecolor": "white", "edgecolor": "none", "pad": 0.5}
                ax.text(1.0, yy[i], f"not fitted ({missing}/{shares[i]['n']})", va="center", fontsize=7, bbox=box)
    ax.set_yticks(y, rows)
    ax.invert_yaxis()
    ax.set_xlim(0, 105)
    ax.set_xlabel("share of the cases [%] (bar) with its 95 % Wilson interval")
    ax.set_title(f"blind test: {doc['n']} cases, each score per family\n(no bar: no case of the family scores it)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(True, axis="x", alpha=0.3)
    fig.tight_layout()
    figures.save_figure(fig, path)


def report_blindtest(out: Path, rrd: Path | None = None) -> tuple[Path, Path]:
    """``report.md``, ``figures/blindtest.png`` and the recording (``blindtest.rrd`` unless ``rrd``: the report as a
    document, the figure as an image) of the blind test in ``out``; returns (report, recording)."""
    out = Path(out)
    src = out / "blindtest.json"
    try:
        doc = json.loads(src.read_text())
        doc["totals"]["targets"]
    except FileNotFoundError:
        raise DataError(f"{out}: not a blind-test directory (no blindtest.json)") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise DataError(f"{src}: not a blind test's output ({exc})") from None
    fig_path = RunDir(out).figures / "blindtest.png"
    _figure(doc, fig_path)
    markdown = _markdown(doc, "figures/blindtest.png")
    atomic_write_text(RunDir(out).report, markdown)

    def log(rec: rr.RecordingStream) -> None:
        rec.send_recording_name(f"flexjoint blind test {doc['n']} cases, seed {doc['seed']}")
        text = "\n".join(x for x in markdown.splitlines() if not x.startswith("![")).replace("\n\n\n", "\n\n")
        rec.log("report", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)  # the figure apart
        rec.log("scores", rr.EncodedImage(contents=fig_path.read_bytes(), media_type="image/png"), static=True)

    blueprint = rrb.Blueprint(
        rrb.Tabs(  # each at full width: the tables uncut
            rrb.TextDocumentView(origin="report", name="blind test"),
            rrb.Spatial2DView(origin="scores", name="scores per family [%]"),
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )
    key = hashlib.sha256(json.dumps({k: doc[k] for k in ("n", "seed", "spec", "families")}, sort_keys=True).encode())
    rec_id = str(uuid.UUID(hex=key.hexdigest()[:32]))
    recording = write_recording(rrd or out / "blindtest.rrd", rec_id, log, blueprint=blueprint)
    return RunDir(out).report, recording
