"""The rig's linear parameters as the data determine them, and the physical values they imply.

Seen from volts to angle, a geared DC drive on a flexible link shows a few numbers, not the dozen of its sheet:

- ``rig.drive_gain`` K = G / D [rad/(V s)]: the hub's steady speed per volt (rigid);
- ``rig.drive_tau`` tau = (Jeq + J_link) / D [s]: the drive's time constant;
- ``rig.inertia_ratio`` r = Jeq / J_link: hub to link inertia (where the link's resonance sits above its clamped
  frequency);
- ``plant.Ks`` and ``plant.zeta_link``: the link's stiffness (its frequency, with the sheet's link inertia) and
  damping;
- ``sensor.theta_gain`` and ``sensor.alpha_gauge_gain``: each sensor's reading per true angle (1 = the data's
  calibration is right).

with G = eta_g Kg eta_m kt / Rm [N m/V] the drive torque per volt, D = Beq + G Kg km [N m s/rad] the viscous plus
back-EMF damping at the hub, J_link = m_link L^2 / 3 + m_tip L^2. :func:`to_plant` maps them back onto the plant FMU's
parameters: Jeq = r J_link, D = (Jeq + J_link) / tau, G = K D carried by kt (Kg, Rm, the efficiencies and km keep the
sheet's values), Beq = D - G Kg km; where that would leave less than MIN_BEQ_SHARE of D to viscous damping, km
gives way instead (the back-EMF is then weaker than the sheet says). On a rig whose km is the sheet's the map is
one to one with (kt, Beq, Jeq).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from .. import spec as specmod

__all__ = ["COMBOS", "SENSORS", "combos", "link_inertia", "physical", "plant_value", "prior_sd", "to_plant"]

COMBOS = ("rig.drive_gain", "rig.drive_tau", "rig.inertia_ratio")
SENSORS = {"sensor.theta_gain": "pot_gain", "sensor.alpha_gauge_gain": "gauge_gain"}  # -> the DAQ's parameter
MIN_BEQ_SHARE = 1e-3  # of the hub's damping D left at least to viscous damping when km gives way


def plant_value(plant: Mapping[str, Any], name: str) -> float:
    """A plant parameter: its value in ``plant``, else the flexjoint FMU's default."""
    return specmod.fmu_value(plant, "flexjoint", name)


def link_inertia(plant: Mapping[str, Any]) -> float:
    """J_link = m_link L^2 / 3 + m_tip L^2 [kg m^2]: the link's inertia about the hub."""
    L = plant_value(plant, "L_link")
    return plant_value(plant, "m_link") * L * L / 3.0 + plant_value(plant, "m_tip") * L * L


def _torque_per_volt(plant: Mapping[str, Any]) -> float:
    p = {k: plant_value(plant, k) for k in ("eta_g", "Kg", "eta_m", "kt", "Rm")}
    return p["eta_g"] * p["Kg"] * p["eta_m"] * p["kt"] / p["Rm"]


def combos(plant: Mapping[str, Any]) -> dict[str, float]:
    """The drive gain [rad/(V s)], time constant [s] and inertia ratio of a plant table (FMU defaults for the
    rest)."""
    G = _torque_per_volt(plant)
    D = plant_value(plant, "Beq") + G * plant_value(plant, "Kg") * plant_value(plant, "km")
    Jl = link_inertia(plant)
    Jeq = plant_value(plant, "Jeq")
    return {"rig.drive_gain": G / D, "rig.drive_tau": (Jeq + Jl) / D, "rig.inertia_ratio": Jeq / Jl}


def to_plant(values: Mapping[str, float], plant: Mapping[str, Any]) -> dict[str, float]:
    """The plant parameters (kt, km, Beq, Jeq) that give the combos ``values`` (any of :data:`COMBOS`; the others
    keep ``plant``'s) with ``plant``'s Kg, Rm, efficiencies, link and (where it can) km."""
    c = {**combos(plant), **{k: float(v) for k, v in values.items() if k in COMBOS}}
    Jl = link_inertia(plant)
    Jeq = c["rig.inertia_ratio"] * Jl
    D = (Jeq + Jl) / c["rig.drive_tau"]
    G = c["rig.drive_gain"] * D
    Kg, km = plant_value(plant, "Kg"), plant_value(plant, "km")
    kt = plant_value(plant, "kt") * G / _torque_per_volt(plant)
    Beq = D - G * Kg * km
    if Beq < MIN_BEQ_SHARE * D:
        Beq = MIN_BEQ_SHARE * D
        km = (D - Beq) / (G * Kg)
    return {"kt": kt, "km": km, "Beq": Beq, "Jeq": Jeq}


def prior_sd(plant: Mapping[str, Any], factor: Callable[[str], float]) -> dict[str, float]:
    """The prior standard deviation [log] of each linear parameter the diagnosis fits (:data:`COMBOS`, plant.Ks,
    plant.zeta_link, :data:`SENSORS`), from the 95 % factor within which each sheet parameter holds
    (``factor(name)``, :meth:`harness.spec.Spec.factor`): a combo's by first-order propagation in log (the sheet's
    parameters independent), sd = ln(factor) / 1.96."""
    sd = {p: math.log(factor(p)) / 1.96 for p in SHEET}
    base = {p: plant_value(plant, p) for p in SHEET if p not in ("pot_gain", "gauge_gain")}
    c0 = combos(base)
    var = dict.fromkeys(COMBOS, 0.0)
    for p in base:
        if base[p] <= 0:
            continue
        c1 = combos({**base, p: base[p] * math.exp(1e-4)})
        for k in COMBOS:
            var[k] += (math.log(c1[k] / c0[k]) / 1e-4 * sd[p]) ** 2
    out = {k: math.sqrt(v) for k, v in var.items()}
    out |= {"plant.Ks": sd["Ks"], "plant.zeta_link": sd["zeta_link"]}
    return out | {s: sd[d] for s, d in SENSORS.items()}


SHEET = ("Kg", "kt", "km", "Rm", "eta_g", "eta_m", "Jeq", "Beq", "m_link", "L_link", "m_tip", "Ks", "zeta_link",
         "pot_gain", "gauge_gain")  # fmt: skip


def physical(over: Mapping[str, Any], plant: Mapping[str, Any]) -> dict[str, Any]:
    """Overrides ``over`` ({"rig.drive_gain": ..., "plant.Ks": ...}) with the plant parameters their combos imply on
    ``plant`` (the sheet) added as "plant.kt", "plant.km", "plant.Beq", "plant.Jeq"."""
    drive = {k: float(v) for k, v in over.items() if k in COMBOS}
    return {**over, **{f"plant.{k}": v for k, v in to_plant(drive, plant).items()}} if drive else dict(over)
