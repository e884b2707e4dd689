"""Run directories that cannot lie: a new run never mixes with an old one, artefacts made from other data are
refused or left out, an interrupted run leaves nothing, and values a rig cannot have are refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader
from test_cli import TINY, _one_line_error, flexjoint

from harness import spec as specmod
from harness.ident.accept import accept
from harness.ident.calibration import calibrate_run
from harness.ident.crossfit import crossfit_run
from harness.ident.identify import identify_run
from harness.render import viewer
from harness.render.load import load_results
from harness.render.report import write_report
from harness.render.viewer import log_run
from harness.rig import campaign as campaign_mod
from harness.rig.campaign import run_campaign
from harness.rundir import DataError, Manifest, RunDir, read_dataset, record_inputs, stale_artefacts, write_dataset

GRID = {"na": [2, 3], "nb": [1, 2], "nc": [1, 2], "doubled_rate": False}


def _small_lab() -> specmod.Spec:
    """The lab spec with its calibration experiments and two 20 s identification experiments, a small grid."""
    raw = specmod.apply_overrides(specmod.load("lab").raw, [])
    raw["experiment"] = [dict(e, duration=20.0) for e in raw["experiment"] if e["name"] in ("prbs_b010", "square_040")]
    raw["identify"] = {**raw.get("identify", {}), **GRID}
    return specmod.from_dict(raw, "lab.toml")


@pytest.fixture(scope="module")
def identified(tmp_path_factory) -> Path:
    """A campaign, calibrated, identified and cross-fitted (no diagnosis: not needed here)."""
    run = tmp_path_factory.mktemp("rundir") / "lab"
    run_campaign(_small_lab(), run, workers=1)
    calibrate_run(run)
    identify_run(run)
    crossfit_run(run)
    return run


def _copy(run: Path, dest: Path) -> Path:
    shutil.copytree(run, dest)
    return dest


def _files(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def test_the_fixture_accepts_and_records_what_each_artefact_was_made_from(identified):
    assert accept(identified).passed
    rec = Manifest.load(identified).artefacts
    assert set(rec) == {"calibration.json", "models", "grid.csv", "crossfit.csv"}
    assert rec["models"]["data"] == rec["crossfit.csv"]["data"] == rec["calibration.json"]["data"]
    assert stale_artefacts(identified) == {}


def test_campaign_onto_an_identified_run_is_refused_and_force_removes_the_old_run(identified, tmp_path):
    run = _copy(identified, tmp_path / "run")
    spec = tmp_path / "tiny.toml"
    spec.write_text(TINY)
    before = _files(run)
    line = _one_line_error(flexjoint("campaign", spec, "--out", run))
    assert "already holds a run" in line and "--force" in line and "--out" in line
    assert _files(run) == before  # nothing touched
    r = flexjoint("campaign", spec, "--out", run, "--force")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in run.iterdir()) == ["data", "manifest.json"]
    assert sorted(p.name for p in (run / "data").iterdir()) == ["sq.parquet"]
    m = Manifest.load(run)
    assert {"calibration.json", "models/", "grid.csv", "crossfit.csv", "data/"} <= set(m.removed)
    line = _one_line_error(flexjoint("accept", run))  # the old model is gone, not "accepted" on new data
    assert "no selected model" in line
    assert not list(tmp_path.glob(".run.*"))  # no aside left behind


def test_import_onto_a_run_is_refused_and_force_replaces_it(identified, tmp_path):
    run = _copy(identified, tmp_path / "run")
    t = np.arange(400) * 0.02
    pd.DataFrame({"t": t, "u": np.sign(np.sin(t)), "theta_v": 0.01 * t, "alpha_v": 0 * t}).to_csv(
        tmp_path / "rec.csv", index=False
    )
    line = _one_line_error(flexjoint("import", tmp_path / "rec.csv", "--out", run))
    assert "already holds a run" in line and "--force" in line
    assert (run / "models" / "selected.json").exists()
    r = flexjoint("import", tmp_path / "rec.csv", "--out", run, "--force")
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in run.iterdir()) == ["calibration.json", "data", "manifest.json"]
    m = Manifest.load(run)
    assert m.kind == "import" and "models/" in m.removed and [e.name for e in m.experiments] == ["rec"]


def _other_data(run: Path) -> None:
    """Replace one identification dataset by other data (the command 2 % larger), as a hand copy would."""
    p = RunDir(run).dataset("square_040")
    df = read_dataset(p)
    write_dataset(p, {c: (df[c] * 1.02 if c == "u" else df[c]).to_numpy() for c in df.columns})


def test_accept_refuses_models_made_from_other_data(identified, tmp_path):
    run = _copy(identified, tmp_path / "run")
    _other_data(run)
    line = _one_line_error(flexjoint("accept", run))
    assert line == "error: models/ were identified from other data than data/ now holds: re-run flexjoint identify"
    with pytest.raises(DataError, match="models/ were identified from other data"):
        accept(run)
    identify_run(run)  # the models again, from these data: the cross-fit is now the stale one
    with pytest.raises(DataError, match="crossfit.csv was computed from other data than data/ now holds"):
        accept(run)
    crossfit_run(run)
    assert accept(run).passed


def test_report_leaves_out_and_names_what_was_made_from_other_data(identified, tmp_path):
    run = _copy(identified, tmp_path / "run")
    _other_data(run)
    res = load_results(run)
    assert set(res.stale) == {"calibration.json", "models", "grid.csv", "crossfit.csv"}
    assert res.models == {} and res.crossfit is None and res.grid is None
    text = write_report(run, res).read_text()
    assert "- models/ were identified from other data than data/ now holds: re-run flexjoint identify" in text
    assert "crossfit.csv was computed from other data" in text
    assert "| selected |" not in text  # no cross-fit row of the old model


def test_diagnose_out_onto_another_run_is_refused_and_never_touches_either(identified, tmp_path):
    real = _copy(identified, tmp_path / "real")
    other = _copy(identified, tmp_path / "other")
    real_before, other_before = _files(real), _files(other)
    line = _one_line_error(flexjoint("diagnose", "--real", real, "--out", other, "--workers", "1"))
    assert "another run" in line and "--force" in line
    assert _files(real) == real_before and _files(other) == other_before


def test_a_diagnosis_written_into_another_run_is_flagged_as_of_that_run(identified, tmp_path):
    real = _copy(identified, tmp_path / "real")
    other = _copy(identified, tmp_path / "other")
    (other / "diagnosis.json").write_text("{}")  # what diagnose --force writes there; its content is not read here
    record_inputs(other, "diagnosis.json", source=real)
    assert Manifest.load(other).artefacts["diagnosis.json"]["run"] == "../real"
    assert "diagnosis.json" not in stale_artefacts(other)  # a copy: the same data, so a diagnosis of these data
    _other_data(real)
    record_inputs(other, "diagnosis.json", source=real)
    assert stale_artefacts(other)["diagnosis.json"] == (
        "diagnosis.json was made from the data of another run (../real), not from data/ here: re-run flexjoint "
        "diagnose on this directory"
    )
    record_inputs(other, "diagnosis.json")  # diagnosed from its own data
    assert "diagnosis.json" not in stale_artefacts(other)


def test_an_interrupted_campaign_leaves_no_partial_folder_and_an_old_run_intact(identified, tmp_path, monkeypatch):
    calls = []

    def interrupted(path, cols):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        write_dataset(path, cols)

    monkeypatch.setattr(campaign_mod, "write_dataset", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(_small_lab(), tmp_path / "new", workers=1)
    assert list(tmp_path.iterdir()) == []  # neither the run nor its aside
    old = _copy(identified, tmp_path / "old")
    before = _files(old)
    calls.clear()
    with pytest.raises(KeyboardInterrupt):
        run_campaign(_small_lab(), old, workers=1, force=True)
    assert _files(old) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]


@pytest.mark.parametrize(
    "setting, words",
    [
        ("plant.backlash=1e9", "[plant].backlash = 1e+09 is outside its physical range [0, 0.2] rad"),
        ("daq.adc_bits=99", "[daq].adc_bits = 99 is outside its physical range [0, 52]"),
        ("plant.eta_g=1.5", "[plant].eta_g = 1.5 is outside its physical range [0, 1]"),
        ("accept.min_fit=101", "[accept].min_fit = 101: a fit threshold is a percentage in 0..100"),
    ],
)
def test_set_values_outside_their_physical_range_are_refused(tmp_path, setting, words):
    line = _one_line_error(flexjoint("campaign", "lab", "--out", tmp_path / "r", "--set", setting))
    assert words in line
    assert not (tmp_path / "r").exists()


def test_a_spec_value_outside_its_range_is_refused():
    raw = specmod.apply_overrides(specmod.load("lab").raw, [])
    raw["experiment"][0]["plant"] = {"backlash": 0.5}
    with pytest.raises(specmod.SpecError, match=r"plant.backlash = 0.5 is outside its physical range \[0, 0.2\] rad"):
        specmod.from_dict(raw, "x.toml")


@pytest.mark.parametrize("option, value", [("--min-fit", "101"), ("--min-average-fit", "-5"), ("--min-fit", "nan")])
def test_accept_thresholds_outside_0_100_are_refused(tmp_path, option, value):
    (tmp_path / "models").mkdir()
    Manifest(kind="campaign", spec={}, experiments=[], sample_rate=50.0).write(tmp_path)
    (tmp_path / "models" / "selected.json").write_text(json.dumps({"cv": {"a": 99.0}}))
    assert flexjoint("accept", tmp_path).returncode == 0
    line = _one_line_error(flexjoint("accept", tmp_path, option, value))
    assert f"{option} = " in line and "a fit threshold is a percentage in 0..100" in line


def _rrd_content(path: Path) -> list[tuple[str, str, pa.RecordBatch]]:
    """What a recording holds, store by store, without what Rerun stamps with the clock: its chunk and row ids (time
    based) and the blueprint's log_time."""
    reader = RrdReader(path)
    out = []
    for store in [*reader.recordings(), *reader.blueprints()]:
        for chunk in reader.stream(store=store):
            rb = chunk.to_record_batch()
            keep = [n for n in rb.schema.names if n not in ("rerun.controls.RowId", "log_time")]
            out.append((store.kind, chunk.entity_path, rb.select(keep).replace_schema_metadata(None)))
    return out


def test_report_twice_writes_the_same_run_rrd_bytes(identified, tmp_path):
    run = _copy(identified, tmp_path / "run")
    sizes = []
    for _ in range(2):  # two processes: the same bytes whatever the clock, the threads and the hash seed
        r = flexjoint("report", run)
        assert r.returncode == 0, r.stderr
        sizes.append((run / "run.rrd").read_bytes())
    assert sizes[0] == sizes[1]


def test_the_stable_recording_holds_what_rerun_wrote(identified, tmp_path, monkeypatch):
    stable = log_run(identified, rrd=tmp_path / "stable.rrd")
    monkeypatch.setattr(viewer, "make_stable", lambda path: None)
    raw = log_run(identified, rrd=tmp_path / "raw.rrd")
    assert raw.read_bytes() != stable.read_bytes()
    a, b = _rrd_content(stable), _rrd_content(raw)
    assert sorted(x[:2] for x in a) == sorted(x[:2] for x in b)
    assert ("recording", "/__properties") in [x[:2] for x in a]  # the recording's name
    by_place = {}
    for kind, entity, rb in b:
        by_place.setdefault((kind, entity), []).append(rb)
    for kind, entity, rb in a:
        assert any(rb.equals(other) for other in by_place[(kind, entity)]), f"{kind} {entity}"


@pytest.mark.parametrize(
    "command",
    [
        ("run", "--workers", "1"),
        ("sweep", "lab", "--vary", "plant.Ks=normal(1.3,0.05)", "--n", "2", "--orders", "2,1,1", "--workers", "1"),
    ],
)
def test_run_and_sweep_onto_a_run_are_refused_before_any_work(identified, tmp_path, command):
    run = _copy(identified, tmp_path / "run")
    before = _files(run)
    line = _one_line_error(flexjoint(*command, "--out", run))
    assert f"--out {run}" in line and ("already holds a run" in line or "holds a run" in line)
    assert _files(run) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_what_was_made_from_a_stale_input_is_stale_and_crossfit_refuses_stale_models(identified, tmp_path):
    run = _copy(identified, tmp_path / "run")
    m = Manifest.load(run)
    m.artefacts["calibration.json"]["data"] = "0" * 64  # as if calibrated from other data than data/ holds
    m.write(run)
    stale = stale_artefacts(run)
    assert stale["calibration.json"].startswith("calibration.json was made from other data than data/ now holds")
    assert stale["models"] == "models/ were identified from calibration.json, which is stale: re-run flexjoint identify"
    assert stale["crossfit.csv"] == "crossfit.csv was computed from models/, which is stale: re-run flexjoint identify"
    with pytest.raises(DataError, match="models/ were identified from calibration.json, which is stale"):
        crossfit_run(run)
    identify_run(run)  # calibrates again (the calibration experiments are in data/), then the models: the same bytes,
    assert stale_artefacts(run) == {}  # so the cross-fit made from them is current again
