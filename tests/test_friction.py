"""Friction at small commands: a P-only loop stops short of its reference; the twin's breakaway and Stribeck drop,
and the diagnoser fitting them (coulomb_friction frees plant.stiction_ratio and plant.stribeck_speed)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from harness import spec as specmod
from harness.diagnosis.diagnose import diagnose_run
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.rig.campaign import run_campaign
from harness.rig.controller import Controller

sys.path.insert(0, str(Path(__file__).parent))
import indeprig as ind  # noqa: E402

K1 = 7.778  # V/rad: the CU lab's gain on the hub angle
FRICTION = {"coulomb_torque": 0.09, "stiction_ratio": 1.3, "stribeck_speed": 0.02}  # stops ~3 deg short at K1
SQUARES = [("sq_a", 0.2, 5.7, 6.0), ("sq_b", 0.125, 5.7, 8.0), ("sq_c", 0.25, 11.4, 6.0), ("sq_d", 0.3, 8.0, 6.0)]
COMB = {"name": "comb", "signal": "comb", "deflections_cm": [-3.7, -2.4, -1.1, 0.0, 1.4, 2.65, 3.9, 5.2],
        "D_cm": 40.0, "hold": 2.5, "ramp": 0.8, "duration": 27.0}  # fmt: skip


def _p_only(base: str, kp: float, plant: dict[str, float] | None = None) -> specmod.Spec:
    """The bundled spec ``base``'s rig under P-only control (PID kind, ki = kd = 0) at 500 Hz with 2 mV of noise on
    both channels: a comb calibration and four closed-loop square references of 5.7-11.4 deg."""
    raw = specmod.load(base).raw
    raw["campaign"] = {**raw["campaign"], "sample_rate": 500.0, "seed": 3}
    raw["plant"] = {**raw["plant"], **(plant or {})}
    raw["daq"] = {**raw.get("daq", {}), "noise_theta": 0.002, "noise_alpha": 0.002}
    raw["controller"] = {"kind": "pid", "kp": kp, "cutoff": 25.0}
    raw["calibration"] = [COMB]
    square = {"loop": "closed", "signal": "square"}
    raw["experiment"] = [{**square, "name": n, "f": f, "amplitude": a, "duration": d} for n, f, a, d in SQUARES]
    return specmod.from_dict(raw, str(specmod.resolve_path(base)))


def _cu_loop(kp: float, ki: float, plant: dict[str, float]) -> dict[str, np.ndarray]:
    """The CU arm at 1 kHz, noise-free, tracking +-5.7 deg (period 10 s, 20 s) under a PI(D) on theta."""
    cu = specmod.load("cu_flexible_arm").plant
    Ts = 1e-3
    t = np.arange(20000) * Ts
    ref = np.radians(np.where(t % 10 < 5, 5.7, -5.7))
    ctrl = Controller(kind="pid", kp=kp, ki=ki, cutoff=25.0).fmu_parameters(1 / Ts)
    ctrl.pop("alpha_bias", None)
    fmus = build_all()
    with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as rig:
        return rig.run_closed(ref, Ts, ctrl, plant={**cu, **plant})


def test_a_p_only_loop_stops_short_and_stays_put_while_a_pi_loop_hunts():
    """The CU arm under its lab's K1 alone, hub friction 0.09 N m with breakaway 1.3x and a Stribeck drop: each
    11.4 deg step stops 2.5-3.1 deg short (measured 3.05, 2.61, 2.47; the CU record's 3.3; Fs / (G K1) = 5.5 deg is
    the band it may stop in; 0.095 N m never leaves its start) and, after its last slip within 0.5 s, stays stuck to
    the next step: a P loop on a passive plant is a spring to the
    reference, friction only takes energy, so no friction law makes it hunt. With integral action (ki 5 V/(rad s))
    the stuck error winds the command up until the hub breaks away again: it hunts."""
    p = _cu_loop(K1, 0.0, FRICTION)
    for k in (5000, 10000, 15000):  # the half periods after the first (11.4 deg steps)
        seg = slice(k, k + 5000)
        short = np.sign(p["ref"][k]) * (p["ref"][k + 4999] - p["theta"][k + 4999])
        assert 2.3 < short < 3.2, short  # deg
        assert np.all(p["theta_dot"][seg][600:] == 0.0)  # stuck from 0.6 s after the step on
    pi = _cu_loop(K1, 5.0, FRICTION)
    late = pi["theta_dot"][12500:15000]  # 2.5-5 s after a step
    assert np.any(late != 0.0) and np.any(late == 0.0)  # sticks, and breaks away again


@pytest.mark.open(
    reason=(
        "issue 34 open: since a fold refitted from the other's keeps its link starts, the breakaway comes out 1.13 "
        "for 1.3 (the torque still within 10 %)"
    ),
)
def test_the_diagnoser_fits_breakaway_and_stribeck_drop_on_a_p_only_twin(tmp_path):
    """The twin (CU arm, P-only at K1, 2 mV noise) with the friction that stops it ~3 deg short, diagnosed against
    the same spec without friction: coulomb_friction, its torque within 10 % (measured +0.4 %), the breakaway and
    the Stribeck speed freed with it within 10 % and 25 % (1.302, 0.0202 rad/s), the held-out gap left 1.95x the
    noise floor. Without them: torque +2.8 %, the viscous damping at its lower bound (-80 %) in their place, 3.0x."""
    sim = _p_only("cu_flexible_arm", K1)
    real = _p_only("cu_flexible_arm", K1, FRICTION)
    run_campaign(real, tmp_path / "real", workers=1)
    d = diagnose_run(tmp_path / "real", sim, tmp_path / "diag", workers=1)
    assert d.verdict == "coulomb_friction"
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.09, rel=0.10)
    assert d.parameters["plant.stiction_ratio"].fitted == pytest.approx(1.3, rel=0.10)
    assert d.parameters["plant.stribeck_speed"].fitted == pytest.approx(0.02, rel=0.25)
    assert abs(d.parameters["plant.Beq"].change_pct) < 30.0
    dec = d.gap.decomposition
    assert dec.after_effects < 2.5 * dec.noise_floor


def test_the_diagnoser_fits_breakaway_and_stribeck_drop_on_an_independent_rig(tmp_path):
    """The independent simulator's textbook rig (its own Stribeck law on a smooth sign, Fc 0.044 N m, breakaway 2x,
    0.02 rad/s) under P-only control (kp 8 V/rad, the steps stop 0.5-1.8 deg short), diagnosed against the twin
    without friction: coulomb_friction within 10 % (measured -0.7 %), the breakaway within 10 % (2.02), the
    Stribeck speed 0.016 rad/s, Jeq and the link damping left at the spec, and the held-out gap 1.36x the noise
    floor. Without the breakaway and the drop: torque +9 %, Jeq +8.6 %, 6.0x the floor."""
    sim = _p_only("blind_closed", 8.0)
    rig = ind.IndepRig(coulomb_torque=0.044, stribeck_ratio=2.0, stribeck_velocity=0.02)
    ind.make_run(tmp_path / "real", sim, rig, seed=7)
    d = diagnose_run(tmp_path / "real", sim, tmp_path / "diag", workers=1)
    assert d.verdict == "coulomb_friction"
    assert d.fitted_effect_params()["plant.coulomb_torque"] == pytest.approx(0.044, rel=0.10)
    assert d.parameters["plant.stiction_ratio"].fitted == pytest.approx(2.0, rel=0.10)
    assert 0.01 < d.parameters["plant.stribeck_speed"].fitted < 0.04
    for prm in ("plant.Jeq", "plant.zeta_link"):
        assert abs(d.parameters[prm].change_pct) < 5.0, prm
    dec = d.gap.decomposition
    assert dec.after_effects < 2.0 * dec.noise_floor
