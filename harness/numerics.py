"""The same floating point on every x86-64 CPU: numpy's and OpenBLAS's code paths pinned before numpy loads.

numpy picks its SIMD kernels (AVX2 or AVX-512 loops of ``exp``, ``log``, sums) and OpenBLAS its BLAS kernels
(Haswell, SkylakeX, Zen) from the CPU it finds, and kernels differ in their last bits. A diagnosis decides by
comparisons of fits, and a closed loop that sticks or rattles where the noise decides turns a last bit into
another basin of a fit: the same records gave another verdict under OpenBLAS's SkylakeX kernels than under its
Haswell ones, on the same machine. :func:`pin_numerics` asks both for the kernels every x86-64 CPU with AVX2 and
FMA has (numpy's ``X86_V3`` loops, OpenBLAS's Haswell kernels) through their own environment variables,
``NPY_DISABLE_CPU_FEATURES`` and ``OPENBLAS_CORETYPE``, which they read when numpy loads; a value already set is
kept. The command line does it first thing (``flexjoint``, ``python -m harness``), so its results are the same bytes
on any such CPU; its Dask workers inherit the variables. The test suite loads this module as a pytest plugin
(``-p harness.numerics`` in pyproject.toml), which pins before the conftest files load numpy. A notebook or script
does it before it imports numpy::

    import harness

    harness.pin_numerics()
    import numpy as np

This module imports nothing but the standard library (``import harness`` loads numpy only on first use of a name).
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import MutableMapping
from importlib import metadata
from pathlib import Path

__all__ = ["OPENBLAS_CORE", "avx512_features", "pin_numerics", "pinnable", "pytest_load_initial_conftests"]

OPENBLAS_CORE = "Haswell"  # OpenBLAS's kernels for AVX2 and FMA
NEEDED_FLAGS = frozenset({"avx2", "fma"})  # /proc/cpuinfo's names of what numpy's X86_V3 and Haswell's kernels use


def avx512_features(numpy_version: str) -> str:
    """numpy's names of its dispatched AVX-512 targets, for ``NPY_DISABLE_CPU_FEATURES``: grouped as ``X86_V4``
    from numpy 2.4 on, one name per extension before (a name numpy does not dispatch is ignored, with a warning)."""
    major, minor = (int(p) for p in numpy_version.split(".")[:2])
    if (major, minor) >= (2, 4):
        return "X86_V4 AVX512_ICL AVX512_SPR"
    return "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"


def _cpu_flags() -> frozenset[str]:
    """The CPU's feature flags as Linux lists them (empty elsewhere: nothing is pinned there)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        if line.startswith("flags"):
            return frozenset(line.split(":", 1)[1].split())
    return frozenset()


def pinnable() -> bool:
    """Is this an x86-64 CPU with AVX2 and FMA, as Linux lists its flags (the CPUs :func:`pin_numerics` pins)?"""
    return platform.machine().lower() in ("x86_64", "amd64") and NEEDED_FLAGS <= _cpu_flags()


def pin_numerics(environ: MutableMapping[str, str] | None = None) -> bool:
    """Pin numpy's SIMD loops and OpenBLAS's kernels to those of x86-64 with AVX2 and FMA, where this is such a CPU
    (Linux); a variable already set is kept.

    Parameters
    ----------
    environ : mutable mapping of str to str, optional
        Where the variables go: default ``os.environ`` (this process, once numpy loads, and the processes it
        starts).

    Returns
    -------
    bool
        True when this process computes pinned: the variables are in its own environment and numpy was not loaded
        before them. False on another CPU or system, for another ``environ``, or when numpy was already loaded (then
        only the processes started from now on are pinned).
    """
    env = os.environ if environ is None else environ
    if not pinnable():
        return False
    try:
        version = metadata.version("numpy")
    except metadata.PackageNotFoundError:
        return False
    env.setdefault("OPENBLAS_CORETYPE", OPENBLAS_CORE)
    env.setdefault("NPY_DISABLE_CPU_FEATURES", avx512_features(version))
    return env is os.environ and "numpy" not in sys.modules


def pytest_load_initial_conftests(early_config: object, parser: object, args: list[str]) -> None:
    """pytest's hook before the conftest files load: :func:`pin_numerics` (the suite's processes, ``-n`` workers and
    the commands they start, compute as the command line does)."""
    pin_numerics()
