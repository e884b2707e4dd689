"""One executor for all parallel work, on Dask ``distributed``: an embedded local cluster, a remote one, or serial.

``Executor(workers, scheduler, progress)`` picks its backend once:

- ``workers == 1`` (or env ``FLEXJOINT_WORKERS=1``): serial, in this process, without a cluster (the debug
  path; breakpoints and tracebacks work as usual);
- inside a Dask task (a worker process) with no explicit ``scheduler``: serial too, so nested parallel code (a
  campaign inside a sweep task) never starts a cluster inside a cluster;
- inside :func:`session` (or :func:`use`) with ``workers`` and ``scheduler`` left at None: the session's
  backend, shared;
- ``scheduler`` (or env ``FLEXJOINT_SCHEDULER``), e.g. ``tcp://10.0.0.5:8786``: ``distributed.Client`` to it;
- else an embedded ``LocalCluster``: ``workers`` (default :func:`harness.machine.default_workers`:
  ``FLEXJOINT_WORKERS``, else min(2, cpu count)) processes of one thread each, no dashboard unless ``dashboard``
  gives an address, logs silenced below ERROR; run by :mod:`harness.localcluster` in a process of its own, so that
  its workers never re-import the caller's ``__main__`` (a plain script calling the library runs once) and a
  terminal's Ctrl-C reaches the command alone, which shuts the cluster down quietly;
- ``backend="processes"``: a plain ``multiprocessing`` pool of ``workers`` spawned processes, no Dask: the
  machine's own reference for the Dask backends (``flexjoint bench`` measures both on the same stage).

``ex.map(fn, items, *shared)`` returns ``[fn(item, *shared) for item in items]`` in item order. ``fn`` must be
importable on the workers (a module-level function of an installed package: it is pickled by reference); the
function and its item travel as bytes the scheduler does not read (:mod:`harness.workercall`: reading them made it
import the package's stack before the first task of a fresh cluster ran); ``shared`` objects are sent to every
worker once per executor (``scatter(broadcast=True)``), not once per task (the ``processes`` backend: pickled once
per executor into a scratch file each process reads once); both know them by identity, so a shared object must not
change between the maps of one executor.
Every call runs with BLAS limited to one thread (threadpoolctl), on the workers and on the serial path alike:
the project's numerical work is small matrices, where BLAS threads only oversubscribe the cores, and one thread
everywhere keeps the results identical in every backend. A task that raises re-raises the same exception type and
message on the client; a task that kills its worker three times (a crash in an FMU) becomes a ``RuntimeError``. A
worker lost mid-map (machine gone) is not an error: Dask reruns its tasks elsewhere and each result is still taken
exactly once; a task the scheduler gave up on with its worker (cancelled, "already forgotten") is submitted again,
up to RESUBMITS times.

A task runs as fast in a Dask worker as in a plain process: :func:`local_cluster` starts its workers without the nanny's
``MALLOC_TRIM_THRESHOLD_`` (which makes glibc map and zero every array above 128 KiB afresh), a task in a worker whose
environment has it anyway (a remote ``dask worker``) first resets both malloc thresholds once per process with
``mallopt`` (to :data:`harness.workercall.MMAP_THRESHOLD`, and twice that for trimming), and the local cluster runs
without Dask's statistical profiler and with a slow event-loop tick and monitors (:data:`CLUSTER_CONFIG`), which would
otherwise take the GIL from a task's thread; a remote cluster keeps its own configuration. The measurements behind each
are on the manual's validation page.

The same bytes on a cluster the user started: numpy and OpenBLAS pick their kernels as numpy loads, from the variables
:func:`harness.numerics.pin_numerics` sets, which a ``dask worker`` started by hand does not have, and which are too
late once its worker process runs (``distributed`` imports numpy; its own ``Environ`` plugin sets them there, and the
kernels stay SkylakeX). Connecting to a remote scheduler registers :class:`PinnedNumerics`, a nanny plugin that puts
the client's variables into each nanny's pre-spawn environment and restarts its worker when they change it, so the
worker process loads numpy pinned: a plain ``dask worker ADDRESS --nworkers 2 --nthreads 1`` then gives the serial
bytes. Then every worker's kernels are checked against the client's (:func:`harness.workercall.check_kernels`), and
so is every task's worker (one that joined later); a worker that differs (started ``--no-nanny``, other numpy) is a
one-line ``RuntimeError`` saying how to start it, before any task runs. A scheduler that does not answer, or workers
that cannot load this package, are one line too, within :data:`CONNECT_TIMEOUT_S`.

No shared filesystem: built FMUs travel as :class:`FmuBytes` and :func:`fmu_file` writes each once per worker
process; the co-simulation's step loops (``fmus/master``) reach a remote cluster's workers as bytes too
(:class:`MasterLibrary`), so a worker needs no compiler; :func:`worker_cache` keeps per-process objects (a loaded
:class:`harness.fmu.cosim.Rig`) between tasks.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import contextvars
import hashlib
import multiprocessing
import os
import pickle
import shutil
import socket
import tempfile
import threading
import uuid
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing.util import Finalize
from pathlib import Path
from typing import Any, TypeVar

from distributed import Client, as_completed, get_worker
from distributed.client import FutureCancelledError
from distributed.comm.addressing import parse_address, parse_host_port
from distributed.diagnostics.plugin import NannyPlugin, WorkerPlugin
from distributed.scheduler import KilledWorker

from .clusterprocess import LocalProcessCluster, adopt, prestart, scheduler_from_env
from .fmu.build import build_master, install_master
from .fmu.cosim import Rig
from .localcluster import CLUSTER_CONFIG
from .machine import default_workers, env_workers
from .numerics import pinned_environ
from .workercall import call, check_kernels, kernels, one_blas_thread, pack, run_packed

__all__ = [
    "CLUSTER_CONFIG",
    "RESUBMITS",
    "Executor",
    "FmuBytes",
    "LocalProcessCluster",
    "MasterLibrary",
    "PinnedNumerics",
    "fmu_bytes",
    "fmu_file",
    "in_session",
    "in_worker",
    "local_cluster",
    "one_blas_thread",
    "prestart",
    "session",
    "use",
    "worker_cache",
    "worker_rig",
]

T = TypeVar("T")
Progress = Callable[[str], None]

CONNECT_TIMEOUT_S = 5.0  # a scheduler that does not answer by then is an error (the command's line well within 10 s)
CACHE_SIZE = 8  # worker_cache entries kept per process (least recently used dropped, and closed, first)
INSTALL = "install flexjoint-harness, the version of this command, where the workers run"
RESUBMITS = 2  # a task the scheduler cancelled on its own (lost with its worker) is submitted this many times more
BACKENDS = ("dask", "processes")
_SESSION: contextvars.ContextVar[Executor | None] = contextvars.ContextVar("flexjoint_executor", default=None)


# ----------------------------------------------------------------------------------------------- FMUs as bytes
@dataclass(frozen=True)
class FmuBytes:
    """A built FMU as bytes (it travels to workers that do not see the client's files): file name, content,
    sha256 (hex) of the content."""

    name: str
    data: bytes
    sha256: str

    def __repr__(self) -> str:  # the bytes would flood any log
        return f"FmuBytes({self.name!r}, {len(self.data)} bytes, sha256={self.sha256[:12]})"


def fmu_bytes(path: Path | str) -> FmuBytes:
    """Read a built FMU into an :class:`FmuBytes`."""
    data = Path(path).read_bytes()
    return FmuBytes(Path(path).name, data, hashlib.sha256(data).hexdigest())


_FMU_LOCK = threading.Lock()
_FMU_FILES: dict[str, Path] = {}
_FMU_DIR: list[Path] = []


def fmu_file(fmu: FmuBytes) -> Path:
    """The FMU as a file in this process's scratch directory, written once per process (keyed by sha256) and
    removed when the process exits."""
    with _FMU_LOCK:
        path = _FMU_FILES.get(fmu.sha256)
        if path is not None and path.is_file():
            return path
        if hashlib.sha256(fmu.data).hexdigest() != fmu.sha256:
            raise ValueError(f"FMU {fmu.name}: content does not match its sha256 (corrupted in transfer)")
        if not _FMU_DIR:
            d = Path(tempfile.mkdtemp(prefix="flexjoint-fmus-"))
            Finalize(None, shutil.rmtree, args=(str(d),), kwargs={"ignore_errors": True}, exitpriority=0)
            _FMU_DIR.append(d)
        path = _FMU_DIR[0] / fmu.sha256[:16] / fmu.name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(fmu.data)
        _FMU_FILES[fmu.sha256] = path
        return path


class MasterLibrary(WorkerPlugin):
    """The co-simulation's step loops (``fmus/master``, built by the client) as bytes for every worker of a remote
    cluster, present and joining later: each installs them into its own cache (:func:`harness.fmu.build.install_master`)
    instead of compiling them, so a worker needs no compiler, as the FMUs travel as bytes."""

    def __init__(self, library: FmuBytes) -> None:
        self.library = library
        self.name = f"flexjoint-master-{library.sha256[:12]}"

    def setup(self, worker: Any) -> None:
        install_master(self.library.name, self.library.data)


class PinnedNumerics(NannyPlugin):
    """The client's pinned numerics (:func:`harness.numerics.pinned_environ`: ``OPENBLAS_CORETYPE``,
    ``NPY_DISABLE_CPU_FEATURES``) for every nanny of a remote cluster, present and joining later: each puts them into
    the environment it starts its worker process with (its pre-spawn environment, set before the process starts and
    so before it loads numpy; distributed's ``Environ`` plugin sets them inside the running process, too late) and
    restarts its worker when that changes its environment. Registered once per cluster and set of variables
    (idempotent): a later command on the same cluster restarts nothing.

    Parameters
    ----------
    environ : mapping of str to str
        The variables, as the client computes under them.
    """

    idempotent = True

    def __init__(self, environ: Mapping[str, str]) -> None:
        self.environ = dict(environ)
        self.restart = False
        digest = hashlib.sha256(repr(sorted(self.environ.items())).encode()).hexdigest()
        self.name = f"flexjoint-numerics-{digest[:12]}"

    def setup(self, nanny: Any) -> None:
        """Set the variables for the worker processes ``nanny`` starts; restart the running one when it was started
        without them (the nanny's own environment is what it started it with)."""
        self.restart = any(os.environ.get(k) != v for k, v in self.environ.items())
        nanny.pre_spawn_env.update(self.environ)
        nanny.env.update(self.environ)


# ----------------------------------------------------------------------------------------------- per-process cache
_CACHE: OrderedDict[tuple[int, str], Any] = OrderedDict()
_CACHE_LOCK = threading.Lock()


def worker_cache(key: str, factory: Callable[[], T]) -> T:
    """A per-process memo: ``factory()`` the first time ``key`` is asked for in this process, the same object
    afterwards. Entries are also per thread (a worker running several threads never hands one object, such as a
    loaded Rig, to two tasks at once); the least recently used beyond :data:`CACHE_SIZE` are dropped and closed.
    """
    k = (threading.get_ident(), key)
    with _CACHE_LOCK:
        if k in _CACHE:
            _CACHE.move_to_end(k)
            return _CACHE[k]
    value = factory()
    evicted = []
    with _CACHE_LOCK:
        _CACHE[k] = value
        while len(_CACHE) > CACHE_SIZE:
            evicted.append(_CACHE.popitem(last=False)[1])
    for v in evicted:
        close = getattr(v, "close", None)
        if callable(close):
            with contextlib.suppress(Exception):
                close()
    return value


def worker_rig(fmus: Mapping[str, FmuBytes | Path | str]) -> Any:
    """The rig twin (:class:`harness.fmu.cosim.Rig`) of ``{"flexjoint": ..., "daq": ...[, "controller": ...]}``,
    loaded once per process (and thread) and reused by every later task; FMUs given as bytes are written with
    :func:`fmu_file`."""

    files = {k: fmu_file(v) if isinstance(v, FmuBytes) else Path(v) for k, v in fmus.items()}
    digest = {k: v.sha256 if isinstance(v, FmuBytes) else str(Path(v).resolve()) for k, v in fmus.items()}
    key = f"rig:{digest['flexjoint']}:{digest['daq']}:{digest.get('controller')}"
    return worker_cache(key, lambda: Rig(files["flexjoint"], files["daq"], files.get("controller")))


# ----------------------------------------------------------------------------------------------- process pool
_IN_POOL: list[bool] = []
_SHARED: OrderedDict[str, tuple] = OrderedDict()


def _pool_init() -> None:
    """A process of the ``processes`` backend: marked as a worker (nested executors run serially in it)."""
    _IN_POOL.append(True)


def _pool_call(fn: Callable[..., T], item: Any, token: str, blob: Path | None) -> T:
    """A task of the ``processes`` backend: the map's shared objects read once per process (from the file the
    client wrote once per map), then ``fn(item, *shared)`` with BLAS at one thread."""
    if token not in _SHARED:
        _SHARED[token] = pickle.loads(blob.read_bytes()) if blob is not None else ()
        while len(_SHARED) > 2:
            _SHARED.popitem(last=False)
    return call(fn, item, *_SHARED[token])


def in_session() -> bool:
    """True inside :func:`session` (or :func:`use`): an ``Executor()`` then runs on that command's cluster."""
    return _SESSION.get() is not None


def in_worker() -> bool:
    """True inside a Dask worker process (a task's code) or a process of the ``processes`` backend."""
    if _IN_POOL:
        return True
    try:
        get_worker()
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------------------------- executor
def _first_line(exc: BaseException) -> str:
    """An exception's message, its first line (its type's name when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _connect(scheduler: str, timeout: float | None = None) -> Any:
    """A ``distributed.Client`` of the scheduler at ``scheduler``, or a one-line ``RuntimeError`` within ``timeout``
    seconds (default :data:`CONNECT_TIMEOUT_S`): a TCP address is first dialled once (nothing listening is an answer
    at once, where Dask retries until its timeout)."""
    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    try:
        protocol, loc = parse_address(scheduler)
        if protocol in ("tcp", "tls"):
            host, port = parse_host_port(loc)
            with socket.create_connection((host, port), timeout=timeout):
                pass
        return Client(scheduler, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise RuntimeError(f"cannot connect to the Dask scheduler at {scheduler}: {_first_line(exc)}") from None
    except Exception as exc:  # something else answers there (Dask read its reply's length as 3 EiB: MemoryError)
        raise RuntimeError(
            f"cannot connect to the Dask scheduler at {scheduler}: what answers there is not one ({type(exc).__name__})"
        ) from None


def local_cluster(n_workers: int, dashboard: str | None = None) -> LocalProcessCluster:
    """The embedded local cluster (:class:`LocalProcessCluster`): ``n_workers`` processes of one thread on
    127.0.0.1, worker logs below CRITICAL silenced, the dashboard only at ``dashboard`` (e.g. ``":8787"``) when
    given, started under :data:`harness.localcluster.CLUSTER_CONFIG` (no malloc trim threshold, no profiler, slow
    ticks and monitors: see the module)."""
    return LocalProcessCluster(n_workers, dashboard)


class Executor:
    """Runs ``fn(item, *shared)`` for many items: serially, on an embedded LocalCluster or on a remote Dask
    scheduler (see the module docstring for which). A context manager; :meth:`close` releases what it started.
    """

    def __init__(
        self,
        workers: int | None = None,
        scheduler: str | None = None,
        progress: Progress | None = None,
        *,
        dashboard: str | None = None,
        backend: str = "dask",
    ) -> None:
        if workers is None:
            workers = env_workers()
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        if backend == "processes" and scheduler is not None:
            raise ValueError("the processes backend runs on this machine: it takes no scheduler")
        self.progress = progress
        self.client: Any = None
        self.pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._pool_size = 0
        self._cluster: Any = None
        self._owns_client = False
        self._scattered: dict[int, tuple[Any, Any]] = {}
        self._blobs: dict[tuple[int, ...], tuple[tuple, str, Path | None]] = {}
        self._scratch: Path | None = None
        self.numerics: dict[str, dict[str, str]] | None = None  # the kernels a remote task checks it runs with
        active = _SESSION.get()
        single = workers is None and scheduler is None and default_workers() == 1
        if workers == 1 or (scheduler is None and in_worker()):
            self.kind = "serial"
        elif active is not None and workers is None and scheduler is None:
            self.kind, self.client, self.numerics = active.kind, active.client, active.numerics
            self.pool, self._pool_size = active.pool, active._pool_size
        elif backend == "processes":
            n = workers or default_workers()
            if n == 1:
                self.kind = "serial"
            else:
                ctx = multiprocessing.get_context("spawn")  # a clean interpreter, as Dask's nanny starts its workers
                self.pool = concurrent.futures.ProcessPoolExecutor(n, mp_context=ctx, initializer=_pool_init)
                self.kind, self._owns_client, self._pool_size = "processes", True, n
        else:
            scheduler = scheduler_from_env(scheduler)
            if scheduler is None and single:
                self.kind = "serial"  # one core: a one-worker cluster would only add its start-up
            else:
                self._start(workers, scheduler, dashboard)

    def _start(self, workers: int | None, scheduler: str | None, dashboard: str | None) -> None:
        if scheduler is not None:
            self.client = _connect(scheduler)
            self.kind, self._owns_client = "remote", True
            self.numerics = {"kernels": kernels(), "pinned": pinned_environ()}
            try:
                self._prepare_remote(scheduler, self.numerics)
            except BaseException:
                self.close()
                raise
        else:
            n = workers or default_workers()
            self._cluster = adopt(n, dashboard) or local_cluster(n, dashboard)
            try:
                self.client = Client(self._cluster.scheduler_address, set_as_default=False)
            except BaseException:
                self._cluster.close()
                raise
            self.kind, self._owns_client = "local", True  # its workers start with this process's environment

    def _prepare_remote(self, scheduler: str, expected: dict[str, dict[str, str]]) -> None:
        """A remote cluster's workers made ready for this client's tasks, or one line why they cannot be: pinned as
        this process is (:class:`PinnedNumerics`, restarting a worker started without), given the co-simulation's step
        loops (:class:`MasterLibrary`), and each one's kernels checked against this process's."""
        plugins: list[Any] = [PinnedNumerics(expected["pinned"])] if expected["pinned"] else []
        plugins.append(MasterLibrary(fmu_bytes(build_master())))
        for plugin in plugins:
            try:
                self.client.register_plugin(plugin)
            except Exception as exc:
                nanny = isinstance(plugin, NannyPlugin)
                with contextlib.suppress(Exception):  # workers or nannies joining later would fail on it too
                    self.client.unregister_worker_plugin(plugin.name, nanny=nanny)
                who = "nannies" if nanny else "workers"
                raise RuntimeError(
                    f"the Dask {who} at {scheduler} cannot take this command's plugin ({_first_line(exc)}): {INSTALL}"
                ) from None
        try:
            self.client.run(check_kernels, expected)
        except RuntimeError:  # the first worker whose kernels differ: what and how to start it, one line
            raise
        except Exception as exc:
            raise RuntimeError(
                f"the Dask workers at {scheduler} cannot check their kernels ({_first_line(exc)}): {INSTALL}"
            ) from None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def n_workers(self) -> int:
        """Workers the tasks are spread over now (1 on the serial path)."""
        if self.pool is not None:
            return self._pool_size
        if self.client is None:
            return 1
        return max(len(self.client.nthreads()), 1)

    def close(self) -> None:
        """Release the scattered data (and the processes backend's scratch files), and close the client, the process
        pool and the local cluster if this executor started them. A local cluster ends at once, its processes killed:
        after the last map nothing is lost but the time of a graceful shutdown, and on an error or a Ctrl-C its running
        tasks end with it instead of being waited for."""
        self._scattered.clear()
        self._blobs.clear()
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)
            self._scratch = None
        if self._owns_client:
            if self.pool is not None:
                self.pool.shutdown(wait=True, cancel_futures=True)
            if self.client is not None:
                with contextlib.suppress(Exception):
                    self.client.close()
            if self._cluster is not None:
                with contextlib.suppress(Exception):
                    self._cluster.close(abort=True)
        self.client, self.pool, self._cluster, self._owns_client = None, None, None, False

    def _scatter(self, obj: Any) -> Any:
        hit = self._scattered.get(id(obj))
        if hit is not None and hit[0] is obj:
            return hit[1]
        fut = self.client.scatter([obj], broadcast=True, hash=False)[0]
        self._scattered[id(obj)] = (obj, fut)  # holding obj keeps its id from being reused
        return fut

    def _shared_file(self, shared: tuple) -> tuple[str, Path | None]:
        """The ``processes`` backend's copy of a map's shared objects: (token, file), pickled once per executor
        (keyed by the objects' identity, as :meth:`_scatter`) into a scratch file each process reads once. Pickled
        once per map, the diagnosis's setup (1.8 MB) was written ~50 times and read as often by every process."""
        key = tuple(id(x) for x in shared)
        hit = self._blobs.get(key)
        if hit is not None and all(a is b for a, b in zip(hit[0], shared, strict=True)):
            return hit[1], hit[2]
        token, blob = uuid.uuid4().hex, None
        if shared:
            if self._scratch is None:
                self._scratch = Path(tempfile.mkdtemp(prefix="flexjoint-shared-"))
                weakref.finalize(self, shutil.rmtree, str(self._scratch), ignore_errors=True)
            blob = self._scratch / f"{token}.pickle"
            blob.write_bytes(pickle.dumps(shared, protocol=pickle.HIGHEST_PROTOCOL))
        self._blobs[key] = (shared, token, blob)  # holding the objects keeps their ids from being reused
        return token, blob

    def _report(self, desc: str, label: str, done: int, n: int, quiet: bool) -> None:
        if self.progress is not None and not quiet:
            self.progress(" ".join(s for s in (desc, label, f"[{done}/{n}]") if s))

    def map(
        self,
        fn: Callable[..., T],
        items: Sequence[Any],
        *shared: Any,
        desc: str = "",
        labels: Sequence[str] | None = None,
        quiet: bool = False,
    ) -> list[T]:
        """``[fn(item, *shared) for item in items]``, computed in parallel, in item order. Progress: one call
        per finished task, ``"<desc> <label> [done/n]"`` (label: ``labels[i]``, default the item's index); none
        when ``quiet`` (many short maps of one computation whose caller reports it)."""
        items = list(items)
        n = len(items)
        names = [str(x) for x in labels] if labels is not None else [str(i) for i in range(n)]
        if len(names) != n:
            raise ValueError(f"{len(names)} labels for {n} items")
        if self.pool is not None:
            return self._map_pool(fn, items, shared, desc, names, quiet)
        if self.client is None:
            if self.kind != "serial":
                raise RuntimeError("executor is closed")
            out = []
            for i, item in enumerate(items):
                out.append(call(fn, item, *shared))
                self._report(desc, names[i], i + 1, n, quiet)
            return out
        return self._map_dask(fn, items, shared, desc, names, quiet)

    def _map_dask(
        self, fn: Callable[..., T], items: list[Any], shared: tuple, desc: str, names: list[str], quiet: bool
    ) -> list:
        if not items:
            return []
        refs = [self._scatter(s) for s in shared]
        stem = f"{desc or getattr(fn, '__name__', 'task')}-{uuid.uuid4().hex[:12]}".replace(" ", "_")
        packed = [pack(fn, item, self.numerics) for item in items]  # opaque to the scheduler (harness.workercall)
        futures = [
            self.client.submit(run_packed, task, *refs, key=f"{stem}-{i}", pure=False) for i, task in enumerate(packed)
        ]
        index = {f.key: i for i, f in enumerate(futures)}
        results: list[Any] = [None] * len(items)
        done, again = 0, [0] * len(items)
        try:
            pending = as_completed(futures, loop=self.client.loop)
            for fut in pending:
                i = index[fut.key]
                try:
                    results[i] = fut.result()
                except KilledWorker as exc:
                    raise RuntimeError(f"{desc or 'task'} {names[i]}: {exc}") from None
                except FutureCancelledError as exc:  # not by this map: the scheduler lost it with a worker
                    if again[i] == RESUBMITS:
                        raise RuntimeError(f"{desc or 'task'} {names[i]}: {exc}") from None
                    again[i] += 1
                    retry = self.client.submit(
                        run_packed, packed[i], *refs, key=f"{stem}-{i}-again{again[i]}", pure=False
                    )
                    index[retry.key] = i
                    futures.append(retry)
                    pending.add(retry)
                    continue
                done += 1
                self._report(desc, names[i], done, len(items), quiet)
        except BaseException:
            self.client.cancel(futures)
            raise
        finally:
            del futures
        return results

    def _map_pool(
        self, fn: Callable[..., T], items: list[Any], shared: tuple, desc: str, names: list[str], quiet: bool
    ) -> list:
        """The ``processes`` backend: the shared objects in a scratch file (:meth:`_shared_file`), the tasks on the
        pool, results taken in completion order for the progress."""
        if not items:
            return []
        assert self.pool is not None
        token, blob = self._shared_file(shared)
        futures = {self.pool.submit(_pool_call, fn, item, token, blob): i for i, item in enumerate(items)}
        results: list[Any] = [None] * len(items)
        try:
            for done, fut in enumerate(concurrent.futures.as_completed(futures), 1):
                i = futures[fut]
                results[i] = fut.result()
                self._report(desc, names[i], done, len(items), quiet)
        except BaseException:
            for f in futures:
                f.cancel()
            concurrent.futures.wait(futures)  # no task of this map runs on after it
            raise
        return results


@contextlib.contextmanager
def use(ex: Executor) -> Iterator[Executor]:
    """Inside the ``with``, every ``Executor()`` created with ``workers`` and ``scheduler`` at None (in this thread
    or task) runs on ``ex``'s backend (its client, its process pool, or serially); ``ex`` stays open afterwards
    (what :func:`session` does for the executor it starts and closes; the bench switches between running ones)."""
    token = _SESSION.set(ex)
    try:
        yield ex
    finally:
        _SESSION.reset(token)


@contextlib.contextmanager
def session(
    workers: int | None = None,
    scheduler: str | None = None,
    progress: Progress | None = None,
    *,
    backend: str = "dask",
) -> Iterator[Executor]:
    """One cluster for a whole command: inside the ``with``, every ``Executor()`` created with ``workers`` and
    ``scheduler`` at None (in this thread or task) uses this session's client (or process pool) instead of
    starting its own, so a pipeline of parallel steps pays the cluster start once. Yields the session's own
    executor."""
    ex = Executor(workers, scheduler, progress, backend=backend)
    try:
        with use(ex):
            yield ex
    finally:
        ex.close()
