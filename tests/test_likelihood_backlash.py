"""The gear's play in the likelihood engine (``plant.backlash``): the filter's impact / dead-zone step
(``fmus/master/kalman.c``) and the draws' (``harness.likelihood.simulate``) against the plant FMU, which integrates
the same hybrid with its events located (the sides apart, a plastic impact where the play closes, one body in
contact), and the play recovered by maximum likelihood from twins through the FMUs, nested on the linear rig: the
null (no play) a wall, its LR there about none. Twins: 3 s at 500 Hz, a random +-0.8 V square (open loop) or the
labs' state feedback on a +-20 deg square (closed loop), 12-bit ADC, 2 mV of noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_likelihood import KE, KP, TS, _readings, _truth
from test_likelihood_effects import ONE, _fit, _random_square, _readings_of, _twin

from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.likelihood import simulate
from harness.likelihood.fit import run_filter
from harness.likelihood.kalman import kalman_filter
from harness.likelihood.model import Noise, rig_model
from harness.likelihood.record import Record
from harness.rig.controller import Controller

QUIET = {"noise.theta": 0.0, "noise.alpha": 0.0, "noise.hub_torque": 0.0, "noise.link_torque": 0.0}
LSB = 20.0 / 2**12  # V: the 12-bit ADC's step


def _record(u: np.ndarray, y: np.ndarray) -> Record:
    return Record("r", TS, u, y, np.ones((u.size, 2), bool))


@pytest.mark.parametrize("play", [0.004, 0.01])
def test_the_filters_play_replays_the_plant_fmus_backlash(play):
    """Sure of its state (no noise, no reading taken), the filter's prediction through a random square with the
    plant's play is the plant FMU's readings: within 8e-3 deg of the hub and the gauge (measured 3.6e-3 and 4.1e-3
    at 0.004 rad: the play closing within its 1 ms steps), where the rigid rig is off by more than 0.15 deg; the
    draws on their 0.05 ms steps within 1.5e-3 deg (5.5e-4)."""
    u = _random_square(3, 3.0, 0.8)
    y = _readings_of(u, ONE | {"backlash": play}, {})
    rec = _record(u, y)
    for values, tol in ((_truth(ONE) | {"plant.backlash": play}, 8e-3), (_truth(ONE), None)):
        model = rig_model(ONE, values, Noise(0.0, 0.0))
        d = replace(model.discretise(TS), Q=np.zeros((len(model.states),) * 2))
        x0 = np.zeros(len(model.states))
        f = kalman_filter(d, model.inputs(u), y, np.zeros_like(rec.mask), x0, np.zeros((x0.size,) * 2), keep=True)
        assert f.xp is not None
        err = np.abs(f.xp @ d.C.T - y).max(axis=0)
        if tol is None:
            assert err.min() > 0.15
        else:
            assert err.max() < tol, err
    drawn = simulate.draw_records(ONE, _truth(ONE) | QUIET | {"plant.backlash": play}, rec, 0,
                                  np.random.default_rng(0), draws=1)[0]  # fmt: skip
    assert np.abs(drawn - y).max() < 1.5e-3


def _closed_twin(play: float, seed: int) -> Record:
    ref = np.radians(np.where(np.arange(1500) * TS % 2.0 < 1.0, 20.0, -20.0))
    ctrl = Controller(K=[9.231, -18.769, 1.203, -0.041], cutoff=15.0).fmu_parameters(1 / TS)
    fmus = build_all()
    daq = {"noise_theta": 0.002, "noise_alpha": 0.002, "seed": seed, "adc_bits": 12}
    with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as rig:
        out = rig.run_closed(ref, TS, ctrl, plant=ONE | {"backlash": play}, daq=daq)
    return Record("closed", TS, out["u"], _readings(out), np.ones((ref.size, 2), bool), (LSB * KP, LSB * abs(KE)))


@pytest.mark.parametrize(("play", "seed", "closed"), [(0.004, 3, False), (0.002, 5, False), (0.004, 7, True)],
                         ids=["open_4mrad", "open_2mrad", "closed_4mrad"])  # fmt: skip
def test_a_gear_play_is_recovered_with_the_linear_model(play, seed, closed):
    """The play fitted beside the linear model from 10 % off and 1.5 times the calibration's small play: within 5 % of
    the plant's (measured 0.1-0.2 % open loop) and inside 3.29 of its standard errors' reach; the LR against the
    linear model above 100 (1300-1500 open loop); the hub's white torque, which carried the play in the linear model,
    near none."""
    if closed:
        rec = _closed_twin(play, seed)
    else:
        rec = replace(_twin(_random_square(seed, 3.0, 0.8), ONE | {"backlash": play}, {"adc_bits": 12}, seed=seed),
                      lattice=(LSB * KP, LSB * abs(KE)))  # fmt: skip
    base = _fit([rec])
    res = _fit([rec], {"plant.backlash": 0.003}, {"plant.backlash": 0.002})
    e = res.estimates["plant.backlash"]
    assert e.value == pytest.approx(play, rel=0.05)
    assert 2.0 * (res.loglik - base.loglik) > 100.0
    assert res.estimates["noise.hub_torque"].value < 0.2 * max(base.estimates["noise.hub_torque"].value, 1e-4)


def test_without_a_play_the_fitted_play_is_at_its_null():
    """A twin without play: the play fitted from 1.5 times the calibration's small one ends at none (its wall), and
    the model gains nothing over the linear one (LR below 1; measured 4e-4)."""
    rec = replace(_twin(_random_square(3, 3.0, 0.8), ONE, {"adc_bits": 12}, seed=3), lattice=(LSB * KP, LSB * abs(KE)))
    base = _fit([rec])
    res = _fit([rec], {"plant.backlash": 0.003}, {"plant.backlash": 0.002})
    assert res.estimates["plant.backlash"].value < 2e-5
    assert 2.0 * (res.loglik - base.loglik) < 1.0


def test_the_play_model_starts_with_its_teeth_anywhere_in_the_play():
    """The filter's start with a play: the gap uniform over the play (variance play^2 / 12), the motor turning with
    the hub (their speeds' covariance one); its first pass through a twin is finite."""
    rec = _record(np.zeros(50), np.zeros((50, 2)))
    model = rig_model(ONE, _truth(ONE) | {"plant.backlash": 0.006}, Noise(0.01, 0.01, 1e-3))
    assert model.states[-2:] == ("gap", "motor_speed")
    f = run_filter(model, model.discretise(TS), rec, keep=True)
    assert f.Pp is not None
    i, w, v = model.states.index("gap"), model.states.index("motor_speed"), model.states.index("theta_dot")
    assert f.Pp[0, i, i] == pytest.approx(0.006**2 / 12)
    assert f.Pp[0, w, v] == pytest.approx(f.Pp[0, v, v]) and f.Pp[0, w, w] == pytest.approx(f.Pp[0, v, v])
    assert np.isfinite(f.loglik)
