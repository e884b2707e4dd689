"""The command's side of the embedded local cluster: its process started (early, in the background), adopted by the
command's executor, and ended. Light on purpose (no Dask, no numpy): a command line starts its cluster with
:func:`prestart` before it loads what it runs, so that the workers start while the command imports.

The cluster itself runs in :mod:`harness.localcluster` (``python -m harness.localcluster``), in a process and
session of its own; the protocol is that module's: the scheduler's address on its first line of stdout once every
worker is up, then it runs until its stdin closes (a byte on stdin first: at once, its workers killed).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Sequence

from .machine import default_workers, env_workers

__all__ = ["CLOSE_TIMEOUT_S", "SCHEDULER_ENV", "LocalProcessCluster", "adopt", "prestart", "scheduler_from_env"]

SCHEDULER_ENV = "FLEXJOINT_SCHEDULER"
CLOSE_TIMEOUT_S = 10.0  # a local cluster not shut down by then is ended by signal


def scheduler_from_env(scheduler: str | None = None) -> str | None:
    """``scheduler`` when given, else ``FLEXJOINT_SCHEDULER`` (None when unset or blank)."""
    return scheduler or os.environ.get(SCHEDULER_ENV, "").strip() or None


class LocalProcessCluster:
    """The embedded local cluster, run by :mod:`harness.localcluster` in a process (and session) of its own: its
    workers never re-import the caller's ``__main__``, a terminal's Ctrl-C does not reach them, and their logs go to
    a scratch file (read only to say why the cluster did not start). Each worker has imported the modules
    ``preload`` before the cluster says it is up. ``scheduler_address`` to connect a client; :meth:`close` (or
    leaving the ``with``) shuts it down."""

    def __init__(self, n_workers: int, dashboard: str | None = None, preload: Sequence[str] = ()) -> None:
        self.n_workers, self.dashboard = n_workers, dashboard
        self._log = tempfile.TemporaryFile()
        cmd = [sys.executable, "-m", "harness.localcluster", str(n_workers), dashboard or "", json.dumps(sys.path)]
        cmd.append(json.dumps(list(preload)))
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, start_new_session=True
        )
        self._address: str | None = None

    @property
    def scheduler_address(self) -> str:
        """The scheduler's address, once every worker is up (waits for it the first time)."""
        if self._address is None:
            try:
                line = self._proc.stdout.readline().decode().strip() if self._proc.stdout else ""
            except BaseException:  # a Ctrl-C while it starts: nothing left behind
                self.close()
                raise
            if not line.startswith("tcp://"):
                self.close()
                raise RuntimeError(f"the local Dask cluster did not start: {self._last_log_line()}")
            self._address = line
        return self._address

    def _last_log_line(self) -> str:
        self._log.seek(0)
        lines = [x.strip() for x in self._log.read().decode(errors="replace").splitlines() if x.strip()]
        return lines[-1] if lines else f"its process ended with code {self._proc.returncode}"

    def __enter__(self) -> LocalProcessCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _kill_group(self) -> None:
        """SIGKILL to the cluster's session (its process group: scheduler, nannies, workers); the process alone where
        there are no process groups (Windows)."""
        with contextlib.suppress(ProcessLookupError, PermissionError, OSError):
            if hasattr(os, "killpg"):
                os.killpg(self._proc.pid, signal.SIGKILL)
            elif self._proc.poll() is None:
                self._proc.kill()

    def close(self, abort: bool = False, timeout: float = CLOSE_TIMEOUT_S) -> None:
        """Close its stdin (the cluster shuts down by itself; ``abort``: at once, its workers killed mid-task, even
        while it starts), wait ``timeout`` seconds, then end its whole process group (scheduler, nannies, workers)."""
        if self._proc.stdin is not None and not self._proc.stdin.closed:
            with contextlib.suppress(OSError):
                if abort:
                    self._proc.stdin.write(b"k")
                self._proc.stdin.close()
        if abort and os.name == "posix":
            with contextlib.suppress(ProcessLookupError, PermissionError, OSError):
                self._proc.send_signal(signal.SIGTERM)  # ends it at once, started or not
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._kill_group()
            self._proc.wait()
        self._kill_group()  # a worker its nanny left behind
        if self._proc.stdout is not None:
            self._proc.stdout.close()
        self._log.close()


_PRESTARTED: list[LocalProcessCluster] = []


def _end_unadopted() -> None:
    """At exit: a prestarted cluster no executor adopted (the command failed, or needed none) ends at once instead
    of starting up, for nothing, behind the finished command."""
    while _PRESTARTED:
        _PRESTARTED.pop().close(abort=True)


atexit.register(_end_unadopted)


def prestart(workers: int | None = None, scheduler: str | None = None, preload: Sequence[str] = ()) -> None:
    """Start, without waiting for it, the local cluster the next ``Executor(workers, scheduler)`` (or
    :func:`harness.executor.session`) of this process would start; that executor adopts it, so a command imports
    what it runs while the workers start, and the workers import the modules ``preload`` meanwhile, not at their
    first task. For a command line's own process, first thing (it is not checked here whether this process is a
    Dask worker or inside a session, where the executor starts no cluster: nothing there calls it). Does nothing
    where that executor would start none (serially, on a scheduler). A cluster never adopted ends at once when this
    process exits."""
    if workers is None:
        workers = env_workers()
    if scheduler_from_env(scheduler) is not None or workers == 1 or _PRESTARTED:
        return
    n = workers or default_workers()
    if n > 1:
        _PRESTARTED.append(LocalProcessCluster(n, preload=preload))


def adopt(n_workers: int, dashboard: str | None) -> LocalProcessCluster | None:
    """The prestarted cluster when it is the one asked for (``n_workers``, ``dashboard``), else None (a prestarted
    cluster of another shape is closed)."""
    pre = _PRESTARTED.pop() if _PRESTARTED else None
    if pre is not None and (pre.n_workers, pre.dashboard) != (n_workers, dashboard):
        pre.close()
        pre = None
    return pre
