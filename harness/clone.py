"""What a clone of the repository has beside the package and a wheel does not: the top-level ``fmus/`` and
``specs/`` (read when no packaged copy exists), the independent rig simulator ``tests/indeprig.py`` and the
benchmarks ``benchmarks/``."""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]  # the clone's root when the package runs from a clone


def load_file(name: str, relpath: str, env: str) -> ModuleType | None:
    """The module at ``relpath`` of the clone (or the file named by the environment variable ``env``), imported
    once as ``name``; None when there is no such file."""
    if name in sys.modules:
        return sys.modules[name]
    path = Path(os.environ.get(env, ROOT / relpath))
    if not path.is_file():
        return None
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"{path}: not a Python module")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def load_package(name: str) -> ModuleType | None:
    """The clone's top-level package ``name`` (e.g. ``benchmarks.bench``), importable with the clone's root on
    the path; None when the clone does not have it."""
    if not (ROOT / name.split(".")[0] / "__init__.py").is_file():
        return None
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return importlib.import_module(name)
