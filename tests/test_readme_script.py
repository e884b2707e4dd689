"""The README's "From a notebook" block, saved as script.py and run with ``python script.py`` as a user would: it
runs once (the local cluster's workers re-imported an unguarded script, ran its body three times and failed with
"Nanny failed to start"), makes its own data and prints a fit and a diagnosis."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

README = Path(__file__).parents[1] / "README.md"


def readme_script() -> str:
    section = README.read_text(encoding="utf-8").split("## From a notebook", 1)[1]
    return section.split("```python\n", 1)[1].split("```", 1)[0]


def test_the_readme_snippet_runs_as_a_plain_script(tmp_path):
    script = tmp_path / "script.py"
    script.write_text("print('body')\n" + readme_script())
    r = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "FLEXJOINT_WORKERS": "2"},  # the local cluster, whatever the machine
    )
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-3000:]
    body, fit, diagnosis = r.stdout.strip().splitlines()  # the body ran once
    assert body == "body"
    assert 50.0 < float(fit) <= 100.0 and not math.isnan(float(fit))
    assert diagnosis.startswith("backlash ")  # the injected effect, found
    assert (tmp_path / "runs" / "backlash" / "diagnosis.json").is_file()
