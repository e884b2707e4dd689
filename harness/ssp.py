"""A spec's rig as an SSP 1.0 archive (System Structure and Parameterization) that other co-simulation masters run.

``ssp_bytes(spec, "square_30")`` is a zip with ``SystemStructure.ssd`` and the FMUs under ``resources/``: elements
``plant`` (fmus/flexjoint), ``daq``, ``controller`` (closed loop) and ``signal`` (fmus/signal: the experiment's
command, reference [rad] or tip torque, one row per sample in its ``resources/signal.csv``), their connections, and
each element's parameters from the spec and the experiment (the DAQ's noise seed drawn as the campaign draws it) as
an inline SSV parameter set.

The master's step is a quarter of the sample period (``osp:FixedStepAlgorithm baseStepSize``) and the plant's a whole
period where a master reads ``osp:StepSizeHint`` (at a quarter its state stays on the grid of the campaign's RK4
steps: the same numbers); the controller computes mid-sample (``compute_time``). A master that steps every FMU at
once then reads the DAQ's samples of t_k one step after t_k and hands the command to the DAQ before the sample ends,
which writes it ``delay_samples`` samples later: the loop of ``flexjoint campaign``. A rig without a command delay
(``daq.delay_samples = 0``) acts within the sample, which only a master that orders the FMUs by their feedthrough
reproduces.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np

from .fmu import modeldesc
from .fmu.build import build_fmu
from .fmu.cosim import controller_parameters
from .ident.export import zip_bytes
from .rig.campaign import experiment_inputs, reference_rad
from .rundir import atomic_write_bytes
from .spec import Experiment, Spec, SpecError

__all__ = ["PARAMETER_SET", "SUBSTEPS", "ssd_text", "ssp_bytes", "ssp_experiment", "write_ssp"]

SUBSTEPS = 4  # master steps per sample: at least 3 carry a sample, the command and u_plant within one period
PARAMETER_SET = "rig"  # every element's parameter set has this name: a master applies one set to all of them
FMUS = {"plant": "flexjoint", "daq": "daq", "controller": "controller", "signal": "signal"}
NS = {
    "ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
    "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
    "ssv": "http://ssp-standard.org/SSP1/SystemStructureParameterValues",
    "osp": "http://opensimulationplatform.com/SSP/OSPAnnotations",
}
UNITS = {  # SI base-unit exponents of the connectors' units
    "V": {"kg": 1, "m": 2, "s": -3, "A": -1},
    "rad": {"rad": 1},
    "N.m": {"kg": 1, "m": 2, "s": -2},
    "rad/s": {"s": -1, "rad": 1},
}
OPEN = [
    ("signal", "u", "daq", "u"),
    ("signal", "tau_tip", "plant", "tau_tip"),
    ("daq", "u_plant", "plant", "u"),
    ("plant", "theta", "daq", "theta"),
    ("plant", "alpha_gauge", "daq", "alpha_gauge"),
]
CLOSED = [
    ("signal", "ref", "controller", "ref"),
    ("signal", "tau_tip", "plant", "tau_tip"),
    ("daq", "theta_v", "controller", "theta_v"),
    ("daq", "alpha_v", "controller", "alpha_v"),
    ("controller", "u", "daq", "u"),
    ("daq", "u_plant", "plant", "u"),
    ("plant", "theta", "daq", "theta"),
    ("plant", "alpha_gauge", "daq", "alpha_gauge"),
]


def ssp_experiment(spec: Spec, experiment: str | None = None, loop: str | None = None) -> Experiment:
    """The experiment an SSP carries: ``experiment`` by name, else the spec's first closed-loop one when it has a
    controller, else its first. ``loop`` ("open" or "closed") asks for that loop and refuses the others."""
    if loop not in (None, "open", "closed"):
        raise SpecError(f"--loop {loop!r} unknown; valid: open, closed")
    if loop == "closed" and spec.controller is None:
        raise SpecError(f"spec {spec.name!r} has no [controller] table: no closed-loop SSP")
    exps = spec.all_experiments()
    if experiment is not None:
        exp = spec.experiment(experiment)
    else:
        want = loop or ("closed" if spec.controller is not None else "open")
        found = next((e for e in exps if e.loop == want), None)
        if found is None:
            raise SpecError(f"spec {spec.name!r} has no {want}-loop experiment")
        exp = found
    if loop is not None and exp.loop != loop:
        raise SpecError(f"experiment {exp.name!r} of spec {spec.name!r} runs {exp.loop} loop, not {loop}")
    return exp


def _parameters(
    spec: Spec, exp: Experiment, reference_deg: np.ndarray | None = None
) -> tuple[dict[str, dict[str, Any]], np.ndarray]:
    """Each element's parameters and the signal table (n x 3: u [V], ref [rad], tau_tip [N m]); ``reference_deg``: a
    closed loop's reference [deg] in place of the experiment's signal (a record's)."""
    u, plant, daq, tau, _ = experiment_inputs(spec, exp)
    if reference_deg is not None:
        if exp.loop != "closed":
            raise SpecError(f"experiment {exp.name!r} runs open loop: it has no reference to replace")
        u = np.asarray(reference_deg, dtype=float)
    fs = spec.sample_rate
    daq = {"sample_rate": fs, **daq}
    table = np.zeros((u.size, 3))
    params = {"plant": plant, "daq": daq, "signal": {"sample_rate": fs}}
    if exp.loop == "closed":
        assert spec.controller is not None  # the spec refuses a closed-loop experiment without a controller
        ctrl = controller_parameters(
            spec.controller.fmu_parameters(fs), daq, modeldesc.source_model("daq").variables, spec.Ts
        )
        params["controller"] = ctrl | {"compute_time": 0.5 / ctrl["sample_rate"]}
        table[:, 1] = reference_rad(spec.controller, u)
    else:
        table[:, 0] = u
        if tau is not None:
            table[:, 2] = tau
    return params, table


def _value(kind: str, v: Any) -> str:
    return repr(float(v)) if kind == "Real" else str(int(v))


def _parameter_set(element: str, values: dict[str, Any], md: modeldesc.ModelDescription) -> list[str]:
    lines = [f'<ssv:ParameterSet version="1.0" name="{PARAMETER_SET}">', "<ssv:Parameters>"]
    for name, v in values.items():
        var = md.variables.get(name)
        if var is None or var.causality != "parameter":
            raise SpecError(f"{element}: {name!r} is not a parameter of {md.model_identifier}")
        kind = "Integer" if var.type in ("Integer", "Boolean") else "Real"
        unit = f' unit="{var.unit}"' if kind == "Real" and var.unit in UNITS else ""
        lines.append(f'<ssv:Parameter name="{name}"><ssv:{kind} value="{_value(kind, v)}"{unit}/></ssv:Parameter>')
    return [*lines, "</ssv:Parameters>", "</ssv:ParameterSet>"]


def _component(element: str, values: dict[str, Any], connectors: list[str], step_hint: float | None) -> list[str]:
    md = modeldesc.source_model(FMUS[element])
    src = f"resources/{FMUS[element]}.fmu"
    lines = [f'<ssd:Component name="{element}" type="application/x-fmu-sharedlibrary" source="{src}">']
    lines.append("<ssd:Connectors>")
    for name in connectors:
        var = md.variables[name]
        unit = f' unit="{var.unit}"' if var.unit in UNITS else ""
        lines.append(f'<ssd:Connector name="{name}" kind="{var.causality}"><ssc:Real{unit}/></ssd:Connector>')
    lines += ["</ssd:Connectors>", "<ssd:ParameterBindings>", "<ssd:ParameterBinding>", "<ssd:ParameterValues>"]
    lines += _parameter_set(element, values, md)
    lines += ["</ssd:ParameterValues>", "</ssd:ParameterBinding>", "</ssd:ParameterBindings>"]
    if step_hint is not None:
        lines += [
            '<ssd:Annotations><ssc:Annotation type="com.opensimulationplatform">',
            f'<osp:StepSizeHint value="{step_hint!r}"/>',
            "</ssc:Annotation></ssd:Annotations>",
        ]
    return [*lines, "</ssd:Component>"]


def ssd_text(spec: Spec, exp: Experiment, params: dict[str, dict[str, Any]], n: int) -> str:
    """SystemStructure.ssd of the rig running ``exp`` for ``n`` samples with the elements' ``params``."""
    links = CLOSED if exp.loop == "closed" else OPEN
    Ts = spec.Ts
    desc = (
        f"spec {spec.name!r}, experiment {exp.name!r} ({exp.loop} loop, {n} samples at {spec.sample_rate:g} Hz): "
        f"step every FMU at {Ts / SUBSTEPS!r} s (a quarter sample), the plant at {Ts!r} s; theta [rad] is "
        "plant.theta"
    )
    ns = " ".join(f'xmlns:{k}="{v}"' for k, v in NS.items())
    name = f"{spec.name}-{exp.name}"
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<ssd:SystemStructureDescription {ns} version="1.0" name={quoteattr(name)} generationTool="flexjoint ssp">',
        f'<ssd:System name="rig" description={quoteattr(desc)}>',
        "<ssd:Elements>",
    ]
    for element in params:
        connectors = [c for a, ca, b, cb in links for e, c in ((a, ca), (b, cb)) if e == element]
        if element == "plant":
            connectors += ["alpha"]
        hint = Ts if element == "plant" else None
        lines += _component(element, params[element], list(dict.fromkeys(connectors)), hint)
    lines.append("</ssd:Elements>")
    lines.append("<ssd:Connections>")
    for a, ca, b, cb in links:
        lines.append(f'<ssd:Connection startElement="{a}" startConnector="{ca}" endElement="{b}" endConnector="{cb}"/>')
    lines += ["</ssd:Connections>", "</ssd:System>", "<ssd:Units>"]
    for unit, exps in UNITS.items():
        base = " ".join(f'{k}="{v}"' for k, v in exps.items())
        lines.append(f'<ssc:Unit name="{unit}"><ssc:BaseUnit {base}/></ssc:Unit>')
    lines += [
        "</ssd:Units>",
        f'<ssd:DefaultExperiment startTime="0.0" stopTime="{n * Ts!r}">',
        '<ssd:Annotations><ssc:Annotation type="com.opensimulationplatform">',
        f'<osp:Algorithm><osp:FixedStepAlgorithm baseStepSize="{Ts / SUBSTEPS!r}"/></osp:Algorithm>',
        "</ssc:Annotation></ssd:Annotations>",
        "</ssd:DefaultExperiment>",
        "</ssd:SystemStructureDescription>",
    ]
    return "\n".join(lines) + "\n"


def _signal_fmu(table: np.ndarray, title: str) -> bytes:
    """fmus/signal with ``table`` as its resources/signal.csv (17 significant digits: the same doubles)."""
    with zipfile.ZipFile(build_fmu("signal")) as zf:
        files = {n: zf.read(n) for n in zf.namelist() if not n.endswith("/")}
    rows = "".join(f"{u!r},{r!r},{t!r}\n" for u, r, t in table.tolist())
    files["resources/signal.csv"] = f"# {title}\nu,ref,tau_tip\n{rows}".encode()
    return zip_bytes(files)


def ssp_bytes(
    spec: Spec, experiment: str | None = None, loop: str | None = None, reference_deg: np.ndarray | None = None
) -> bytes:
    """The SSP archive of ``spec``'s rig running one experiment (see :func:`ssp_experiment`); ``reference_deg``: a
    closed loop's reference [deg], one per sample, in place of its signal (a record's reference)."""
    exp = ssp_experiment(spec, experiment, loop)
    params, table = _parameters(spec, exp, reference_deg)
    files = {"SystemStructure.ssd": ssd_text(spec, exp, params, len(table)).encode()}
    for element in params:
        if element != "signal":
            files[f"resources/{FMUS[element]}.fmu"] = build_fmu(FMUS[element]).read_bytes()
    files["resources/signal.fmu"] = _signal_fmu(table, f"spec {spec.name}, experiment {exp.name}")
    return zip_bytes(files)


def write_ssp(spec: Spec, out: Path, experiment: str | None = None, loop: str | None = None) -> Path:
    """Write :func:`ssp_bytes` to ``out`` atomically; returns ``out``."""
    data = ssp_bytes(spec, experiment, loop)
    atomic_write_bytes(Path(out), data)
    return Path(out)
