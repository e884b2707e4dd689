"""The diagnosis (:class:`harness.diagnosis.result.Diagnosis`) in words and tables for a person: the verdict and
what it means, each effect's importance, the gap stage by stage (the waterfall), the folds of the cross-fit,
where the gap lies. Nothing is printed as a raw dictionary; the full detail stays in ``diagnosis.json``, and what
each part means is in the manual (:data:`MANUAL`, "Reading the report"), which the text names where it says less."""

from __future__ import annotations

import math
from typing import Any

from ..diagnosis.effects import SELECTED_BY_SPREAD
from ..diagnosis.result import Diagnosis, FittedParameter
from .tables import fmt, fmt_any, num, table, wrap_prose

__all__ = ["LATTICE", "MANUAL", "diagnosis_markdown", "gap_rows", "manual", "verdict_sentence"]

MANUAL = "docs/concepts/diagnosis.md"  # the manual's page that explains what the report of a diagnosis says


def manual(section: str) -> str:
    """Where the manual explains ``section`` (a heading of :data:`MANUAL`, as its anchor): "`docs/...md#section`"."""
    return f"`{MANUAL}#{section}`"


VERDICT_MEANING = {
    "none": "no gap beyond the measurement noise: the simulation explains the rig",
    "quantization": "no gap beyond the measurement noise, but every sample sits on an ADC lattice: the rig's "
    "converter quantises (found by this signature in the data, not by closing a gap)",
    "unexplained": "the candidate effects together do not close enough of the gap beyond noise; the gap has a "
    "cause outside the library (the partial candidates are listed with their honest shrink)",
}
STAGE_LABELS = {"before": "simulation as given", "after_recalibration": "after recalibration"}
LATTICE = "ADC lattice"
FOUND_BY = {
    "held-out closure": "closes the held-out gap",
    "adc lattice in the data": f"{LATTICE} of the data (kept without closing the gap)",
    SELECTED_BY_SPREAD: "its own spread in closed loop (sized where the replays' spread matches the record's gap)",
}
_ORDINAL = {1: "first", 2: "second", 3: "third", 4: "fourth", 5: "fifth", 6: "sixth"}


def gap_rows(diag: Diagnosis) -> list[tuple[str, float, float]]:
    """(experiment with its fold, gap before, gap after) with the final parameters, in the diagnoser's order."""
    return [
        (f"{name} ({diag.folds.role(name)})", before, after)
        for name, before, after in diag.gap.per_experiment()
        if math.isfinite(before) or math.isfinite(after)
    ]


def _params_text(params: dict[str, float]) -> str:
    return ", ".join(f"{k} = {fmt_any(v)}" for k, v in params.items()) or "—"


def verdict_sentence(diag: Diagnosis) -> str:
    """What the verdict means, in one to three sentences with the numbers of the diagnosis."""
    verdict, effects = diag.verdict, diag.effects
    if verdict in VERDICT_MEANING:
        return f"`{verdict}`: {VERDICT_MEANING[verdict]}."
    if not effects:
        return ""
    if any(e.effect == verdict and e.selected_by == SELECTED_BY_SPREAD for e in effects):
        others = [f"`{e.effect}`" for e in effects if e.effect != verdict]
        return (
            f"`{verdict}` is found by its spread in closed loop (below): with it the replays' gap is their own spread "
            f"between noise draws, which accounts for {fmt(diag.gap.explained_pct, 1)} % of the gap beyond noise on "
            f"held-out experiments{' together with ' + ', '.join(others) if others else ''}."
        )
    if len(effects) == 1:
        return (
            f"`{verdict}` is the only effect found; modelled on top of the recalibrated simulation it closes "
            f"{fmt(diag.gap.explained_pct, 1)} % of the gap beyond noise on held-out experiments."
        )
    imp = diag.importance_pct()
    text = (
        f"{len(effects)} effects found. The verdict names the most important one: removing `{verdict}` alone from the "
        f"final rig (fitted on every record) reopens the most of its gap ({fmt(imp.get(verdict), 1)} % of what the "
        "drop-one removals reopen together)."
    )
    shrinks = [e.shrink_pct if math.isfinite(e.shrink_pct) else -math.inf for e in effects]
    k = max(range(len(effects)), key=shrinks.__getitem__)
    if effects[k].effect != verdict:
        text += (
            f" It is not the effect that closed most when it was added: `{effects[k].effect}`, added "
            f"{_ORDINAL.get(k + 1, f'as number {k + 1}')}, closed {fmt(effects[k].shrink_pct, 1)} % of the gap left "
            "at that point; the effects act together, so each one's share is in the waterfall below."
        )
    return text


def _verdict_lines(diag: Diagnosis) -> list[str]:
    lines = [f"Verdict: **{diag.verdict}**", ""]
    sentence = verdict_sentence(diag)
    if sentence:
        lines += [sentence, ""]
    findings = diag.off_spec_findings()
    if findings:
        lines += ["Linear findings: " + "; ".join(findings) + ".", ""]
    if diag.caveats:
        lines += ["Caveats:", "", *[f"- {c}" for c in diag.caveats], ""]
    if diag.replays:
        groups: dict[tuple[str, str], list[str]] = {}
        for n, r in diag.replays.items():
            groups.setdefault((r["replay"], r["reason"]), []).append(f"`{n}`")
        lines += ["How each experiment was re-simulated:", ""]
        lines += [f"- {kind} ({why}): {', '.join(names)}" for (kind, why), names in groups.items()]
        lines += [""]
    return lines


def _effects_lines(diag: Diagnosis) -> list[str]:
    if not diag.effects:
        return []
    rows = [
        [
            e.effect,
            _params_text(e.params),
            fmt(e.importance_pct, 1),
            fmt(e.gap_before, 4),
            fmt(e.gap_after, 4),
            fmt(e.shrink_pct, 1),
            FOUND_BY.get(e.selected_by, e.selected_by),
        ]
        for e in diag.effects
    ]
    header = ["effect", "fitted parameters", "importance [%]", "gap before", "gap after", "shrink [%]", "found by"]
    lines = ["Effects, in the order they were added (gaps on held-out experiments):", "", *table(header, rows), ""]
    lines += [f"- `{e.effect}`: {e.against_record}." for e in diag.effects if e.against_record]
    lines += [""] if any(e.against_record for e in diag.effects) else []
    lines += _held_out_fit_lines(diag)
    lines += [
        "Importance: removing each effect alone from the final rig (fitted on every record) reopens part of its gap; "
        "an effect's importance is its share of what the removals reopen. Shrink: how much the held-out gap fell "
        "when the effect was added.",
        "",
    ]
    if any(LATTICE in r[-1] for r in rows):
        lines += [
            f"Quantization is found by its signature in the data (every sample on an {LATTICE}), not by closing the "
            f"gap. It is kept although its shrink is negative, and has no importance (why: {manual('effects-found')}).",
            "",
        ]
    for e in (e for e in diag.effects if e.selected_by == SELECTED_BY_SPREAD):
        lines += [
            f"{e.effect} is sized by its spread in closed loop: its size is the one whose replays' spread between "
            "noise draws matches the record's gap on the fitted fold. It is kept by the held-out score that counts "
            f"that spread (why not least squares: {manual('effects-found')}).",
            "",
        ]
    return lines


def _held_out_fit_lines(diag: Diagnosis) -> list[str]:
    """Each held-out experiment's fit [%] before -> after each effect entered, a column per effect."""
    effects = [e for e in diag.effects if e.held_out_fit_pct]
    if not effects:
        return []
    names = list(dict.fromkeys(n for e in effects for n in e.held_out_fit_pct or {}))
    columns: dict[str, list[str]] = {}  # effects that entered together (a pair: the same fits) share a column
    for e in effects:
        fits = e.held_out_fit_pct or {}
        cells = [f"{fmt(fits[n][0], 1)} -> {fmt(fits[n][1], 1)}" if n in fits else "—" for n in names]
        same = next((k for k, c in columns.items() if c == cells), None)
        if same is not None:
            columns[f"{same} + {e.effect}"] = columns.pop(same)
        else:
            columns[e.effect] = cells
    rows = [[n, *(c[i] for c in columns.values())] for i, n in enumerate(names)]
    return [
        "Each held-out experiment's fit [%] before -> after each effect entered (where the evidence for it lies):",
        "",
        *table(["experiment", *columns], rows),
        "",
    ]


def _ci_halfwidth(ci95: list[float], fitted: float, nominal: float = 1.0) -> str:
    """A 95 % interval as +- its half-width, in % of the fitted value (the interval's ends agree to more digits
    than a table shows); of an offset about 0 (``nominal`` 0), in its own unit."""
    if len(ci95) != 2 or not all(math.isfinite(v) for v in ci95):
        return "—"
    half = (ci95[1] - ci95[0]) / 2.0
    return f"± {100.0 * half / abs(fitted):.2g} %" if fitted and nominal else f"± {half:.2g}"


def _folds_text(p: FittedParameter) -> str:
    """Recalibration alone on each fold, "a / b", with "(apart)" where their 95 % intervals exclude each other."""
    if not p.folds:
        return "—"
    return " / ".join(fmt_any(f[0]) for f in p.folds) + (" (apart)" if p.folds_disagree else "")


def _records_text(p: FittedParameter) -> str:
    """Each record's own fit, "a / b / c", with "(apart: a, b)" naming the records whose intervals exclude each
    other."""
    if not p.records:
        return "—"
    apart = sorted({n for pair in p.records_apart for n in pair}, key=list(p.records).index)
    return " / ".join(fmt_any(v[0]) for v in p.records.values()) + (f" (apart: {', '.join(apart)})" if apart else "")


def _parameters_lines(diag: Diagnosis) -> list[str]:
    if not diag.parameters:
        return []
    alone = any(p.recalibrated is not None for p in diag.parameters.values())
    per_fold = any(p.folds for p in diag.parameters.values())
    records = next((list(p.records) for p in diag.parameters.values() if p.records), [])
    rows = [
        [
            name,
            p.unit,
            fmt_any(p.nominal),
            fmt_any(p.fitted),
            _ci_halfwidth(p.ci95, p.fitted, p.nominal),
            fmt(p.change_pct, 1),
            p.finding or "—",
            *([fmt_any(p.recalibrated) if p.recalibrated is not None else "—"] if alone else []),
            *([_folds_text(p)] if per_fold else []),
            *([_records_text(p)] if records else []),
        ]
        for name, p in diag.parameters.items()
    ]
    note = " It was applied." if diag.recalibration_applied else " It closed too little to be kept."
    header = ["parameter", "unit", "nominal", "fitted", "95 % interval", "change [%]", "finding"]
    header += ["recalibration alone"] if alone else []
    header += ["each fold alone (A / B)"] if per_fold else []
    header += [f"each record alone ({' / '.join(records)})"] if records else []
    lines = [
        "Linear parameters of the simulation recalibrated against the data (within physical bounds): a linear "
        f"mismatch is a finding about the rig, not an effect.{note}",
        "",
        *table(header, rows),
        "",
    ]
    if per_fold:
        lines += [
            'Each fold alone: recalibrated on that fold\'s experiments only; "(apart)" where the two 95 % intervals '
            "exclude each other (the model, not the noise, separates the folds).",
            "",
        ]
    if records:
        lines += [
            "Each record alone: recalibrated on that record only, the effects held at their joint values; "
            '"(apart: ...)" names the records whose 95 % intervals exclude each other (the model does not describe '
            "them as one rig).",
            "",
        ]
    if alone:
        text = (
            "Fitted: jointly with the effects found, on every experiment (the interval, change and finding are this "
            "fit's). Recalibration alone: before any effect (geometric mean of the two folds' fits), what the "
            "waterfall's recalibration stage scores."
        )
        moves = diag.recalibration_moves()
        if any(p.kept for p in diag.parameters.values()):
            text += (
                " The linear parameters keep the spec's values: recalibrating them did not improve the held-out fit, "
                "and no effect was refitted jointly with them."
            )
        lines += [text, ""]
        if moves:
            lines += [
                "Where they differ, the linear parameters traded off against the effects "
                f"(why: {manual('fitted-and-recalibrated')}):",
                "",
                *(f"- {m}{'.' if i == len(moves) - 1 else ';'}" for i, m in enumerate(moves)),
                "",
            ]
    return lines


def sensor_lines(diag: Diagnosis) -> list[str]:
    """One line per record: its gauge offset as fitted (with its interval) or read at rest, and where its replay
    started the link."""
    out = []
    for name, r in (diag.sensors or {}).items():
        v, lo, hi = r.gauge_offset_deg
        how = f"95 % interval {lo:.4g}..{hi:.4g}" if math.isfinite(lo) else "its least squares in an open loop"
        text = f"{name}: gauge offset {v:.4g} deg ({how})"
        if r.link_start_deg is not None and r.link_rate_start_deg_s is not None:
            text += (f"; its replay starts the link at {r.link_start_deg:.3g} deg, "
                     f"{r.link_rate_start_deg_s:.3g} deg/s (its ring at the start)")  # fmt: skip
        out.append(text)
    return out


BEHAVIOUR_LABELS = {
    "overshoot_pct": "overshoot [%]",
    "settling_s": "settling [s]",
    "stop_error_deg": "stop error [deg]",
    "peak_alpha_deg": "peak alpha [deg]",
    "peak_u_v": "peak command [V]",
    "ring_alpha_deg": "ringing [deg RMS]",
    "ring_hz": "ringing [Hz]",
}


def behaviour_outside(diag: Diagnosis) -> dict[str, list[str]]:
    """Per closed-loop record, its measured metrics outside their replays' band ("stop error at 5 s (down)")."""
    out: dict[str, list[str]] = {}
    for name, rb in (diag.behaviour or {}).items():
        out[name] = [
            f"{BEHAVIOUR_LABELS[m].split(' [')[0]} at {st.start_s:.3g} s ({'up' if st.direction > 0 else 'down'})"
            for st in rb.steps
            for m, b in st.metrics.items()
            if math.isfinite(b.measured) and math.isfinite(b.lo) and not b.inside
        ]
    return out


def _sensors_lines(diag: Diagnosis) -> list[str]:
    """A row per record: its gauge offset as fitted, with its interval or how it was read, and where its replay
    started the link (the rows :func:`sensor_lines` words for the terminal)."""
    sensors = diag.sensors or {}
    if not sensors:
        return []
    fitted = any(math.isfinite(r.gauge_offset_deg[1]) for r in sensors.values())  # else open-loop least squares
    starts = [(r.link_start_deg, r.link_rate_start_deg_s) for r in sensors.values()]
    at_rest = all(a == 0.0 and b == 0.0 for a, b in starts)
    ring = not at_rest and any(a is not None and b is not None for a, b in starts)
    rows = []
    for name, r in sensors.items():
        v, lo, hi = r.gauge_offset_deg
        row = [name, f"{v:.4g}"]
        row += [f"{lo:.4g}..{hi:.4g}" if math.isfinite(lo) else "— (least squares, open loop)"] if fitted else []
        start = (r.link_start_deg, r.link_rate_start_deg_s)
        row += [f"{x:.3g}" if x is not None else "—" for x in start] if ring else []
        rows.append(row)
    header = ["record", "gauge offset [deg]", *(["95 % interval"] if fitted else [])]
    header += ["replay's link start [deg]", "its rate [deg/s]"] if ring else []
    how = "" if fitted else " (by least squares in an open loop)"
    link = "; where its replay started the link, its ring at the start from the data" if ring else ""
    link = "; every replay starts the link at rest" if at_rest else link
    return [
        f"Each record's strain-gauge offset as fitted, its reading of the link at rest in the record's own zero{how}"
        f"{link} ({manual('sensors-behaviour-and-replays')}):",
        "",
        *table(header, rows),
        "",
    ]


def _behaviour_lines(diag: Diagnosis) -> list[str]:
    if not diag.behaviour:
        return []
    lines = [
        "Behaviour step by step, as the record measured it and as the final rig replays it: median and 95 % band "
        "of replays with other noise draws and other draws of the fitted parameters, what the model says the record "
        f"may do ({manual('sensors-behaviour-and-replays')}). Outside its band: **bold**.",
        "",
    ]
    for name, rb in diag.behaviour.items():
        rows = []
        for st in rb.steps:
            for m, b in st.metrics.items():
                if not math.isfinite(b.measured) and not math.isfinite(b.median):
                    continue
                cell = fmt(b.measured, 3)
                cell = f"**{cell}**" if math.isfinite(b.lo) and math.isfinite(b.measured) and not b.inside else cell
                step = f"{st.start_s:.3g} s {'up' if st.direction > 0 else 'down'} {st.size_deg:.3g} deg"
                rows.append([step, BEHAVIOUR_LABELS.get(m, m), cell, fmt(b.median, 3),
                             f"{fmt(b.lo, 3)}..{fmt(b.hi, 3)}"])  # fmt: skip
        lines += [f"{name}: {fmt(100.0 * rb.coverage, 0)} % of its metrics inside their bands.", ""]
        lines += [*table(["step", "metric", "measured", "median", "95 % band"], rows), ""]
    return lines


def _decomposition_lines(diag: Diagnosis, figure: str | None) -> list[str]:
    rows = diag.waterfall()
    noise = diag.gap.decomposition.noise_floor
    body = [[stage, fmt(g, 4), fmt(100.0 * (1.0 - g), 2), fmt(c, 1)] for stage, g, c in rows]
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


def _overall_lines(diag: Diagnosis) -> list[str]:
    gap = diag.gap
    held, b, a = gap.held_out, gap.before, gap.after
    rows = [
        [
            "in sample (one experiment in both folds)" if _in_sample(diag) else "held out (fitted on the other fold)",
            fmt(held.gap_before, 4),
            fmt(held.gap_after, 4),
            fmt(held.fit_pct_before),
            fmt(held.fit_pct_after),
        ],
        ["all experiments, final parameters", fmt(b.gap, 4), fmt(a.gap, 4), fmt(b.fit_pct), fmt(a.fit_pct)],
    ]
    lines = [
        *table(["gap", "before", "after", "fit before [%]", "fit after [%]"], rows),
        "",
        f"Held-out shrink {fmt(gap.shrink_pct, 1)} % (in sample {fmt(gap.shrink_pct_in_sample, 1)} %).",
        "",
    ]
    dec = gap.decomposition
    if dec.channels:
        stages = {"before": "as given", "after_recalibration": "recalibrated", "after_effects": "with the effects"}
        body = [
            [stages.get(k, k), *(fmt(by.get(c, math.nan)) for c in ("theta", "alpha"))]
            for k, by in dec.channel_stages()
        ]
        lines += [
            *table(["held-out fit [%]", "theta", "alpha"], body),
            "",
            f"{stages[dec.last_stage()].capitalize()}, "
            + (
                "what is left is within the replays' own spread."
                if dec.at_floor()
                else f"the gap is in {dec.gap_channel()}: the channel that fits worse."
            ),
            "",
        ]
    return lines


def _channels(fit_pct: dict[str, float], channels: list[str]) -> str:
    return ", ".join(fmt(fit_pct.get(k)) for k in channels) or "—"


def _experiments_lines(diag: Diagnosis) -> list[str]:
    before, after = diag.gap.before.experiments, diag.gap.after.experiments
    if not before:
        return []
    chans = list(dict.fromkeys(k for e in [*before.values(), *after.values()] for k in e.fit_pct))
    rows = []
    for name, eb in before.items():
        ea = after.get(name)
        rows.append(
            [
                name,
                diag.folds.role(name),
                _channels(eb.fit_pct, chans),
                _channels(ea.fit_pct, chans) if ea else "—",
                fmt(eb.gap, 4),
                fmt(ea.gap, 4) if ea else "—",
            ]
        )
    of = f" ({', '.join(chans)})" if chans else ""
    header = ["experiment", "fold", f"fit before [%]{of}", f"fit after [%]{of}", "gap before", "gap after"]
    split = diag.folds.scheme.split(";", 1)[1].strip() + "; " if ";" in diag.folds.scheme else ""  # a lone record
    intro = (
        "Per experiment (2-fold cross-fit: fitted on one fold, scored on the other, so every experiment is held out "
        f"once; {split}'after' here uses the final parameters):"
    )
    if _in_sample(diag):
        intro = (
            "Per experiment: one experiment, in both folds, so the 'held-out' figures of this file are in-sample "
            "('after' uses the final parameters):"
        )
    return [intro, "", *table(header, rows), ""]


def _in_sample(diag: Diagnosis) -> bool:
    """A diagnosis whose lone experiment was both folds (older files): its held-out figures are in-sample."""
    return bool(diag.folds.A) and diag.folds.A == diag.folds.B


def _candidates_lines(diag: Diagnosis) -> list[str]:
    if not diag.candidates:
        return []
    rows = [
        [c.effect, _params_text(c.params), fmt(c.held_out_share_pct, 1), fmt(c.shrink_pct, 1), c.note or "—"]
        for c in diag.candidates
    ]
    header = ["candidate", "fitted parameters", "closes [%] of the excess", "shrink [%]", "note"]
    return ["Candidates, each alone on the first round (held out):", "", *table(header, rows), ""]


def _noise_lines(diag: Diagnosis) -> list[str]:
    n = diag.noise_floor
    lines = [
        f"Noise floor (from the data, {n.method}): gap {fmt(n.gap, 4)} (fit {fmt(n.fit_pct)} %), theta "
        f"{fmt_any(n.theta_deg)} deg rms, alpha {fmt_any(n.alpha_deg)} deg rms.",
        "",
    ]
    if diag.calibration.gauge_delay_method:
        how = "every replay reads it so" if diag.calibration.gauge_delay_s else "read from the records"
        lines += [f"Gauge timing ({how}): {diag.calibration.gauge_delay_method}.", ""]
    return lines


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


def _speed_lines(speed: Any) -> list[str]:
    """The hub's speed per volt by amplitude over the open-loop square waves (``where.speed_per_volt``): the finding,
    a row per amplitude, and the records not read."""
    if not isinstance(speed, dict) or not speed.get("line"):
        return []
    lines = [f"In amplitude, from the open-loop square waves: {speed['line']}.", ""]
    rows = [
        [fmt(num(a["amplitude_v"]), 3), str(a["n_plateaus"]), str(a["n_still"]), fmt(num(a["speed_per_volt"]), 1),
         fmt(100.0 * num(a["relative"]), 0), ", ".join(a["records"])]
        for a in speed.get("amplitudes") or []
    ]  # fmt: skip
    if rows:
        header = ["amplitude [V]", "plateaus", "at rest", "speed per volt [deg/s/V]", "of the linear gain [%]",
                  "records"]  # fmt: skip
        lines += [*table(header, rows), ""]
    skipped = speed.get("skipped") or {}
    if skipped:
        lines += ["Not read: " + "; ".join(f"{k} ({v})" for k, v in skipped.items()) + ".", ""]
    return lines


def _where_lines(diag: Diagnosis) -> list[str]:
    where = diag.where
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
        if all(r[-1] != "—" for r in rows):  # each finding says its band, amplitude law and events: not twice
            header, rows = [*header[:2], header[-1]], [[*r[:2], r[-1]] for r in rows]
        lines += ["Where the gap is (pooled over experiments; per experiment in `diagnosis.json`):", ""]
        lines += [*table(header, rows), ""]
        used = (where.get("after_recalibration") or {}).get("parameters")
        if isinstance(used, dict):
            what = ", ".join(f"{k.split('.', 1)[-1]} {fmt_any(v)}" for k, v in used.items())
            lines += [
                "After recalibration: the simulation with the linear parameters recalibration alone fitted, before any "
                f"effect ({what})."
                if used
                else "After recalibration: recalibration was not applied (it did not "
                "improve the held-out fit), so this is the simulation as given.",
                "",
            ]
    lines += _speed_lines(where.get("speed_per_volt"))
    masked = where.get("masked")
    if isinstance(masked, dict) and masked:
        share = ", ".join(f"{k} {fmt(100.0 * num(v), 1)} %" for k, v in masked.items())
        lines += [f"Samples masked as invalid (pot dead band, ADC clipping) and left out of every gap: {share}.", ""]
    return lines


def diagnosis_markdown(diag: Diagnosis, waterfall_figure: str | None = None) -> list[str]:
    """Markdown lines summarising the diagnosis for a person: verdict and what it means, recalibrated parameters,
    effects with their importance, the gap stage by stage (with ``waterfall_figure`` when given), overall and
    per-experiment gaps with the folds, first-round candidates, noise floor and where the gap is."""
    lines = _verdict_lines(diag)
    lines += _parameters_lines(diag)
    lines += _sensors_lines(diag)
    lines += _effects_lines(diag)
    lines += _decomposition_lines(diag, waterfall_figure)
    lines += _overall_lines(diag)
    lines += _experiments_lines(diag)
    lines += _behaviour_lines(diag)
    lines += _candidates_lines(diag)
    lines += _noise_lines(diag)
    return wrap_prose(lines + _where_lines(diag))
