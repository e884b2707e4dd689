"""The diagnosis (``diagnosis.json``) in words and tables for a person: the verdict and what it means, each
effect's importance, the gap stage by stage (the waterfall), the folds of the cross-fit, where the gap lies.
Nothing is printed as a raw dictionary; the full detail stays in the JSON."""

from __future__ import annotations

import math
from typing import Any

from .tables import fmt, fmt_any, num, table

__all__ = ["diagnosis_markdown", "fold_roles", "gap_rows", "waterfall"]

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
    vals = [num(v) for v in fit.values()] if isinstance(fit, dict) else [num(fit)]
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
        (str(e.get("effect", "?")), num(e.get("gap_before")), num(e.get("gap_after")))
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
    if not isinstance(dec, dict) or not math.isfinite(num(dec.get("before"))):
        return []
    rows = [("simulation as given", num(dec["before"]), math.nan)]
    for s in dec.get("steps") or []:
        if isinstance(s, dict):
            rows.append((str(s.get("stage", "?")), num(s.get("gap_after")), num(s.get("closed_pct"))))
    return rows


def _channels(entry: Any) -> str:
    fit = entry.get("fit_pct") if isinstance(entry, dict) else entry
    if isinstance(fit, dict):
        return ", ".join(f"{k} {fmt(v)}" for k, v in fit.items())
    return fmt(fit)


def _params_text(params: Any) -> str:
    if not isinstance(params, dict) or not params:
        return "—"
    return ", ".join(f"{k} = {fmt_any(v)}" for k, v in params.items())


def _effects(diag: dict[str, Any]) -> list[dict[str, Any]]:
    return [e for e in diag.get("effects", []) or [] if isinstance(e, dict)]


def verdict_sentence(diag: dict[str, Any]) -> str:
    """What the verdict means, in one or two sentences with the numbers of ``diagnosis.json``."""
    verdict = str(diag.get("verdict", "—"))
    effects = _effects(diag)
    if verdict in VERDICT_MEANING:
        return f"`{verdict}`: {VERDICT_MEANING[verdict]}."
    if not effects:
        return ""
    gap = diag.get("gap") or {}
    if len(effects) == 1:
        share = fmt(gap.get("explained_pct"), 1)
        return (
            f"`{verdict}` is the only effect found; modelled on top of the recalibrated simulation it closes {share} % "
            "of the gap beyond noise on held-out experiments."
        )
    named = {str(e.get("effect")): e for e in effects}
    v = named.get(verdict, {})
    text = (
        f"{len(effects)} effects found. The verdict names the most important one: removing `{verdict}` alone from the "
        f"final model reopens the most gap ({fmt(v.get('importance_pct'), 1)} % of what the drop-one removals "
        "reopen together)."
    )
    biggest = max(effects, key=lambda e: num(e.get("shrink_pct")) if math.isfinite(num(e.get("shrink_pct"))) else -1e9)
    if str(biggest.get("effect")) != verdict:
        order = effects.index(biggest) + 1
        text += (
            f" It is not the effect that closed most when it was added: `{biggest.get('effect')}`, added "
            f"{_ORDINAL.get(order, f'as number {order}')}, closed {fmt(biggest.get('shrink_pct'), 1)} % of the gap "
            "left at that point; the effects act together, so each one's share is in the waterfall below."
        )
    return text


_ORDINAL = {1: "first", 2: "second", 3: "third", 4: "fourth", 5: "fifth", 6: "sixth"}


def _verdict_lines(diag: dict[str, Any]) -> list[str]:
    lines = [f"Verdict: **{diag.get('verdict', '—')}**", ""]
    sentence = verdict_sentence(diag)
    if sentence:
        lines += [sentence, ""]
    params = diag.get("parameters")
    findings = [
        str(p["finding"])
        for p in (params.values() if isinstance(params, dict) else [])
        if isinstance(p, dict) and p.get("finding") and "matches" not in str(p["finding"])
    ]
    if findings:
        lines += ["Linear findings: " + "; ".join(findings) + ".", ""]
    return lines


LATTICE = "ADC lattice"
FOUND_BY = {
    "held-out closure": "closes the held-out gap",
    "adc lattice in the data": f"{LATTICE} of the data (kept without closing the gap)",
}


def _effects_lines(diag: dict[str, Any]) -> list[str]:
    effects = _effects(diag)
    if not effects:
        return []
    rows = [
        [
            str(e.get("effect", "?")),
            _params_text(e.get("params")),
            fmt(e.get("importance_pct"), 1),
            fmt(e.get("gap_before"), 4),
            fmt(e.get("gap_after"), 4),
            fmt(e.get("shrink_pct"), 1),
            FOUND_BY.get(str(e.get("selected_by")), str(e.get("selected_by", "—"))),
        ]
        for e in effects
    ]
    header = ["effect", "fitted parameters", "importance [%]", "gap before", "gap after", "shrink [%]", "found by"]
    lines = ["Effects, in the order they were added (gaps on held-out experiments):", "", *table(header, rows), ""]
    lines += [
        "Importance: remove each effect alone from the final model and part of the gap reopens; an effect's "
        "importance is its share of what the removals reopen. Shrink: how much the held-out gap fell when the "
        "effect was added.",
        "",
    ]
    if any(LATTICE in r[-1] for r in rows):
        lines += [
            "Quantization is not found by closing the gap but by its signature in the data: every sample sits on the "
            "lattice of a converter's steps. It is kept for the record although its shrink is negative, because "
            "quantisation error looks like noise and the simulation scores it against a noisy record (it has no "
            "importance for the same reason).",
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
        ci_text = f"{fmt_any(ci[0])} .. {fmt_any(ci[1])}" if isinstance(ci, list) and len(ci) == 2 else "—"
        rows.append(
            [
                str(name),
                str(p.get("unit", "—")),
                fmt_any(p.get("nominal")),
                fmt_any(p.get("fitted")),
                ci_text,
                fmt(p.get("change_pct"), 1),
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
        *table(header, rows),
        "",
    ]


def _decomposition_lines(diag: dict[str, Any], figure: str | None) -> list[str]:
    rows = waterfall(diag)
    if not rows:
        return []
    dec = diag["gap"]["decomposition"]
    body = [[stage, fmt(g, 4), fmt(100.0 * (1.0 - g), 2), fmt(c, 1)] for stage, g, c in rows]
    noise = num(dec.get("noise_floor"))
    body.append(["noise floor", fmt(noise, 4), fmt(100.0 * (1.0 - noise), 2), "—"])
    first, last = rows[0][1], rows[-1][1]
    lines = [
        f"The gap waterfall, effect by effect: the held-out gap falls from {fmt(first, 4)} (fit "
        f"{fmt(100.0 * (1.0 - first), 1)} %) for the simulation as given to {fmt(last, 4)} (fit "
        f"{fmt(100.0 * (1.0 - last), 1)} %) with every effect, against a noise floor of {fmt(noise, 4)}. "
        "Closed: the share of the excess squared gap above the floor that each stage closes.",
        "",
        *table(["stage", "held-out gap", "fit [%]", "closed [%]"], body),
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
        gaps = [fmt(held.get("gap_before"), 4), fmt(held.get("gap_after"), 4)]
        rows.append(
            [
                "held out (fitted on the other fold)",
                *gaps,
                fmt(held.get("fit_pct_before")),
                fmt(held.get("fit_pct_after")),
            ]
        )
    b, a = gap.get("before"), gap.get("after")
    if isinstance(b, dict) and isinstance(a, dict) and "gap" in b:
        rows.append(
            [
                "all experiments, final parameters",
                fmt(b.get("gap"), 4),
                fmt(a.get("gap"), 4),
                fmt(b.get("fit_pct")),
                fmt(a.get("fit_pct")),
            ]
        )
    if not rows:
        return []
    lines = [*table(["gap", "before", "after", "fit before [%]", "fit after [%]"], rows), ""]
    if "shrink_pct" in gap:
        shrink = fmt(gap.get("shrink_pct"), 1)
        lines += [f"Held-out shrink {shrink} % (in sample {fmt(gap.get('shrink_pct_in_sample'), 1)} %).", ""]
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
            fmt(_exp_gap(eb[name]), 4),
            fmt(_exp_gap(ea.get(name)), 4),
        ]
        for name in eb
    ]
    header = ["experiment", "fold", "fit before [%]", "fit after [%]", "gap before", "gap after"]
    return [
        "Per experiment (2-fold cross-fit: what is fitted on one fold is scored on the other, so every experiment "
        "is held out once; 'after' here uses the final parameters):",
        "",
        *table(header, rows),
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
            fmt(c.get("held_out_share_pct"), 1),
            fmt(c.get("shrink_pct"), 1),
            str(c.get("note", "")) or "—",
        ]
        for c in cands
    ]
    header = ["candidate", "fitted parameters", "closes [%] of the excess", "shrink [%]", "note"]
    return ["Candidates, each alone on the first round (held out):", "", *table(header, rows), ""]


def _where_stages(where: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(label, where-dict) per stage: {"before": ..., "after_recalibration": ...}, or today's flat structure."""
    staged = [(STAGE_LABELS[k], where[k]) for k in STAGE_LABELS if isinstance(where.get(k), dict)]
    return staged or [("simulation as given", where)]


def _where_cells(s: dict[str, Any]) -> list[str]:
    """Dominant band, amplitude regime, events and headline of one channel's pooled where-summary."""
    fr = s.get("frequency") or {}
    band = fr.get("dominant_band")
    band_text = f"{band} ({fmt(100.0 * num(fr.get('dominant_share')), 0)} %)" if band else "—"
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
        lines += [*table(header, rows), ""]
    masked = where.get("masked")
    if isinstance(masked, dict) and masked:
        share = ", ".join(f"{k} {fmt(100.0 * num(v), 1)} %" for k, v in masked.items())
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
        parts = [f"gap {fmt(noise.get('gap'), 4)} (fit {fmt(noise.get('fit_pct'))} %)"]
        for ch in ("theta", "alpha"):
            if f"{ch}_deg" in noise:
                parts.append(f"{ch} {fmt_any(noise[f'{ch}_deg'])} deg rms")
        how = f", {noise['method']}" if isinstance(noise.get("method"), str) else ""
        lines += [f"Noise floor (from the data{how}): " + ", ".join(parts) + ".", ""]
    lines += _where_lines(diag)
    return lines
