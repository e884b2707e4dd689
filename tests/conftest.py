"""Shared fixtures: the built rig-twin FMUs, a minimal fmpy stepping loop for tests, and the runs several test files
read (the lab campaign, a diagnosed run, the Quanser record diagnosed, the CU unit's lone record diagnosed:
tests/shared_runs.py), each made once for the
whole session and shared by the test processes of ``-n N``."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from shared_runs import make_cu_lone_run, make_diagnosed_run, make_lab_campaign, make_quanser_run, shared_dir

from harness.fmu import modeldesc
from harness.fmu.build import build_all


@pytest.fixture
def lab1_model():
    """Lab 1's final model as printed in its report (eq. 12, coefficients rounded to two digits): ARMAX(5,3,0,1),
    Ts 20 ms."""
    from harness.ident.armax import ArmaxModel

    return ArmaxModel(
        A=np.array([1.0, -4.33, 7.64, -6.87, 3.16, -0.59]),
        B=np.array([0.0, -0.05, 0.14, -0.09]),
        C=np.array([1.0]),
        na=5,
        nb=3,
        nc=0,
        nk=1,
        Ts=0.02,
    )


@pytest.fixture(scope="session")
def fmus() -> dict[str, Path]:
    """{"flexjoint": Path, "daq": Path} of the built FMUs (from the build cache when up to date)."""
    return build_all()


@pytest.fixture(scope="session")
def lab_campaign(tmp_path_factory, fmus) -> Path:
    """The lab spec's campaign (:func:`shared_runs.make_lab_campaign`), once per session: copy it to write into it."""
    return shared_dir(tmp_path_factory, "lab_campaign", lambda path: make_lab_campaign(path, fmus))


@pytest.fixture(scope="session")
def diagnosed_run(tmp_path_factory, fmus) -> Path:
    """A run directory through every stage, diagnosed (:func:`shared_runs.make_diagnosed_run`: the blind rig with
    Coulomb friction and a one-sample delay, three 10 s experiments), once per session: copy it to write into it."""
    return shared_dir(tmp_path_factory, "diagnosed_run", make_diagnosed_run)


@pytest.fixture(scope="session")
def quanser_run(tmp_path_factory) -> Path:
    """The Quanser record imported and diagnosed (:func:`shared_runs.make_quanser_run`), once per session: copy it to
    write into it."""
    return shared_dir(tmp_path_factory, "quanser_run", make_quanser_run)


@pytest.fixture(scope="session")
def cu_lone_run(tmp_path_factory) -> Path:
    """The CU unit's first record alone, imported and diagnosed against its lab sheet
    (:func:`shared_runs.make_cu_lone_run`: ``run/`` and ``returned.json``), once per session: copy it to write into
    it."""
    return shared_dir(tmp_path_factory, "cu_lone_run", make_cu_lone_run)


class FmuRun:
    """Steps one FMU with fmpy's FMU2Slave: parameters by name, inputs held over each step.

    ``run(params, inputs, outputs, dt, n)``: ``inputs`` maps input names to arrays of length n (value
    held over [t_k, t_k + dt)) or to constants.  Returns ``{"init": {name: value after
    ExitInitializationMode}, name: array of n values read after doStep(t_k)}``.
    """

    def __init__(self, fmu: Path, workdir: Path) -> None:
        from fmpy import extract

        self.md = modeldesc.read(fmu)
        self.unzipdir = extract(str(fmu), unzipdir=str(workdir / fmu.stem))
        self.vars = self.md.variables
        self.messages: list[str] = []

    def vr(self, name: str) -> int:
        return self.vars[name].value_reference

    def _logger(self):
        from ctypes import byref

        from fmpy.fmi2 import defaultCallbacks, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE
        from fmpy.logging import addLoggerProxy

        def log(env, instance, status, category, message):  # noqa: ARG001
            self.messages.append(message.decode())

        cb = fmi2CallbackFunctions()
        cb.logger = fmi2CallbackLoggerTYPE(log)
        cb.allocateMemory = defaultCallbacks.allocateMemory
        cb.freeMemory = defaultCallbacks.freeMemory
        addLoggerProxy(byref(cb))
        self._cb = cb  # keep alive
        return cb

    @contextmanager
    def instance(self, params: Mapping[str, float] | None = None, start: Mapping[str, float] | None = None):
        """An initialised instance (parameters and start inputs set, ExitInitializationMode done)."""
        from fmpy.fmi2 import FMU2Slave

        fmu = FMU2Slave(
            guid=self.md.guid,
            unzipDirectory=self.unzipdir,
            modelIdentifier=self.md.model_identifier,
            instanceName="test",
        )
        fmu.instantiate(callbacks=self._logger())
        try:
            fmu.setupExperiment(startTime=0.0)
            for name, value in (params or {}).items():
                if self.vars[name].type == "Integer":
                    fmu.setInteger([self.vr(name)], [int(value)])
                else:
                    fmu.setReal([self.vr(name)], [float(value)])
            fmu.enterInitializationMode()
            if start:
                fmu.setReal([self.vr(k) for k in start], [float(v) for v in start.values()])
            fmu.exitInitializationMode()
            yield _Handle(fmu, self)
        finally:
            fmu.freeInstance()

    def run(
        self,
        params: Mapping[str, float] | None,
        inputs: Mapping[str, Sequence[float] | np.ndarray | float],
        outputs: Sequence[str],
        dt: float,
        n: int,
    ) -> dict:
        in_names = list(inputs)
        table = np.column_stack([np.broadcast_to(np.asarray(inputs[k], float), (n,)) for k in in_names])
        with self.instance(params, dict(zip(in_names, table[0], strict=True)) if in_names else None) as h:
            res = {"init": dict(zip(outputs, h.get(*outputs), strict=True))}
            out = np.empty((n, len(outputs)))
            in_vrs = [self.vr(k) for k in in_names]
            out_vrs = [self.vr(k) for k in outputs]
            for k in range(n):
                if in_vrs:
                    h.fmu.setReal(in_vrs, list(table[k]))
                h.fmu.doStep(currentCommunicationPoint=k * dt, communicationStepSize=dt)
                out[k] = h.fmu.getReal(out_vrs)
        for i, name in enumerate(outputs):
            res[name] = out[:, i]
        return res


class _Handle:
    """set / step / get on one initialised FMU instance."""

    def __init__(self, fmu, run: FmuRun) -> None:
        self.fmu, self._run = fmu, run

    def set(self, **values: float) -> None:
        self.fmu.setReal([self._run.vr(k) for k in values], [float(v) for v in values.values()])

    def get(self, *names: str) -> list[float]:
        return list(self.fmu.getReal([self._run.vr(k) for k in names]))

    def step(self, t: float, h: float) -> None:
        self.fmu.doStep(currentCommunicationPoint=t, communicationStepSize=h)


@pytest.fixture(scope="session")
def fmu_runner(fmus):
    """{"flexjoint": FmuRun, "daq": FmuRun} sharing one extraction per session."""
    workdir = Path(tempfile.mkdtemp(prefix="fj-test-"))
    yield {name: FmuRun(path, workdir) for name, path in fmus.items()}
    shutil.rmtree(workdir, ignore_errors=True)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A case marked ``open`` (``@pytest.mark.open(reason=...)``: an open issue's case that a loop sticking where the
    noise decides passes or fails by rounding) is an xfail, not strict, with its reason."""
    for item in items:
        mark = item.get_closest_marker("open")
        if mark is not None:
            item.add_marker(pytest.mark.xfail(strict=False, reason=mark.kwargs["reason"]))
