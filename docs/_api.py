"""The API reference's list, generated from ``harness.__all__`` on every build so that a new public name is
documented without anyone editing a page (docs/reference/api.md includes what this writes)."""

from __future__ import annotations

import inspect
from pathlib import Path

import harness

STAGES = {  # the package's stages in data-flow order: the first module part of each name's home
    "spec": "Campaign specs",
    "fmu": "The FMUs",
    "rig": "Campaigns and real records",
    "rundir": "Run directories",
    "ident": "Identification",
    "diagnosis": "Diagnosis",
    "twin": "Design and prediction",
    "loopspecs": "Design and prediction",
    "prediction": "Design and prediction",
    "design": "Design and prediction",
    "render": "Reports and recordings",
    "pipeline": "Pipelines",
    "sweep": "Pipelines",
    "executor": "Parallel work",
    "numerics": "Parallel work",
}


def write_api_page(path: Path) -> None:
    """Write the MyST page fragment: one section per stage, one autodoc directive per public name."""
    sections: dict[str, list[str]] = {}
    for name in harness.__all__:
        if name == "__version__":
            continue
        obj = getattr(harness, name)
        module = obj.__module__.split(".")[1]
        kind = (
            "autoexception"
            if inspect.isclass(obj) and issubclass(obj, BaseException)
            else ("autoclass" if inspect.isclass(obj) else "autofunction")
        )
        options = "\n   :members:" if kind == "autoclass" else ""
        block = f"```{{eval-rst}}\n.. {kind}:: harness.{name}{options}\n```\n"  # autodoc writes reST
        sections.setdefault(STAGES[module], []).append(block)
    text = "\n".join(f"## {title}\n\n" + "\n".join(blocks) for title, blocks in sections.items())
    if not path.exists() or path.read_text(encoding="utf-8") != text:  # unchanged: Sphinx need not re-read it
        path.write_text(text, encoding="utf-8")
