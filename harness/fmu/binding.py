"""The FMU binding: load an FMI 2.0 co-simulation FMU with fmpy's ``FMU2Slave``, set parameters by name, and call
its functions, checking every status. The model description comes from :mod:`harness.fmu.modeldesc`.

``Instance.dll`` and ``Instance.component`` are the loaded binary and its instance, for hot loops that call
``fmi2SetReal`` / ``fmi2DoStep`` / ``fmi2GetReal`` directly with preallocated ctypes arrays
(``harness.fmu.cosim.Rig``, ``harness.ident.export.ModelFMU``).
"""

from __future__ import annotations

import ctypes
import shutil
import tempfile
from dataclasses import dataclass, field
from functools import cached_property
from multiprocessing.util import Finalize
from pathlib import Path
from typing import Any

from fmpy import extract
from fmpy.fmi2 import (
    FMU2Slave,
    defaultCallbacks,
    fmi2Boolean,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
    fmi2Integer,
    fmi2Real,
    fmi2ValueReference,
)

from .modeldesc import ModelDescription, Variable, read

SETTERS = {  # a parameter type: its Python type, the FMI function that sets it and the C type it takes
    "Real": (float, "fmi2SetReal", fmi2Real),
    "Integer": (int, "fmi2SetInteger", fmi2Integer),
    "Boolean": (bool, "fmi2SetBoolean", fmi2Boolean),
}


PLANS_KEPT = 64  # parameter-name tuples whose setting plan an instance keeps (Instance.set_parameters)
Plan = list[tuple[str, Any, Any, list[int]]]  # per type: its name, FMI setter, value references, the names' positions


class FMUError(RuntimeError):
    """An FMU refused a call; the message carries the FMU's last log line."""


@dataclass
class Instance:
    """One loaded, instantiated FMU with its variables by name."""

    path: Path
    slave: FMU2Slave
    description: ModelDescription
    unzipdir: str
    log: list[str] = field(default_factory=list)
    callbacks: Any = None
    cleanup: Any = None
    _plans: dict[tuple[str, ...], Plan] = field(default_factory=dict, repr=False)

    @property
    def variables(self) -> dict[str, Variable]:
        return self.description.variables

    @property
    def dll(self) -> Any:
        """The loaded binary (its ``fmi2*`` functions)."""
        return self.slave.dll

    @property
    def component(self) -> Any:
        """The fmi2Component of this instance."""
        return self.slave.component

    def vr(self, name: str) -> int:
        return self.variables[name].value_reference

    def check(self, status: int, what: str) -> None:
        """Raise :class:`FMUError` with the FMU's last log line for fmi2Discard, fmi2Error or fmi2Fatal."""
        if status > 1:
            msg = self.log[-1] if self.log else f"status {status}"
            raise FMUError(f"{self.path.stem}: {what} failed: {msg}")

    def reset(self) -> None:
        """fmi2Reset: back to the start values, parameters settable again."""
        self.log.clear()
        self.check(self.dll.fmi2Reset(self.component), "reset")

    def set_parameters(self, values: dict[str, Any]) -> None:
        """Set parameters by name (Real, Integer or Boolean as their declared type), one FMI call per type."""
        names = tuple(values)
        plan = self._plans.get(names)
        if plan is None:
            plan = self._plan(names)
        given = list(values.values())
        for kind, setter, refs, at in plan:
            cast, _, ctype = SETTERS[kind]
            n = len(at)
            self.check(setter(self.component, refs, n, (ctype * n)(*[cast(given[i]) for i in at])),
                       f"set {kind} parameters")  # fmt: skip

    def _plan(self, names: tuple[str, ...]) -> Plan:
        """How :meth:`set_parameters` sets parameters ``names`` (in that order): per type, its FMI setter, the value
        references and which of the names they are; kept per instance for the next call with the same names (a fit
        sets the same ones thousands of times)."""
        settable = self._settable
        by_kind: dict[str, list[int]] = {kind: [] for kind in SETTERS}
        for i, name in enumerate(names):
            found = settable.get(name)
            if found is None:
                if name not in self.variables:
                    valid = sorted(self.description.parameters())
                    raise FMUError(f"{self.path.stem}: unknown parameter {name!r}; valid: {', '.join(valid)}")
                raise FMUError(f"{self.path.stem}: parameter {name!r} has unsupported type {self.variables[name].type}")
            by_kind[found[0]].append(i)
        plan = [(kind, getattr(self.dll, SETTERS[kind][1]),
                 (fmi2ValueReference * len(at))(*[settable[names[i]][1] for i in at]), at)
                for kind, at in by_kind.items() if at]  # fmt: skip
        if len(self._plans) >= PLANS_KEPT:
            self._plans.clear()
        self._plans[names] = plan
        return plan

    @cached_property
    def _settable(self) -> dict[str, tuple[str, int]]:
        """Each variable of a type :meth:`set_parameters` sets: its type and value reference, by name."""
        return {n: (v.type, v.value_reference) for n, v in self.variables.items() if v.type in SETTERS}

    def get(self, names: list[str]) -> dict[str, float | int]:
        """Current values by name (Real as float, Integer as int)."""
        out: dict[str, float | int] = {}
        for name in names:
            v = self.variables[name]
            vr = (ctypes.c_uint * 1)(v.value_reference)
            if v.type == "Integer":
                val: Any = (ctypes.c_int * 1)()
                self.check(self.dll.fmi2GetInteger(self.component, vr, 1, val), f"get {name}")
            else:
                val = (ctypes.c_double * 1)()
                self.check(self.dll.fmi2GetReal(self.component, vr, 1, val), f"get {name}")
            out[name] = val[0]
        return out

    def initialize(self, params: dict[str, Any], stop: float) -> None:
        """Reset, set parameters by name, set up an experiment from 0 to ``stop`` [s], enter initialisation mode."""
        self.reset()
        self.set_parameters(params)
        f, c = self.dll, self.component
        self.check(
            f.fmi2SetupExperiment(c, fmi2Boolean(0), fmi2Real(0.0), fmi2Real(0.0), fmi2Boolean(1), fmi2Real(stop)),
            "setup experiment",
        )
        self.check(f.fmi2EnterInitializationMode(c), "initialisation")

    def exit_initialization(self) -> None:
        self.check(self.dll.fmi2ExitInitializationMode(self.component), "initialisation")

    def terminate(self) -> None:
        self.check(self.dll.fmi2Terminate(self.component), "terminate")

    def free(self) -> None:
        """Free the instance and remove its extracted files."""
        try:
            self.slave.terminate()
        except Exception:  # noqa: BLE001 (already failed FMUs may refuse terminate)
            pass
        self.slave.freeInstance()
        self.cleanup()


def load(path: Path, instance_name: str | None = None) -> Instance:
    """Extract and instantiate a co-simulation FMU, collecting its log messages."""
    md = read(path)
    unzipdir = extract(str(path), unzipdir=tempfile.mkdtemp(prefix="flexjoint-fmu-"))
    slave = FMU2Slave(
        guid=md.guid,
        unzipDirectory=unzipdir,
        modelIdentifier=md.model_identifier,
        instanceName=instance_name or md.model_identifier,
    )
    inst = Instance(Path(path), slave, md, unzipdir)
    # remove the extracted files even when the owner never calls free(): at garbage collection, at interpreter
    # exit, and in pool workers, which leave through multiprocessing's exit handlers rather than atexit
    inst.cleanup = Finalize(inst, shutil.rmtree, args=(unzipdir,), kwargs={"ignore_errors": True}, exitpriority=0)

    def logger(env: Any, instance: Any, status: int, category: Any, message: bytes | None) -> None:  # FMI 2.0
        inst.log.append(message.decode(errors="replace") if message else "")

    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(logger)
    callbacks.allocateMemory = defaultCallbacks.allocateMemory
    callbacks.freeMemory = defaultCallbacks.freeMemory
    inst.callbacks = callbacks  # keep the ctypes callbacks alive as long as the instance
    slave.instantiate(loggingOn=True, callbacks=callbacks)
    return inst
