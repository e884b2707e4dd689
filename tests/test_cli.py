"""The command line: user mistakes are one line on stderr and a non-zero exit, never a traceback."""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io

from harness.rundir import Manifest


def flexjoint(*args, cwd=None, env=None):
    env = None if env is None else {**os.environ, **env}
    return subprocess.run(
        [sys.executable, "-m", "harness.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=300,
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


@pytest.mark.parametrize("cell, kinds", [(np.inf, "infinite/NaN"), (-np.inf, "infinite/NaN"), (np.nan, "NaN")])
def test_import_says_what_a_non_finite_cell_holds(tmp_path, cell, kinds):
    t = np.arange(200) * 0.02
    rec = {"t": t, "u": np.sign(np.sin(t)), "theta_v": 0.01 * t, "alpha_v": 0 * t}
    rec["theta_v"][17] = cell
    scipy.io.savemat(tmp_path / "bad.mat", rec)
    line = _one_line_error(flexjoint("import", tmp_path / "bad.mat", "--out", tmp_path / "run"))
    assert line == (
        f"error: bad.mat: column 'theta_v' (theta) has 1 {kinds}/missing/non-numeric value(s), first at row 17: "
        f"{cell:g}; MATLAB v5"
    )
    assert not (tmp_path / "run").exists()


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
    accept = {"accept": {"min_fit": 80, "min_average_fit": 85}}
    Manifest(kind="campaign", spec=accept, experiments=[], sample_rate=50.0).write(tmp_path)
    cv = {n: (None if np.isnan(f) else f) for n, f in zip(names, fits, strict=True)}
    (tmp_path / "models" / "selected.json").write_text(json.dumps({"cv": cv}))
    r = flexjoint("accept", tmp_path)
    assert r.returncode == code, r.stderr + r.stdout
    if code:
        assert "b: 79.00 % < 80 %" in r.stderr and "c: unstable" in r.stderr


def test_malformed_manifest_is_one_line(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"kind": "campaign", "experiments": []}))
    r = flexjoint("accept", tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "manifest.json: manifest: missing key 'sample_rate'" in r.stderr
    (tmp_path / "manifest.json").write_text(
        json.dumps({"kind": "campaign", "experiments": [{"name": 3}], "sample_rate": 50})
    )
    r = flexjoint("accept", tmp_path)
    assert r.returncode == 2 and "manifest.experiments[0].name: expected str, got 3" in r.stderr


TINY = (
    '[campaign]\nname = "tiny"\nsample_rate = 50.0\n[plant]\ncoulomb_torque = 0.044\n'
    '[[experiment]]\nname = "sq"\nsignal = "square"\nf = 0.5\namplitude = 1.0\nduration = 4.0\n'
)


def test_version():
    from harness import __version__

    r = flexjoint("--version")
    assert r.returncode == 0 and r.stdout.strip() == f"flexjoint-harness {__version__}"


def test_out_that_is_a_file_is_one_line(tmp_path):
    f = tmp_path / "existing"
    f.write_text("not a run")
    line = _one_line_error(flexjoint("campaign", "specs/lab.toml", "--out", f, cwd=Path(__file__).parents[1]))
    assert line == f"error: --out {f}: not a directory; give a new or existing directory"
    line = _one_line_error(flexjoint("campaign", "lab", "--out", f / "run"))
    assert f"({f} is a file)" in line
    assert "not a directory" in _one_line_error(flexjoint("diagnose", "--real", tmp_path, "--out", f))
    assert f.read_text() == "not a run"


def test_campaign_too_large_for_the_machine_is_refused_with_the_estimate(tmp_path):
    t0 = time.perf_counter()
    line = _one_line_error(flexjoint("campaign", "lab", "--out", tmp_path / "r", "--set", "campaign.sample_rate=1e9"))
    assert time.perf_counter() - t0 < 60  # refused before allocating anything
    assert "needs ~" in line and "TiB of memory" in line and "this machine has" in line and "sample_rate" in line
    assert not (tmp_path / "r").exists()


def test_specs_lists_the_bundled_specs_and_init_copies_one(tmp_path):
    r = flexjoint("specs")
    assert r.returncode == 0, r.stderr
    names = [ln.split()[0] for ln in r.stdout.splitlines()[:-1]]
    assert {"lab", "nominal", "blind"} <= set(names) and "first lab" in r.stdout
    r = flexjoint("init", tmp_path / "mine", "--spec", "nominal")
    assert r.returncode == 0, r.stderr
    copied = tmp_path / "mine" / "nominal.toml"
    from harness.spec import SPEC_DIR

    assert copied.read_text() == (SPEC_DIR / "nominal.toml").read_text()
    assert "exists; pass --force" in _one_line_error(flexjoint("init", tmp_path / "mine", "--spec", "nominal"))
    assert flexjoint("init", tmp_path / "mine", "--spec", "nominal", "--force").returncode == 0
    bundled = "bundled: blind, blind_closed, closed_loop, cu_flexible_arm, lab, nominal"
    assert bundled in _one_line_error(flexjoint("init", tmp_path, "--spec", "nope"))


def test_build_failure_exits_non_zero(tmp_path, fmus):
    """A model and then the co-simulation master that do not compile: one line each. The cache starts with what the
    session built, so only the broken sources are compiled."""
    from harness.fmu.build import build_fmu, build_master, cache_dir
    from harness.fmu.sources import bundled_dir

    src = tmp_path / "fmus"
    shutil.copytree(bundled_dir("fmus"), src)
    model = src / "flexjoint" / "model.c"
    model.write_text(model.read_text() + "\nint broken( {\n")
    cache = tmp_path / "cache"
    cache.mkdir()
    for built in (*fmus.values(), build_fmu("armax"), build_master()):
        for f in (built, built.with_name(built.name + ".sha256")):
            if f.is_file():
                shutil.copy2(f, cache / f.name)
    assert cache_dir() != cache
    env = {"FLEXJOINT_FMU_SRC": str(src), "FLEXJOINT_CACHE": str(cache)}
    line = _one_line_error(flexjoint("build", env=env))
    assert line.startswith("error: building flexjoint failed: model.c:") and "error" in line[6:]
    model.write_text(model.read_text().replace("\nint broken( {\n", ""))
    master = src / "master" / "master.c"
    master.write_text(master.read_text() + "\nint broken( {\n")
    line = _one_line_error(flexjoint("build", env=env))
    assert line.startswith("error: building the co-simulation master failed: ") and "error" in line[6:], line
    env["FLEXJOINT_FMU_SRC"] = str(tmp_path / "empty")
    assert "empty ($FLEXJOINT_FMU_SRC) does not exist" in _one_line_error(flexjoint("build", env=env))


def test_truncated_fmu_in_the_cache_is_rebuilt_not_a_crash(fmus, tmp_path):
    """An interrupted build or a full disk left half an FMU in the cache: the campaign rebuilds it and runs."""
    cache = tmp_path / "cache"
    cache.mkdir()
    for path in fmus.values():
        for f in (path, path.with_name(path.name + ".sha256")):
            shutil.copy2(f, cache / f.name)
    bad = cache / fmus["flexjoint"].name
    bad.write_bytes(bad.read_bytes()[:1000])
    spec = tmp_path / "tiny.toml"
    spec.write_text(TINY)
    r = flexjoint("campaign", spec, "--out", tmp_path / "run", env={"FLEXJOINT_CACHE": str(cache)})
    assert r.returncode == 0, r.stderr
    from harness.fmu.build import cached_fmu_ok

    assert "Traceback" not in r.stderr and cached_fmu_ok(bad) and bad.stat().st_size > 1000
    assert (tmp_path / "run" / "manifest.json").exists()


def test_progress_is_a_live_status_in_a_terminal_and_lines_elsewhere(monkeypatch):
    """The library's progress(str) callable: per-item lines with the elapsed time; in a terminal also a live status
    line, which the command's result on stdout ends first."""
    import io

    from rich.console import Console

    from harness import cli

    for tty in (False, True):
        err_buf, out_buf = io.StringIO(), io.StringIO()
        monkeypatch.setattr(cli, "err", Console(file=err_buf, force_terminal=tty, width=100))
        monkeypatch.setattr(cli, "out", Console(file=out_buf, force_terminal=tty, width=100))
        say = cli._progress("simulated")
        assert (cli._status is not None) == tty
        say("prbs_b005 [1/9]")
        time.sleep(0.2)
        cli.out.print("9 experiments")
        assert cli._status is None  # stopped by the result (or never started)
        assert "prbs_b005 [1/9]" in err_buf.getvalue() and " s)" in err_buf.getvalue()
        cli._stop_status()


def test_help_lists_every_command_with_its_first_sentence_whole():
    """`flexjoint --help` on a narrow terminal: each command's summary is its docstring's first sentence, wrapped,
    never cut with "..."."""
    from harness.cli import app

    r = flexjoint("--help", env={"COLUMNS": "60"})
    listed = "".join(r.stdout.split("Commands:", 1)[1].split())  # the wrapping's spaces and breaks left out
    assert r.returncode == 0 and "..." not in listed, r.stdout
    for cmd in app.registered_commands:
        name = cmd.name or cmd.callback.__name__.rstrip("_")
        words = cmd.callback.__doc__.split("\n\n")[0].split()
        end = next(i for i, w in enumerate(words) if w.endswith(".") or i == len(words) - 1)  # click's sentence
        assert name + "".join(words[: end + 1]) in listed, name
