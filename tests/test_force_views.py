"""The missing force drawn (issue 63 item 5): force_picture.parquet and force_picture.png beside likelihood.json, the
report's "Missing force" lines and the recording's force entities, checked on a picture whose numbers are built here
(:func:`_picture`: a Coulomb-like force against a sine of the hub's speed, other seeds and sizes alike) and, end to
end, on a twin with friction through ``flexjoint diagnose --engine likelihood``."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from harness import spec as specmod
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.likelihood.force import ForcePicture, ForceTrace, MissingForce
from harness.likelihood.record import Record
from harness.likelihood.traces import COLUMNS, read_traces
from harness.render import force as views
from harness.render.load import RunResults, _verdict
from harness.render.report import _force_lines
from harness.render.viewer import _log_with_blueprint, write_recording
from harness.rig.campaign import run_campaign
from harness.rundir import DataError, Manifest, RunDir

try:
    from test_likelihood import KE, KP, NOISE_V, PLANT, _readings, _truth
    from test_viewer import blueprint_views, check_every_view_shows_data, read_chunks
except ImportError:  # tests/ imported as a package
    from tests.test_likelihood import KE, KP, NOISE_V, PLANT, _readings, _truth
    from tests.test_viewer import blueprint_views, check_every_view_shows_data, read_chunks

TS = 2e-3
VERDICT = MissingForce("friction", 0.03, "N m", 0.125, 7)


def _picture(seed: int, records: int, seconds: float) -> ForcePicture:
    """``records`` records of ``seconds`` at 500 Hz: the hub's speed a sine of 120 deg/s (its own phase and period per
    record), the force -0.03 N m sign(speed) plus noise, its sd 2 mN, the command and the deflection sines."""
    rng = np.random.default_rng(seed)
    traces = []
    for i in range(records):
        t = np.arange(int(seconds / TS)) * TS
        speed = 120.0 * np.sin(2 * np.pi * t / rng.uniform(0.8, 1.5) + rng.uniform(0, 2 * np.pi))
        force = -0.03 * np.sign(speed) + 0.002 * rng.standard_normal(t.size)
        traces.append(ForceTrace(f"rec{i}", t, force, np.full(t.size, 0.002), speed, np.full(t.size, 1.5),
                                 np.sin(3 * t + i), 0.2 * np.cos(5 * t + i)))  # fmt: skip
    return ForcePicture(0.01, 250.0, tuple(traces), 0.24)


@pytest.mark.parametrize(("seed", "records", "seconds"), [(0, 2, 3.0), (5, 3, 1.5)])
def test_the_figure_draws_the_traces_and_the_parquet_stores_them(tmp_path, seed, records, seconds):
    """The parquet read back gives every trace's samples exactly (float64), by record in order; the figure's four
    panels hold one line per record, the force against speed, command, deflection and time, the time panel its +-2
    sd band; the classifier's verdict is the title; the same picture gives the same bytes twice (both files)."""
    pic = _picture(seed, records, seconds)
    verdict = VERDICT.words()
    assert verdict == "friction of 0.03 N m (0.125 V of command)"
    parquet, png = views.write_force_views(tmp_path, pic, verdict)
    assert (parquet, png) == (RunDir(tmp_path).force_traces, RunDir(tmp_path).force_figure)
    back = read_traces(parquet)
    assert [tr.name for tr in back] == [tr.name for tr in pic.traces]
    for a, b in zip(back, pic.traces, strict=True):
        for c in COLUMNS:
            np.testing.assert_array_equal(getattr(a, c), getattr(b, c), err_msg=c)
    fig = views.force_figure(back, verdict)
    axes = fig.axes
    assert [ax.get_xlabel() for ax in axes] == [label for _, label in views.PANELS]
    assert all("[" in ax.get_xlabel() for ax in axes) and axes[0].get_ylabel() == "missing force [N m]"
    assert verdict in fig._suptitle.get_text()
    for ax, (x, _) in zip(axes, views.PANELS, strict=True):
        lines = [ln for ln in ax.get_lines() if ln.get_label() in {tr.name for tr in pic.traces}]
        assert len(lines) == records
        for ln, tr in zip(lines, pic.traces, strict=True):
            np.testing.assert_array_equal(ln.get_xdata(), getattr(tr, x))
            np.testing.assert_array_equal(ln.get_ydata(), tr.force)
    bands = axes[3].collections
    assert len(bands) == records
    for band, tr in zip(bands, pic.traces, strict=True):
        y = band.get_paths()[0].vertices[:, 1]
        assert y.min() == pytest.approx((tr.force - 2 * tr.force_sd).min())
        assert y.max() == pytest.approx((tr.force + 2 * tr.force_sd).max())
    first = parquet.read_bytes(), png.read_bytes()
    views.write_force_views(tmp_path, pic, verdict)
    assert (parquet.read_bytes(), png.read_bytes()) == first
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and b"Software" not in png.read_bytes()


def test_a_file_that_is_no_force_picture_is_one_line(tmp_path):
    """A parquet that is not one, a likelihood.json without the verdict's fields: one DataError line each."""
    bad = tmp_path / "force_picture.parquet"
    bad.write_text("not parquet")
    with pytest.raises(DataError, match="not a force picture"):
        read_traces(bad)
    with pytest.raises(DataError, match=r"missing_force lacks dead_band_v, samples_near_zero \(re-run"):
        _verdict(tmp_path / "likelihood.json", {"missing_force": {"shape": "none", "size": 0.0, "unit": "N m"}})
    assert _verdict(tmp_path / "likelihood.json", {"missing_force": VERDICT.to_json()}) == VERDICT
    old = {k: v for k, v in VERDICT.to_json().items() if k != "levels"}  # written before the levels were
    assert _verdict(tmp_path / "likelihood.json", {"missing_force": old}) == VERDICT


def _results(tmp_path: Path, pic: ForcePicture, png: bool) -> RunResults:
    """What load_results gives for a directory that holds the force picture (no diagnosis needed by these parts)."""
    if png:
        views.write_force_views(tmp_path, pic, "friction")
    return RunResults(run=tmp_path, manifest=Manifest(kind="diagnosis", experiments=[], sample_rate=None),
                      missing_force=VERDICT, force=pic.traces)  # fmt: skip


def test_each_shape_is_said_in_the_same_words_everywhere():
    """The verdict's words, the one phrase the summary, the report, the figure and the recording use: friction with
    its size and command, asymmetric friction with its levels each way, a limit's and an offset's level, a hub that
    never rests said so, none; likelihood.json's form reads back to the same verdict."""
    cases = [
        (MissingForce("friction", 0.03, "N m", 0.125, 7), "friction of 0.03 N m (0.125 V of command)"),
        (MissingForce("asymmetric_friction", 0.03, "N m", 0.125, 7, (0.04, 0.02)),
         "asymmetric_friction, 0.04 forward and 0.02 backward of 0.03 N m (0.125 V of command)"),
        (MissingForce("limit", 1.2, "V", 0.0, 0), "limit at 1.2 V"),
        (MissingForce("offset", -0.1, "V", 0.0, 0), "offset of -0.1 V"),
        (MissingForce("too_few_at_rest", 0.0, "N m", 0.0, 2), "too few samples at rest (the hub never rests: "
         "friction and an offset look alike)"),
        (MissingForce("none", 0.0, "N m", 0.0, 900), "none"),
    ]  # fmt: skip
    for mf, words in cases:
        assert mf.words() == words
        assert MissingForce.from_json(json.loads(json.dumps(mf.to_json()))) == mf
    sized = MissingForce("friction", 0.0301, "N m", 0.234, 7, sized_by="coulomb_friction", picture_size=0.028)
    assert MissingForce.from_json(json.loads(json.dumps(sized.to_json()))) == sized


def test_the_effect_that_entered_is_drawn_over_its_panel():
    """Friction's curve, -Fc sign(speed) with the stick phase the vertical at zero, goes over the speed panel across
    the traces' speeds; a limit's, the drive's torque of what it clips, over the command panel: zero within +-L,
    drive (L - u) beyond (1.5 V on a 1.2 V limit with 0.24 N m/V: -0.072 N m)."""
    from harness.likelihood.force import effect_curve

    pic = _picture(2, 2, 1.0)
    fr = effect_curve("plant.coulomb_torque", 0.03, pic)
    top = max(np.abs(tr.speed).max() for tr in pic.traces)
    np.testing.assert_allclose(fr.xs, [-top, 0, 0, top])
    np.testing.assert_allclose(fr.ys, [0.03, 0.03, -0.03, -0.03])
    fig = views.force_figure(pic.traces, "friction", fr)
    drawn = [line for ax in fig.axes for line in ax.get_lines() if line.get_label() == fr.label]
    assert len(drawn) == 1 and drawn[0] in fig.axes[0].get_lines() and drawn[0].get_color() == "k"
    assert list(drawn[0].get_ydata()) == list(fr.ys)
    pic = ForcePicture(pic.intensity, pic.gain, tuple(dataclasses.replace(tr, u=1.5 * np.sign(tr.u)) for tr in
                       pic.traces), 0.24)  # fmt: skip
    lim = effect_curve("plant.amp_limit", 1.2, pic)
    assert lim.x == "u" and lim.xs[0] == -1.5 and lim.xs[-1] == 1.5
    assert lim.ys[-1] == pytest.approx(-0.072) and lim.ys[0] == pytest.approx(0.072)
    assert np.all(lim.ys[np.abs(lim.xs) <= 1.2] == 0.0)
    fig = views.force_figure(pic.traces, "limit", lim)
    assert [line.get_label() for line in fig.axes[1].get_lines()].count(lim.label) == 1
    with pytest.raises(ValueError, match="no curve"):
        effect_curve("plant.Ks", 1.0, pic)


def test_the_report_says_the_shape_its_size_and_the_samples_at_rest(tmp_path):
    """The section names the classifier's shape and size, the samples at rest of all, and links the figure beside
    report.md; no line over 200 characters; without the figure, no link."""
    pic = _picture(1, 2, 1.0)
    lines = _force_lines(_results(tmp_path, pic, png=True))
    text = "\n".join(lines)
    assert lines[0] == "### Missing force"
    assert "- shape: **friction of 0.03 N m (0.125 V of command)**" in text
    assert "samples at rest (hub speed within three standard deviations of zero): 7 of 1000" in text
    assert "(force_picture.png)" in text and "`rec0`, `rec1`" in text
    assert max(map(len, lines)) < 200
    none = views.force_markdown(MissingForce("none", 0.0, "N m", 0.0, 3), pic.traces, None)
    assert "- shape: **none**" in none and not any("![" in x for x in none)
    assert not any("not white" in x for x in lines)


def test_the_report_says_where_the_residuals_are_not_white(tmp_path):
    """likelihood.json's ``where`` read back (Where.from_json of its asdict) names the flagged bands and stretches;
    the report lists the first eight record channels and says how many more."""
    import dataclasses as dc

    from harness.likelihood.whiteness import Band, Where, Window

    w = Where((Band(3.1, 6.2, 2.5, 1e-9, True), Band(6.3, 12.4, 1.0, 0.5, False)),
              (Window(0.0, 3.0, 0.4, False), Window(3.0, 6.0, 1e-6, True)))  # fmt: skip
    back = Where.from_json(json.loads(json.dumps(dc.asdict(w))))
    assert back == w and back.words() == "3.1-6.2 Hz, 3-6 s"
    res = dc.replace(_results(tmp_path, _picture(1, 2, 1.0), png=False),
                     not_white=tuple(f"rec{i} alpha: {w.words()}" for i in range(10)))  # fmt: skip
    lines = _force_lines(res)
    assert "- rec0 alpha: 3.1-6.2 Hz, 3-6 s" in lines and "- and 2 more (`likelihood.json`)" in lines
    assert "- rec8 alpha: 3.1-6.2 Hz, 3-6 s" not in lines


@pytest.mark.parametrize(("coulomb", "seed"), [(0.03, 1), (0.02, 4)])
def test_a_twins_friction_is_named_with_its_size_in_the_report_and_the_figure(tmp_path, coulomb, seed):
    """A 2 s twin at 500 Hz through the FMUs under a +-1 V square command with Coulomb friction the model lacks (the
    rig's linear parameters given, 2 mV of noise): the classifier's friction and its size (within 5 % of the twin's;
    measured 0.14 % and 0.04 %) are the report's shape and size and the figure's title; the figure draws the
    picture's own traces."""
    from harness.likelihood.force import classify, force_picture

    n = 1000
    u = np.where(np.arange(n) * TS % 1.0 < 0.5, 1.0, -1.0)
    with Rig(build_all()["flexjoint"], build_all()["daq"]) as rig:
        out = rig.run(u, TS, plant={**PLANT, "coulomb_torque": coulomb}, daq={"noise_theta": NOISE_V,
                      "noise_alpha": NOISE_V, "seed": seed})  # fmt: skip
    rec = Record("square", TS, u, _readings(out), np.ones((n, 2), bool))
    values = _truth(PLANT) | {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0, "noise.theta": NOISE_V * KP,
                              "noise.alpha": NOISE_V * abs(KE)}  # fmt: skip
    pic = force_picture(PLANT, values, [rec])
    mf = classify(pic)
    assert mf.shape == "friction" and mf.size == pytest.approx(coulomb, rel=0.05)
    verdict = mf.words()
    _, png = views.write_force_views(tmp_path, pic, verdict)
    lines = views.force_markdown(mf, pic.traces, png.name)
    assert f"- shape: **friction of {mf.size:.3g} N m ({mf.dead_band_v:.3g} V of command)**" in lines
    fig = views.force_figure(read_traces(RunDir(tmp_path).force_traces), verdict)
    assert fig._suptitle.get_text().endswith(f"friction of {mf.size:.3g} N m ({mf.dead_band_v:.3g} V of command)")
    np.testing.assert_array_equal(fig.axes[0].get_lines()[0].get_xdata(), pic.traces[0].speed)


def test_the_recording_holds_the_force_over_time_and_against_speed(tmp_path):
    """Per record the force over ``time`` with its +-2 sd band as series (the values logged exactly), the force
    against the hub's speed as 2D points (their coordinates proportional to speed and force, one scale for every
    record), in a "missing force" tab whose views all show data, with where the residuals are not white when they
    are not somewhere; the same results give the same bytes twice."""
    rr.set_strict_mode(True)
    pic = _picture(3, 2, 1.0)
    res = _results(tmp_path, pic, png=False)
    rrds = [write_recording(tmp_path / f"{k}.rrd", "0" * 8 + "-0000-0000-0000-" + "0" * 12,
                            lambda rec: _log_with_blueprint(rec, res)) for k in ("a", "b")]  # fmt: skip
    assert rrds[0].read_bytes() == rrds[1].read_bytes()
    chunks = read_chunks(rrds[0])
    scale = None
    for tr in pic.traces:
        base = f"/diagnosis/force/time/{tr.name}"
        for leaf, want in (("force", tr.force), ("upper", tr.force + 2 * tr.force_sd),
                           ("lower", tr.force - 2 * tr.force_sd)):  # fmt: skip
            got = [d for d in chunks[f"{base}/{leaf}"] if "Scalars:scalars" in d]
            np.testing.assert_allclose(np.array(got[0]["Scalars:scalars"])[:, 0], want, rtol=0, atol=1e-15)
            t_ns = np.array([x.value for x in got[0]["time"]])
            np.testing.assert_allclose(t_ns * 1e-9, tr.t, atol=1e-9)
        (pts,) = [d for d in chunks[f"/diagnosis/force/speed/{tr.name}"] if "Points2D:positions" in d]
        xy = np.array(pts["Points2D:positions"][0])
        sx, sy = xy[:, 0] / tr.speed, -xy[:, 1] / tr.force  # Rerun's y points down
        assert np.ptp(sx) < 1e-6 * sx.mean() and np.ptp(sy) < 1e-6 * sy.mean()
        scale = scale or (sx.mean(), sy.mean())
        assert (sx.mean(), sy.mean()) == pytest.approx(scale)
    views_ = check_every_view_shows_data(rrds[0])
    names = {v["name"]: v["origin"] for v in views_}
    assert names["missing force [N m] vs t [s], +-2 sd band"] == "diagnosis/force/time"
    assert names["missing force [N m] (up) vs hub speed [deg/s] (right)"] == "diagnosis/force/speed"
    assert blueprint_views(rrds[0])[1] == "time"
    assert "where not white" not in names  # white everywhere: no view without data
    grey = dataclasses.replace(res, not_white=("rec0 alpha: 3.1-6.2 Hz, 3-6 s",))
    rrd = write_recording(tmp_path / "c.rrd", "0" * 8 + "-0000-0000-0000-" + "0" * 12,
                          lambda rec: _log_with_blueprint(rec, grey))  # fmt: skip
    assert {v["name"]: v["origin"] for v in check_every_view_shows_data(rrd)}["where not white"] == (
        "diagnosis/force/where"
    )
    (doc,) = [d for d in read_chunks(rrd)["/diagnosis/force/where"] if "TextDocument:text" in d]
    assert "- rec0 alpha: 3.1-6.2 Hz, 3-6 s" in doc["TextDocument:text"][0][0]
    overview = [d for d in chunks["/overview"] if "TextDocument:text" in d][0]["TextDocument:text"][0][0]
    assert "missing force (likelihood engine): **friction of 0.03 N m (0.125 V of command)**" in overview


def _friction_twin(tmp_path: Path) -> Path:
    """The nominal rig with Coulomb friction of 0.02 N m, its calibration and two 2 s records (a PRBS and a square
    wave) at 500 Hz through a 12-bit ADC with 2 mV of noise."""
    raw = specmod.load("nominal").raw
    raw["campaign"] = {**raw["campaign"], "sample_rate": 500.0}
    raw["plant"] = {**raw["plant"], "coulomb_torque": 0.02}
    raw["daq"] = {"noise_theta": 0.002, "noise_alpha": 0.002, "adc_bits": 12}
    raw["experiment"] = [{**e, "duration": 2.0} for e in raw["experiment"] if e["name"] in ("prbs_b010", "square_030")]
    real = specmod.from_dict(raw, str(specmod.resolve_path("nominal")))
    run_campaign(real, tmp_path / "real", workers=1)
    return tmp_path / "real"


def test_diagnose_with_the_likelihood_engine_draws_the_missing_force(tmp_path):
    """``flexjoint diagnose --engine likelihood --out DIR`` on a friction twin writes force_picture.png and
    force_picture.parquet beside likelihood.json, the parquet's records those of likelihood.json, and gives
    diagnosis.json's candidates the engine fitted their likelihood (friction's, which enters, as likelihood.json has
    it); then ``flexjoint report DIR``: report.md's "Missing force" names the shape likelihood.json gives, run.rrd the
    force's entities."""
    run = _friction_twin(tmp_path)
    out = tmp_path / "diag"
    r = subprocess.run([sys.executable, "-m", "harness", "diagnose", "--real", str(run), "--out", str(out),
                        "--engine", "likelihood", "--workers", "1"], capture_output=True, text=True,
                       timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr
    paths = RunDir(out)
    doc = json.loads(paths.likelihood.read_text())
    candidates = {c["effect"]: c for c in json.loads(paths.diagnosis.read_text())["candidates"]}
    friction = candidates["coulomb_friction"]["likelihood"]  # each model tried, with its likelihood
    assert friction == doc["effects"]["coulomb_friction"]["likelihood"]
    assert {"logL", "k", "n", "lr", "p", "critical"} <= set(friction) and friction["enters"]
    traces = read_traces(paths.force_traces)
    assert [tr.name for tr in traces] == doc["records"]
    assert paths.force_figure.read_bytes()[:4] == b"\x89PNG" and "force_picture.png" in r.stdout
    r = subprocess.run([sys.executable, "-m", "harness", "report", str(out)], capture_output=True, text=True,
                       timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr
    text = paths.report.read_text()
    words = MissingForce.from_json(doc["missing_force"]).words()
    assert "### Missing force" in text and f"- shape: **{words}**" in text
    assert "![missing force against hub speed, command, deflection and time](force_picture.png)" in text
    entities = {c.entity_path for c in RrdReader(paths.recording).stream()}
    assert {f"/diagnosis/force/speed/{tr.name}" for tr in traces} <= entities
