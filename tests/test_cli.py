"""The command line: user mistakes are one line on stderr and a non-zero exit, never a traceback."""

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest


def flexjoint(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "harness.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300
    )


def _one_line_error(r, code=2):
    assert r.returncode == code, r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    assert "Traceback" not in r.stderr
    return lines[0]


def test_unknown_spec_key_lists_valid_names(tmp_path):
    line = _one_line_error(flexjoint("campaign", "lab", "--out", tmp_path / "r", "--set", "plant.backlsh=0.004"))
    assert "backlsh" in line and "backlash" in line and "coulomb_torque" in line
    assert not (tmp_path / "r").exists()


def test_missing_spec_and_missing_run(tmp_path):
    assert "not found" in _one_line_error(flexjoint("campaign", tmp_path / "nope.toml", "--out", tmp_path / "r"))
    assert "manifest.json" in _one_line_error(flexjoint("identify", tmp_path))


def test_import_rejects_nan_and_accepts_good_csv(tmp_path):
    t = np.arange(200) * 0.02
    good = pd.DataFrame({"t": t, "u": np.sign(np.sin(t)), "theta_v": 0.01 * t, "alpha_v": 0 * t})
    good.to_csv(tmp_path / "good.csv", index=False)
    bad = good.copy()
    bad.loc[17, "theta_v"] = np.nan
    bad.to_csv(tmp_path / "bad.csv", index=False)
    line = _one_line_error(flexjoint("import", tmp_path / "bad.csv", "--out", tmp_path / "run"))
    assert "theta_v" in line and "row 17" in line
    r = flexjoint("import", tmp_path / "good.csv", "--out", tmp_path / "run")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "run" / "data" / "good.parquet").exists()


def test_campaign_command_writes_a_run(tmp_path):
    spec = tmp_path / "tiny.toml"
    spec.write_text(
        '[campaign]\nname = "tiny"\nsample_rate = 50.0\n[plant]\ncoulomb_torque = 0.044\n'
        '[[experiment]]\nname = "sq"\nsignal = "square"\nf = 0.5\namplitude = 1.0\nduration = 4.0\n'
    )
    r = flexjoint("campaign", spec, "--out", tmp_path / "run")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert m["experiments"][0]["n"] == 200


@pytest.mark.parametrize("fits, code", [([92.0, 90.5, 95.0], 0), ([92.0, 79.0, float("nan")], 1)])
def test_accept_gates_the_selected_model(tmp_path, fits, code):
    names = ["a", "b", "c"]
    (tmp_path / "models").mkdir()
    (tmp_path / "manifest.json").write_text(
        json.dumps({"kind": "campaign", "spec": {"accept": {"min_fit": 80, "min_average_fit": 85}}, "experiments": []})
    )
    cv = {n: (None if np.isnan(f) else f) for n, f in zip(names, fits, strict=True)}
    (tmp_path / "models" / "selected.json").write_text(json.dumps({"cv": cv}))
    r = flexjoint("accept", tmp_path)
    assert r.returncode == code, r.stderr + r.stdout
    if code:
        assert "b: 79.00 % < 80 %" in r.stderr and "c: unstable" in r.stderr
