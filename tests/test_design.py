"""flexjoint design: the three methods on a rig, the search against the prediction, the files, and bad input."""

from __future__ import annotations

import io
import json
import math
import subprocess
import sys
import tomllib
import zipfile

import numpy as np
import pytest

from harness import spec as specmod
from harness.design import DesignError, controller_toml, design, pd_controller
from harness.linloop import closed_loop, design_model, spectral_radius
from harness.loopspecs import LoopSpecs
from harness.prediction import reference_from
from harness.render.prediction import write_design
from harness.spec import controller_table
from harness.twin import twin_of_spec

SPECS = LoopSpecs.parse("settling=1.0,overshoot=5,alpha=20,voltage=10")


def flexjoint(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "harness.cli", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def lab():
    """The lab rig under its effects (friction, second mode, 12-bit ADC, noise, a command delay), a datasheet's
    uncertainty on its parameters."""
    return twin_of_spec(specmod.load("closed_loop"))


@pytest.fixture(scope="module")
def lqg(lab):
    """The LQG designed to :data:`SPECS` on the lab rig (40 members), which test_the_files_a_design_writes writes."""
    return design(lab, "lqg", reference_from("square:f=0.4;amplitude=25;duration=5", 500.0), SPECS, n=40, workers=1)


@pytest.mark.parametrize("method", ["lqr", "pd", "lqg"])
def test_each_method_meets_the_specs_as_predicted(lab, lqg, method):
    ref = reference_from("square:f=0.4;amplitude=25;duration=5", 500.0)
    d = lqg if method == "lqg" else design(lab, method, ref, SPECS, n=40, workers=1)
    assert d.passed and d.searched > 100
    bands = d.prediction.metric_bands()
    for m, limit in SPECS.limits.items():
        assert bands[m].hi <= limit, m
    assert d.margins["disk_margin"] > 0.5  # the most robust of the designs that meet the specs
    assert d.chosen.metrics is not None and d.chosen.metrics["settling_s"] <= 1.0
    if method == "lqg":
        assert d.controller.kind == "lqg" and d.controller.estimator.n == 7  # two modes, the command delay


def test_pd_places_the_rigid_drives_poles():
    """The hub's gains put the rigid drive K / (s (tau s + 1)) under u = kp (r - theta) - kd theta_dot at the
    natural frequency and damping asked for."""
    m = design_model(twin_of_spec(specmod.load("nominal")).tables(noise=False), 1 / 500, n_modes=1)
    c = pd_controller(m, 15.0, 0.7, 0.0, 0.0, 25.0, 500.0)
    K, tau = m.drive_gain, m.drive_tau
    poles = np.roots([tau, 1.0 + K * c.K[2], K * c.K[0]])
    wn = math.sqrt(abs(poles[0] * poles[1]))
    assert wn == pytest.approx(15.0, rel=1e-9) and -poles.real.sum() / 2 / wn == pytest.approx(0.7, rel=1e-9)


def test_specs_no_design_meets_are_one_line_naming_them(lab, tmp_path):
    ref = reference_from("square:f=0.4;amplitude=25;duration=5", 500.0)
    with pytest.raises(DesignError, match=r"settling time <= 0.02 s: the closest design reaches .* \(\d+x\)"):
        design(lab, "lqr", ref, LoopSpecs.parse("settling=0.02"), n=10, workers=1)
    out = tmp_path / "d"
    r = flexjoint("design", "closed_loop", "--method", "pd", "--specs", "settling=0.02", "--n", "10", "--out", str(out))
    errors = [x for x in r.stderr.splitlines() if x.startswith("error: ")]  # after the search's progress line
    assert r.returncode == 2 and errors == [r.stderr.splitlines()[-1]] and "Traceback" not in r.stderr
    assert errors[0].startswith("error: no pd design meets the specs on the linear loop: settling time <= 0.02 s")
    assert not out.exists()
    for args, why in [(["--method", "h2"], "--method 'h2' unknown"), (["--method", "pd", "--weights", "q=1,1,1,1"],
                      "pd method has no weights"), (["--method", "lqr", "--weights", "q=1,1"], "q takes 4 numbers"),
                      (["--method", "lqr", "--specs", "settle=1"], "'settle' is not a spec")]:  # fmt: skip
        r = flexjoint("design", "closed_loop", *args, "--out", str(out))
        assert r.returncode == 2 and why in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert not out.exists()


def test_the_files_a_design_writes(lab, lqg, tmp_path):
    """design.json, controller.toml (a [controller] table that reads back as the same controller, an LQG's arrays
    too), loop.ssp (the twin under it as SSP 1.0) and the prediction with its report; accept judges it. The module's
    LQG design (its own search and prediction here repeated test_each_method_meets_the_specs_as_predicted's)."""
    d = lqg
    write_design(d, lab, tmp_path, rrd=False)
    doc = json.loads((tmp_path / "design.json").read_text())
    assert doc["method"] == "lqg" and doc["passed"] and set(doc["specs"]) == set(SPECS.limits)
    assert doc["linear"]["disk_margin"] == pytest.approx(d.margins["disk_margin"])
    back = controller_table(tomllib.loads((tmp_path / "controller.toml").read_text())["controller"])
    assert back.estimator is not None and np.array_equal(
        back.estimator.arrays()["L"], d.controller.estimator.arrays()["L"]
    )
    assert back.fmu_parameters(500.0) == d.controller.fmu_parameters(500.0)
    with zipfile.ZipFile(io.BytesIO((tmp_path / "loop.ssp").read_bytes())) as zf:
        assert "resources/controller.fmu" in zf.namelist() and b"lqg_L[1,1]" in zf.read("SystemStructure.ssd")
    for name in ("prediction.json", "prediction.parquet", "report.md", "figures/prediction_traces.png"):
        assert (tmp_path / name).is_file(), name
    assert "# Design: lqg" in (tmp_path / "report.md").read_text()
    r = flexjoint("accept", str(tmp_path))
    assert r.returncode == 0 and "settling time <= 1 s" in r.stdout
    r = flexjoint("accept", str(tmp_path), "--specs", "settling=0.05")
    assert r.returncode == 1 and "settling time <= 0.05 s: predicted up to" in r.stderr and "NOT met" in r.stderr
    r = flexjoint("report", str(tmp_path))  # the report again from the files, with its recording
    assert r.returncode == 0 and (tmp_path / "prediction.rrd").stat().st_size > 10_000, r.stderr


def test_given_weights_are_designed_as_they_are(lab):
    """--weights skip the search: the closed_loop spec's own Q on its own rig, judged, not refused."""
    ref = reference_from("square:f=0.4;amplitude=25;duration=5", 500.0)
    from harness.loopspecs import Weights

    d = design(lab, "lqr", ref, LoopSpecs.parse("settling=0.05"), weights=Weights((100, 500, 1, 1)), n=10, workers=1)
    assert d.searched == 0 and not d.passed
    assert spectral_radius(closed_loop(design_model(lab.tables(noise=False), 1 / 500), d.controller)) < 1
    assert controller_toml(d.controller, "x").startswith('# x\n[controller]\nkind = "state_feedback"')
