"""What a task runs in its worker: BLAS at one thread, the allocator as in a plain process, and the function and its
item unpacked from the bytes it travelled as.

Kept apart from :mod:`harness.executor`, and light (no harness stage; numpy only, which ``distributed`` has loaded
already), for Dask's scheduler: it unpickles
every task it is sent, and with it every module the task names. A task sent as ``fn(item, *shared)`` made the local
cluster's scheduler import what the item's class lives in (a campaign's ``harness.spec.Experiment``: the spec and
scipy.signal, 1.1-1.6 s before the first experiment of a fresh cluster ran). Sent as ``run_packed(pack(fn, item),
*shared)``, the scheduler reads this module and bytes; the shared objects stay futures it sees, and the worker
unpacks the rest.

The allocator: the nanny's default environment sets ``MALLOC_TRIM_THRESHOLD_=65536``, and glibc, once any malloc
threshold is set by hand, stops raising its mmap threshold dynamically: every array above 128 KiB is then a fresh
``mmap`` whose pages fault in and are zeroed (see :mod:`harness.executor`). A task in a worker whose environment has
it (a remote ``dask worker`` started by its nanny) first resets both thresholds once per process with ``mallopt``.

The kernels: a task packed with the client's :func:`kernels` first checks, once per process, that its
worker computes with the same (:func:`check_kernels`), and raises a one-line ``RuntimeError`` saying how to start the
workers when it does not: a worker that joined a remote cluster unpinned after the client checked the others.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import os
import pickle
import sys
from collections.abc import Callable, Mapping
from importlib import metadata
from typing import Any, TypeVar

import cloudpickle
import numpy as np
from distributed import get_worker
from threadpoolctl import ThreadpoolController, threadpool_info

from .numerics import kernels_mismatch

__all__ = ["MMAP_THRESHOLD", "call", "check_kernels", "kernels", "one_blas_thread", "pack", "run_packed", "worker_call"]

T = TypeVar("T")
# glibc's ceiling for its dynamic mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX): what a plain process
# reaches after its first large free; a worker whose thresholds were fixed by hand gets it back
MMAP_THRESHOLD = 32 << 20
_MALLOC_ENV = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
_BLAS: list[Any] = []
_MALLOC_TUNED: list[bool] = []
_KERNELS: list[dict[str, str]] = []
try:  # what numpy's loops dispatch to: the CPU's features less those NPY_DISABLE_CPU_FEATURES left out
    _UMATH = importlib.import_module("numpy._core._multiarray_umath")
except ImportError:  # numpy 1.x
    _UMATH = importlib.import_module("numpy.core._multiarray_umath")


def one_blas_thread() -> contextlib.AbstractContextManager:
    """Limit BLAS to one thread for the duration, as every task runs (the controller is built once per process:
    ~0.01 ms a call); for numerical work the client does between maps that must give the tasks' numbers."""
    if not _BLAS:
        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


def malloc_as_plain_process() -> bool:
    """Once per process, in a worker whose environment fixes a glibc malloc threshold (the nanny's default
    ``MALLOC_TRIM_THRESHOLD_=65536``, which also freezes the mmap threshold at 128 KiB): set the mmap threshold
    to glibc's dynamic ceiling and the trim threshold to twice that, as a plain process has them once it has freed
    one large array. Returns whether it changed anything (False off glibc, or when nothing was fixed)."""
    if _MALLOC_TUNED:
        return False
    _MALLOC_TUNED.append(True)
    if not sys.platform.startswith("linux") or not any(k in os.environ for k in _MALLOC_ENV):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
    return bool(mallopt(m_mmap_threshold, MMAP_THRESHOLD)) and bool(mallopt(m_trim_threshold, 2 * MMAP_THRESHOLD))


def call(fn: Callable[..., T], item: Any, *shared: Any) -> T:
    """``fn(item, *shared)`` with BLAS at one thread: a task, wherever it runs."""
    with one_blas_thread():
        return fn(item, *shared)


def worker_call(fn: Callable[..., T], item: Any, *shared: Any) -> T:
    """A task on a Dask worker: the allocator set as in a plain process (once), BLAS at one thread."""
    if not _MALLOC_TUNED:
        malloc_as_plain_process()
    return call(fn, item, *shared)


def kernels() -> dict[str, str]:
    """What this process computes with, as far as the bytes of a result depend on it: numpy's and scipy's versions,
    the SIMD targets numpy's loops dispatch to (``X86_V3``; with AVX-512 unpinned also ``X86_V4 ...``) and the
    kernels of every BLAS loaded (OpenBLAS's core type: ``Haswell``, ``SkylakeX``).

    Returns
    -------
    dict of str to str
        ``{"numpy": ..., "scipy": ..., "numpy loops": ..., "BLAS kernels": ...}``, for
        :func:`harness.numerics.kernels_mismatch`.
    """
    try:
        scipy = metadata.version("scipy")
    except metadata.PackageNotFoundError:
        scipy = "none"
    loops = " ".join(f for f in _UMATH.__cpu_dispatch__ if _UMATH.__cpu_features__.get(f)) or "baseline"
    blas = sorted(
        {str(i.get("architecture") or i.get("internal_api")) for i in threadpool_info() if i["user_api"] == "blas"}
    )
    return {"numpy": np.__version__, "scipy": scipy, "numpy loops": loops, "BLAS kernels": " ".join(blas) or "none"}


def check_kernels(expected: Mapping[str, Mapping[str, str]], dask_worker: Any = None) -> None:
    """Raise a one-line ``RuntimeError`` when this process does not compute with the kernels ``expected`` (the
    client's: ``{"kernels": kernels(), "pinned": harness.numerics.pinned_environ()}``); this
    process's kernels are read once. Run on every worker of a remote cluster as the client connects
    (``Client.run``, which passes ``dask_worker``), and by every task packed with them (:func:`run_packed`).

    Parameters
    ----------
    expected : mapping
        ``"kernels"``: the client's :func:`kernels`; ``"pinned"``: the variables it computes under.
    dask_worker : distributed.Worker, optional
        The worker it runs in (default: the task's, else none: the line names the process).

    Raises
    ------
    RuntimeError
        What differs and how to start the workers (:func:`harness.numerics.kernels_mismatch`).
    """
    if not _KERNELS:
        _KERNELS.append(kernels())
    if expected["kernels"] == _KERNELS[0]:
        return
    if dask_worker is None:
        with contextlib.suppress(ValueError):  # not in a task
            dask_worker = get_worker()
    where = dask_worker.address if dask_worker is not None else f"process {os.getpid()}"
    msg = kernels_mismatch(expected["kernels"], _KERNELS[0], where, expected["pinned"])
    if msg is not None:
        raise RuntimeError(msg)


def pack(fn: Callable[..., Any], item: Any, expected: Mapping[str, Mapping[str, str]] | None = None) -> bytes:
    """A task's function and item as bytes (cloudpickle: a module-level function by reference), opaque to the
    scheduler; with ``expected``, the kernels the task must run with (:func:`check_kernels`)."""
    return cloudpickle.dumps((fn, item, expected), protocol=pickle.HIGHEST_PROTOCOL)


def run_packed(packed: bytes, *shared: Any) -> Any:
    """The task :func:`pack` made, run on this worker with its ``shared`` objects (:func:`worker_call`), once its
    kernels are checked when it carries the client's."""
    fn, item, expected = pickle.loads(packed)
    if expected is not None:
        check_kernels(expected)
    return worker_call(fn, item, *shared)
