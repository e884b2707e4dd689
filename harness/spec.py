"""Campaign specs: TOML files naming the rig parameters, the sampling rate and the experiments.

A spec has these tables (everything but ``[campaign]`` and one experiment is optional)::

    [campaign]   name, sample_rate [Hz], seed, internal_step [s]
    [plant]      flexjoint FMU parameters by their FMI names (Rm, Beq, coulomb_torque, n_modes, ...)
    [daq]        daq FMU parameters by their FMI names (adc_bits, delay_samples, noise_theta, ...)
    [[calibration]]  experiments for Kp (pot_ramp), Ke (comb) and the dead zone (ramp)
    [[experiment]]   identification experiments: name, signal, duration [s] and the signal's parameters,
                     optional ``plant = {...}`` / ``daq = {...}`` overrides for that experiment only
    [controller] the closed loop's controller: kind ("state_feedback", "pid" or "lqg"), K = [4 gains] or kp, ki, kd,
                 cutoff [Hz] of its velocity filter, u_limit [V], sample_rate [Hz] (default the campaign's),
                 alpha_gain [deg/V] the gauge calibration it reads alpha with (default the DAQ's gauge_gain);
                 an lqg's arrays in [controller.estimator] (A, B, C, L, K, N, X0: harness.rig.controller.Estimator)
    [[experiment]] with ``loop = "closed"``: run under the controller, its signal the theta reference [deg]
    [identify]   na, nb, nc ranges, nk, af, output, fit_threshold [%], selection tolerance [fit points]
    [accept]     min_fit [%] per dataset, min_average_fit [%] for the selected model
    [uncertainty] how far the sheet's numbers can be trusted: ``sheet`` = "datasheet" (default), "lab" or
                 "measured" sets the default of every parameter, and a parameter's own (``Ks = "x2"``, a factor;
                 ``kt = "10 %"``), both as 95 % ranges: the priors of the diagnosis's recalibration

Unknown keys anywhere are an error that lists the valid ones.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypedDict, cast

from .fmu.modeldesc import Variable, source_model
from .fmu.sources import bundled_dir
from .machine import default_workers, machine_memory
from .rig.controller import Controller
from .rig.signals import SIGNAL_KINDS, check_params

SPEC_DIR = bundled_dir("specs")  # the bundled specs: harness/_specs in a wheel, specs/ in a clone

CAMPAIGN_KEYS = {"name", "sample_rate", "seed", "internal_step", "description"}
EXPERIMENT_KEYS = {"name", "signal", "duration", "plant", "daq", "role", "loop"}
CONTROLLER_KEYS = {"kind", "K", "kp", "ki", "kd", "cutoff", "u_limit", "sample_rate", "ref_delay", "alpha_gain",
                   "alpha_bias", "estimator"}  # fmt: skip
LOOPS = ("open", "closed")
COMB_PARAMS = {"deflections_cm", "D_cm", "hold", "ramp"}


class IdentifySettings(TypedDict):
    """The ``[identify]`` table, every key filled (:data:`IDENTIFY_DEFAULTS` where the spec gives none): the ARMAX
    orders ``na``, ``nb``, ``nc`` (an integer or [lo, hi]) and the delay ``nk`` [samples]; the prefilter's pole ``af``;
    the identified ``output`` ("y" tip angle, "theta", "alpha"); ``fit_threshold`` [%] a model must reach;
    the selection's ``tolerance`` [fit points]; the initial state ``ic`` of the fits ("z" zero, "e" estimated);
    ``doubled_rate``: run lab 1's doubled-rate check."""

    na: int | list[int]
    nb: int | list[int]
    nc: int | list[int]
    nk: int
    af: float
    output: str
    fit_threshold: float
    tolerance: float
    ic: str
    doubled_rate: bool


class AcceptThresholds(TypedDict):
    """The ``[accept]`` table: ``min_fit`` [%] on every identification dataset, ``min_average_fit`` [%] on their
    mean, for the selected model."""

    min_fit: float
    min_average_fit: float


IDENTIFY_DEFAULTS: IdentifySettings = {
    "na": [1, 8],
    "nb": [1, 3],
    "nc": [1, 8],
    "nk": 1,
    "af": 0.8,
    "output": "y",
    "fit_threshold": 89.0,
    "tolerance": 1.0,
    "ic": "z",
    "doubled_rate": True,
}
ACCEPT_DEFAULTS: AcceptThresholds = {"min_fit": 80.0, "min_average_fit": 85.0}
# 95 % factors by kind of sheet: what a maker measured (datasheet), what a lab wrote down or derived (lab), what was
# measured on this unit (measured). Nobody's sheet knows damping: Beq a factor 3 on every sheet, a link's damping
# ratio a factor 10 (0.001-0.1 about a steel ruler's 0.01).
SHEETS: dict[str, dict[str, float]] = {
    "datasheet": {"default": 1.1, "Ks": 1.2, "gauge_gain": 1.1, "pot_gain": 1.01, "Kg": 1.01},
    "lab": {"default": 2.0, "m_link": 1.1, "L_link": 1.05, "m_tip": 1.1, "Kg": 1.01, "pot_gain": 1.05},
    "measured": {"default": 1.02, "Ks": 1.05, "gauge_gain": 1.05},
}
UNDAMPED = {"Beq": 3.0, "zeta_link": 10.0}
UNCERTAIN = ("Kg", "kt", "km", "Rm", "eta_g", "eta_m", "Jeq", "Beq", "m_link", "L_link", "m_tip", "Ks", "zeta_link",
             "pot_gain", "gauge_gain")  # fmt: skip


class SpecError(ValueError):
    """A spec that cannot be run; the message is one line meant for the user."""


def _model_parameters(model: str) -> dict[str, Variable]:
    """The parameters of an FMU source model (:func:`harness.fmu.modeldesc.source_model`: the modelDescription.xml
    of ``$FLEXJOINT_FMU_SRC`` or the bundled sources)."""
    try:
        return source_model(model).parameters()
    except FileNotFoundError as e:
        raise SpecError(str(e)) from None


def fmu_parameters(model: str) -> dict[str, tuple[str, Any]]:
    """Parameters of an FMU source model as ``{name: (type, start)}``."""
    return {name: (v.type, v.start) for name, v in _model_parameters(model).items()}


def physical_range(model: str, name: str) -> tuple[float, float]:
    """The range [min, max] a parameter of FMU ``model`` declares (-inf / inf where it declares none)."""
    v = _model_parameters(model)[name]
    return (-math.inf if v.min is None else float(v.min), math.inf if v.max is None else float(v.max))


def fmu_value(table: Mapping[str, Any], model: str, name: str) -> float:
    """Parameter ``name`` of FMU ``model`` ("flexjoint", "daq"): its value in ``table``, else the FMU's default."""
    return float(table[name] if name in table else fmu_parameters(model)[name][1])


def _check_range(where: str, v: Variable, value: float) -> None:
    """One :class:`SpecError` line for a value outside the range the modelDescription.xml declares (inclusive)."""
    lo = -math.inf if v.min is None else v.min
    hi = math.inf if v.max is None else v.max
    if not lo <= value <= hi:
        unit = f" {v.unit}" if v.unit and v.unit != "1" else ""
        bounds = f"[{lo:g}, {hi:g}]" if v.min is not None and v.max is not None else (
            f">= {lo:g}" if v.max is None else f"<= {hi:g}")  # fmt: skip
        raise SpecError(f"{where} = {value:g} is outside its physical range {bounds}{unit} ({v.description})")


@dataclass(frozen=True)
class Experiment:
    """One experiment: the command signal and per-experiment parameter overrides."""

    name: str
    signal: str
    duration: float
    params: dict[str, Any] = field(default_factory=dict)
    plant: dict[str, Any] = field(default_factory=dict)
    daq: dict[str, Any] = field(default_factory=dict)
    role: str = "identification"
    loop: str = "open"  # "closed": under the spec's controller, the signal is the theta reference [deg]


@dataclass
class Spec:
    """A parsed, validated campaign spec."""

    name: str
    sample_rate: float
    seed: int
    internal_step: float
    plant: dict[str, Any]
    daq: dict[str, Any]
    calibration: list[Experiment]
    experiments: list[Experiment]
    identify: IdentifySettings
    accept: AcceptThresholds
    raw: dict[str, Any]
    path: str = ""
    controller: Controller | None = None
    uncertainty: dict[str, float] = field(default_factory=dict)

    def factor(self, name: str) -> float:
        """The 95 % factor within which the sheet's value of ``name`` (:data:`UNCERTAIN`) holds on the rig: the
        spec's ``[uncertainty]``, else its sheet's default for that kind of parameter."""
        if name in self.uncertainty:
            return self.uncertainty[name]
        sheet = SHEETS[str(self.raw.get("uncertainty", {}).get("sheet", "datasheet"))]
        return UNDAMPED.get(name, sheet.get(name, sheet["default"]))

    @property
    def Ts(self) -> float:
        """Sampling period [s]."""
        return 1.0 / self.sample_rate

    def sha256(self) -> str:
        """Hash of the resolved spec (after overrides), stable across key order."""
        return hashlib.sha256(json.dumps(self.raw, sort_keys=True).encode()).hexdigest()

    def all_experiments(self) -> list[Experiment]:
        return [*self.calibration, *self.experiments]

    def experiment(self, name: str) -> Experiment:
        for e in self.all_experiments():
            if e.name == name:
                return e
        raise SpecError(f"no experiment named {name!r}; have {', '.join(e.name for e in self.all_experiments())}")


def check_percent(where: str, value: Any) -> float:
    """A fit threshold [%]: a number in 0..100, else one :class:`SpecError` line."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= 100:
        raise SpecError(f"{where} = {value!r}: a fit threshold is a percentage in 0..100")
    return float(value)


def _check_keys(where: str, given: dict[str, Any], valid: set[str] | dict[str, Any]) -> None:
    unknown = sorted(set(given) - set(valid))
    if unknown:
        raise SpecError(f"unknown key(s) {', '.join(unknown)} in {where}; valid: {', '.join(sorted(valid))}")


def _check_params(where: str, model: str, values: dict[str, Any]) -> dict[str, Any]:
    """FMU parameter values checked against ``model``'s modelDescription.xml: known names, their types, their
    declared ranges."""
    valid = _model_parameters(model)
    _check_keys(where, values, valid)
    out: dict[str, float | int | bool] = {}
    for k, v in values.items():
        kind = valid[k].type
        if kind == "Integer":
            if isinstance(v, bool) or not (isinstance(v, int) or (isinstance(v, float) and v.is_integer())):
                raise SpecError(f"{where}.{k} must be an integer, got {v!r}")
            out[k] = int(v)
        elif kind == "Boolean":
            if not isinstance(v, bool):
                raise SpecError(f"{where}.{k} must be true or false, got {v!r}")
            out[k] = v
        else:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise SpecError(f"{where}.{k} must be a finite number, got {v!r}")
            out[k] = float(v)
        if kind != "Boolean":
            _check_range(f"{where}.{k}", valid[k], out[k])
    return out


def _experiment(where: str, d: dict[str, Any], role: str) -> Experiment:
    if not isinstance(d, dict):
        raise SpecError(f"{where} must be a table")
    for req in ("name", "signal", "duration"):
        if req not in d:
            raise SpecError(f"{where} is missing {req!r}")
    signal = d["signal"]
    kinds = (*SIGNAL_KINDS, "comb")
    if signal not in kinds:
        raise SpecError(f"{where}.signal {signal!r} unknown; valid: {', '.join(kinds)}")
    params = {k: v for k, v in d.items() if k not in EXPERIMENT_KEYS}
    if signal == "comb":
        _check_keys(f"{where} (comb)", params, COMB_PARAMS)
    duration = d["duration"]
    if not isinstance(duration, (int, float)) or not duration > 0:
        raise SpecError(f"{where}.duration must be a positive number of seconds")
    return Experiment(
        name=str(d["name"]),
        signal=signal,
        duration=float(duration),
        params=params,
        plant=_check_params(f"{where}.plant", "flexjoint", d.get("plant", {})),
        daq=_check_params(f"{where}.daq", "daq", d.get("daq", {})),
        role=str(d.get("role", role)),
        loop=_loop(where, d.get("loop", "open"), signal),
    )


def _loop(where: str, loop: Any, signal: str) -> str:
    if loop not in LOOPS:
        raise SpecError(f"{where}.loop {loop!r} unknown; valid: {', '.join(LOOPS)}")
    if loop == "closed" and signal == "comb":
        raise SpecError(f"{where}: a comb calibration holds the hub and cannot run closed loop")
    return loop


def controller_table(d: Any) -> Controller:
    """The ``[controller]`` table as a :class:`Controller`; one :class:`SpecError` line for a bad one."""
    if not isinstance(d, dict):
        raise SpecError("[controller] must be a table")
    _check_keys("[controller]", d, CONTROLLER_KEYS)
    if "estimator" in d and not isinstance(d["estimator"], dict):
        raise SpecError("[controller].estimator must be a table of the LQG's arrays (A, B, C, L, K, N, X0)")
    for k, v in d.items():
        vals = v if k == "K" and isinstance(v, list) else [v]
        if k not in ("kind", "estimator") and any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in vals):
            raise SpecError(f"[controller].{k} must be {'a list of 4 numbers' if k == 'K' else 'a number'}, got {v!r}")
    if "K" in d and not isinstance(d["K"], list):
        raise SpecError(f"[controller].K must be a list of 4 numbers, got {d['K']!r}")
    kw: dict[str, Any] = {k: [float(x) for x in v] if k == "K" else v for k, v in d.items()}
    try:
        c = Controller(**kw)
    except (TypeError, ValueError) as err:
        raise SpecError(f"[controller]: {err}") from None
    declared = _model_parameters("controller")
    for k, v in c.fmu_parameters(float(c.sample_rate or 1.0)).items():
        if k in declared:
            _check_range(f"[controller] {k}", declared[k], v)
    return c


def _uncertainty(d: Any) -> dict[str, float]:
    """The ``[uncertainty]`` table as 95 % factors per parameter ("x2" -> 2.0, "10 %" -> 1.1); one
    :class:`SpecError` line for a malformed one."""
    if not isinstance(d, dict):
        raise SpecError("[uncertainty] must be a table")
    _check_keys("[uncertainty]", d, {"sheet", *UNCERTAIN})
    if "sheet" in d and d["sheet"] not in SHEETS:
        raise SpecError(f"[uncertainty].sheet = {d['sheet']!r} unknown; valid: {', '.join(SHEETS)}")
    out = {}
    for k, v in d.items():
        if k == "sheet":
            continue
        text = str(v).strip().replace(" ", "") if isinstance(v, str) else ""
        factor = math.nan
        if text[:1] in ("x", "*") or text[-1:] == "x":
            factor = _number(text.strip("x*"))
        elif text.endswith("%"):
            factor = 1.0 + _number(text[:-1]) / 100.0
        if not (math.isfinite(factor) and factor > 1.0):
            raise SpecError(
                f'[uncertainty].{k} = {v!r}: give a factor ("x2", more than 1) or a percentage ("10 %", more '
                "than 0), the 95 % range of the sheet's value"
            )
        out[k] = factor
    return out


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan


def parse_value(text: str) -> Any:
    """Parse a ``--set`` value as a TOML literal (number, bool, string, array); bare words are strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(raw: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``table.name=value`` overrides (``--set plant.backlash=0.004``) to a raw spec dict."""
    raw = copy.deepcopy(raw)
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise SpecError(f"--set {item!r}: expected table.name=value, e.g. plant.backlash=0.004")
        key, value = item.split("=", 1)
        table, name = key.strip().split(".", 1)
        if table not in ("campaign", "plant", "daq", "controller", "identify", "accept", "uncertainty"):
            raise SpecError(
                f"--set {item!r}: table must be one of campaign, plant, daq, controller, identify, accept, uncertainty"
            )
        raw.setdefault(table, {})[name.strip()] = parse_value(value.strip())
    return raw


def from_dict(raw: dict[str, Any], path: str = "") -> Spec:
    """Validate a raw spec dict (as read from TOML) into a :class:`Spec`."""
    _check_keys(
        "spec",
        raw,
        {"campaign", "plant", "daq", "controller", "calibration", "experiment", "identify", "accept", "uncertainty"},
    )
    camp = raw.get("campaign", {})
    _check_keys("[campaign]", camp, CAMPAIGN_KEYS)
    rate = camp.get("sample_rate", 50.0)
    if not isinstance(rate, (int, float)) or not rate > 0:
        raise SpecError("[campaign].sample_rate must be a positive number of Hz")
    internal = camp.get("internal_step", 1e-3)
    if not isinstance(internal, (int, float)) or not internal > 0:
        raise SpecError("[campaign].internal_step must be a positive number of seconds")
    seed = camp.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise SpecError("[campaign].seed must be a non-negative integer")
    plant = _check_params("[plant]", "flexjoint", raw.get("plant", {}))
    daq = _check_params("[daq]", "daq", raw.get("daq", {}))
    cal = [_experiment(f"[[calibration]] #{i + 1}", d, "calibration") for i, d in enumerate(raw.get("calibration", []))]
    exps = [
        _experiment(f"[[experiment]] #{i + 1}", d, "identification") for i, d in enumerate(raw.get("experiment", []))
    ]
    if not exps:
        raise SpecError("spec has no [[experiment]]")
    names = [e.name for e in (*cal, *exps)]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise SpecError(f"duplicate experiment name(s): {', '.join(dup)}")
    controller = controller_table(raw["controller"]) if "controller" in raw else None
    closed = [e.name for e in (*cal, *exps) if e.loop == "closed"]
    if closed and controller is None:
        raise SpecError(f"experiment(s) {', '.join(closed)} run closed loop but the spec has no [controller] table")
    _check_keys("[identify]", raw.get("identify", {}), dict(IDENTIFY_DEFAULTS))
    identify = cast(IdentifySettings, {**IDENTIFY_DEFAULTS, **raw.get("identify", {})})  # its keys checked above
    _check_keys("[accept]", raw.get("accept", {}), dict(ACCEPT_DEFAULTS))
    accept = cast(AcceptThresholds, {**ACCEPT_DEFAULTS, **raw.get("accept", {})})
    for k, v in accept.items():
        check_percent(f"[accept].{k}", v)
    check_percent("[identify].fit_threshold", identify["fit_threshold"])
    spec = Spec(
        name=str(camp.get("name", Path(path).stem or "campaign")),
        sample_rate=float(rate),
        seed=seed,
        internal_step=float(internal),
        plant=plant,
        daq=daq,
        calibration=cal,
        experiments=exps,
        identify=identify,
        accept=accept,
        raw=raw,
        path=path,
        controller=controller,
        uncertainty=_uncertainty(raw.get("uncertainty", {})),
    )
    check_memory(spec)  # before the signal checks below generate any signal at this rate
    for e in spec.all_experiments():
        if e.signal != "comb":
            try:
                check_params(e.signal, spec.Ts, e.params)
            except ValueError as err:
                raise SpecError(f"experiment {e.name!r}: {err}") from None
    return spec


def resolve_path(spec: str | Path) -> Path:
    """A spec path, or a bare name looked up in the bundled specs (``lab`` -> specs/lab.toml; a bundled name wins
    over a directory of that name here, such as the ``blind`` a blind test wrote)."""
    p = Path(spec)
    if p.is_file():
        return p
    for cand in (SPEC_DIR / p, SPEC_DIR / f"{p}.toml"):
        if cand.is_file():
            return cand
    if p.is_dir():
        raise SpecError(f"spec {spec} is a directory, not a TOML file")
    have = ", ".join(bundled_specs()) or "none"
    raise SpecError(f"spec {spec} not found (looked in . and {SPEC_DIR}; bundled: {have})")


def bundled_specs() -> dict[str, str]:
    """The specs shipped with the package: ``{name: description}`` (``[campaign].description``, else the first
    comment line of the file)."""
    out: dict[str, str] = {}
    if not SPEC_DIR.is_dir():
        return out
    for path in sorted(SPEC_DIR.glob("*.toml")):
        text = path.read_text(encoding="utf-8")
        try:
            desc = str(tomllib.loads(text).get("campaign", {}).get("description", ""))
        except tomllib.TOMLDecodeError:
            desc = ""
        if not desc:
            comments = [ln.lstrip("#").strip() for ln in text.splitlines() if ln.startswith("#")]
            desc = next((c for c in comments if c), "")
        out[path.stem] = desc
    return out


# --- what a campaign needs before it runs -------------------------------------------------------------------

RK4_WORK_ARRAYS = 24  # float64 arrays of n samples alive per running experiment: command, torque, the (n, 6)
# output table of the co-simulation loop, t and the converted angles, signal temporaries and the Arrow copy


def memory_estimate(spec: Spec, workers: int | None = None) -> dict[str, Any]:
    """Bytes a campaign of ``spec`` needs: every dataset held until it is written (samples x columns x 8 bytes
    over all experiments) plus the co-simulation work of the experiments running at once: the longest ``workers``
    of them, by default as many as the executor starts on this machine (:func:`harness.machine.default_workers`:
    ``FLEXJOINT_WORKERS``, else min(2, cpu count)), at most one per experiment; ``workers`` in the result."""
    exps = spec.all_experiments()
    ns = [int(round(e.duration * spec.sample_rate)) for e in exps]
    cols = [8 if e.signal == "comb" else 6 for e in exps]
    if workers is None:
        workers = min(len(exps), default_workers())
    running = sorted(ns, reverse=True)[: max(1, workers)]
    data = sum(n * c * 8 for n, c in zip(ns, cols, strict=True))
    work = sum(running) * RK4_WORK_ARRAYS * 8
    return {
        "bytes": data + work,
        "data": data,
        "work": work,
        "samples": sum(ns),
        "columns": sorted(set(cols)),
        "experiments": len(exps),
        "workers": workers,
    }


def _gib(n: float) -> str:
    """Bytes in MiB, GiB or TiB, three significant digits."""
    unit = "MiB" if n < 2**30 else "GiB" if n < 2**40 else "TiB"
    return f"{n / 2 ** {'MiB': 20, 'GiB': 30, 'TiB': 40}[unit]:.3g} {unit}"


def check_memory(spec: Spec, workers: int | None = None, available: int | None = None) -> dict[str, Any]:
    """Refuse (:class:`SpecError`, one line with the estimate) a campaign that needs more memory than the machine
    has (``available`` bytes, default :func:`machine_memory`); returns the estimate otherwise."""
    est = memory_estimate(spec, workers)
    have = machine_memory() if available is None else available
    if have is not None and est["bytes"] > have:
        raise SpecError(
            f"campaign {spec.name!r} needs ~{_gib(est['bytes'])} of memory ({est['samples']:,} samples x "
            f"{'-'.join(map(str, est['columns']))} columns x 8 bytes = {_gib(est['data'])} over "
            f"{est['experiments']} experiments, plus {_gib(est['work'])} of RK4 work) but this machine has "
            f"{_gib(have)}: lower campaign.sample_rate ({spec.sample_rate:g} Hz) or the durations"
        )
    return est


def load(spec: str | Path, overrides: list[str] | None = None) -> Spec:
    """Read, override and validate a spec.

    Parameters
    ----------
    spec : str or Path
        A path to a TOML file, or the name of a bundled spec (``lab``, ``nominal``, ...; ``flexjoint specs``).
    overrides : list of str, optional
        ``table.name=value`` items applied on top of the file, as ``--set`` does (``["plant.backlash=0.004"]``).

    Returns
    -------
    Spec
        The validated spec: every parameter checked against the range its FMU declares.

    Raises
    ------
    SpecError
        One line naming what is wrong (an unknown key with the valid ones, a value out of range, ...).
    """
    path = resolve_path(spec)
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise SpecError(f"{path}: malformed TOML: {err}") from None
    return from_dict(apply_overrides(raw, overrides or []), str(path))
