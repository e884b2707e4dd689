"""The command line starts at once and a Ctrl-C at any moment is one line and exit code 130. No test here waits a
set time: an interrupt during loading is raised by an import hook at a chosen module, one during the work is sent
when the command has reported progress."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

# a child that raises KeyboardInterrupt (what Ctrl-C raises) when module argv[1] is first imported, then runs the
# console script's entry point with the remaining arguments
INTERRUPT_AT_IMPORT = """
import sys
AT = sys.argv[1]
class Interrupt:
    def find_spec(self, name, path=None, target=None):
        if name == AT:
            raise KeyboardInterrupt
        return None
sys.meta_path.insert(0, Interrupt())
sys.argv = ["flexjoint", *sys.argv[2:]]
from harness.__main__ import main
main()
"""


def _interrupted_at(module: str, *args: str, tmp_path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", INTERRUPT_AT_IMPORT, module, *args],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "FLEXJOINT_WORKERS": "1"},
        timeout=300,
    )


def test_the_command_line_loads_without_the_numerical_stack():
    code = (
        "import sys, harness.cli; print(sorted(m for m in ('numpy', 'pandas', 'fmpy', 'distributed', 'rerun', "
        "'matplotlib', 'scipy', 'control') if m in sys.modules))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
    r = subprocess.run([sys.executable, "-m", "harness", "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("flexjoint-harness "), r.stderr


@pytest.mark.parametrize(
    "module, args",
    [
        ("typer", ["--version"]),  # the command line itself still loading
        ("harness.rig.campaign", ["campaign", "lab", "--out", "r"]),  # a command loading what it runs
        ("pyarrow", ["campaign", "lab", "--out", "r"]),  # ... deeper, inside the library's imports
        ("harness.diagnosis.diagnose", ["diagnose", "--real", "r"]),
    ],
)
def test_ctrl_c_while_loading_is_one_line_and_exit_130(tmp_path, module, args):
    r = _interrupted_at(module, *args, tmp_path=tmp_path)
    assert r.returncode == 130, r.stderr
    assert r.stderr.strip() == "error: interrupted", r.stderr
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
    assert not (tmp_path / "r" / "manifest.json").exists()
