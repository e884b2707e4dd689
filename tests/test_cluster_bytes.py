"""The same bytes on a cluster a user starts (issue 61): ``dask scheduler`` and ``dask worker --nworkers 2 --nthreads
1`` started by hand, from a shell without the variables that pin numpy's and OpenBLAS's kernels (on an AVX-512 CPU its
workers compute with OpenBLAS's SkylakeX kernels and numpy's X86_V4 loops, and fits differed from the serial ones in
their 13th to 15th digit), give the serial bytes for ``sweep``, ``identify`` and ``blindtest``: the command pins the
workers through their nannies as it connects. A scheduler at nothing, or a cluster whose workers lack the package or
compute with other kernels, is one line and exit 2 within 10 s, nothing written.

The commands run as a user runs them (``python -m harness``, the environment without the pinning variables the suite's
own processes have); one cluster serves the module's tests (in one test process: its tests are one xdist group)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import SimpleNamespace

import pytest
from distributed import Client
from test_executor import TINY_SPEC

import harness
from harness.diagnosis.blindtest import blindtest
from harness.executor import PinnedNumerics
from harness.numerics import PIN_VARS, _cpu_flags
from harness.sweep import run_sweep
from harness.workercall import check_kernels, kernels, pack, run_packed

pytestmark = pytest.mark.xdist_group("user_cluster")

ROOT = Path(harness.__file__).resolve().parents[1]  # this checkout: the workers import its harness, as the commands
PINNED = ("numpy loops", "BLAS kernels")  # what the pinning variables change
AVX512 = "avx512f" in _cpu_flags()  # a CPU where an unpinned worker computes with other kernels than the command


def user_env(path: Sequence[Path] = ()) -> dict[str, str]:
    """A user's shell: the suite's environment without the pinning variables, ``path`` and this checkout first on
    ``PYTHONPATH``."""
    env = {k: v for k, v in os.environ.items() if k not in PIN_VARS}
    env["PYTHONPATH"] = os.pathsep.join(map(str, [*path, ROOT, *filter(None, [os.environ.get("PYTHONPATH")])]))
    return env


class Flexjoint:
    """``flexjoint ARGS`` started as a user runs it (in ``cwd``), not waited for until :meth:`wait`, so that a serial
    reference computes beside the cluster's run (two cores: the serial command on one, a one-task map on the other).
    """

    def __init__(self, *args: object, cwd: Path) -> None:
        t0 = time.perf_counter()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "harness", *map(str, args)],
            cwd=cwd, env=user_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        self.err, self.took = "", math.inf

        def run() -> None:
            self.err = self.proc.communicate(timeout=300)[1]
            self.took = time.perf_counter() - t0

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def wait(self, code: int = 0) -> tuple[str, float]:
        """Its stderr and wall time (s, from its start to its end), once it has ended with exit code ``code``."""
        self.thread.join(timeout=310)
        assert self.proc.returncode == code, self.err
        return self.err, self.took


def flexjoint(*args: object, cwd: Path, code: int = 0) -> tuple[str, float]:
    """``flexjoint ARGS`` run to its end with exit code ``code``: its stderr and wall time (s)."""
    return Flexjoint(*args, cwd=cwd).wait(code)


class UserCluster:
    """``dask scheduler --port 0 --scheduler-file F`` and ``dask worker --scheduler-file F WORKER_ARGS`` started as
    a user starts them (in ``env``, default :func:`user_env`), not waited for until :meth:`wait`; every process ended
    by :meth:`close`. The processes also end by themselves: the scheduler after 5 idle minutes, the workers a minute
    after it is gone."""

    def __init__(self, tmp: Path, worker_args: Sequence[str], env: dict[str, str] | None = None) -> None:
        self.file = tmp / "scheduler.json"
        env = env or user_env()
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True, "cwd": tmp}
        dask = [sys.executable, "-m", "dask"]
        self.procs = [
            subprocess.Popen(
                [*dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--scheduler-file", str(self.file),
                 "--no-dashboard", "--idle-timeout", "300"], env=env, **quiet,
            ),
            subprocess.Popen(
                [*dask, "worker", "--scheduler-file", str(self.file), *worker_args, "--death-timeout", "60"],
                env=env, **quiet,
            ),
        ]  # fmt: skip
        self.n = int(worker_args[worker_args.index("--nworkers") + 1]) if "--nworkers" in worker_args else 1

    def wait(self) -> str:
        """Block until every worker has joined; the scheduler's address."""
        for _ in range(600):
            if self.file.is_file() and self.file.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(self.file.read_text())["address"]
        with Client(address, timeout=60, set_as_default=False) as c:
            c.wait_for_workers(self.n, timeout=90)
        return address

    def kernels(self) -> dict[str, dict[str, str]]:
        """What each worker computes with (:func:`harness.workercall.kernels`), by its address."""
        with Client(self.wait(), timeout=60, set_as_default=False) as c:
            return c.run(kernels)

    def close(self) -> None:
        for p in self.procs:  # the scheduler first: the workers without it close at once
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[UserCluster]:
    """A user's cluster: ``dask worker --nworkers 2 --nthreads 1``, started unpinned, shared by the module's tests."""
    c = UserCluster(tmp_path_factory.mktemp("user_cluster"), ["--nworkers", "2", "--nthreads", "1"])
    try:
        yield c
    finally:
        c.close()


def _files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _same_bytes(a: Path, b: Path, skip: Sequence[str] = ()) -> None:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb)
    for f in fa:
        if f not in skip:
            assert fa[f] == fb[f], f


PINNED_WORKERS: dict[str, dict[str, str]] = {}  # the workers once the first command pinned them


def test_a_sweep_on_a_users_cluster_is_the_serial_bytes(tmp_path, cluster):
    """The workers start unpinned (on an AVX-512 CPU: other kernels than the command's); the first command pins them
    (their nannies restart them) and its sweep is the serial one, byte for byte."""
    (tmp_path / "tiny.toml").write_text(TINY_SPEC)
    sweep = ["sweep", "tiny.toml", "--vary", "plant.Ks=uniform(1.3,1.8)", "--vary", "plant.amp_limit=uniform(20,30)",
             "--n", 6, "--seed", 5, "--orders", "3,2,1"]  # fmt: skip
    run_sweep(tmp_path / "tiny.toml", sweep[3:6:2], 6, 5, tmp_path / "serial", orders="3,2,1", workers=1)  # meanwhile
    here = kernels()
    if AVX512:  # the workers as started compute with other kernels than the command
        before = cluster.kernels()
        assert all({k: w[k] for k in PINNED} != {k: here[k] for k in PINNED} for w in before.values()), before
    flexjoint(*sweep, "--out", "remote", "--scheduler", cluster.wait(), cwd=tmp_path)
    PINNED_WORKERS.update(cluster.kernels())
    assert list(PINNED_WORKERS.values()) == [here, here]
    _same_bytes(tmp_path / "serial", tmp_path / "remote", skip=["sweep.timing.json"])


def test_identify_on_a_users_cluster_is_the_serial_bytes(tmp_path, cluster):
    """After the sweep's command pinned them, the workers are those it left: a later command restarts none."""
    (tmp_path / "tiny.toml").write_text(TINY_SPEC)
    flexjoint("campaign", "tiny.toml", "--out", "serial", "--workers", 1, cwd=tmp_path)
    shutil.copytree(tmp_path / "serial", tmp_path / "remote")
    serial = Flexjoint("identify", "serial", "--workers", 1, cwd=tmp_path)
    flexjoint("identify", "remote", "--scheduler", cluster.wait(), cwd=tmp_path)
    serial.wait()
    _same_bytes(tmp_path / "serial", tmp_path / "remote")
    if PINNED_WORKERS:
        assert cluster.kernels() == PINNED_WORKERS


def test_a_blind_test_on_a_users_cluster_is_the_serial_bytes(tmp_path, cluster):
    """A closed-loop case, whose searches carried an unpinned worker's last digits on to other fits (the numbers of
    its verdict differed from their 2nd digit on)."""
    blind = ["blindtest", "--family", "closed", "--quick", "--n", 1, "--seed", 5]
    remote = Flexjoint(*blind, "--out", "remote", "--scheduler", cluster.wait(), cwd=tmp_path)
    blindtest(1, 5, tmp_path / "serial", workers=1, quick=True, families=("closed",))  # on the other core meanwhile
    remote.wait()
    _same_bytes(tmp_path / "serial", tmp_path / "remote", skip=["blindtest.timing.json"])


def test_a_scheduler_at_nothing_or_workers_without_the_package_is_one_line(tmp_path):
    """One line, exit 2, within 10 s, nothing written: nothing listening at the address; a user's cluster whose workers
    do not have the package (its editable install hidden from them)."""
    hide = _mkdir(tmp_path / "hide")
    (hide / "sitecustomize.py").write_text(
        "import sys\nsys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in repr(f).lower()]\n"
    )
    env = {k: v for k, v in user_env().items() if k != "PYTHONPATH"} | {"PYTHONPATH": str(hide)}
    nopkg = UserCluster(_mkdir(tmp_path / "nopkg-cluster"), ["--nworkers", "1", "--nthreads", "1"], env=env)
    try:
        (tmp_path / "tiny.toml").write_text(TINY_SPEC)
        sweep = ["sweep", "tiny.toml", "--vary", "plant.Ks=uniform(1.3,1.8)", "--n", 2]
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            nothing = f"tcp://127.0.0.1:{s.getsockname()[1]}"
        runs = {"nothing": Flexjoint(*sweep, "--out", "nothing", "--scheduler", nothing, cwd=tmp_path)}
        runs["nopkg"] = Flexjoint(*sweep, "--out", "nopkg", "--scheduler", nopkg.wait(), cwd=tmp_path)
        lines = {}
        for name, run in runs.items():
            err, took = run.wait(code=2)
            assert took < 10 and not (tmp_path / name).exists(), (name, took)
            assert len(err.strip().splitlines()) == 1 and err.startswith("error: "), err
            lines[name] = err
    finally:
        nopkg.close()
    assert "cannot connect to the Dask scheduler" in lines["nothing"] and "Connection refused" in lines["nothing"]
    assert "No module named 'harness'" in lines["nopkg"] and "install flexjoint-harness" in lines["nopkg"]


def test_a_worker_with_other_kernels_refuses_the_task_in_one_line():
    """What every worker runs as the client connects, and every task first (a worker that joined later): a worker
    whose kernels are not the client's (here: the client's BLAS kernels said to be another core type) says what
    differs and how to start it, and runs nothing."""
    here = kernels()
    other = {**here, "BLAS kernels": "Zen"}
    expected = {"kernels": other, "pinned": {"OPENBLAS_CORETYPE": "Zen"}}
    ran: list[int] = []
    with pytest.raises(RuntimeError) as e:
        run_packed(pack(ran.append, 1, expected))
    assert not ran and len(str(e.value).splitlines()) == 1
    assert f"BLAS kernels {here['BLAS kernels']} (here Zen)" in str(e.value)
    assert "not --no-nanny" in str(e.value) and "OPENBLAS_CORETYPE='Zen'" in str(e.value)
    other = {**here, "numpy": "1.0.0"}
    with pytest.raises(RuntimeError, match="same numpy and scipy"):
        check_kernels({"kernels": other, "pinned": {}})
    late = {**here, "BLAS kernels": "Prescott"}  # a client that loaded numpy before it was pinned
    with pytest.raises(RuntimeError, match="loaded numpy before it was pinned"):
        check_kernels({"kernels": late, "pinned": {"OPENBLAS_CORETYPE": "Haswell"}})
    check_kernels({"kernels": here, "pinned": {}})  # the same: nothing to say
    assert run_packed(pack(len, "abc", {"kernels": here, "pinned": {}})) == 3


def test_a_nanny_starts_its_worker_with_the_clients_variables_and_restarts_it_only_when_they_change_it(monkeypatch):
    """The nanny plugin sets the variables where the nanny starts its worker process from (its pre-spawn environment:
    before the process loads numpy) and asks for a restart only when the worker running was started without them."""
    pinned = {"OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": "X86_V4"}
    plugin = PinnedNumerics(pinned)
    assert plugin.idempotent and plugin.name == PinnedNumerics(dict(reversed(pinned.items()))).name
    nanny = SimpleNamespace(pre_spawn_env={"MALLOC_TRIM_THRESHOLD_": "65536"}, env={})
    for k in pinned:
        monkeypatch.delenv(k, raising=False)
    plugin.setup(nanny)
    assert plugin.restart and nanny.pre_spawn_env == {"MALLOC_TRIM_THRESHOLD_": "65536", **pinned}
    for k, v in pinned.items():  # what the nanny's environment holds once it started its worker with them
        monkeypatch.setenv(k, v)
    plugin.setup(nanny)
    assert not plugin.restart


def _mkdir(d: Path) -> Path:
    d.mkdir()
    return d
