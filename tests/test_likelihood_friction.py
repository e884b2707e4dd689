"""Coulomb friction in the likelihood engine's filter (``fmus/master/kalman.c``): its step against the exact moments
of the time-stepping friction law over a normal speed (quadrature), and the friction with the rig's linear parameters
recovered by maximum likelihood from twins run through the FMUs (Karnopp friction with its stick phase, integrated
by the plant FMU), open and closed loop, where the linear model alone bent the drive's gain by 20-25 %."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.stats import norm
from test_likelihood import KE, KP, NOISE_V, PLANT, TS, _readings, _truth

from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.likelihood import fit as mlfit
from harness.likelihood.kalman import Discrete, kalman_filter
from harness.likelihood.record import Record
from harness.rig.controller import Controller


def _exact(mean: float, var: float, b: float, fc: float, fs: float = 0.0, vs: float = 0.0) -> tuple[float, float]:
    """The mean and variance of v + b f(v) for v ~ N(mean, var), by quadrature: f = -v / b where that is within
    +-Fs (Fs = max(fs, fc)), else -sign(v) (fc + (Fs - fc) exp(-(v / vs)^2)) (fc alone where vs = 0)."""
    top = max(fs, fc)

    def after(v: float) -> float:
        if abs(v) <= b * top:
            return 0.0
        drop = (top - fc) * math.exp(-((v / vs) ** 2)) if vs > 0 else 0.0
        return v - b * math.copysign(fc + drop, v)

    sd = math.sqrt(var)
    lo, hi = mean - 12 * sd, mean + 12 * sd
    pts = sorted({min(max(p, lo), hi) for p in (-top * b, top * b)})
    m = quad(lambda v: after(v) * norm.pdf(v, mean, sd), lo, hi, points=pts, epsabs=1e-14, limit=200)[0]
    m2 = quad(lambda v: after(v) ** 2 * norm.pdf(v, mean, sd), lo, hi, points=pts, epsabs=1e-14, limit=200)[0]
    return m, m2 - m * m


@pytest.mark.parametrize(
    ("mean", "var", "fc"),
    [(0.0, 1.0, 0.5), (0.3, 0.04, 0.5), (2.0, 0.25, 0.5), (-1.0, 1.0, 0.8), (5.0, 1e-4, 0.5), (0.1, 1e-30, 0.5)],
    ids=["at_rest", "sticks", "slides", "either", "sure_slides", "sure_sticks"],
)
def test_the_filters_friction_step_has_the_exact_moments_of_the_friction_law(mean, var, fc):
    """One speed state N(mean, var) and a unit torque's effect b = 2 over the sample: after the filter's time update
    its mean and variance are those of v + b clip(-v / b, -Fc, Fc) (the time-stepping friction law) over that normal,
    to 1e-9 by quadrature; for one state the assumed-density step is exact. Sure of its speed, the hard law."""
    b = 2.0
    model = Discrete(A=np.eye(1), B=np.zeros((1, 1)), Q=np.zeros((1, 1)), C=np.eye(1), r=np.ones(1),
                     friction=fc, hub=np.array([b]), speed=0)  # fmt: skip
    f = kalman_filter(model, np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1), bool), np.array([mean]),
                      np.array([[var]]), keep=True)  # fmt: skip
    assert f.xp is not None and f.Pp is not None
    if var < 1e-20:
        assert f.xp[1, 0] == pytest.approx(mean + b * min(max(-mean / b, -fc), fc), abs=1e-15)
        return
    m, v = _exact(mean, var, b, fc)
    assert f.xp[1, 0] == pytest.approx(m, abs=1e-9)
    assert f.Pp[1, 0, 0] == pytest.approx(v, abs=1e-9 * max(var, 1e-3))


@pytest.mark.parametrize(
    ("mean", "var", "fs", "vs"),
    [(0.0, 1.0, 0.8, 0.0), (1.4, 0.04, 0.8, 0.0), (1.0, 0.25, 0.8, 0.5), (-2.0, 1.0, 0.8, 0.5), (4.0, 1e-4, 0.8, 2.0),
     (0.3, 1e-30, 0.8, 0.5)],
    ids=["breakaway_at_rest", "breaks_away", "stribeck", "stribeck_back", "sure_slides", "sure_sticks"],
)  # fmt: skip
def test_the_filters_friction_step_has_the_exact_moments_with_breakaway_and_stribeck(mean, var, fs, vs):
    """The friction step with a breakaway Fs = 0.8 above the Coulomb level 0.5 (b = 2): the hub held within +-Fs,
    sliding friction Fc + (Fs - Fc) exp(-(v / vs)^2) (Fc alone at vs 0, the plant FMU's Karnopp law): after the
    filter's time update one speed state's mean and variance are the law's over the normal, to 1e-9 by quadrature (its
    regions in closed form); sure of its speed, the hard law."""
    b, fc = 2.0, 0.5
    model = Discrete(A=np.eye(1), B=np.zeros((1, 1)), Q=np.zeros((1, 1)), C=np.eye(1), r=np.ones(1),
                     friction=fc, breakaway=fs, stribeck=vs, hub=np.array([b]), speed=0)  # fmt: skip
    f = kalman_filter(model, np.zeros((2, 1)), np.zeros((2, 1)), np.zeros((2, 1), bool), np.array([mean]),
                      np.array([[var]]), keep=True)  # fmt: skip
    assert f.xp is not None and f.Pp is not None
    m, v = _exact(mean, max(var, 1e-300), b, fc, fs, vs)
    if var < 1e-20:
        assert f.xp[1, 0] == 0.0 and m == pytest.approx(0.0, abs=1e-12)  # within +-b Fs: held
        return
    assert f.xp[1, 0] == pytest.approx(m, abs=1e-9)
    assert f.Pp[1, 0, 0] == pytest.approx(v, abs=1e-9 * max(var, 1e-3))


def _twin(closed: bool, coulomb: float, seed: int = 1, Ts: float = TS, n: int = 2500) -> Record:
    """A twin of ``n`` samples every ``Ts`` (5 s at 500 Hz) through a 12-bit ADC (2 mV of noise) with Coulomb friction
    ``coulomb`` [N m]: open loop a random +-1 V square (a switch every 0.2 s on average), closed loop the state
    feedback on a +-20 deg square reference."""
    rng = np.random.default_rng(seed)
    daq = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "seed": seed, "adc_bits": 12}
    fmus, plant = build_all(), {**PLANT, "coulomb_torque": coulomb}
    if closed:
        ref = np.radians(np.where(np.arange(n) * Ts % 2.0 < 1.0, 20.0, -20.0))
        ctrl = Controller(K=[9.231, -18.769, 1.203, -0.041], cutoff=15.0).fmu_parameters(1 / Ts)
        with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as rig:
            out = rig.run_closed(ref, Ts, ctrl, plant=plant, daq=daq)
    else:
        u = np.where(np.cumsum(rng.random(n) < 5.0 * Ts) % 2 == 0, 1.0, -1.0)
        with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
            out = rig.run(u, Ts, plant=plant, daq=daq)
    y = _readings(out)
    assert np.abs(y[:, 0]).max() < 170  # the pot on its track
    lsb = 20.0 / 2**12
    return Record("twin", Ts, out["u"], y, np.ones((n, 2), bool), (lsb * KP, lsb * abs(KE)))


@pytest.mark.parametrize(
    ("closed", "coulomb", "rate"),
    [(False, 0.03, 500), (True, 0.01, 500), (True, 0.0, 500), (False, 0.03, 50)],
    ids=["open_loop_0.03", "closed_loop_0.01", "closed_loop_none", "open_loop_0.03_at_50Hz"],
)
def test_friction_and_the_linear_model_are_recovered_together(closed, coulomb, rate):
    """From a start 15-25 % off and friction at 0.005 N m, the friction within 5 % of the twin's (measured: 0.029759
    for 0.03 in open loop, where the linear model alone put the drive's gain 25 % low and a white hub torque in the
    friction's place) and the linear parameters within 2 % of the rig's (3 % at 50 Hz); in closed loop each inside
    3.29 of its standard errors. In open loop, where the hub sticks at every reversal, the intervals are too narrow:
    the inertia ratio -0.47 % at 6.4 standard errors, the drive's time constant -0.18 % at 3.2 (the filter holds one
    friction torque over each 1 ms substep, the FMU switches at the instant; with the 2 ms sample as the step, -0.69 %
    at 6.7 and 90 nats less). At 50 Hz (10 s, 20 substeps a sample) the friction -1.0 %, the drive's gain -0.2 %, the
    inertia ratio -0.55 %, the link's damping -2.1 %; with the 20 ms sample as the step, the friction -43 %, the
    drive's gain -12 % and 991 nats less. On the friction-free twin, the friction at its lower bound (under 1e-3 N
    m)."""
    rec = _twin(closed, coulomb, Ts=1.0 / rate, n=2500 if rate == 500 else 500)
    truth = _truth(PLANT)
    off = dict(zip(truth, (1.15, 0.85, 1.2, 0.8, 1.25), strict=True))
    noise = mlfit.noise_start([rec])
    start = {k: v * off[k] for k, v in truth.items()} | noise | {"plant.coulomb_torque": 0.005}
    fixed = {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0}
    res = mlfit.fit(PLANT, [rec], start, fixed=fixed, nominal=truth | noise | {"plant.coulomb_torque": 0.01})
    fc = res.estimates["plant.coulomb_torque"]
    if coulomb:
        assert fc.value == pytest.approx(coulomb, rel=0.05)
    else:
        assert fc.value < 1e-3 and fc.at == "lower", fc
    for name, want in truth.items() | ({"plant.coulomb_torque": coulomb}.items() if coulomb else set()):
        e, b = res.estimates[name], mlfit.BOUNDS[name]
        half = (b.to_x(e.ci95[1], want) - b.to_x(e.ci95[0], want)) / 2
        assert e.value == pytest.approx(
            want, rel=0.05 if name == "plant.coulomb_torque" else 0.02 if rate == 500 else 0.03
        ), name
        assert half > 0, (name, e)
        assert not closed or abs(b.to_x(e.value, want) - b.to_x(want, want)) < 3.29 / 1.96 * half, (name, want, e)


def test_frictions_breakaway_and_stribeck_drop_are_recovered_beside_its_coulomb_level():
    """A 5 s open-loop twin (random +-0.8 V square, one mode, 12-bit ADC) with Coulomb friction 0.03 N m, a breakaway
    1.3 times it and a Stribeck speed of 0.05 rad/s (the plant FMU's Karnopp law, the independent simulator's shape):
    fitted from the Coulomb-only fit with the shape from 1.5 and 0.05 rad/s, the ratio within 5 % and the speed within
    30 % (measured 1.3075, 0.0576 rad/s), the Coulomb level within 2 % (0.02983), and the shape passes the rule's test
    against the Coulomb-only model on the same filter (its breakaway held at none; the law of a wall and an
    undetermined parameter: LR 503 against 8.27). The breakaway alone (no drop) comes back within 5 % (1.2986, the
    speed at the bottom of its range: LR 101); without a breakaway the shape stays out (1.0055, LR -1.4)."""
    from test_likelihood_effects import ONE, _fit, _random_square
    from test_likelihood_effects import _twin as _one_mode_twin

    from harness.likelihood.rule import Rule

    def fitted(ratio: float, vs: float) -> tuple[mlfit.MLFit, float]:
        rec = _one_mode_twin(_random_square(3, 5.0, 0.8), ONE | {"coulomb_torque": 0.03, "stiction_ratio": ratio,
                             "stribeck_speed": vs}, {"adc_bits": 12}, seed=3)  # fmt: skip
        lsb = 20.0 / 2**12
        rec = Record(rec.name, rec.Ts, rec.u, rec.y, rec.mask, (lsb * KP, lsb * abs(KE)))
        coulomb = _fit([rec], {"plant.coulomb_torque": 0.02}, {"plant.coulomb_torque": 0.0128})
        held = {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0}
        shape = {"plant.stiction_ratio": 1.5, "plant.stribeck_speed": 0.05}
        scale = {k: v for k, v in coulomb.values().items()} | shape
        null = mlfit.fit(ONE, [rec], coulomb.values(), fixed=held | {"plant.stiction_ratio": 1.0}, nominal=scale)
        shaped = mlfit.fit(ONE, [rec], null.values() | shape, fixed=held, nominal=scale)
        return shaped, 2.0 * (shaped.loglik - null.loglik)

    shaped, lr = fitted(1.3, 0.05)
    test = Rule().test(lr, shaped.estimates["plant.stiction_ratio"].inflation, (False, True))
    assert shaped.estimates["plant.stiction_ratio"].value == pytest.approx(1.3, rel=0.05)
    assert shaped.estimates["plant.stribeck_speed"].value == pytest.approx(0.05, rel=0.3)
    assert shaped.estimates["plant.coulomb_torque"].value == pytest.approx(0.03, rel=0.02)
    assert test.enters, test
    alone, lr = fitted(1.3, 0.0)
    assert alone.estimates["plant.stiction_ratio"].value == pytest.approx(1.3, rel=0.05)
    assert alone.estimates["plant.stribeck_speed"].value < 0.01
    assert Rule().test(lr, alone.estimates["plant.stiction_ratio"].inflation, (False, True)).enters
    plain, lr = fitted(1.0, 0.0)
    assert not Rule().test(lr, plain.estimates["plant.stiction_ratio"].inflation, (False, True)).enters
