"""run.rrd read back with rerun.chunk.RrdReader (rerun-sdk 0.41): the data checked against its inputs, and the
blueprint checked view by view: every view's contents resolve to entities that hold data of the view's kind,
static or on the time panel's timeline, so no view opens blank."""

from __future__ import annotations

import json
import shutil
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from harness.ident import armax
from harness.render import figures
from harness.render.viewer import APPLICATION_ID, CORR_HEIGHT, DB_PER_UNIT, log_run, recording_id
from harness.rundir import Manifest, RunDir

try:
    from test_report import AF, NAMES, REAL_EXPERIMENTS, TS, build_run, campaign_only, exp_gap
except ImportError:  # tests/ imported as a package
    from tests.test_report import AF, NAMES, REAL_EXPERIMENTS, TS, build_run, campaign_only, exp_gap

# what each kind of view draws (the component that carries the data)
VIEW_DATA = {
    "TimeSeries": {"Scalars:scalars"},
    "2D": {"LineStrips2D:strips", "Points2D:positions", "Image:buffer", "EncodedImage:blob"},
    "Tensor": {"Tensor:data"},
    "TextDocument": {"TextDocument:text"},
    "BarChart": {"BarChart:values"},
}
DATA = set().union(*VIEW_DATA.values())
HELD_OUT = rr.escape_entity_path_part("held-out gap")


def read_chunks(rrd: Path) -> dict[str, list[dict]]:
    chunks: dict[str, list[dict]] = {}
    for c in RrdReader(rrd).stream():
        chunks.setdefault(c.entity_path, []).append(c.to_record_batch().to_pydict())
    return chunks


@pytest.fixture(scope="module")
def real(diagnosed_run) -> tuple[Path, dict]:
    """The session's diagnosed run (read-only) and its diagnosis."""
    return diagnosed_run, json.loads(RunDir(diagnosed_run).diagnosis.read_text())


@pytest.fixture(scope="module")
def logged(tmp_path_factory, real) -> tuple[Path, dict, dict[str, list[dict]], Path]:
    rr.set_strict_mode(True)
    root = tmp_path_factory.mktemp("vrun")
    truth = build_run(root, real[1])
    rrd = log_run(root)
    return root, truth, read_chunks(rrd), rrd


def _column(chunks: dict[str, list[dict]], path: str, col: str) -> list:
    for d in chunks[path]:
        if col in d:
            return d[col]
    raise KeyError(f"{path} has no column {col}")


# ----------------------------------------------------------------------------------------------- the blueprint
def blueprint_views(rrd: Path) -> tuple[list[dict], str]:
    """The views of the recording's blueprint ({class, name, origin, queries}) and the time panel's timeline."""
    reader = RrdReader(rrd)
    (store,) = reader.blueprints()
    views: dict[str, dict] = {}
    timeline = ""
    for c in reader.stream(store=store):
        d = c.to_record_batch().to_pydict()
        parts = c.entity_path.strip("/").split("/")
        if "TimePanelBlueprint:timeline" in d:
            timeline = d["TimePanelBlueprint:timeline"][-1][0]
        if parts[0] != "view":
            continue
        v = views.setdefault(parts[1], {"queries": ["$origin/**"]})
        for key, field in (("class", "class_identifier"), ("name", "display_name"), ("origin", "space_origin")):
            if d.get(f"ViewBlueprint:{field}"):
                v[key] = d[f"ViewBlueprint:{field}"][-1][0]
        if d.get("ViewContents:query"):
            v["queries"] = d["ViewContents:query"][-1]
    return list(views.values()), timeline


def data_index(rrd: Path) -> dict[str, dict[str, set[str]]]:
    """entity -> {"static" or timeline name: data components logged there}."""
    out: dict[str, dict[str, set[str]]] = {}
    for c in RrdReader(rrd).stream():
        cols = {k for k, v in c.to_record_batch().to_pydict().items() if k in DATA and any(x is not None for x in v)}
        if not cols:
            continue
        where = out.setdefault(c.entity_path, {})
        for key in ["static"] if c.is_static else c.timeline_names:
            where.setdefault(key, set()).update(cols)
    return out


def resolve(origin: str, queries: list[str], entities: list[str]) -> list[str]:
    """Entities a view's contents select: ``$origin/x`` exact, ``.../**`` a subtree, ``- expr`` excluded."""

    def match(expr: str, path: str) -> bool:
        expr = "/" + expr.replace("$origin", origin.strip("/")).strip("/")
        if expr.endswith("/**"):
            root = expr[:-3].rstrip("/")
            return path == root or path.startswith(root + "/") or root == ""
        return path == expr

    chosen = []
    for path in entities:
        plus = [q for q in queries if not q.strip().startswith("-")]
        minus = [q.strip()[1:].strip() for q in queries if q.strip().startswith("-")]
        if any(match(q.strip().lstrip("+").strip(), path) for q in plus) and not any(match(q, path) for q in minus):
            chosen.append(path)
    return chosen


def check_every_view_shows_data(rrd: Path) -> list[dict]:
    views, timeline = blueprint_views(rrd)
    assert timeline == "time"
    index = data_index(rrd)
    for v in views:
        wanted = VIEW_DATA[v["class"]]
        ents = resolve(v["origin"], v["queries"], list(index))
        shown = [e for e in ents if any(wanted & cols for cols in index[e].values())]
        assert shown, f"view {v['name']!r} ({v['class']}, {v['origin']}) selects no entity with {sorted(wanted)}"
        for e in shown:
            visible = {k for k, cols in index[e].items() if wanted & cols}
            if v["class"] == "TimeSeries":
                assert visible == {timeline}, f"{v['name']!r}: {e} has its series on {visible}, not {timeline!r}"
            else:
                assert visible <= {"static", timeline}, f"{v['name']!r}: {e} is only on timeline(s) {visible}"
    return views


def test_every_view_of_the_blueprint_shows_data(logged):
    _, _, _, rrd = logged
    views = check_every_view_shows_data(rrd)
    kinds = {v["class"] for v in views}
    assert {"TimeSeries", "Tensor", "TextDocument", "2D"} <= kinds
    names = [v["name"] for v in views]
    for label in ("Bode magnitude [dB] vs log10 f [Hz]", "Bode phase [deg] vs log10 f [Hz]",
                  "residual autocorrelation r_ee vs lag [samples]"):  # fmt: skip
        assert label in names
    bode = [v for v in views if v["origin"].strip("/").startswith("bode")]
    assert bode and all(v["class"] == "2D" for v in bode)  # not a TimeSeries on a frequency timeline


def test_every_view_shows_data_for_a_real_run(real, tmp_path):
    """The real run (identified, cross-fitted, diagnosed): every view has data; its summary holds the verdict
    sentence and the waterfall the diagnosis's gaps."""
    run = tmp_path / "real"
    shutil.copytree(real[0], run)
    rrd = log_run(run)
    views = check_every_view_shows_data(rrd)
    assert {"TimeSeries", "Tensor", "TextDocument", "2D"} <= {v["class"] for v in views}
    chunks = read_chunks(rrd)
    d = real[1]
    summary = _column(chunks, "/diagnosis/summary", "TextDocument:text")[0][0]
    assert "removing `coulomb_friction` alone from the final rig (fitted on every record) reopens the most" in summary
    stages = _column(chunks, f"/diagnosis/waterfall/{HELD_OUT}/values", "Points2D:labels")[0]
    dec = d["gap"]["decomposition"]
    assert stages == [f"{g:.3f}" for g in [dec["before"], *(s["gap_after"] for s in dec["steps"])]]
    for name in REAL_EXPERIMENTS:
        assert f"/datasets/{name}/simulated" in chunks and f"/resid/acf/{name}" in chunks


def test_every_view_shows_data_for_a_run_without_models(real, tmp_path):
    views = check_every_view_shows_data(log_run(campaign_only(real[0], tmp_path / "campaign")))
    assert {v["class"] for v in views} == {"TimeSeries", "TextDocument", "2D"}


def test_recording_ids(logged):
    root, _, _, rrd = logged
    assert rrd == root / "run.rrd"
    (recording,) = RrdReader(rrd).recordings()
    assert recording.application_id == APPLICATION_ID == "flexjoint"
    manifest = Manifest.load(root)
    assert recording.recording_id == recording_id(manifest)
    assert recording_id(manifest) != recording_id(replace(manifest, spec_sha256="00" * 32))
    assert not list(root.glob(".run.rrd*"))


# ----------------------------------------------------------------------------------------------- the data
def test_series_match_the_data(logged):
    _, truth, chunks, _ = logged
    for name in NAMES:
        base = f"/datasets/{name}"
        for leaf in ("measured", "simulated", "command", "tip/measured", "tip/simulated"):
            assert f"{base}/{leaf}" in chunks
        t_ns = np.array([td.value for td in _column(chunks, f"{base}/measured", "time")])  # Timedelta -> ns
        y = np.array(_column(chunks, f"{base}/measured", "Scalars:scalars"))[:, 0]
        assert t_ns[:4].tolist() == [0, 20_000_000, 40_000_000, 60_000_000]
        assert y.size == truth["y_f"][name].size
        np.testing.assert_allclose(y, truth["y_f"][name], atol=1e-9)
        sim = np.array(_column(chunks, f"{base}/simulated", "Scalars:scalars"))[:, 0]
        ref = armax.simulate(truth["models"]["selected"], truth["u_d"][name])
        np.testing.assert_allclose(sim, ref, atol=1e-12)
        u = np.array(_column(chunks, f"{base}/command", "Scalars:scalars"))[:, 0]
        np.testing.assert_array_equal(u, truth["u"][name])
        names = _column(chunks, f"{base}/simulated", "SeriesLines:names")
        assert names == [["simulated y_f"]]


def test_crossfit_tensor_heatmap_and_table(logged):
    _, truth, chunks, _ = logged
    (tensor,) = _column(chunks, "/crossfit/matrix", "Tensor:data")[0]
    assert tensor["names"] == ["model", "dataset"]
    cf = truth["crossfit"]
    assert tensor["shape"] == [len(cf), len(NAMES)]
    np.testing.assert_allclose(np.reshape(tensor["buffer"], tensor["shape"]), cf.to_numpy(), atol=5e-7)
    # the heat map: the report's figure (models and datasets by name, each value readable on its cell) as a PNG
    (blob,) = _column(chunks, "/crossfit/heatmap", "EncodedImage:blob")[0]
    assert bytes(blob) == figures.png_bytes(figures.crossfit_figure(cf))
    assert _column(chunks, "/crossfit/heatmap", "EncodedImage:media_type")[0] == ["image/png"]
    text = _column(chunks, "/crossfit/table", "TextDocument:text")[0][0]
    header = next(line for line in text.splitlines() if line.startswith("| Models/Data Sets"))
    assert [c.strip() for c in header.strip("|").split("|")][1:4] == ["1", "2", "3"]
    assert "1 = `prbs_a`, 2 = `prbs_b`, 3 = `square_c`" in text and "The heat map names them" in text
    row = next(line for line in text.splitlines() if line.startswith("| selected"))
    assert row.split("|")[-2].strip() == f"{cf.loc['selected'].mean():.2f}"


def test_pole_zero_and_bode_in_2d(logged):
    _, truth, chunks, _ = logged
    m = truth["models"]["selected"]
    poles = np.array(_column(chunks, "/models/selected/pz/poles", "Points2D:positions")[0])
    ref = np.roots(np.convolve(m.A, [1.0, -1.0]))
    got = poles[:, 0] - 1j * poles[:, 1]  # drawn at (Re, -Im): 2D views point y down
    np.testing.assert_allclose(np.sort_complex(got), np.sort_complex(ref), atol=1e-6)  # stored as float32
    assert len(_column(chunks, "/models/selected/pz/zeros", "Points2D:positions")[0]) == 4

    # Bode of the selected model near 1 Hz: x = log10 f, y = -magnitude / 20 dB; |B/A / H| evaluated directly
    (strip,) = _column(chunks, "/bode/magnitude/selected", "LineStrips2D:strips")[0]
    xy = np.array(strip, dtype=float)
    assert np.all(np.diff(xy[:, 0]) > 0) and xy[-1, 0] == pytest.approx(np.log10(0.999 * 0.5 / TS), abs=1e-5)
    k = int(np.argmin(np.abs(xy[:, 0])))
    f = 10.0 ** xy[k, 0]
    zi = np.exp(-2j * np.pi * f * TS)
    h = np.polyval(m.B[::-1], zi) / np.polyval(m.A[::-1], zi) * (1 - AF * zi) / ((1 - AF) * (1 - zi))
    assert -DB_PER_UNIT * xy[k, 1] == pytest.approx(20 * np.log10(abs(h)), abs=2e-3)  # float32 positions
    for name in NAMES:
        assert f"/bode/phase/{name}" in chunks
    ticks = _column(chunks, "/bode/magnitude/axes/ticks", "Points2D:labels")[0]
    assert "1 Hz" in ticks and any(t.endswith(" dB") for t in ticks)


def test_residual_correlations_in_2d(logged):
    _, truth, chunks, _ = logged
    (acf,) = _column(chunks, f"/resid/acf/{NAMES[0]}", "LineStrips2D:strips")[0]
    acf = np.array(acf, dtype=float)
    assert acf[0, 0] == 0.0 and -acf[0, 1] / CORR_HEIGHT == pytest.approx(1.0, abs=1e-6)  # r_ee(0) = 1
    (ccf,) = _column(chunks, f"/resid/ccf/{NAMES[0]}", "LineStrips2D:strips")[0]
    ccf = np.array(ccf, dtype=float)
    assert ccf.shape[0] == 51 and ccf[0, 0] == pytest.approx(-ccf[-1, 0])  # lags -25..25
    bounds = _column(chunks, "/resid/acf/bounds", "LineStrips2D:strips")[0]
    bound = 2.58 / np.sqrt(truth["y_f"][NAMES[0]].size)
    assert abs(np.array(bounds[0], dtype=float)[0, 1]) / CORR_HEIGHT == pytest.approx(bound, rel=1e-5)


def _bar_tops(chunks: dict[str, list[dict]], path: str) -> tuple[np.ndarray, np.ndarray]:
    """(x, top) of each bar of a 2D bar chart: an upright strip's upper end plus its radius (its round end)."""
    strips = _column(chunks, path, "LineStrips2D:strips")[0]
    radii = np.array(_column(chunks, path, "LineStrips2D:radii")[0], dtype=float)
    ends = np.array([np.array(st, dtype=float)[1] for st in strips])
    return ends[:, 0], -ends[:, 1] + radii


def test_diagnosis_bars_show_before_and_after(logged, real):
    """The gap per experiment as 2D bars in named categories (the experiments), as given and with the effects side by
    side, heights proportional to the gaps, each value over its bar; the waterfall's stages named likewise."""
    _, _, chunks, _ = logged
    d = real[1]
    exps = d["gap"]["before"]["experiments"]
    assert _column(chunks, "/diagnosis/gap/categories", "Points2D:labels")[0] == list(exps)
    stages = ("simulation as given", "recalibrated, with the effects")
    given, final = (f"/diagnosis/gap/{rr.escape_entity_path_part(s)}" for s in stages)
    want_b = [exp_gap(exps[n]) for n in exps]
    want_a = [exp_gap(d["gap"]["after"]["experiments"][n]) for n in exps]
    assert _column(chunks, f"{given}/values", "Points2D:labels")[0] == [f"{g:.3f}" for g in want_b]
    assert _column(chunks, f"{final}/values", "Points2D:labels")[0] == [f"{g:.3f}" for g in want_a]
    xb, hb = _bar_tops(chunks, given)
    xa, _ = _bar_tops(chunks, final)
    np.testing.assert_allclose(hb / hb.max(), np.array(want_b) / max(want_b), rtol=1e-5)  # float32 positions
    assert np.all(xb < xa) and np.all(np.diff(xb) == pytest.approx(1.0))  # side by side, one slot per experiment
    summary = _column(chunks, "/diagnosis/summary", "TextDocument:text")[0][0]
    assert "Verdict: **coulomb_friction**" in summary and "as given red (left)" in summary
    stages = _column(chunks, "/diagnosis/waterfall/categories", "Points2D:labels")[0]
    assert stages == ["simulation as given", *(s["stage"] for s in d["gap"]["decomposition"]["steps"])]
    _, tops = _bar_tops(chunks, f"/diagnosis/waterfall/{HELD_OUT}")
    assert tops[0] == pytest.approx(4.0, rel=1e-5)  # the gap before: the tallest bar, BAR_HEIGHT


def test_recording_opens_on_the_overview_with_replays_and_data(real, tmp_path):
    """The blueprint's root tabs open on the overview (not the datasets); the replays of each experiment and the data
    of each as time series, the same numbers as diagnosis.replays.parquet and the datasets."""
    from harness.diagnosis.replays import STAGES, read_replays

    run = tmp_path / "real"
    shutil.copytree(real[0], run)
    rrd = log_run(run)
    reader = RrdReader(rrd)
    (store,) = reader.blueprints()
    names, active = {}, []
    for c in reader.stream(store=store):
        d = c.to_record_batch().to_pydict()
        if d.get("ViewBlueprint:display_name"):
            names[c.entity_path.strip("/")] = d["ViewBlueprint:display_name"][-1][0]
        if d.get("ContainerBlueprint:container_kind") and d.get("ContainerBlueprint:active_tab"):
            active.append((d["ContainerBlueprint:contents"][-1], d["ContainerBlueprint:active_tab"][-1][0]))
    root = next((contents, tab) for contents, tab in active if any(names.get(x.strip("/")) == "overview"
                                                                     for x in contents))  # fmt: skip
    assert names[root[1].strip("/")] == "overview" and root[0][0] == root[1]
    chunks = read_chunks(rrd)
    for name, rp in read_replays(RunDir(run).diagnosis_replays).items():
        base = f"/diagnosis/replays/{rr.escape_entity_path_part(name)}"
        for ch in ("theta", "alpha"):
            rec = np.array(_column(chunks, f"{base}/{ch}/record", "Scalars:scalars"))[:, 0]
            np.testing.assert_array_equal(np.isnan(rec), np.isnan(rp.record[ch]))
            for stage in STAGES:
                sim = np.array(_column(chunks, f"{base}/{ch}/{stage}", "Scalars:scalars"))[:, 0]
                np.testing.assert_allclose(sim, rp.sim[stage][ch], equal_nan=True)
                (label,) = _column(chunks, f"{base}/{ch}/{stage}", "SeriesLines:names")[0]
                assert label.startswith(f"{STAGES[stage]} (fit ") and label.endswith(" %)")
    for e in Manifest.load(run).experiments:
        u = np.array(_column(chunks, f"/data/{e.name}/u", "Scalars:scalars"))[:, 0]
        np.testing.assert_array_equal(u, pd.read_parquet(RunDir(run).dataset(e.name))["u"].to_numpy())
        assert f"/data/{e.name}/theta" in chunks and f"/data/{e.name}/alpha" in chunks


def test_connect_and_errors_leave_no_half_file(logged, real, tmp_path):
    root, _, _, rrd = logged
    with pytest.raises(ValueError, match="invalid viewer URL"):
        log_run(root, rrd=tmp_path / "x.rrd", connect="http://localhost:9876")
    assert not (tmp_path / "x.rrd").exists()

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    server = rr.RecordingStream("flexjoint-test-server")
    url = server.serve_grpc(grpc_port=port)
    out = log_run(root, rrd=tmp_path / "live.rrd", connect=url)
    assert out == tmp_path / "live.rrd" and RrdReader(out).recordings()
    server.disconnect()

    before = rrd.read_bytes()
    bad = tmp_path / "bad"
    build_run(bad, real[1])
    (bad / "models" / "selected.json").write_text('{"na": 2}')
    with pytest.raises(ValueError, match=r"selected\.json: ARMAX model dict lacks the key"):
        log_run(bad)
    assert not (bad / "run.rrd").exists() and not list(bad.glob(".run.rrd*"))
    assert rrd.read_bytes() == before
