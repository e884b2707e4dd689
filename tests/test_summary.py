"""A summary that fits one screen (issue 65, item 3): what every command prints when its work is done is at most 40
lines of at most 100 characters, tables included, on the lab run and on an imported closed-loop unit; a list longer
than five items is cut with "and N more (see FILE)", a long caveat to its first sentence and where the rest is."""

from __future__ import annotations

import copy
import io
import json
import os
import shutil
import subprocess
import sys

import pytest

from harness import cli
from harness.diagnosis.result import Diagnosis
from harness.pipeline import PipelineResult
from harness.render.summary import MAX_LINES, WIDTH, Summary, brief, cut, joined

ONE_SCREEN = {"COLUMNS": str(WIDTH), "FLEXJOINT_WORKERS": "1"}


def _console(monkeypatch: pytest.MonkeyPatch) -> tuple[io.StringIO, object]:
    """A console made as the command line makes ``out`` (its width from $COLUMNS when piped), at 100 columns."""
    monkeypatch.setenv("COLUMNS", str(WIDTH))
    buf = io.StringIO()
    return buf, cli._LazyConsole(highlight=False, file=buf)


def _on_one_screen(text: str) -> list[str]:
    lines = text.rstrip("\n").splitlines()
    assert len(lines) <= MAX_LINES, f"{len(lines)} lines:\n{text}"
    too_wide = [x for x in lines if len(x.rstrip()) > WIDTH]
    assert not too_wide, too_wide
    assert "…" not in text
    return lines


def _flat(lines: list[str]) -> str:
    """The lines as one line (the wrapping's breaks and indents as single spaces)."""
    return " ".join(" ".join(lines).split())


def _as_out(monkeypatch: pytest.MonkeyPatch) -> None:
    """The command line's ``out`` (which a table is fitted to) made at 100 columns."""
    monkeypatch.setattr(cli, "out", _console(monkeypatch)[1])


def _printed(summary: Summary, monkeypatch: pytest.MonkeyPatch) -> list[str]:
    buf, console = _console(monkeypatch)
    summary.print(console)  # type: ignore[arg-type]
    return _on_one_screen(buf.getvalue())


def _flexjoint(*args: object) -> subprocess.CompletedProcess:
    """The command with stdout piped and COLUMNS=100, as a CI log or ``| less`` in a 100-column terminal."""
    return subprocess.run([sys.executable, "-m", "harness", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env={**os.environ, **ONE_SCREEN})  # fmt: skip


# ----------------------------------------------------------------------------------------------- the rule


def test_a_list_longer_than_five_is_cut_naming_the_file_that_holds_it():
    items = [f"r{i}" for i in range(8)]
    assert cut(items[:5], "diagnosis.json") == items[:5]
    assert cut(items, "diagnosis.json") == [*items[:5], "and 3 more (see diagnosis.json)"]
    assert joined(items, "grid.csv") == "r0, r1, r2, r3, r4, and 3 more (see grid.csv)"


def test_a_long_caveat_keeps_its_first_sentence_and_its_conclusion():
    pairs = " and ".join(f"test_{i} 1.{i} [1.01-1.{i + 1}] / test_{i + 1} 2.{i} [2.01-2.{i + 1}]" for i in range(45))
    caveat = (
        f"recalibrated on each record alone, the 95 % intervals exclude each other (drive gain {pairs}): "
        "the linear model with saturation does not describe these records as one rig (model error, not noise)"
    )
    assert len(caveat) > 2500  # 45 pairs of records
    assert brief(caveat, "diagnosis.json") == (
        "recalibrated on each record alone, the 95 % intervals exclude each other (...): the linear model with "
        "saturation does not describe these records as one rig (model error, not noise) (see diagnosis.json)"
    )
    short = "verdict 'backlash' reached with hub inertia at its upper bound"
    assert brief(short, "diagnosis.json") == short  # whole when short
    long = "First sentence, said plainly. " + "Then a second one that goes on " * 10
    assert brief(long, "report.md") == "First sentence, said plainly ... (see report.md)"
    words = brief("word " * 100, "x.json")
    assert words.endswith("word ... (see x.json)") and len(words) <= 200 + len(" ... (see x.json)")


def test_a_summary_too_long_keeps_its_first_lines_and_where_the_detail_is(monkeypatch):
    s = Summary("grid.csv")
    s.lines(f"line {i}: " + "word " * 29 + "word" for i in range(30))  # 2 terminal lines each
    s.close("full detail: RUN/grid.csv")
    lines = _printed(s, monkeypatch)
    assert len(lines) == MAX_LINES and lines[-1] == "full detail: RUN/grid.csv"
    assert lines[-2] == "and 22 more lines (see grid.csv)" and lines[-3].startswith("    word")  # whole lines out
    assert lines[1].startswith("    word") and "%" not in lines[1]  # a wrapped line's continuation, indented
    assert str(s).splitlines()[0] == "line 0: " + "word " * 29 + "word"  # the text, unwrapped


# ----------------------------------------------------------------------------------------------- the lab run


def test_diagnose_and_run_on_the_lab_run_fit_one_screen(diagnosed_run, monkeypatch):
    d = Diagnosis.load(diagnosed_run)
    lines = _printed(cli.diagnosis_screen(d, diagnosed_run), monkeypatch)
    text = "\n".join(lines)
    assert lines[0] == f"verdict: {d.verdict}" and "held-out fit: before " in text and "noise floor" in text
    assert "+ coulomb_friction (plant.coulomb_torque=" in text and "+ delay (daq.delay_samples=1)" in text
    assert "parameters that moved most:" in text and "more (see diagnosis.json)" in text
    detail = f"full detail: {diagnosed_run / 'diagnosis.json'}, report.md (flexjoint report {diagnosed_run})"
    assert _flat(lines).endswith(detail)
    result = PipelineResult("RUN: selected ARMAX(3,2,2,1); cross-fit average 79.92 %; acceptance passed; "
                            "diagnosis coulomb_friction + delay; 40 s", {"build": 0.1, "campaign": 3.0})  # fmt: skip
    lines = _printed(cli.run_screen(result, diagnosed_run), monkeypatch)
    assert lines[0].startswith("RUN: selected ARMAX") and f"verdict: {d.verdict}" in lines  # ends with the diagnosis


def test_identify_and_crossfit_on_the_lab_run_fit_one_screen(diagnosed_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(diagnosed_run, run)
    grid = [x for g in ("na=[2, 4]", "nb=[1, 2]", "nc=[1, 2]") for x in ("--set", f"identify.{g}")]
    r = _flexjoint("identify", run, *grid)
    assert r.returncode == 0, r.stderr
    lines = _on_one_screen(r.stdout)
    assert any(x.strip().startswith("│ sel (") for x in lines) and "datasets: 1 " in r.stdout
    assert _flat(lines).endswith(f"full detail: {run / 'grid.csv'}, {run / 'models'}")
    r = _flexjoint("crossfit", run)
    assert r.returncode == 0, r.stderr
    lines = _on_one_screen(r.stdout)
    assert any(x.strip().startswith("│ selected") for x in lines) and _flat(lines).endswith(f"{run / 'crossfit.csv'}")
    # every number of crossfit.csv's selected row is on the screen, rounded as it was
    csv = (run / "crossfit.csv").read_text().splitlines()
    sel = next(x for x in csv if x.startswith("selected,")).split(",")[1:]
    row = next(x for x in lines if x.strip().startswith("│ selected")).replace("│", " ").split()[1:]
    assert row == [f"{float(v):.2f}" for v in sel]


# ----------------------------------------------------------------------------------------------- a closed-loop unit


def _unit_of_ten(d: Diagnosis) -> Diagnosis:
    """The imported closed-loop record's diagnosis made a unit of ten records, as a real unit's: a gauge offset,
    a behaviour, a fit and a replay (its controller's own R^2) each, and the caveat that lists every pair of records
    whose intervals exclude each other (45 pairs, 3,000 characters)."""
    doc = d.to_dict()
    names = [f"unit_{i:02d}" for i in range(10)]
    sensor = next(iter(doc["sensors"].values()))
    behaviour = next(iter(doc["behaviour"].values()))
    doc["sensors"] = {n: copy.deepcopy(sensor) for n in names}
    doc["behaviour"] = {n: copy.deepcopy(behaviour) for n in names}
    doc["gap"]["records"] = {n: {"own": 90.0 + i / 10, "joint": 89.0 + i / 10} for i, n in enumerate(names)}
    doc["replays"] = {n: {"replay": "closed", "reason": f"a closed-loop record with its controller (identified, R^2 "
                          f"0.9{i:02d})"} for i, n in enumerate(names)}  # fmt: skip
    pairs = " and ".join(f"{a} -0.0{i} [-0.05--0.01] / {b} 0.0{i} [0.01-0.05]"
                         for i, (a, b) in enumerate((a, b) for a in names for b in names if a < b))  # fmt: skip
    doc["caveats"] = [
        f"recalibrated on each record alone, the 95 % intervals exclude each other (command offset {pairs}): the "
        "linear model with second_mode does not describe these records as one rig (model error, not noise)",
        *(f"caveat number {i}, short" for i in range(6)),
    ]
    return Diagnosis.from_dict(json.loads(json.dumps(doc)))


def test_diagnose_on_an_imported_closed_loop_unit_fits_one_screen(quanser_run, monkeypatch):
    d = Diagnosis.load(quanser_run)
    text = "\n".join(_printed(cli.diagnosis_screen(d, quanser_run), monkeypatch))
    assert f"verdict: {d.verdict}" in text and "replay: closed" in text and "each record's step metrics" in text
    unit = _unit_of_ten(d)
    assert len(unit.caveats[0]) > 2500  # 45 pairs of records
    lines = _printed(cli.diagnosis_screen(unit, quanser_run), monkeypatch)
    text = _flat(lines)
    assert "unit_04 90.4 -> 89.4 %" in text and "unit_05 " not in text  # five records of ten, then:
    assert text.count("and 5 more (see diagnosis.json)") >= 2  # fits, gauge offsets (behaviour, when it fits)
    assert "exclude each other (...): the linear model with second_mode does not describe these records as one rig" in (
        text
    )
    assert "caveat number 3, short" in text and "caveat number 4" not in text
    assert "and 2 more (see diagnosis.json)" in text  # the caveats past five
    assert "replay: closed, 10 experiments (a closed-loop record with its controller (identified, R^2 0.900)), and " \
        "9 more reasons (see diagnosis.json)" in text  # fmt: skip
    assert text.endswith(f"full detail: {quanser_run / 'diagnosis.json'}, report.md (flexjoint report {quanser_run})")
    # the file keeps everything: the summary only says less
    assert unit.to_dict()["caveats"][0] == unit.caveats[0] and len(unit.sensors or {}) == 10


def test_predict_design_and_blindtest_summaries_fit_one_screen(monkeypatch, tmp_path):
    """Their summaries from what they wrote: a prediction of eight metrics measured on a record and seven specs, a
    design of seven specs, the blind test of every family with the wrong-sheet rows."""
    from harness.diagnosis import blindtest as bt

    band = {"median": 1.234, "lo": 1.0, "hi": 1.5, "measured": 1.3}
    metrics = {f"metric_{i}": band for i in range(8)} | {"ring_hz": band}
    specs = {f"s{i}": {"spec": f"spec {i} <= {i}", "predicted": 1.0, "met": True} for i in range(7)}
    doc = {"metrics": metrics, "fit_pct": {"theta": 97.0, "alpha": 92.2}, "specs": specs, "passed": True}
    lines = _printed(cli.prediction_screen(doc, tmp_path, 200), monkeypatch)
    assert lines[1] == "  metric_0 1.234 [1..1.5], measured 1.3" and "  and 3 more (see prediction.json)" in lines
    assert "ring_hz" not in _flat(lines) and "spec 4 <= 4, and 2 more (see prediction.json))" in _flat(lines)
    design = {"parameters": {"q_theta": 30.0, "r": 1.0}, "linear": {"disk_margin": 0.834}, "specs": specs}
    lines = _printed(cli.design_screen(design, "lqr", tmp_path), monkeypatch)
    assert lines[1] == "spec 0 <= 0: predicted 1 (met)" and "and 2 more (see design.json)" in lines
    cases = [{"case": i, "family": f, "kind": "none", "truth_effects": [], "score": {"verdict": "none",
              "correct": True, "turned_into_effect": False, "shrink_pct": 0.0, "fitted": {}}}
             for i, f in enumerate((*bt.FAMILIES, "wrong_sheet", "real_like"))]  # fmt: skip
    _as_out(monkeypatch)
    s = Summary("blindtest.json")
    s.table(cli._table(cli.blindtest_table(bt.totals(cases))))
    s.close(f"6 cases in 100 s -> {tmp_path / 'blindtest.json'}")
    lines = _printed(s, monkeypatch)
    assert "and 4 more (see blindtest.json)" in _flat(lines)  # nine targets, five shown


def test_a_matrix_of_more_than_ten_datasets_shows_the_first_nine(monkeypatch):
    """The cross-fit of twelve datasets: its first nine, their average over all twelve, and where the rest is."""
    import numpy as np
    import pandas as pd

    names = [f"record_{i:02d}" for i in range(12)]
    df = pd.DataFrame(np.arange(13 * 12).reshape(13, 12) / 3, index=[*names, "selected"], columns=names)
    df["average"] = df.mean(axis=1)
    _as_out(monkeypatch)
    s = Summary("crossfit.csv")
    s.table(cli._table(cli.crossfit_table(df)))
    lines = _printed(s, monkeypatch)
    header = next(x for x in lines if x.strip().startswith("┃ model")).replace("┃", " ").split()
    assert header == ["model", *map(str, range(1, 10)), "average"]
    rows = [x.replace("│", " ").split() for x in lines if x.startswith("│")]
    assert [r[0] for r in rows] == [*map(str, range(1, 10)), "selected"]
    assert rows[-1][1:] == [f"{v:.2f}" for v in (*df.loc["selected", names[:9]], df.loc["selected", "average"])]
    assert "9 record_08, and 3 more (see crossfit.csv)" in _flat(lines)
