"""One unit's records under two controllers (P only on a small reference, P + tip feedback on a large one) from a
CU arm whose drive is off the sheet by 2x, with an effect, imported as a lab logs them and diagnosed against the
sheet: the linear model alone fits them worse than the sheet, so the effect is found only by refitting it jointly
with the linear parameters, and one record may hardly touch it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from harness import spec as specmod
from harness.diagnosis.diagnose import diagnose_run
from harness.diagnosis.result import Diagnosis
from harness.diagnosis.search import MIN_CLOSURE
from harness.rig.campaign import run_campaign
from harness.rig.records import ImportOptions, import_records

WRONG_DRIVE = {"kt": 0.0214, "Jeq": 0.003, "Ks": 1.79584}  # kt x2, Jeq x1.5, Ks x0.8 of cu_flexible_arm
DRIVE_GAIN = 1.8847  # rad/(V s): the truth's, against the sheet's 1.841 (the drive's time constant 0.103 s: 0.54x)
RECORDS = [  # name, controller, reference amplitude [deg], seed
    ("p_only", {"kind": "pid", "kp": 6.0}, 5.7, 11),
    ("p_tip", {"kind": "state_feedback", "K": [6.0, 2.0, 0.0, 0.0]}, 17.19, 12),
]


def _record(tmp: Path, name: str, controller: dict[str, Any], amplitude: float, seed: int, plant: dict) -> Path:
    """One 10 s closed-loop record at 1 kHz with 2 mV of sensor noise, as a lab logs it: a CSV of the sensors'
    volts, the reference [deg] and the command [V]."""
    raw = specmod.load("cu_flexible_arm").raw
    raw["campaign"] = {**raw["campaign"], "seed": seed}
    raw["plant"] = {**raw["plant"], **WRONG_DRIVE, **plant}
    raw["daq"] = {"noise_theta": 0.002, "noise_alpha": 0.002}
    raw["controller"] = {**controller, "cutoff": 25.0}
    raw["experiment"] = [
        {"name": name, "loop": "closed", "signal": "square", "f": 0.1, "amplitude": amplitude, "duration": 10.0}
    ]
    run_campaign(specmod.from_dict(raw, str(specmod.resolve_path("cu_flexible_arm"))), tmp / name, workers=1)
    d = pd.read_parquet(tmp / name / "data" / f"{name}.parquet")
    path = tmp / f"{name}.csv"
    d[["t", "theta_v", "alpha_v", "ref", "u"]].rename(columns={"theta_v": "theta", "alpha_v": "alpha"}).to_csv(
        path, index=False
    )
    return path


def _diagnose_unit(tmp: Path, plant: dict[str, float]) -> Diagnosis:
    files = [_record(tmp, *r, plant) for r in RECORDS]
    import_records(files, tmp / "unit", ImportOptions(units={"theta": "V", "alpha": "V", "ref": "deg"}))
    return diagnose_run(tmp / "unit", "cu_flexible_arm", tmp / "diag", workers=2)


def _held_out_fits(d: Diagnosis) -> tuple[float, float]:
    """The held-out fit [%] recalibrated alone and with the effects."""
    dec = d.gap.decomposition
    return 100.0 * (1.0 - dec.after_recalibration), 100.0 * (1.0 - dec.after_effects)


def test_friction_beside_a_drive_off_by_twice_is_found_by_refitting_every_candidate_jointly(tmp_path):
    """Hub friction (0.03 N m, breakaway 1.3x, Stribeck 0.02 rad/s): the linear model alone fits 41.8 -> 22.4 %
    held out (each record pulls the drive its own way), and each effect alone on the sheet's rig closes nothing
    (screening <= 4 %), so none leads. With the gap left 73x the floor (beyond LOST_RATIO), every candidate is then
    refitted jointly with the linear parameters: friction closes the gap (98.7 %, floor 98.9 %), the drive gain and
    Ks within 0.2 % and 0.01 % of the truth, the torque within 0.5 % (0.0302). Before, nothing was refitted:
    unexplained at 41.8 %. Each record alone, with the friction held, fits the drive's time constant, the link
    damping and theta's gain 0.3-4.7 % apart, with intervals that exclude each other: under APART_MIN, no caveat
    calls that model error."""
    d = _diagnose_unit(tmp_path, {"coulomb_torque": 0.03, "stiction_ratio": 1.3, "stribeck_speed": 0.02})
    assert max(r["screen_score"] for r in d.rounds[0]) < 0.5 * MIN_CLOSURE  # nothing leads by its screening
    assert d.verdict == "coulomb_friction"
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.03, rel=0.05)
    assert d.parameters["rig.drive_gain"].fitted == pytest.approx(DRIVE_GAIN, rel=0.02)
    assert d.parameters["plant.Ks"].fitted == pytest.approx(1.79584, rel=0.01)
    recalibrated, with_effects = _held_out_fits(d)
    assert recalibrated < 50.0 and with_effects > 97.0
    assert not d.caveats


def test_a_limit_one_record_hardly_reaches_is_fitted_from_the_other_folds_start(tmp_path):
    """An amplifier limit of 1.0 V: the P-only record's command reaches -1.2 V, the other's -3.6 V. Fitted on the
    P-only record from the screening's 1.85 V, the limit stays there (no command reaches it: no gradient), and its
    held-out fit on the other record was 26 % (unexplained at 50.7 %). A fold whose refit left the limit where it
    started, while the other's ended more than FOLDS_APART away, is refitted from the other fold's parameters, the
    lower cost on its own record kept: the P-only fold's own fit is better at 1.0 V (98.45 against 98.12 %), so the
    limit is found (measured 98.8 % held out, floor 98.9 %)."""
    d = _diagnose_unit(tmp_path, {"amp_limit": 1.0})
    assert d.verdict == "saturation"
    assert d.fitted_effect_params()["plant.amp_limit"] == pytest.approx(1.0, rel=0.03)
    assert d.parameters["rig.drive_gain"].fitted == pytest.approx(DRIVE_GAIN, rel=0.03)
    recalibrated, with_effects = _held_out_fits(d)
    assert recalibrated < 50.0 and with_effects > 97.0


def test_two_effects_that_each_close_little_alone_are_refitted_together(tmp_path):
    """Friction (0.02 N m) and an amplifier limit (1.5 V) beside the drive off by 2x: refitted jointly, the limit
    alone closes 22 % and the friction 17 % of the gap (under MIN_CLOSURE), so neither entered (unexplained at
    47.4 %). With the linear model lost, the two best are refitted together: both found, within 0.1 % and 0.3 %
    (1.5003 V, 0.02005 N m), the drive gain within 0.2 %. The held-out fit reaches only 73.6 %: the P-only record's
    command never reaches 1.5 V, so its fold sets the limit where its own noise likes it (1.17 V), which the other
    record pays for."""
    d = _diagnose_unit(
        tmp_path, {"coulomb_torque": 0.02, "stiction_ratio": 1.3, "stribeck_speed": 0.02, "amp_limit": 1.5}
    )
    assert {e.effect for e in d.effects} == {"coulomb_friction", "saturation"}
    fitted = d.fitted_effect_params()
    assert fitted["plant.amp_limit"] == pytest.approx(1.5, rel=0.02)
    assert fitted["plant.coulomb_torque"] == pytest.approx(0.02, rel=0.05)
    assert d.parameters["rig.drive_gain"].fitted == pytest.approx(DRIVE_GAIN, rel=0.02)
    _, with_effects = _held_out_fits(d)
    assert with_effects > 70.0
