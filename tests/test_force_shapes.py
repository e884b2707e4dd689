"""The missing force's classifier (harness.likelihood.force.classify): twins run through the plant and DAQ FMUs with
one effect switched on that the model lacks (the rig's linear parameters given true, as in
tests/test_likelihood.py), each named by its shape with its size against the FMU parameter that made it; twins
without any effect, open and closed loop, ideal and through 10- and 12-bit ADCs, named none; a hub that never rests
said to be one. Commands are random-phase multisines drawn from each test's seeds (not tuned on one)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from harness.diagnosis import rigmodel
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.fmu.modeldesc import bundled_model
from harness.fmu.plant import PlantParams, motor_constants
from harness.likelihood.force import SHAPES, ForcePicture, MissingForce, classify, force_picture
from harness.likelihood.record import Record
from harness.rig.controller import Controller

DAQ = bundled_model("daq").parameters()
KP, KE = DAQ["pot_gain"].start, DAQ["gauge_gain"].start  # deg/V: the readings' calibration
PLANT = {"n_modes": 2}  # the textbook rig with its second mode: the link rings on the hub's torque
NOISE_V = 0.002  # V rms on both channels
TS = 2e-3
DRIVE, _ = motor_constants(PlantParams(**PLANT))  # N m/V


def _multisine(seed: int, peak: float, seconds: float) -> np.ndarray:
    """A command [V] of peak ``peak``: sines at 0.4-4 Hz in steps of 0.4 Hz, amplitudes falling as 1/f (the hub's
    travel stays on the pot's track), phases drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    t = np.arange(round(seconds / TS)) * TS
    u = sum(np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) / f for f in np.arange(0.4, 4.01, 0.4))
    return peak * u / np.abs(u).max()


def _readings(out: dict[str, np.ndarray]) -> np.ndarray:
    th = (out["theta_v"] - DAQ["pot_offset"].start) * KP
    al = (out["alpha_v"] - DAQ["gauge_offset"].start) * KE
    return np.column_stack([th, al])


def _picture(u: np.ndarray, plant: dict | None = None, seed: int = 1, bits: int = 0, encoder: bool = False,
             closed: bool = False) -> ForcePicture:  # fmt: skip
    """The force picture of a twin: the command ``u`` (closed loop: the reference [rad] of the closed_loop spec's
    state feedback, its logged command the record's) through the FMUs with the ``plant`` effect, 2 mV of noise, an
    ADC of ``bits`` over +-10 V (0: none), the hub read by a 4096-count encoder if ``encoder``; the model the rig's
    true linear parameters and reading noise."""
    daq = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "seed": seed, "adc_bits": bits,
           "theta_sensor": int(encoder)}  # fmt: skip
    fmus = build_all()
    if closed:
        ctrl = Controller(K=[9.231, -18.769, 1.203, -0.041], cutoff=15.0).fmu_parameters(1 / TS)
        with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as rig:
            out = rig.run_closed(u, TS, ctrl, plant={**PLANT, **(plant or {})}, daq=daq)
    else:
        with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
            out = rig.run(u, TS, plant={**PLANT, **(plant or {})}, daq=daq)
    y = _readings(out)
    lsb = 20.0 / 2**bits if bits else 0.0
    lattice = (360.0 / 4096 if encoder else lsb * KP, lsb * abs(KE))
    rec = Record("twin", TS, out["u"], y, np.ones((u.size, 2), bool), lattice)
    values = rigmodel.combos(PLANT) | {
        "plant.Ks": rigmodel.plant_value(PLANT, "Ks"),
        "plant.zeta_link": rigmodel.plant_value(PLANT, "zeta_link"),
        "sensor.theta_gain": 1.0,
        "sensor.alpha_gauge_gain": 1.0,
        "noise.theta": max(NOISE_V * KP, 0.1 * lattice[0]),
        "noise.alpha": NOISE_V * abs(KE),
    }
    return force_picture(PLANT, values, [rec])


@pytest.mark.parametrize("coulomb", [0.01, 0.03])
@pytest.mark.parametrize("seed", [21, 22])
def test_friction_is_named_with_its_coulomb_level(coulomb, seed):
    """Coulomb friction of 0.01 or 0.03 N m under a +-1 V multisine (6 s): named friction, its level within 20 % of
    the FMU's (measured within 1.3 % on seeds 3 and 20-22), the same both ways, its dead band the level over the
    drive's torque per volt; the hub passes through rest (samples near zero speed). On ten blind draws of
    0.008-0.04 N m (seeds 30-39) all named friction, within 1.0 %."""
    named = classify(_picture(_multisine(seed, 1.0, 6.0), {"coulomb_torque": coulomb}, seed=seed))
    assert named.shape == "friction", named
    assert named.unit == "N m" and named.size == pytest.approx(coulomb, rel=0.2)
    assert named.levels == (named.size, named.size)
    assert named.dead_band_v == pytest.approx(coulomb / DRIVE, rel=0.2)
    assert named.samples_near_zero > 0


@pytest.mark.parametrize(("limit", "peak", "seed"), [(1.0, 1.5, 23), (0.7, 1.2, 24)])
def test_an_amplifier_limit_is_named_with_its_level_in_volts(limit, peak, seed):
    """The amplifier saturating at ``limit`` V under a multisine of peak ``peak`` V (6 s): named limit, its level in
    volts within 20 % (measured 1.002 and 0.702 V here; within 1 % on seeds 4 and 20-22 at 1.0 V; within 5.5 % on
    ten blind draws of 0.6-1.2 V, seeds 30-39)."""
    named = classify(_picture(_multisine(seed, peak, 6.0), {"amp_limit": limit}, seed=seed))
    assert named.shape == "limit", named
    assert named.unit == "V" and named.size == pytest.approx(limit, rel=0.2)


@pytest.mark.parametrize(("offset", "seed"), [(0.1, 25), (-0.05, 26)])
def test_a_command_offset_is_named_with_its_size_in_volts(offset, seed):
    """The amplifier's input offset ``u_offset`` under a +-1 V multisine (6 s): a constant force of drive times the
    offset, named offset with its signed size in volts within 20 % (measured within 0.01 %, here and on ten blind
    draws of +-0.03-0.15 V, seeds 30-39)."""
    named = classify(_picture(_multisine(seed, 1.0, 6.0), {"u_offset": offset}, seed=seed))
    assert named.shape == "offset", named
    assert named.unit == "V" and named.size == pytest.approx(offset, rel=0.2)


def _random_square(seed: int, n: int) -> np.ndarray:
    """A +-0.8 V square switching at random (the link rings after every switch)."""
    rng = np.random.default_rng(seed)
    return 0.8 * np.where(np.cumsum(rng.random(n) < 0.015) % 2 == 0, 1.0, -1.0)


def _square_reference(n: int) -> np.ndarray:
    t = np.arange(n) * TS
    return np.radians(np.where(t % 2.0 < 1.0, 20.0, -20.0))


@pytest.mark.parametrize(
    ("kind", "bits"),
    [("multisine", 0), ("multisine", 10), ("multisine", 12), ("square", 10), ("closed", 10), ("closed", 12)],
)
def test_friction_free_twins_are_named_none(kind, bits):
    """Ten friction-free twins (seeds 1-10, 4-5 s) per kind: open loop under a multisine, ideal and through 10- and
    12-bit ADCs; open loop under a random square (the link ringing after every switch) through 10 bits; closed loop
    (the closed_loop spec's state feedback on a +-20 deg square reference) through 10 and 12 bits. At least 9 of 10
    are named none (measured 10 of 10 in every group; the largest column 2.6 standard errors out, against a level of
    5; before the random walk's own likelihood gain gated the varying shapes, 3 closed-loop 12-bit twins showed a
    limit column 5-15 standard errors out on either side). Through an 8-bit ADC (not asserted: issue 63's open
    lattice case) 5 of 10 closed-loop twins are named friction of 1.4-1.6e-4 N m."""
    named = []
    for seed in range(1, 11):
        if kind == "multisine":
            pic = _picture(_multisine(100 + seed, 1.0, 4.0), seed=seed, bits=bits)
        elif kind == "square":
            pic = _picture(_random_square(seed, 2500), seed=seed, bits=bits)
        else:
            pic = _picture(_square_reference(2500), seed=seed, bits=bits, closed=True)
        named.append(classify(pic).shape)
    assert named.count("none") >= 9, named


@pytest.mark.parametrize("effect", [{"coulomb_torque": 0.01}, {"u_offset": 0.1}], ids=["friction", "offset"])
def test_a_hub_that_never_rests_says_so(effect):
    """A hub turning one way throughout (started at 1.2 rad/s, a command of 0.5 +- 0.15 V, 5 s read by an encoder):
    friction then is a constant force, as an offset is; neither is named, the classifier says the records hold too
    few samples at rest (none near zero speed)."""
    t = np.arange(2500) * TS
    u = 0.5 + 0.15 * np.sin(2 * np.pi * 1.5 * t)
    named = classify(_picture(u, {**effect, "theta_dot_start": 1.2}, encoder=True))
    assert named.shape == "too_few_at_rest", named
    assert named.samples_near_zero == 0 and named.size == 0.0


def test_friction_unequal_on_the_two_sides_is_named_asymmetric():
    """The plant FMU's friction is symmetric (one coulomb_torque, fmus/flexjoint/model.c), so the shape is built
    from a friction twin's own picture: 0.03 N m both ways, 0.015 N m taken off the force while the hub turns
    forward (the smoother's ringing and noise kept). Named asymmetric friction with its two levels (0.015 forward,
    0.03 backward) within 20 % and its size their mean; the picture as the twin drew it is named friction."""
    pic = _picture(_multisine(27, 1.0, 6.0), {"coulomb_torque": 0.03}, seed=27)
    assert classify(pic).shape == "friction"
    tr = pic.traces[0]
    forward = tr.speed > 3.0 * tr.speed_sd
    bent = replace(pic, traces=(replace(tr, force=tr.force + np.where(forward, 0.015, 0.0)),))
    named = classify(bent)
    assert named.shape == "asymmetric_friction", named
    assert named.levels[0] == pytest.approx(0.015, rel=0.2) and named.levels[1] == pytest.approx(0.03, rel=0.2)
    assert named.size == pytest.approx(0.0225, rel=0.2) and named.unit == "N m"
    assert named.dead_band_v == pytest.approx(named.size / DRIVE, rel=1e-12)


def test_the_missing_forces_json_keeps_the_issues_keys():
    """likelihood.json's missing_force holds the five keys issue 63 names, whatever the shape, and friction's levels
    each way and where its size comes from; the shapes are the documented ones."""
    keys = {"shape", "size", "unit", "dead_band_v", "samples_near_zero", "levels", "sized_by", "picture_size"}
    assert set(MissingForce("limit", 1.0, "V", 0.0, 3).to_json()) == keys
    assert set(MissingForce("asymmetric_friction", 0.02, "N m", 0.16, 3, (0.01, 0.03)).to_json()) == keys
    assert set(SHAPES) == {"friction", "asymmetric_friction", "limit", "offset", "too_few_at_rest", "none"}
