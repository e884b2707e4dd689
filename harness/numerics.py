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

A Dask worker the command did not start computes as its own environment says, and a variable set in a running worker
is too late: numpy (which ``distributed`` imports) has picked its kernels. :func:`harness.workercall.kernels` says
what a process computes with and :func:`kernels_mismatch` what differs between two of them, in one line that says how
to start the workers; :class:`harness.executor.PinnedNumerics` pins a remote cluster's workers by their nannies, which
set the variables before the worker process they start loads numpy.

This module imports nothing but the standard library (``import harness`` loads numpy only on first use of a name).
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Mapping, MutableMapping
from importlib import metadata
from pathlib import Path

__all__ = [
    "OPENBLAS_CORE",
    "PIN_VARS",
    "avx512_features",
    "computes_pinned",
    "kernels_mismatch",
    "pin_numerics",
    "pinnable",
    "pinned_environ",
    "pytest_load_initial_conftests",
]

OPENBLAS_CORE = "Haswell"  # OpenBLAS's kernels for AVX2 and FMA
PIN_VARS = ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")  # what pin_numerics sets, read once numpy loads
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


def pinned_environ(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """The variables of :data:`PIN_VARS` that ``environ`` (default ``os.environ``) sets: what a process started with
    it computes under, and what a remote cluster's workers are started with (:class:`harness.executor.PinnedNumerics`).
    """
    env = os.environ if environ is None else environ
    return {k: env[k] for k in PIN_VARS if k in env}


def computes_pinned(kernels: Mapping[str, str], pinned: Mapping[str, str]) -> bool:
    """Does a process with these kernels (:func:`harness.workercall.kernels`) compute as the variables ``pinned`` say
    (no loop numpy was told to leave out, OpenBLAS's kernels the core type asked for)? False for one that loaded numpy
    before it was pinned.

    Parameters
    ----------
    kernels : mapping of str to str
        :func:`harness.workercall.kernels` of the process.
    pinned : mapping of str to str
        :func:`pinned_environ` of the process.

    Returns
    -------
    bool
        True when nothing in ``kernels`` contradicts ``pinned``.
    """
    left_out = set(pinned.get("NPY_DISABLE_CPU_FEATURES", "").split())
    core = pinned.get("OPENBLAS_CORETYPE", "").lower()
    blas = {b.lower() for b in kernels.get("BLAS kernels", "").split()} - {"mkl", "blis", "none"}  # not OpenBLAS
    return not (left_out & set(kernels.get("numpy loops", "").split())) and (not core or blas <= {core})


def kernels_mismatch(
    here: Mapping[str, str], there: Mapping[str, str], where: str, pinned: Mapping[str, str]
) -> str | None:
    """What differs between the kernels this process computes with (``here``) and a worker's (``there``, at
    ``where``), as one line that says how to start the worker so that it gives this process's bytes; None when
    nothing differs.

    Parameters
    ----------
    here, there : mapping of str to str
        :func:`harness.workercall.kernels` of this process and of the worker.
    where : str
        The worker, as the line names it (its address).
    pinned : mapping of str to str
        :func:`pinned_environ` of this process: the variables the worker must be started with.

    Returns
    -------
    str or None
        ``"worker tcp://...: BLAS kernels SkylakeX (here Haswell), ...; start ..."``, or None.
    """
    diff = [f"{k} {there.get(k)} (here {v})" for k, v in here.items() if there.get(k) != v]
    if not diff:
        return None
    line = f"worker {where} computes with {', '.join(diff)}: its results would not be this process's bytes; "
    if any(there.get(k) != here.get(k) for k in ("numpy", "scipy")):
        return line + "install the same numpy and scipy on the workers as here"
    if pinned and not computes_pinned(here, pinned):
        return line + "this process loaded numpy before it was pinned: call harness.pin_numerics() before numpy loads"
    if pinned:
        env = " ".join(f"{k}='{v}'" for k, v in pinned.items())
        return line + (
            "start the workers with their nanny (plain `dask worker ADDRESS`, not --no-nanny: flexjoint pins them"
            f" itself) or with {env} in their environment"
        )
    return (
        line + "this process is not pinned: call harness.pin_numerics() before numpy is imported (as the command does)"
    )


def pytest_load_initial_conftests(early_config: object, parser: object, args: list[str]) -> None:
    """pytest's hook before the conftest files load: :func:`pin_numerics` (the suite's processes, ``-n`` workers and
    the commands they start, compute as the command line does)."""
    pin_numerics()
