"""The one reader of ``modelDescription.xml``: a model's variables (name, value reference, type, start, min, max,
unit, description) from the FMU source tree or from a built ``.fmu``.

Everything the Python side knows about an FMU's parameters comes from here: the spec's parameter check
(``harness.spec``), the value references of the co-simulation master (``harness.fmu.cosim``), the FMU binding
(``harness.fmu.binding``) and the names, defaults and ranges of :class:`harness.fmu.plant.PlantParams`.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from .sources import bundled_dir, fmu_source_dir

TYPES = ("Real", "Integer", "Boolean")


@dataclass(frozen=True)
class Variable:
    """One ScalarVariable: ``start``, ``min``, ``max`` as float (Real), int (Integer) or bool (Boolean); ``min`` and
    ``max`` are None when the XML gives none (FMI bounds are inclusive)."""

    name: str
    value_reference: int
    causality: str
    variability: str
    type: str
    start: float | int | bool | None
    min: float | int | None
    max: float | int | None
    unit: str
    description: str


@dataclass(frozen=True)
class ModelDescription:
    """The parts of a modelDescription.xml the harness uses."""

    model_identifier: str
    guid: str
    description: str
    variables: dict[str, Variable]

    def parameters(self) -> dict[str, Variable]:
        """The variables of causality ``parameter``, in XML order."""
        return {n: v for n, v in self.variables.items() if v.causality == "parameter"}


def _value(kind: str, text: str | None) -> float | int | bool | None:
    if text is None:
        return None
    if kind == "Real":
        return float(text)
    if kind == "Integer":
        return int(text)
    return text == "true"


def parse(xml: str | bytes) -> ModelDescription:
    """A :class:`ModelDescription` from the text of a modelDescription.xml."""
    root = ET.fromstring(xml)
    cs = root.find("CoSimulation")
    variables: dict[str, Variable] = {}
    for sv in root.iter("ScalarVariable"):
        el = next(e for e in sv if e.tag in TYPES)
        variables[sv.get("name", "")] = Variable(
            name=sv.get("name", ""),
            value_reference=int(sv.get("valueReference", "-1")),
            causality=sv.get("causality", "local"),
            variability=sv.get("variability", "continuous"),
            type=el.tag,
            start=_value(el.tag, el.get("start")),
            min=_value(el.tag, el.get("min")) if el.tag != "Boolean" else None,
            max=_value(el.tag, el.get("max")) if el.tag != "Boolean" else None,
            unit=el.get("unit", ""),
            description=sv.get("description", ""),
        )
    return ModelDescription(
        model_identifier=cs.get("modelIdentifier", "") if cs is not None else "",
        guid=root.get("guid", ""),
        description=root.get("description", ""),
        variables=variables,
    )


def read(source: str | Path) -> ModelDescription:
    """The model description of a built ``.fmu`` (zip), a ``modelDescription.xml`` or a model directory."""
    path = Path(source)
    if path.is_dir():
        path = path / "modelDescription.xml"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing")
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as zf:
            return parse(zf.read("modelDescription.xml"))
    return parse(path.read_bytes())


@cache
def _read_cached(path: str, mtime_ns: int) -> ModelDescription:
    return read(path)


def source_model(name: str) -> ModelDescription:
    """The model description of FMU ``name`` in the source tree the build uses (``$FLEXJOINT_FMU_SRC`` or the
    bundled sources); cached while the file is unchanged."""
    xml = fmu_source_dir() / name / "modelDescription.xml"
    if not xml.is_file():
        raise FileNotFoundError(f"FMU source {xml} is missing")
    return _read_cached(str(xml), xml.stat().st_mtime_ns)


def bundled_model(name: str) -> ModelDescription:
    """The model description of FMU ``name`` as shipped with the package (not overridden by the environment)."""
    return read(bundled_dir("fmus") / name)
