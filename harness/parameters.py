"""Every parameter of the rig twin (plant, DAQ, controller FMUs) with its unit, default and range, from the FMUs'
modelDescription.xml, and the value a spec gives it: what ``flexjoint info [SPEC]`` lists."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from .fmu.modeldesc import source_model
from .spec import UNCERTAIN, Spec

__all__ = ["TABLES", "Parameter", "parameters", "value_text"]

TABLES = {"plant": "flexjoint", "daq": "daq", "controller": "controller"}  # spec table -> FMU model


@dataclass(frozen=True)
class Parameter:
    """One FMU parameter as a spec names it (``table.name``): unit (SI, spaces between factors, "" when
    dimensionless), the FMU's start value, its declared range (None: unbounded), the spec's value (None: the spec
    leaves it at the default), the description of the modelDescription.xml and, for a sheet parameter the diagnosis
    recalibrates, the spec's 95 % factor on it (:meth:`harness.spec.Spec.factor`)."""

    key: str
    unit: str
    default: float | int | bool | None
    min: float | int | None
    max: float | int | None
    spec: float | int | bool | None
    description: str
    uncertainty: float | None = None  # the spec's 95 % factor on the sheet's value, where it has one

    @property
    def range(self) -> str:
        """The declared range as text: ``0..1``, ``>= 0``, ``<= 10`` or "" (unbounded)."""
        if self.min is not None and self.max is not None:
            return f"{value_text(self.min)}..{value_text(self.max)}"
        if self.min is not None:
            return f">= {value_text(self.min)}"
        return f"<= {value_text(self.max)}" if self.max is not None else ""

    @property
    def within(self) -> str:
        """The uncertainty as text: ``10 %`` below a factor 1.5, else ``x2``; "" when the spec gives none."""
        u = self.uncertainty
        if u is None:
            return ""
        return f"{100 * (u - 1):.3g} %" if u < 1.5 else f"x{u:.3g}"

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "range": self.range}


def value_text(v: Any) -> str:
    """A value as text, at full precision without trailing noise (``1.3``, ``0.00768``, ``4096``)."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and math.isfinite(v) and v.is_integer() and abs(v) < 1e15:
        return str(int(v))
    return f"{v:.10g}" if isinstance(v, float) else str(v)


def _unit(unit: str) -> str:
    """The XML's unit as people write it: ``N.m/rad`` -> ``N m/rad``, ``1`` -> ""."""
    return "" if unit in ("", "1") else unit.replace(".", " ")


def spec_values(spec: Spec) -> dict[str, dict[str, Any]]:
    """The values a spec sets per table, as the campaign hands them to the FMUs: its ``[plant]`` and ``[daq]``
    tables, its sample rate and internal step, and its controller's FMU parameters."""
    values: dict[str, dict[str, Any]] = {
        "plant": {"internal_step": spec.internal_step, **spec.plant},
        "daq": {"sample_rate": spec.sample_rate, **spec.daq},
        "controller": {},
    }
    if spec.controller is not None:
        values["controller"] = spec.controller.fmu_parameters(spec.sample_rate)
    return values


def parameters(spec: Spec | None = None) -> list[Parameter]:
    """Every parameter of the plant, DAQ and controller FMUs in that order (each in its modelDescription.xml's
    order), with ``spec``'s value where it sets one."""
    given = spec_values(spec) if spec is not None else {}
    out = []
    for table, model in TABLES.items():
        for name, v in source_model(model).parameters().items():
            out.append(
                Parameter(
                    f"{table}.{name}",
                    _unit(v.unit),
                    v.start,
                    v.min,
                    v.max,
                    given.get(table, {}).get(name),
                    v.description,
                    spec.factor(name) if spec is not None and name in UNCERTAIN and table != "controller" else None,
                )
            )
    return out
