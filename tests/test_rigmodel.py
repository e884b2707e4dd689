"""The rig's identifiable linear parameters (harness.diagnosis.rigmodel) against the analytic model of the plant
(harness.fmu.plant: beam integrals by quadrature, its own mass matrix), and the spec's uncertainty behind their
priors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harness import spec as specmod
from harness.diagnosis.rigmodel import COMBOS, combos, prior_sd, to_plant
from harness.fmu.plant import PlantParams, state_space


def _slow_pole_and_speed_gain(plant: dict[str, float]) -> tuple[float, float]:
    """The analytic rig's slowest non-zero pole [1/s] and its steady hub speed per volt [rad/(V s)]."""
    A, B, C, _ = state_space(PlantParams(**plant))
    lam = np.linalg.eigvals(A)
    slow = min((x for x in lam if abs(x) > 1e-9 and abs(x.imag) < 1e-9), key=abs).real
    n = A.shape[0] // 2
    # steady speed: every acceleration and the link's rates zero, theta free: solve A x + B u = 0 without theta
    keep = [i for i in range(A.shape[0]) if i != 0]
    x = np.linalg.lstsq(A[np.ix_(keep, keep)], -B[keep, 0], rcond=None)[0]
    return slow, float(x[n - 1])


@pytest.mark.parametrize("spec", ["nominal", "cu_flexible_arm"])
def test_combos_are_the_analytic_rigs_time_constant_and_speed_gain(spec):
    """K is the steady hub speed per volt; tau the time constant of the rig with a rigid link (the analytic rig with
    a link of 1000 N m/rad: the flexible one's slow pole moves with the link, 24 % on the CU arm's 1.8 Hz)."""
    plant = dict(specmod.load(spec).plant)
    c = combos(plant)
    _, gain = _slow_pole_and_speed_gain(plant)
    assert gain == pytest.approx(c["rig.drive_gain"], rel=1e-9)
    slow, _ = _slow_pole_and_speed_gain({**plant, "Ks": 1000.0})
    assert -1.0 / slow == pytest.approx(c["rig.drive_tau"], rel=1e-3)


def test_to_plant_gives_the_combos_it_was_asked_for():
    sheet = specmod.load("cu_flexible_arm").plant
    for factors in [(1.0, 1.0, 1.0), (3.0, 0.4, 2.0), (0.33, 3.0, 0.5), (2.0, 1.0, 1.0)]:
        want = {p: combos(sheet)[p] * f for p, f in zip(COMBOS, factors, strict=True)}
        got = combos({**sheet, **to_plant(want, sheet)})
        for p in COMBOS:
            assert got[p] == pytest.approx(want[p], rel=1e-12)
    # on a rig whose km is the sheet's, the map is one to one with kt, Beq and Jeq
    truth = {**sheet, "kt": 0.02, "Beq": 0.01, "Jeq": 0.004}
    back = to_plant(combos(truth), sheet)
    assert back == pytest.approx({"kt": 0.02, "km": sheet["km"], "Beq": 0.01, "Jeq": 0.004}, rel=1e-12)


def test_priors_follow_the_sheet_kind():
    lab = specmod.load("cu_flexible_arm")  # [uncertainty] sheet = "lab": a factor 2, damping 3, masses 10 %
    sheet = specmod.load("cu_flexible_arm", ['uncertainty.sheet="datasheet"'])
    sd_lab, sd_sheet = prior_sd(lab.plant, lab.factor), prior_sd(sheet.plant, sheet.factor)
    assert sd_lab["plant.Ks"] == pytest.approx(math.log(2.0) / 1.96)
    assert sd_sheet["plant.Ks"] == pytest.approx(math.log(1.2) / 1.96)
    assert sd_lab["plant.zeta_link"] == sd_sheet["plant.zeta_link"] == pytest.approx(math.log(10.0) / 1.96)
    for p in COMBOS:
        assert sd_lab[p] > 3 * sd_sheet[p]
    # a parameter's own uncertainty wins over its sheet's
    own = specmod.load("cu_flexible_arm", ['uncertainty.Ks="5 %"'])
    assert prior_sd(own.plant, own.factor)["plant.Ks"] == pytest.approx(math.log(1.05) / 1.96)


@pytest.mark.parametrize(
    ("value", "said"),
    [
        ("2", "give a factor"),
        ('"x0.5"', "give a factor"),
        ('"ten %"', "give a factor"),
        ('"-3 %"', "give a factor"),
    ],
)
def test_a_malformed_uncertainty_is_one_line(value, said):
    with pytest.raises(specmod.SpecError, match=said) as e:
        specmod.load("nominal", [f"uncertainty.Ks={value}"])
    assert "\n" not in str(e.value)
    with pytest.raises(specmod.SpecError, match="unknown key"):
        specmod.load("nominal", ['uncertainty.Kss="x2"'])
    with pytest.raises(specmod.SpecError, match="sheet = 'napkin' unknown"):
        specmod.load("nominal", ['uncertainty.sheet="napkin"'])
