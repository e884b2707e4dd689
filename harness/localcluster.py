"""The embedded local Dask cluster as a process of its own: ``python -m harness.localcluster N DASHBOARD SYS_PATH``.

A ``LocalCluster`` started in the caller's process spawns its workers from there, and multiprocessing's spawn
re-imports the parent's ``__main__`` in every child: a library call from a plain script (no ``if __name__ ==
"__main__"`` guard) re-ran the script in each worker, which then failed to start ("Nanny failed to start"). Here the
scheduler and the nannies live in this module's process, so the workers re-import this module (whose work is
guarded), never the caller's. The process is a session of its own: a Ctrl-C at the terminal reaches only the
command, which closes the cluster; the cluster's logs go to the file its parent gives as stderr, never the terminal.

The caller's ``sys.path`` comes as an argument and the workers get it (as spawned workers get their parent's), so
a task's function from a module beside the caller's script (or a test module) imports on them as before.

On Linux the workers are forked from a fork server (multiprocessing's ``forkserver``, a process that only imports
and forks) that has imported Dask and the modules the command's tasks need (``preload``) once, instead of each worker
spawning an interpreter and importing them itself: the cluster is up sooner, for about half the CPU, and shuts down
sooner. Elsewhere (macOS, Windows) the workers are spawned, as Python does by default there.

Protocol: the scheduler's address on the first line of stdout once every worker is up; then the cluster runs until
stdin closes (its parent closed it, or died) and shuts down; a byte on stdin instead ends it at once (its workers
killed mid-task: the command was interrupted, or failed, and waits for nothing), and so does SIGTERM, even while the
cluster starts (a command that failed before it needed its cluster). The workers' scratch files (FMUs written as
files) live in a directory of the cluster's own (their ``TMPDIR``), removed in every case.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import sys
import tempfile
from typing import Any

import dask
import psutil
from distributed import LocalCluster
from distributed.utils import get_mp_context

__all__ = ["CLUSTER_CONFIG", "serve"]

# what every local cluster runs under (see harness.executor): the nanny's pre-spawn environment without its malloc
# trim threshold (the one-thread BLAS variables it also sets stay; the tasks limit BLAS themselves anyway), and its
# processes without the wake-ups that take the GIL from a task: no statistical profiler (a stack sample every 10 ms;
# kept when a dashboard is asked for), the event loop's tick every 1 s (20 ms), the system and memory monitors every
# 5 s and 1 s (0.5 s, 0.1 s)
CLUSTER_CONFIG = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
}


def serve(
    n_workers: int, dashboard: str | None = None, path: list[str] | None = None, preload: list[str] | None = None
) -> None:
    """Start ``n_workers`` processes of one thread on 127.0.0.1 (worker logs below CRITICAL silenced, the dashboard
    only at ``dashboard``, ``sys.path`` set to ``path``, the modules ``preload`` imported before the workers take
    tasks: once by the fork server they are forked from, on Linux; by each worker as it starts elsewhere), print the
    scheduler's address on the real stdout, run until stdin closes, shut down."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when the cluster ends
    scratch = tempfile.mkdtemp(prefix="flexjoint-cluster-")
    signal.signal(signal.SIGTERM, lambda *_: _end_at_once(scratch))  # even while it starts
    if path is not None:
        sys.path[:] = path  # the spawned workers take this process's sys.path
    os.environ["TMPDIR"] = scratch  # the workers' scratch files, removed with the cluster
    address_out = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # what the workers print goes to the log, not the pipe
    config: dict[str, Any] = {**CLUSTER_CONFIG, "distributed.worker.profile.enabled": dashboard is not None}
    config["distributed.worker.preload"] = list(preload or [])
    forked = sys.platform.startswith("linux")
    if forked:
        config["distributed.worker.multiprocessing-method"] = "forkserver"
    try:
        with dask.config.set(config):  # the nannies take the config (and their pre-spawn environment) when created
            if forked:  # the fork server starts with the first worker, its environment the nanny's pre-spawn one
                get_mp_context().set_forkserver_preload(["distributed", *(preload or [])])
            cluster = LocalCluster(
                n_workers=n_workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=dashboard,
                worker_dashboard_address=None,
                silence_logs=logging.CRITICAL,
                host="127.0.0.1",
                # no dashboard: the scheduler's plain HTTP endpoints then take a free port, not 8787
                scheduler_kwargs=None if dashboard else {"dashboard_address": "127.0.0.1:0"},
            )
        with cluster:
            with contextlib.suppress(BrokenPipeError):  # the parent gave up on it while it started
                address_out.write(cluster.scheduler_address + "\n")
                address_out.close()
            if sys.stdin.buffer.read(1):  # a byte: end at once; nothing: closed (the parent is done, or died)
                _end_at_once(scratch)
        if forked:
            _end_fork_server()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _end_at_once(scratch: str, timeout: float = 2.0) -> None:
    """End the cluster now: every process of it killed, its scratch directory removed, this process gone. The
    workers die first and their parent (the fork server) reaps them before it dies in turn, reaped here: their CPU
    time counts in this process's children's, as after a graceful shutdown (``/usr/bin/time``, a benchmark's
    accounting)."""
    me = psutil.Process()
    children = me.children()
    deeper = [p for p in me.children(recursive=True) if p not in children]
    for level in (deeper, children):
        for p in level:
            with contextlib.suppress(psutil.Error):
                p.kill()
        psutil.wait_procs(level, timeout)
    shutil.rmtree(scratch, ignore_errors=True)
    os._exit(0)


def _end_fork_server(timeout: float = 5.0) -> None:
    """The fork server, its workers gone with the cluster, ended and waited for here (it would end by itself once
    this process has, unwaited): its CPU time, and its workers', then counts in this process's children's, as a
    spawned worker's does (``/usr/bin/time``, a benchmark's accounting)."""
    servers = [p for p in psutil.Process().children() if "multiprocessing.forkserver" in " ".join(_cmdline(p))]
    for p in servers:
        with contextlib.suppress(psutil.Error):
            p.terminate()
    _, alive = psutil.wait_procs(servers, timeout)
    for p in alive:
        with contextlib.suppress(psutil.Error):
            p.kill()


def _cmdline(p: psutil.Process) -> list[str]:
    try:
        return p.cmdline()
    except psutil.Error:
        return []


if __name__ == "__main__":
    serve(int(sys.argv[1]), sys.argv[2] or None, *(json.loads(a) for a in sys.argv[3:5]))
