"""The manual's library tutorial (docs/tutorials/library.md): its script, the code cell after the page's "the
script" comment, saved as script.py and run with ``python script.py`` as a user would (the manual's build runs it
in a notebook's kernel): it runs once (the local cluster's workers re-imported an unguarded script, ran its body
three times and failed with "Nanny failed to start"), makes its own data and prints a fit and a diagnosis."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

PAGE = Path(__file__).parents[1] / "docs" / "tutorials" / "library.md"


def page_script() -> str:
    """The code cell that follows the page's "% the script:" comment."""
    after = PAGE.read_text(encoding="utf-8").split("\n% the script:", 1)[1]
    return after.split("```{code-cell} ipython3\n", 1)[1].split("```", 1)[0]


def test_the_tutorial_script_runs_as_a_plain_script(tmp_path):
    script = tmp_path / "script.py"
    script.write_text("print('body')\n" + page_script())
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
