"""The command line starts at once and a Ctrl-C at any moment is one line and exit code 130. No test here waits a
set time: an interrupt during loading comes from an import hook at a chosen module, one during the work is sent
once the command has reported progress, one during the exit from an exit handler."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

HEAVY = ("numpy", "pandas", "fmpy", "dask", "distributed", "rerun", "matplotlib", "scipy", "control", "pyarrow")

# The console script's entry point run with argv[3:] as its arguments, Ctrl-C coming at a chosen moment:
# argv[2] "raise": KeyboardInterrupt (what Ctrl-C raises) when module argv[1] is first imported;
# "signal": a real SIGINT to the process at that import (through the signal handler in force then);
# "twice": a SIGINT there and another while the first is being handled (the library cleaning up after it);
# "exit": a SIGINT while the process runs its exit handlers, the command done (argv[1] unused).
CTRL_C_AT = """
import atexit, os, signal, sys, time
at, how, args = sys.argv[1], sys.argv[2], sys.argv[3:]

def ctrl_c():
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(30)  # the handler runs at the latest when the signal interrupts the sleep

class CtrlC:
    def find_spec(self, name, path=None, target=None):
        if name != at:
            return None
        sys.meta_path.remove(self)
        if how == "raise":
            raise KeyboardInterrupt
        if how == "signal":
            ctrl_c()
        try:
            ctrl_c()
        except KeyboardInterrupt:
            ctrl_c()

if how == "exit":
    atexit.register(ctrl_c)
else:
    sys.meta_path.insert(0, CtrlC())
sys.argv = ["flexjoint", *args]
from harness.__main__ import main
main()
"""


def _ctrl_c_at(module: str, how: str, *args: str, tmp_path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", CTRL_C_AT, module, how, *args],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "FLEXJOINT_WORKERS": "1"},
        timeout=300,
    )


def _loaded(args: list[str] | None) -> list[str]:
    """The heavy modules (and rich) loaded by a child that imports the command line and, unless ``args`` is None,
    runs it with ``args`` (exit code 2 for none: usage shown)."""
    run = "" if args is None else f"sys.argv = ['flexjoint', *{args!r}]; from harness.__main__ import main; main()"
    loaded = f"json.dumps([m for m in {(*HEAVY, 'rich')!r} if m in sys.modules])"
    code = f"import atexit, json, sys; atexit.register(lambda: print({loaded}))\nimport harness.cli\n{run}"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode in (0, 2) and "Traceback" not in r.stderr, r.stdout + r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_the_command_line_loads_without_the_numerical_stack():
    assert _loaded(None) == []
    assert _loaded(["--version"]) == []  # rich (~40 ms) too is loaded only to print through it
    for args in (["--help"], ["campaign", "--help"], []):
        assert _loaded(args) in ([], ["rich"]), args  # typer's help is drawn by rich
    r = subprocess.run([sys.executable, "-m", "harness", "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("flexjoint-harness "), r.stderr


@pytest.mark.parametrize(
    "args, loaded",
    [
        (["campaign", "no_such_spec", "--out", "r"], {"numpy"}),  # the spec read: numpy for its signals' tables
        (["campaign", "lab", "--set", "plant.backlsh=0.004", "--out", "r"], {"numpy"}),
        (["run", "--spec", "no_such_spec", "--out", "r"], {"numpy"}),
        (["diagnose", "--real", "r", "--sim", "no_such_spec"], {"numpy"}),
        (["identify", "no_such_run"], {"numpy", "pandas", "pyarrow"}),  # the manifest read
        (["diagnose", "--real", "no_such_run"], {"numpy", "pandas", "pyarrow"}),
        (["design", "closed_loop", "--method", "h2", "--out", "r"], set()),
        (["design", "closed_loop", "--method", "lqr", "--weights", "q=1,1", "--out", "r"], set()),
        (["design", "closed_loop", "--method", "pd", "--specs", "settle=1", "--out", "r"], set()),
        (["predict", "nominal", "--controller", "lqr:K=1,2,3,4", "--out", "r"], {"numpy"}),  # the controller's arrays
        (["predict", "nominal", "--controller", "pid:kp=1", "--specs", "settling=0", "--out", "r"], {"numpy"}),
        (["predict", "nominal", "--out", "r"], {"numpy"}),  # no controller given, nor a record to take it from
    ],
)
def test_a_mistake_in_what_a_command_is_given_is_told_before_it_loads_its_work(args, loaded):
    """A bad spec, --set, run directory, design method, weights, loop specs or controller is one line before the
    command loads what it runs (scipy, fmpy, Dask, matplotlib) or starts its cluster: a mistake is told in a fraction
    of a second."""
    assert set(_loaded(args)) - {"rich"} == loaded, args


def test_the_modules_run_preloads_into_its_workers_exist():
    """flexjoint run's workers import every stage's task modules as they start (harness.cli.PIPELINE_TASKS): a module
    renamed away would stop the workers from starting (spawned workers import them one by one)."""
    import importlib.util

    from harness.cli import PIPELINE_TASKS

    for name in PIPELINE_TASKS:
        assert importlib.util.find_spec(name) is not None, name
    assert set(PIPELINE_TASKS) >= {"harness.rig.campaign", "harness.ident.gridfit", "harness.render.figures"}


@pytest.mark.parametrize(
    "module, how, args",
    [
        ("typer", "raise", ["--version"]),  # the command line itself still loading
        ("typer", "signal", ["--version"]),
        ("harness.rig.campaign", "raise", ["campaign", "lab", "--out", "r"]),  # a command loading what it runs
        ("harness.rig.campaign", "signal", ["campaign", "lab", "--out", "r"]),
        ("pyarrow", "signal", ["campaign", "lab", "--out", "r"]),  # ... deeper, inside the library's imports
        ("harness.diagnosis.diagnose", "raise", ["diagnose", "--real", "real", "--out", "r"]),  # past its checks
        ("harness.rig.campaign", "twice", ["campaign", "lab", "--out", "r"]),  # twice: the second ends it at once
        ("", "exit", ["specs"]),  # while the process ends, the command done
    ],
)
def test_ctrl_c_at_any_moment_is_one_line_and_exit_130(tmp_path, module, how, args):
    (tmp_path / "real").mkdir()  # a run directory (its manifest only), for a command that checks its input first
    (tmp_path / "real" / "manifest.json").write_text('{"kind": "import", "experiments": [], "sample_rate": null}')
    r = _ctrl_c_at(module, how, *args, tmp_path=tmp_path)
    assert r.returncode == 130, r.stderr
    assert r.stderr == "error: interrupted\n", r.stderr
    assert not (tmp_path / "r").exists()


def test_ctrl_c_during_the_work_is_one_line_and_exit_130(tmp_path):
    """SIGINT to the whole process group once the campaign has reported its first experiment."""
    p = subprocess.Popen(
        [sys.executable, "-m", "harness", "campaign", "lab", "--out", str(tmp_path / "r")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "FLEXJOINT_WORKERS": "1"},  # serial: the CLI's own handling, not Dask's shutdown
    )
    seen = []
    for line in p.stderr:  # progress lines: "simulated <experiment> [k/n] (t s)"
        seen.append(line)
        if line.startswith("simulated"):
            break
    os.killpg(p.pid, signal.SIGINT)
    _, rest = p.communicate(timeout=120)
    stderr = "".join(seen) + rest
    assert p.returncode == 130, stderr
    assert "Traceback" not in stderr and stderr.strip().splitlines()[-1] == "error: interrupted", stderr
    assert all(x.startswith("simulated") for x in stderr.strip().splitlines()[:-1]), stderr
    assert not (tmp_path / "r" / "manifest.json").exists()


@pytest.mark.parametrize(
    "args, busy",
    [
        (["campaign", "lab", "--out", "r"], "simulated"),  # after the first experiment: both workers simulating
        (["run", "--out", "r"], "run calibration"),  # calibrated: both workers in the identification grid
    ],
)
def test_ctrl_c_while_the_workers_are_busy_is_one_line(tmp_path, args, busy):
    """SIGINT to the whole process group (a terminal's Ctrl-C) while the local cluster's workers run tasks: the
    command's one line, no worker's traceback (the workers printed their KeyboardInterrupt, the client a
    ``KeyError: 'tcp://...'``), exit 130, and no cluster process left behind."""
    p = subprocess.Popen(
        [sys.executable, "-m", "harness", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        start_new_session=True,
        env={**os.environ, "FLEXJOINT_WORKERS": "2"},
    )
    seen = []
    for line in p.stderr:
        seen.append(line)
        if line.startswith(busy):
            break
    os.killpg(p.pid, signal.SIGINT)
    _, rest = p.communicate(timeout=120)
    assert p.returncode == 130, "".join(seen) + rest
    assert rest == "error: interrupted\n", rest
    left = subprocess.run(["pgrep", "-f", f"harness.localcluster.*{tmp_path}"], capture_output=True, text=True)
    assert left.stdout == "", left.stdout
