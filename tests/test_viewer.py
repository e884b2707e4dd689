"""run.rrd of a hand-built run directory read back with rerun.chunk.RrdReader, checked against its inputs."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from harness import armax
from harness.viewer import APPLICATION_ID, log_run, recording_id

try:
    from test_report import AF, GAPS, NAMES, TS, build_run
except ImportError:  # tests/ imported as a package
    from tests.test_report import AF, GAPS, NAMES, TS, build_run


@pytest.fixture(scope="module")
def logged(tmp_path_factory) -> tuple[Path, dict, dict[str, list[dict]], Path]:
    rr.set_strict_mode(True)
    root = tmp_path_factory.mktemp("vrun")
    truth = build_run(root)
    rrd = log_run(root)
    chunks: dict[str, list[dict]] = {}
    reader = RrdReader(rrd)
    for c in reader.stream():
        chunks.setdefault(c.entity_path, []).append(c.to_record_batch().to_pydict())
    return root, truth, chunks, rrd


def _column(chunks: dict[str, list[dict]], path: str, col: str) -> list:
    for d in chunks[path]:
        if col in d:
            return d[col]
    raise KeyError(f"{path} has no column {col}")


def test_recording_ids_and_blueprint(logged):
    root, _, _, rrd = logged
    assert rrd == root / "run.rrd"
    reader = RrdReader(rrd)
    (recording,) = reader.recordings()
    assert recording.application_id == APPLICATION_ID == "flexjoint"
    manifest = json.loads((root / "manifest.json").read_text())
    assert recording.recording_id == recording_id(manifest)
    assert recording_id(manifest) != recording_id({**manifest, "spec_sha256": "00" * 32})
    views = set()
    for c in reader.stream(store=reader.blueprints()[0]):
        d = c.to_record_batch().to_pydict()
        views.update(v[0] for v in d.get("ViewBlueprint:class_identifier", []) if v)
    assert {"TimeSeries", "Tensor", "TextDocument", "2D", "BarChart"} <= views
    assert not list(root.glob(".run.rrd*"))


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


def test_crossfit_tensor_and_table(logged):
    _, truth, chunks, _ = logged
    (tensor,) = _column(chunks, "/crossfit/matrix", "Tensor:data")[0]
    assert tensor["names"] == ["model", "dataset"]
    cf = truth["crossfit"]
    assert tensor["shape"] == [len(cf), len(NAMES)]
    np.testing.assert_allclose(np.reshape(tensor["buffer"], tensor["shape"]), cf.to_numpy(), atol=5e-7)
    assert _column(chunks, "/crossfit/table", "TextDocument:media_type") == [["text/markdown"]]
    text = _column(chunks, "/crossfit/table", "TextDocument:text")[0][0]
    row = next(line for line in text.splitlines() if line.startswith("| selected"))
    assert row.split("|")[-2].strip() == f"{cf.loc['selected'].mean():.2f}"


def test_pole_zero_bode_resid_diagnosis(logged):
    _, truth, chunks, _ = logged
    m = truth["models"]["selected"]
    poles = np.array(_column(chunks, "/models/selected/pz/poles", "Points2D:positions")[0])
    ref = np.roots(np.convolve(m.A, [1.0, -1.0]))
    got = poles[:, 0] + 1j * poles[:, 1]
    np.testing.assert_allclose(np.sort_complex(got), np.sort_complex(ref), atol=1e-6)  # stored as float32
    assert len(_column(chunks, "/models/selected/pz/zeros", "Points2D:positions")[0]) == 4
    circle = np.array(_column(chunks, "/models/selected/pz/unit_circle", "LineStrips2D:strips")[0][0])
    np.testing.assert_allclose(np.hypot(circle[:, 0], circle[:, 1]), 1.0, atol=1e-6)

    # Bode of the selected model at 1 Hz: |B/A / H| evaluated directly, H = (1-af)(1-z^-1)/(1-af z^-1)
    f_mhz = np.array(_column(chunks, "/bode/magnitude/selected", "frequency_mHz"))
    mag = np.array(_column(chunks, "/bode/magnitude/selected", "Scalars:scalars"))[:, 0]
    k = int(np.argmin(np.abs(f_mhz - 1000)))
    zi = np.exp(-2j * np.pi * f_mhz[k] / 1000.0 * TS)
    h = np.polyval(m.B[::-1], zi) / np.polyval(m.A[::-1], zi) * (1 - AF * zi) / ((1 - AF) * (1 - zi))
    assert mag[k] == pytest.approx(20 * np.log10(abs(h)), abs=1e-9)
    for name in NAMES:
        assert f"/bode/phase/{name}" in chunks

    acf = np.array(_column(chunks, f"/resid/acf/{NAMES[0]}", "Scalars:scalars"))[:, 0]
    assert acf[0] == pytest.approx(1.0)
    lags = _column(chunks, f"/resid/ccf/{NAMES[0]}", "lag")
    assert lags[0] == -25 and lags[-1] == 25
    bound = np.array(_column(chunks, "/resid/acf/bound_upper", "Scalars:scalars"))[:, 0]
    assert bound[0] == pytest.approx(2.58 / np.sqrt(truth["y_f"][NAMES[0]].size))
    before = _column(chunks, "/diagnosis/gap_before", "BarChart:values")[0][0]
    after = _column(chunks, "/diagnosis/gap_after", "BarChart:values")[0][0]
    gaps = np.array(list(GAPS.values()))
    np.testing.assert_allclose(before["buffer"], gaps[:, 0], atol=1e-6)
    np.testing.assert_allclose(after["buffer"], gaps[:, 1], atol=1e-6)
    summary = _column(chunks, "/diagnosis/summary", "TextDocument:text")[0][0]
    assert "0 = rig_a, 1 = rig_b" in summary and "Verdict: **coulomb_friction**" in summary


def test_connect_and_errors_leave_no_half_file(logged, tmp_path):
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
    build_run(bad)
    (bad / "models" / "selected.json").write_text('{"na": 2}')
    with pytest.raises(ValueError, match=r"selected\.json: ARMAX model dict lacks the key"):
        log_run(bad)
    assert not (bad / "run.rrd").exists() and not list(bad.glob(".run.rrd*"))
    assert rrd.read_bytes() == before
