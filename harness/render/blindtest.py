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

from ..rundir import DataError, RunDir, atomic_write_text
from . import figures
from .tables import fmt, table
from .viewer import write_recording

__all__ = ["SCORES", "report_blindtest"]

# score row -> where its share sits in a family's (or the pooled) scores
SCORES = {
    "single: top-1": ("single", "top1"),
    "single: magnitude within 25 %": ("single", "param_within_25pct"),
    "none answered none": ("none", "correct"),
    "two: both found": ("two", "both_found"),
    "recalibrated Ks +-10 % and Beq +-25 %": ("recalibration", "ks_within_10pct_and_beq_within_25pct"),
    "out of library: unexplained": ("out_of_library", "unexplained"),
}


def _share(scores: dict[str, Any], row: str) -> dict[str, Any]:
    group, key = SCORES[row]
    return scores[group][key]


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
    rows = [[row, *(_cell(_share(tot["families"][c] if c != "pooled" else tot, row)) for c in cols)] for row in SCORES]
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
    ]
    lines += [f"Skipped: {why}." for why in doc.get("skipped") or []]
    return "\n".join(lines).rstrip() + "\n"


def _figure(doc: dict[str, Any], path: Path) -> None:
    """Each score per family as a bar [%] with its 95 % interval, the rows of :data:`SCORES`."""
    tot = doc["totals"]
    fams = [*tot.get("families", {}), "pooled"]
    fig = figures.new_figure(9, 0.55 * len(SCORES) * max(1, len(fams)) / 2 + 2.0)
    ax = fig.subplots()
    h = 0.8 / len(fams)
    y = np.arange(len(SCORES))
    for j, fam in enumerate(fams):
        scores = tot["families"][fam] if fam != "pooled" else tot
        shares = [_share(scores, row) for row in SCORES]
        pct = np.array([s["pct"] if s["n"] else np.nan for s in shares], dtype=float)
        lo = np.array([s["ci95"][0] if s["n"] else np.nan for s in shares], dtype=float)
        hi = np.array([s["ci95"][1] if s["n"] else np.nan for s in shares], dtype=float)
        yy = y - 0.4 + (j + 0.5) * h
        ax.barh(yy, np.nan_to_num(pct), h, label=fam, color=f"C{j}")
        ax.errorbar(pct, yy, xerr=[pct - lo, hi - pct], fmt="none", ecolor="k", elinewidth=0.8, capsize=2)
    ax.set_yticks(y, list(SCORES))
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
