"""Where the FMU and spec source trees live: the clone's ``fmus/`` and ``specs/``, or the copies an installed wheel
ships as package data (``harness/_fmus``, ``harness/_specs``); ``$FLEXJOINT_FMU_SRC`` overrides the FMU sources."""

from __future__ import annotations

import os
from functools import cache
from importlib import resources
from pathlib import Path

from .. import clone

__all__ = ["available_models", "bundled_dir", "fmu_source_dir"]


@cache
def bundled_dir(kind: str) -> Path:
    """Where the package's data tree ``kind`` ('fmus' or 'specs') lives (looked up once per process).

    An installed wheel ships it as package data (``harness/_fmus``, ``harness/_specs``); an editable install or a
    plain checkout reads the clone's top-level ``fmus/`` and ``specs/``. Returns the first that exists (the
    packaged path when neither does, so that error messages name where it was looked for).
    """
    if kind not in ("fmus", "specs"):
        raise ValueError(f"unknown data tree {kind!r}")
    packaged = Path(str(resources.files("harness").joinpath(f"_{kind}")))
    if packaged.is_dir():
        return packaged
    in_clone = clone.ROOT / kind
    return in_clone if in_clone.is_dir() else packaged


def fmu_source_dir() -> Path:
    """The FMU source tree: ``$FLEXJOINT_FMU_SRC``, else the bundled sources (see :func:`bundled_dir`)."""
    env = os.environ.get("FLEXJOINT_FMU_SRC")
    return Path(env) if env else bundled_dir("fmus")


def available_models() -> list[str]:
    """Model directories under the source tree (those with a modelDescription.xml)."""
    root = fmu_source_dir()
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if (p / "modelDescription.xml").is_file() and p.name != "common")
