"""The Dask executor: serial path, a real ``dask scheduler`` with two ``dask worker`` processes on 127.0.0.1,
the same bytes either way, and worker errors surfacing as the original exception (one line in the CLI)."""

from __future__ import annotations

import contextlib
import json
import math
import operator
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from distributed import get_worker

from harness.executor import Executor, FmuBytes, fmu_bytes, fmu_file, in_worker, session, worker_cache

# a campaign of a few seconds: short calibration (pot ramp, 3-hold comb) and two 12 s identification experiments
TINY_SPEC = """
[campaign]
name = "tiny"
sample_rate = 50.0
seed = 3

[plant]
n_modes = 1

[daq]
noise_theta = 0.002
noise_alpha = 0.002

[[calibration]]
name = "pot_ramp"
signal = "constant"
amplitude = 2.0
duration = 12.0

[[calibration]]
name = "comb"
signal = "comb"
deflections_cm = [-3.7, 0.0, 3.9]
D_cm = 40.0
hold = 2.5
ramp = 0.8
duration = 10.0

[[experiment]]
name = "prbs"
signal = "prbs"
B = 0.10
amplitude = 1.5
duration = 12.0

[[experiment]]
name = "square"
signal = "square"
f = 0.4
amplitude = 1.5
duration = 12.0

[identify]
na = [3, 4]
nb = [1, 2]
nc = [1, 2]
fit_threshold = 50.0

[accept]
min_fit = 80.0
min_average_fit = 85.0
"""


def tiny_spec(tmp_path: Path) -> Path:
    p = tmp_path / "tiny.toml"
    p.write_text(TINY_SPEC)
    return p


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DaskCluster:
    """A real ``dask scheduler`` and ``n`` ``dask worker`` processes (one thread, no nanny, so a kill is final,
    harness preloaded) on 127.0.0.1 with free ports. Started on entering (without waiting, so the test can do its
    serial work meanwhile); :meth:`wait` blocks until the workers are up; everything is stopped on exit. The
    processes also stop by themselves: the scheduler after 5 idle minutes, the workers 30 s after it is gone."""

    def __init__(self, n: int = 2, env: dict[str, str] | None = None) -> None:
        self.n, self.env = n, env
        self.address = f"tcp://127.0.0.1:{_free_port()}"
        self.scheduler: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []

    def __enter__(self) -> DaskCluster:
        dask = [sys.executable, "-m", "dask"]
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL, "start_new_session": True}
        http = ["--no-dashboard", "--dashboard-address", "127.0.0.1:0"]
        port = self.address.rsplit(":", 1)[1]
        cmd = [*dask, "scheduler", "--host", "127.0.0.1", "--port", port, *http, "--idle-timeout", "300"]
        self.scheduler = subprocess.Popen(cmd, **quiet)
        cmd = [*dask, "worker", self.address, "--nthreads", "1", "--no-nanny", "--host", "127.0.0.1", *http]
        cmd += ["--death-timeout", "30", "--preload", "harness.sweep"]
        self.workers = [subprocess.Popen(cmd, **quiet, env=self.env) for _ in range(self.n)]
        return self

    def wait(self) -> str:
        """Block until every worker has joined; returns the scheduler address."""
        from distributed import Client

        with Client(self.address, timeout=60, set_as_default=False) as c:
            c.wait_for_workers(self.n, timeout=90)
        return self.address

    def __exit__(self, *exc: object) -> None:
        procs = [p for p in (self.scheduler, *self.workers) if p is not None]
        for p in procs:  # the scheduler first: workers without one close at once
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def flexjoint(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "harness.cli", *map(str, args)], capture_output=True, text=True, timeout=300
    )


def test_serial_path_keeps_order_reports_progress_and_raises_the_original_error():
    seen: list[str] = []
    with Executor(workers=1, progress=seen.append) as ex:
        assert ex.kind == "serial" and ex.n_workers == 1
        assert ex.map(operator.mul, [3, 1, 2], 10, desc="mul", labels=["a", "b", "c"]) == [30, 10, 20]
        assert ex.map(operator.call, [in_worker]) == [False]
        with pytest.raises(ValueError, match="math domain error"):
            ex.map(math.sqrt, [4.0, -1.0])
    assert seen == ["mul a [1/3]", "mul b [2/3]", "mul c [3/3]", "0 [1/1]", "0 [1/2]"]
    with pytest.raises(ValueError, match="positive integer"):
        Executor(workers=0)


def _nested_kind(_: object) -> str:
    """A task that asks for an executor of its own: inside a worker it must be serial (no cluster in a cluster)."""
    with Executor() as ex:
        return ex.kind


def test_processes_backend_is_the_serial_result_on_plain_processes():
    seen: list[str] = []
    with pytest.raises(ValueError, match="backend"):
        Executor(workers=2, backend="threads")
    with pytest.raises(ValueError, match="no scheduler"):
        Executor(scheduler="tcp://127.0.0.1:1", backend="processes")
    with session(2, progress=seen.append, backend="processes") as ex:
        assert ex.kind == "processes" and ex.n_workers == 2 and Executor().kind == "processes"
        assert ex.map(operator.mul, [3, 1, 2], 10, desc="mul", labels=["a", "b", "c"]) == [30, 10, 20]
        assert ex.map(operator.call, [in_worker] * 3) == [True] * 3 and not in_worker()
        assert ex.map(_nested_kind, [0, 1]) == ["serial", "serial"]
        with pytest.raises(ValueError, match="math domain error"):
            ex.map(math.sqrt, [4.0, -1.0])
    # one progress line per finished task, in completion order: every label once, the count rising
    assert sorted(x.split()[1] for x in seen[:3]) == ["a", "b", "c"]
    assert [x.split()[2] for x in seen[:3]] == ["[1/3]", "[2/3]", "[3/3]"]
    assert ex.pool is None and Executor(workers=1, backend="processes").kind == "serial"


class Counted:
    """A shared object that counts its picklings in this process and its unpicklings in the one that loads it."""

    pickled = 0
    loaded = 0

    def __getstate__(self) -> dict:
        Counted.pickled += 1
        return {}

    def __setstate__(self, state: dict) -> None:
        Counted.loaded += 1


def _loads_here(_: int, shared: Counted) -> tuple[int, int]:
    """(this process's id, how many times it has unpickled a Counted)."""
    return os.getpid(), Counted.loaded


def test_processes_backend_sends_shared_objects_once_per_executor():
    """A map's shared objects go to the processes once per executor (the diagnosis maps its 1.8 MB setup ~50 times),
    not once per map; a quiet map reports no progress; the scratch file goes with the executor."""
    seen: list[str] = []
    shared = Counted()
    with Executor(workers=2, backend="processes", progress=seen.append) as ex:
        loads = [ex.map(_loads_here, range(4), shared, quiet=True) for _ in range(3)]
        scratch = ex._scratch
        assert scratch is not None and any(scratch.iterdir())
        ex.map(_loads_here, [0], Counted())  # another object: sent anew
    assert Counted.pickled == 2 and seen == ["0 [1/1]"]
    assert all(n == 1 for rows in loads for _, n in rows), loads
    assert not scratch.exists()


def _housekeeping(_: int) -> tuple[bool, float]:
    """(does this worker run Dask's statistical profiler, its event loop's tick interval [s])."""
    w = get_worker()
    return "profile" in w.periodic_callbacks, w._tick_interval


def test_local_workers_leave_the_gil_to_their_task():
    """A local worker's task ran 7 % slower than in a plain process, its GIL taken by the profiler's stack samples
    every 10 ms and the event loop's tick every 20 ms: the local cluster starts without the profiler (unless a
    dashboard is watched) and with a 1 s tick."""
    with Executor(workers=2) as ex:
        assert ex.map(_housekeeping, [0, 1]) == [(False, 1.0)] * 2


def _slow_double(x: int) -> int:
    import time

    time.sleep(0.4)
    return 2 * x


def test_a_task_the_scheduler_cancels_on_its_own_is_submitted_again():
    """A task cancelled by someone other than the map (here another client forgets it; the scheduler does so with
    a result lost with its worker and its data: "already forgotten") is submitted again, and the map still returns
    every result once, in order."""
    from distributed import Client, Future

    def cancel(ex: Executor, ending: str) -> None:
        with Client(ex.client.scheduler.address, set_as_default=False) as other:
            keys = other.run_on_scheduler(lambda dask_scheduler: list(dask_scheduler.tasks))
            (key,) = [k for k in keys if str(k).startswith("_slow_double-") and str(k).endswith(ending)]
            other.cancel([Future(key, other)], force=True)

    with Executor(workers=2) as ex:
        seen: list[str] = []
        ex.progress = lambda msg: (seen.append(msg), len(seen) == 1 and cancel(ex, "-5"))
        assert ex.map(_slow_double, range(6), quiet=False) == [0, 2, 4, 6, 8, 10]
        assert len(seen) == 6


def _alloc_faults(n: int) -> tuple[str | None, int]:
    """Minor page faults of this thread while ``n`` 1 MiB arrays are allocated, written and freed in turn (after
    one untimed), and the MALLOC_TRIM_THRESHOLD_ this process was started with."""
    import resource

    import numpy as np

    np.ones(1 << 17)
    r0 = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    for _ in range(n):
        np.ones(1 << 17)
    return os.environ.get("MALLOC_TRIM_THRESHOLD_"), resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - r0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc and RUSAGE_THREAD")
def test_workers_allocate_as_a_plain_process():
    """The nanny's MALLOC_TRIM_THRESHOLD_=65536 froze glibc's mmap threshold: every array above 128 KiB was a
    fresh mmap, its pages faulted in again (a grid task 1.8x slower in a worker). The local cluster's workers
    start without it; a worker that has it anyway (a remote nanny) resets the thresholds before its first task."""
    with Executor(workers=2) as ex:
        assert ex.kind == "local"
        for env, faults in ex.map(_alloc_faults, [100, 100]):
            assert env is None and faults < 2000, (env, faults)
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]); import test_executor as t; from harness import workercall as w;"
        "print(*t._alloc_faults(100)[1:], *w.worker_call(t._alloc_faults, 100)[1:], w._MALLOC_TUNED)"
    )
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    out = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent)], env=env, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()  # fmt: skip
    before, after = int(out[0]), int(out[1])
    assert before > 20000 and after < 2000 and out[2] == "[True]", out


def test_fmu_bytes_are_written_once_per_process_and_worker_cache_memoises(fmus):
    fb = fmu_bytes(fmus["daq"])
    assert isinstance(fb, FmuBytes) and fb.data == Path(fmus["daq"]).read_bytes() and len(fb.sha256) == 64
    p1, p2 = fmu_file(fb), fmu_file(fb)
    assert p1 == p2 and p1.read_bytes() == fb.data and p1.name == Path(fmus["daq"]).name
    with pytest.raises(ValueError, match="sha256"):
        fmu_file(FmuBytes("x.fmu", b"not the content", fb.sha256[::-1]))
    calls: list[int] = []
    make = lambda: calls.append(1) or object()  # noqa: E731
    assert worker_cache("test-key", make) is worker_cache("test-key", make) and calls == [1]


def test_remote_cluster_gives_the_serial_bytes_and_the_workers_errors(tmp_path, fmus, capsys, monkeypatch):
    from harness import cli
    from harness import spec as specmod
    from harness.rig.campaign import run_campaign

    spec = tiny_spec(tmp_path)
    with DaskCluster(2) as cluster:
        run_campaign(specmod.load(spec), tmp_path / "serial", fmus=fmus, workers=1)  # while the workers start
        addr = cluster.wait()
        with Executor(scheduler=addr) as ex:
            assert ex.kind == "remote" and ex.n_workers == 2
            # tasks really run in worker processes, in item order, and a task's error is the original one
            assert ex.map(operator.call, [in_worker] * 4) == [True] * 4
            assert ex.map(operator.truediv, [6.0, 3.0], 3.0) == [2.0, 1.0]
            with pytest.raises(ZeroDivisionError):
                ex.map(operator.truediv, [1.0, 2.0], 0.0)
        remote = flexjoint("campaign", spec, "--out", tmp_path / "remote", "--scheduler", addr)
        assert remote.returncode == 0, remote.stderr
        assert "[4/4]" in remote.stderr  # progress per finished task
        # an FMU error raised on a worker, through the CLI: one line with the FMU's own message, exit 2
        argv = ["flexjoint", "campaign", str(spec), "--out", str(tmp_path / "bad"), "--set", "plant.n_modes=9"]
        monkeypatch.setattr(sys, "argv", [*argv, "--scheduler", addr])
        capsys.readouterr()
        with pytest.raises(SystemExit) as code:
            cli.main()
    bad = capsys.readouterr().err
    assert code.value.code == 2 and "Traceback" not in bad
    errors = [x for x in bad.splitlines() if x.startswith("error")]
    assert len(errors) == 1 and "n_modes = 9" in errors[0], bad
    files = sorted(p.relative_to(tmp_path / "serial") for p in (tmp_path / "serial").rglob("*") if p.is_file())
    assert len(files) == 5  # manifest + 4 datasets
    for f in files:
        assert (tmp_path / "serial" / f).read_bytes() == (tmp_path / "remote" / f).read_bytes(), f


def test_unreachable_scheduler_is_one_clear_error(monkeypatch):
    monkeypatch.setattr("harness.executor.CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(RuntimeError, match="cannot connect to the Dask scheduler"):
        Executor(scheduler=f"tcp://127.0.0.1:{_free_port()}")


def test_blind_test_on_a_remote_cluster_gives_the_serial_bytes(tmp_path, fmus):
    """A case of each family (the families take turns), one on each remote worker."""
    from harness.diagnosis.blindtest import blindtest

    with DaskCluster(2) as cluster:
        blindtest(2, seed=4, out=tmp_path / "serial", workers=1, quick=True, families=("twin", "nuisance"))
        remote = flexjoint("blindtest", "--n", 2, "--seed", 4, "--quick", "--family", "twin", "--family",
                           "nuisance", "--out", tmp_path / "remote", "--scheduler", cluster.wait())  # fmt: skip
    assert remote.returncode == 0, remote.stderr
    assert "pooled" in remote.stdout and "[2/2]" in remote.stderr
    serial = (tmp_path / "serial" / "blindtest.json").read_bytes()
    assert serial == (tmp_path / "remote" / "blindtest.json").read_bytes()
    assert [c["family"] for c in json.loads(serial)["cases"]] == ["twin", "nuisance"]
    timing = json.loads((tmp_path / "remote" / "blindtest.timing.json").read_text())
    assert sorted(timing["cases_s"]) == ["0", "1"] and timing["scheduler"].startswith("tcp://127.0.0.1:")


CLOSED = """
[controller]
kind = "state_feedback"
K = [9.231, -18.769, 1.203, -0.041]
cutoff = 15.0
u_limit = 10.0

[[experiment]]
name = "square_closed"
loop = "closed"
signal = "square"
f = 0.4
amplitude = 20.0
duration = 6.0
"""


def test_a_remote_worker_without_a_compiler_runs_a_closed_loop(tmp_path, fmus):
    """The co-simulation's step loops (fmus/master) travel to remote workers as bytes, as the FMUs do: workers
    with an empty cache and no C compiler (CC=false, PATH without one) run a closed-loop campaign, the same bytes
    as serially. Before, each worker compiled the loops itself and failed here."""
    from harness import spec as specmod
    from harness.rig.campaign import run_campaign

    spec = tmp_path / "closed.toml"
    spec.write_text(TINY_SPEC + CLOSED)
    cache = tmp_path / "worker-cache"
    env = {**os.environ, "FLEXJOINT_CACHE": str(cache), "CC": "false", "PATH": str(Path(sys.executable).parent)}
    with DaskCluster(2, env=env) as cluster:
        run_campaign(specmod.load(spec), tmp_path / "serial", workers=1)
        run_campaign(specmod.load(spec), tmp_path / "remote", scheduler=cluster.wait())
    assert [p.name for p in cache.iterdir() if p.name.startswith("master-")]  # installed, not built: no .lock dir
    for f in ("square_closed", "prbs"):
        data = f"data/{f}.parquet"
        assert (tmp_path / "serial" / data).read_bytes() == (tmp_path / "remote" / data).read_bytes(), f
