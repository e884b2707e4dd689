"""The blind family ``real_like``: units of a lab's arm logged as real records are, with what such records show.

A unit is the CU arm's sheet (``specs/cu_flexible_arm.toml``) with its linear parameters drawn off it as a real rig's
are (:data:`harness.diagnosis.blindtest.NUISANCE`) and its link's damping drawn over 0.002-0.05, one library effect or
none, and the nuisances real records carry: an amplifier input offset (``plant.u_offset``, to 0.2 V: a holding force
that depends on the direction beside friction), each record's gauge reading its own zero error (to 5 deg, which the
lab's controller acts on: it believes its gauge reads 0 at rest), and a link still ringing when each record starts.
Two records per unit, as a lab logs them: P only on a small reference, then P with tip feedback on a larger one, 8 s
each at 1 kHz, written as CSV files of the sensors' volts and imported with ``--zero-alpha`` as the lab would. Every
other unit is simulated by the independent simulator (``tests/indeprig.py``: its own beam with the tip mass, its own
friction, play, DAQ and lab controller) instead of our FMUs.

Scored as the other families (top-1, magnitude, ``none``), and on the offsets: every record's gauge offset within
OFFSET_TOL_DEG of the truth in the record's own zero (its raw zero error less what the import's zeroing took), and
the command offset within OFFSET_TOL_V.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pandas as pd

from .. import spec as specmod
from ..rig.campaign import run_campaign
from ..rig.records import ImportOptions, import_records
from ..rundir import Manifest
from .effects import EFFECTS
from .simulation import fmu_value, offset_key

__all__ = ["NUISANCE", "OFFSET_TOL_DEG", "OFFSET_TOL_V", "RECORDS", "make_unit", "offsets_ok", "plan_units"]

# linear parameter -> (low factor, high factor, log-uniform) of the textbook value: a real rig's spread
NUISANCE: dict[str, tuple[float, float, bool]] = {
    "plant.Ks": (0.75, 1.25, False),
    "plant.Beq": (0.5, 2.0, True),
    "plant.zeta_link": (0.5, 3.0, True),
    "plant.Jeq": (0.85, 1.15, False),
    "plant.kt": (0.9, 1.1, False),  # the motor gain kt eta_g eta_m
}
SHEET = "cu_flexible_arm"
RECORDS = (  # name, controller, reference amplitude [deg]
    ("p_only", {"kind": "pid", "kp": 6.0, "cutoff": 25.0}, 5.7),
    ("p_tip", {"kind": "state_feedback", "K": [6.0, 2.0, 0.0, 0.0], "cutoff": 25.0}, 17.19),
)
DURATION_S, RATE_HZ, SQUARE_HZ = 8.0, 1000.0, 0.25  # each record: 8 s at 1 kHz, a square reference of 0.25 Hz
GAUGE_OFFSET_DEG = 5.0  # each record's gauge zero error, uniform in +-this
RING_DEG = (0.3, 1.5)  # the link's ring at each record's start, amplitude [deg], uniform; its phase uniform
U_OFFSET_V = 0.2  # the amplifier's input offset, uniform in +-this
ZETA = (0.002, 0.05)  # the link's damping ratio, log-uniform
NOISE_V = 0.002  # the sensors' noise [V rms]
OFFSET_TOL_DEG, OFFSET_TOL_V = 0.1, 0.02  # offsets within these of the truth


def _textbook(param: str) -> float:
    table, name = param.split(".", 1)
    return fmu_value(specmod.load(SHEET).plant, "flexjoint", name)


def plan_units(n: int, seed: int) -> list[dict[str, Any]]:
    """``n`` units: every other one with one in-library effect (cycling through the library from a random start,
    drawn as the other families draw them), the rest none, shuffled; each with its nuisance (:data:`NUISANCE` factors
    on the sheet's values, the link's damping, the command offset), each record's gauge offset and ring, and its
    simulator (our twin, or the independent one for every other unit)."""
    rng = np.random.Generator(np.random.PCG64([seed, 2]))  # a stream of its own: the other families' draws unchanged
    lib = list(EFFECTS)
    first = int(rng.integers(len(lib)))
    kinds = [("single", lib[(first + i // 2) % len(lib)]) if i % 2 == 0 else ("none", None) for i in range(n)]
    cases = []
    for i, j in enumerate(rng.permutation(n)):
        kind, what = kinds[int(j)]
        truth = {EFFECTS[what].param: EFFECTS[what].draw_blind(rng)} if what else {}
        nuisance = {}
        for p, (lo, hi, log) in NUISANCE.items():
            if p == "plant.zeta_link":
                continue
            f = math.exp(rng.uniform(math.log(lo), math.log(hi))) if log else rng.uniform(lo, hi)
            nuisance[p] = _textbook(p) * float(f)
        nuisance["plant.zeta_link"] = float(math.exp(rng.uniform(*np.log(ZETA))))
        nuisance["plant.u_offset"] = float(rng.uniform(-U_OFFSET_V, U_OFFSET_V))
        records = [
            {
                "name": name,
                "gauge_deg": float(rng.uniform(-GAUGE_OFFSET_DEG, GAUGE_OFFSET_DEG)),
                "ring_deg": float(rng.uniform(*RING_DEG)),
                "ring_phase": float(rng.uniform(0.0, 2.0 * math.pi)),
            }
            for name, _, _ in RECORDS
        ]
        cases.append(
            {
                "family": "real_like",
                "kind": kind,
                "truth_effects": [what] if what else [],
                "truth_params": truth,
                "nuisance": nuisance,
                "sensor": {},
                "unit": {"simulator": "independent" if i % 2 else "twin", "records": records},
                "campaign_seed": int(rng.integers(1, 2**31 - 1)),
            }
        )
    return cases


def _ring_state(case: dict[str, Any], rec: dict[str, Any], ks: float) -> tuple[float, float]:
    """The link's deflection [rad] and rate [rad/s] at a record's start: its ring's amplitude and phase at the
    link's clamped frequency with the tip mass."""
    sheet = specmod.load(SHEET).plant
    jl = sheet["m_link"] * sheet["L_link"] ** 2 / 3.0 + sheet["m_tip"] * sheet["L_link"] ** 2
    w = math.sqrt(ks / jl)
    a, ph = math.radians(rec["ring_deg"]), rec["ring_phase"]
    return a * math.cos(ph), -a * w * math.sin(ph)


def _twin_record(case: dict[str, Any], rec: dict[str, Any], spec_rec: tuple, tmp: Path, fmus: Any) -> pd.DataFrame:
    name, controller, amplitude = spec_rec
    raw = specmod.load(SHEET).raw
    plant = {k.split(".", 1)[1]: v for k, v in {**case["nuisance"], **case["truth_params"]}.items()
             if k.startswith("plant.")}  # fmt: skip
    daq = {k.split(".", 1)[1]: v for k, v in case["truth_params"].items() if k.startswith("daq.")}
    if "coulomb_torque" in plant:
        plant |= {"stiction_ratio": 1.3, "stribeck_speed": 0.02}  # a breakaway and a Stribeck drop: a dead band
    gg = fmu_value({}, "daq", "gauge_gain")
    alpha0, rate0 = _ring_state(case, rec, float(plant.get("Ks", raw["plant"]["Ks"])))
    raw["campaign"] = {**raw["campaign"], "seed": int(case["campaign_seed"]) % 100_000 + len(rec["name"])}
    raw["plant"] = {**raw["plant"], **plant}
    raw["daq"] = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "gauge_offset": rec["gauge_deg"] / gg, **daq}
    raw["controller"] = {**controller, "alpha_bias": rec["gauge_deg"]}  # the lab believes its gauge reads 0 at rest
    start = {"theta_start": math.radians(amplitude), "alpha_start": alpha0, "alpha_dot_start": rate0}
    raw["experiment"] = [{"name": name, "loop": "closed", "signal": "square", "f": SQUARE_HZ, "amplitude": amplitude,
                          "duration": DURATION_S, "plant": start}]  # fmt: skip
    raw["campaign"]["sample_rate"] = RATE_HZ
    spec = specmod.from_dict(raw, str(specmod.resolve_path(SHEET)))
    run_campaign(spec, tmp / name, fmus=fmus, workers=1)
    return pd.read_parquet(tmp / name / "data" / f"{name}.parquet")


def _independent_record(ind: ModuleType, case: dict[str, Any], rec: dict[str, Any], spec_rec: tuple) -> pd.DataFrame:
    name, controller, amplitude = spec_rec
    sheet = specmod.load(SHEET).plant
    params = {**case["nuisance"], **case["truth_params"]}
    kw: dict[str, Any] = {k: sheet[k] for k in ("Kg", "kt", "km", "Rm", "eta_g", "eta_m", "Jeq", "m_link", "L_link",
                                                "m_tip")}  # fmt: skip
    kw |= {k.split(".", 1)[1]: v for k, v in params.items() if k not in ("plant.Ks", "plant.kt")}
    if "plant.kt" in params:
        kw["motor_gain"] = params["plant.kt"] / sheet["kt"]
    gg = ind.IndepRig.gauge_Ke
    kw |= {"gauge_offset": rec["gauge_deg"] / gg, "noise_theta": NOISE_V, "noise_alpha": NOISE_V}
    rig = ind.IndepRig.from_Ks(float(params.get("plant.Ks", sheet["Ks"])), **kw)
    n = int(round(DURATION_S * RATE_HZ))
    t = np.arange(n) / RATE_HZ
    ref = amplitude * np.where(np.floor(2.0 * SQUARE_HZ * t) % 2 == 0, 1.0, -1.0)
    alpha0, rate0 = _ring_state(case, rec, float(params.get("plant.Ks", sheet["Ks"])))
    believed = (rig.pot_gain, rig.pot_offset, rig.gauge_Ke, 0.0)  # the lab believes its gauge reads 0 at rest
    seed = int(case["campaign_seed"]) + len(rec["name"])
    res = ind.simulate_closed(rig, np.radians(ref), 1.0 / RATE_HZ, controller, seed, start=(
        math.radians(amplitude), alpha0, 0.0, rate0), calibration=believed)  # fmt: skip
    return pd.DataFrame({k: res[k] for k in ("t", "theta_v", "alpha_v", "ref", "u")})


def make_unit(case: dict[str, Any], dest: Path, ind: ModuleType | None, fmus: Any = None) -> Path:
    """A unit's records simulated (our twin, or ``ind``: the independent simulator), written as a lab's CSV files of
    volts, reference [deg] and command [V], and imported into ``dest`` with ``--zero-alpha``."""
    with tempfile.TemporaryDirectory(prefix="flexjoint-unit-") as tmp_s:
        tmp = Path(tmp_s)
        files = []
        for rec, spec_rec in zip(case["unit"]["records"], RECORDS, strict=True):
            if case["unit"]["simulator"] == "independent":
                if ind is None:
                    raise ValueError("the real_like family's independent units need tests/indeprig.py")
                d = _independent_record(ind, case, rec, spec_rec)
            else:
                d = _twin_record(case, rec, spec_rec, tmp, fmus)
            path = tmp / f"{spec_rec[0]}.csv"
            cols = d[["t", "theta_v", "alpha_v", "ref", "u"]].rename(columns={"theta_v": "theta", "alpha_v": "alpha"})
            cols.to_csv(path, index=False)
            files.append(path)
        opts = ImportOptions(units={"theta": "V", "alpha": "V", "ref": "deg"}, zero_alpha=True)
        import_records(files, dest, opts)
    return dest


def offsets_ok(case: dict[str, Any], run: Path, final: dict[str, float]) -> dict[str, Any]:
    """The unit's offsets against the truth: each record's gauge offset in its own zero (its zero error less what
    the import's zeroing took: the controller's ``alpha_bias`` in the manifest) and the command offset; each error
    and whether all are within OFFSET_TOL_DEG and OFFSET_TOL_V."""
    entries = {e.name: e for e in Manifest.load(run).experiments}
    errors: dict[str, float] = {}
    for rec in case["unit"]["records"]:
        zero = float((entries[rec["name"]].controller or {}).get("alpha_bias", 0.0))
        fitted = final.get(offset_key(rec["name"]))
        errors[rec["name"]] = math.inf if fitted is None else abs(float(fitted) - (rec["gauge_deg"] - zero))
    u_err = abs(float(final.get("plant.u_offset", 0.0)) - case["nuisance"]["plant.u_offset"])
    ok = all(e <= OFFSET_TOL_DEG for e in errors.values()) and u_err <= OFFSET_TOL_V
    return {"gauge_offset_errors_deg": errors, "u_offset_error_v": u_err, "offsets_ok": bool(ok)}
