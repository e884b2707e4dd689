"""The effects the likelihood engine fits beside the linear rig (harness.likelihood.effects), each against twins run
through the plant and DAQ FMUs with the effect switched on: the amplifier's output limit (``plant.amp_limit``, a
continuous effect searched as the share of the peak command over it, its null a wall), the command's transport
delay (``daq.delay_samples``) and a second link mode (``plant.n_modes``), both chosen by profile likelihood. Twins are
2-3 s at 500 Hz with 2 mV of noise; commands are random-phase multisines or random squares drawn from each test's
seed."""

from __future__ import annotations

import numpy as np
import pytest
from test_force_shapes import _multisine
from test_likelihood import NOISE_V, TS, _readings, _truth

from harness.diagnosis.decide import Decision, decide
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.likelihood import fit as mlfit
from harness.likelihood.effects import command_peak, profile_delay, profile_modes
from harness.likelihood.model import Noise, rig_model
from harness.likelihood.record import Record
from harness.likelihood.rule import Rule
from harness.likelihood.unit import fit_unit, linear_start

ONE = {"n_modes": 1}  # the textbook rig: one link mode
SENSORS = {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0}
OFF = (1.1, 0.9, 1.1, 0.9, 1.1)  # the start's factors on the truth (drive gain, tau, inertia ratio, Ks, zeta)


def _ramped(u: np.ndarray, seconds: float = 0.1) -> np.ndarray:
    """The command ramped in from 0 over ``seconds`` (half a cosine): the DAQ's delay line holds zeros before the
    record, the record's delayed command its first value."""
    n = round(seconds / TS)
    w = np.ones(u.size)
    w[:n] = 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / n)
    return u * w


def _random_square(seed: int, seconds: float, volts: float = 0.8) -> np.ndarray:
    """A +-``volts`` square switching at random (1.5 % of samples), from 0 for its first 5 samples."""
    rng = np.random.default_rng(seed)
    n = round(seconds / TS)
    u = volts * np.where(np.cumsum(rng.random(n) < 0.015) % 2 == 0, 1.0, -1.0)
    u[:5] = 0.0
    return u


def _twin(u: np.ndarray, plant: dict, daq: dict | None = None, seed: int = 1, noise: float = NOISE_V) -> Record:
    """The command ``u`` [V] through the plant FMU with ``plant`` and the DAQ with ``daq``, ``noise`` V rms on both
    readings, read as a user's calibrated degrees."""
    fmus = build_all()
    with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
        out = rig.run(u, TS, plant=plant, daq={"noise_theta": noise, "noise_alpha": noise, "seed": seed, **(daq or {})})
    y = _readings(out)
    assert np.abs(y[:, 0]).max() < 170  # the pot on its track
    return Record("twin", TS, out["u"], y, np.ones((u.size, 2), bool))


def _start(truth: dict[str, float]) -> dict[str, float]:
    return {k: v * f for (k, v), f in zip(truth.items(), OFF, strict=True)}


def _assert_linear(res: mlfit.MLFit, truth: dict[str, float], intervals: bool = True) -> None:
    """Each linear parameter within 5 % of the rig's and (``intervals``) inside 3.29 of its standard errors."""
    for name, want in truth.items():
        e, b = res.estimates[name], mlfit.BOUNDS[name]
        se = (b.to_x(e.ci95[1], want) - b.to_x(e.ci95[0], want)) / (2 * 1.96)
        assert e.value == pytest.approx(want, rel=0.05), name
        assert not intervals or abs(b.to_x(e.value, want) - b.to_x(want, want)) < 3.29 * se, (name, want, e)


@pytest.mark.parametrize(
    ("limit", "offset", "delay"), [(1.0, 0.1, 0), (0.7, -0.2, 2)], ids=["limit_offset", "limit_offset_delay"]
)
def test_the_models_input_replays_the_fmus_limit_offset_and_delay(limit, offset, delay):
    """Without noise, the sampled one-mode model fed :meth:`StochasticModel.inputs` of the command delayed by
    ``delay`` samples (the record's) is the plant and DAQ FMUs' readings, the plant clamping u + u_offset at
    +-amp_limit, the DAQ delaying by delay_samples: the hub within 1e-6 deg, the gauge within 2e-5 deg, where the
    unclipped input is degrees off."""
    u = _ramped(_multisine(3, 1.5, 4.0))
    plant = ONE | {"amp_limit": limit, "u_offset": offset}
    y = _readings_of(u, plant, {"delay_samples": delay})
    values = _truth(ONE) | {"plant.u_offset": offset}
    rec = Record("r", TS, u, y, np.ones((u.size, 2), bool))
    clipped = _simulate(rig_model(ONE, values | {"plant.amp_limit": limit}, Noise(0.0, 0.0)), rec.delayed(delay))
    plain = _simulate(rig_model(ONE, values, Noise(0.0, 0.0)), rec.delayed(delay))
    np.testing.assert_allclose(clipped[:, 0], y[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(clipped[:, 1], y[:, 1], rtol=0, atol=2e-5)
    assert np.abs(plain[:, 0] - y[:, 0]).max() > 1.0


def test_a_delayed_command_is_none_before_the_record():
    """A record whose command starts at 1.5 V on its first sample, delayed 3 samples by the DAQ: the model fed
    :meth:`Record.delayed` replays the FMUs from the first sample (the DAQ's delay line holds none before the record),
    the hub within 1e-6 deg; the first value held before the record instead is off by more than 1e-3 deg."""
    u = 1.5 * np.ones(200)
    y = _readings_of(u, ONE, {"delay_samples": 3})
    rec = Record("r", TS, u, y, np.ones((u.size, 2), bool))
    model = rig_model(ONE, _truth(ONE), Noise(0.0, 0.0))
    np.testing.assert_allclose(_simulate(model, rec.delayed(3))[:, 0], y[:, 0], rtol=0, atol=1e-6)
    held = np.concatenate([np.full(3, u[0]), u[:-3]])
    assert np.abs(_simulate(model, held)[:, 0] - y[:, 0]).max() > 1e-3


@pytest.mark.parametrize("tau", [0.02, 0.06])
def test_the_models_gauge_low_pass_replays_the_daqs(tau):
    """Without noise, the sampled one-mode model with the gauge's low-pass ``sensor.gauge_tau`` is the DAQ FMU's
    gauge filtered at the samples with ``gauge_tau``: within 1e-6 deg (measured 3e-8), where the model without it is
    off by more than 10 % of the reading's range (15.5 % and 43 %); the hub's reading is the same."""
    u = _ramped(_multisine(4, 1.5, 4.0))
    y = _readings_of(u, ONE, {"gauge_tau": tau})
    model = rig_model(ONE, _truth(ONE) | {"sensor.gauge_tau": tau}, Noise(0.0, 0.0))
    assert model.states[-2:] == ("gauge", "b_alpha")
    filtered, plain = _simulate(model, u), _simulate(rig_model(ONE, _truth(ONE), Noise(0.0, 0.0)), u)
    np.testing.assert_allclose(filtered, y, rtol=0, atol=1e-6)
    assert np.abs(plain[:, 1] - y[:, 1]).max() > 0.1 * np.ptp(y[:, 1])


@pytest.mark.parametrize("cubic", [0.05, -0.08])
def test_the_models_bent_gauge_replays_the_daqs(cubic):
    """Without noise, the one-mode model with the gauge's nonlinearity ``daq.gauge_cubic`` reads the gauge as the DAQ
    FMU bends it, a (1 + c (a / 10 deg)^2): within 2e-5 deg of the gauge's reading, where the straight model is off by
    more than 0.3 % of its +-3.6 deg (0.45 % at 0.05: a thousand times the tolerance); with the gauge's gain 0.8, the
    same bend read through it."""
    u = _ramped(_multisine(4, 1.5, 4.0))
    y = _readings_of(u, ONE, {"gauge_cubic": cubic})
    bent, plain = (_simulate(rig_model(ONE, _truth(ONE) | v, Noise(0.0, 0.0)), u)
                   for v in ({"daq.gauge_cubic": cubic}, {}))  # fmt: skip
    np.testing.assert_allclose(bent, y, rtol=0, atol=2e-5)
    assert np.abs(plain[:, 1] - y[:, 1]).max() > 0.003 * np.ptp(y[:, 1])
    gain = {"sensor.alpha_gauge_gain": 0.8, "daq.gauge_cubic": cubic}
    np.testing.assert_allclose(_simulate(rig_model(ONE, _truth(ONE) | gain, Noise(0.0, 0.0)), u)[:, 1], 0.8 * y[:, 1],
                               rtol=0, atol=2e-5)  # fmt: skip


def _readings_of(u: np.ndarray, plant: dict, daq: dict) -> np.ndarray:
    fmus = build_all()
    with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
        return _readings(rig.run(u, TS, plant=plant, daq=daq))


def _simulate(model, u: np.ndarray) -> np.ndarray:
    d = model.discretise(TS)
    x = np.zeros(d.A.shape[0])
    out = np.empty((u.size, 2))
    for k, uk in enumerate(model.inputs(u)):
        out[k] = d.C @ x + (0.0 if d.cubic is None or d.bend is None else d.cubic * (d.bend @ x) ** 3)
        x = d.A @ x + d.B @ uk
    return out


def _fit(records: list[Record], effects: dict[str, float] | None = None, nominal: dict | None = None,
         torques: bool = True) -> mlfit.MLFit:  # fmt: skip
    """The one-mode model fitted from 10 % off the truth (:data:`OFF`), the noise free from the data's start (the
    white torques held at none unless ``torques``), the sensors' gains held true."""
    truth, noise = _truth(ONE), mlfit.noise_start(records)
    held = SENSORS | ({} if torques else dict.fromkeys(mlfit.TORQUES, 0.0))
    free = {k: v for k, v in noise.items() if k not in held}
    return mlfit.fit(ONE, records, _start(truth) | free | (effects or {}), fixed=held,
                     nominal=truth | free | (nominal or {}))  # fmt: skip


@pytest.mark.parametrize(("seed", "limit"), [(4, 1.0), (11, 0.8)])
def test_an_amplifier_limit_is_recovered_with_the_linear_model(seed, limit):
    """A 3 s twin under a +-1.5 V multisine through an amplifier limited to ``limit`` V: fitted from 10 % off with
    the five linear parameters and the readings' noise (the white torques held at none, as in the FMUs), the limit
    starting at 0.8 of the peak command, the limit comes back within 20 % (the issue's target) and inside its 95 %
    interval (measured 0.99992 V in 0.99966-1.00018 for 1.0 V, 0.79979 V in 0.79953-0.80006 for 0.8 V), the linear
    parameters within 5 % and 3.29 standard errors (measured within 1.3 %, the link's damping the furthest). The
    linear model alone, its noise free, puts the inertia ratio 170-300 % high and a white hub torque of 1.9e-3 and
    3.5e-3 N m sqrt(s) in the limit's place, and its log-likelihood falls short of the limit model's by more than 100
    nats (measured 532 and 607; with its torques free too the limit model could only gain more). On ten blind draws
    (seeds 30-39, limits log-uniform in 0.6-1.2 V, drawn 0.60-1.12 V) the limit came back within
    0.023 % and inside its interval on all ten, the linear parameters within 2.1 % and 2.5 standard errors, the
    linear model 481-615 nats short."""
    rec = _twin(_ramped(_multisine(seed, 1.5, 3.0)), ONE | {"amp_limit": limit}, seed=seed)
    peak = command_peak([rec])
    lin = _fit([rec])
    res = _fit([rec], {"plant.amp_limit": 0.8 * peak}, {"plant.amp_limit": peak}, torques=False)
    est = res.estimates["plant.amp_limit"]
    assert est.value == pytest.approx(limit, rel=0.2)
    assert est.at is None and est.ci95[0] < limit < est.ci95[1], est
    _assert_linear(res, _truth(ONE))
    assert res.loglik - lin.loglik > 100.0


@pytest.mark.parametrize("seed", [7, 12])
def test_without_a_limit_the_fitted_limit_is_at_its_null_wall(seed):
    """A 3 s twin under a +-1.5 V multisine, no limit: the limit, started at 0.8 of the peak command, ends at its
    null wall (the share's wall within the search's 1e-3: the limit within about 1 % of the peak) and the data
    cannot tell it from none: its log-likelihood over the null's (the fit's values with the limit at the peak, an
    upper bound of the likelihood ratio) under 5.4 nats, chi-square's 0.1 % level on one degree of freedom (a limit
    is a change point in the command: its ratio's tail is heavier than chi-square's). Measured: at the peak on seeds
    7 and 12, the ratio 0; on ten blind seeds (40-49) all at the wall, within 0.25 % of the peak, the ratio at most
    3.5 nats. The linear parameters within 5 % (measured 1.3 %; their intervals are not checked: the fit's
    information is taken at the limit's wall)."""
    rec = _twin(_ramped(_multisine(seed, 1.5, 3.0)), ONE, seed=seed)
    peak = command_peak([rec])
    res = _fit([rec], {"plant.amp_limit": 0.8 * peak}, {"plant.amp_limit": peak}, torques=False)
    est = res.estimates["plant.amp_limit"]
    null = mlfit.log_likelihood(ONE, res.values() | SENSORS | {"plant.amp_limit": peak}, [rec])
    assert est.at == "lower" and est.value <= peak, est
    assert res.loglik - null < 5.4
    _assert_linear(res, _truth(ONE), intervals=False)


@pytest.mark.parametrize(("delay", "seed"), [(0, 6), (1, 5), (2, 8)])
def test_the_commands_delay_is_the_profiles_best(delay, seed):
    """A 2 s twin under a +-1 V multisine (ramped in from 0: the DAQ's delay line starts at zero) through the DAQ
    delaying the command by ``delay`` samples: the profile over 0-3 samples, each a fit of the linear parameters and
    the noise from 10 % off, is highest at ``delay`` by more than 10 nats over the next (measured 56, 96 and 75
    nats), the linear parameters there within 5 % and 3.29 standard errors. On eight blind draws (seeds 50-57, the
    delay drawn from 0-3) the profile picked the twin's delay on all eight, by 19-106 nats."""
    rec = _twin(_ramped(_multisine(seed, 1.0, 2.0)), ONE, {"delay_samples": delay}, seed=seed)
    truth, noise = _truth(ONE), mlfit.noise_start([rec])
    prof = profile_delay(ONE, [rec], _start(truth) | noise, fixed=SENSORS, nominal=truth | noise)
    ll = prof.loglik
    assert prof.settings == (0, 1, 2, 3) and prof.best == delay
    assert np.sort(ll)[-1] - np.sort(ll)[-2] > 10.0
    _assert_linear(prof.fit_at(delay), truth)


@pytest.mark.parametrize(("modes", "seed"), [(2, 5), (1, 9)])
def test_a_second_link_mode_is_the_profiles_choice_where_the_link_has_one(modes, seed):
    """A 2 s twin under a random +-0.8 V square (the link ringing after every switch) with ``modes`` link modes:
    the one- and the two-mode model each fitted from 10 % off with the noise. On the two-mode twin the two-mode
    model's log-likelihood beats the one-mode model's by more than 1000 nats (measured 2457: the one-mode model ends
    with the drive's gain and the inertia ratio at their bounds and a white hub torque of 0.44 N m sqrt(s)); on the
    one-mode twin the second mode gains under 3 nats (measured -916: it loses, its mode at 18.9 Hz rings where the
    link does not). The chosen model's linear parameters within 5 % and 3.29 standard errors. On six blind draws
    (seeds 60-65) the profile picked the twin's modes on all six: the second mode gained 1641 nats on the one
    two-mode twin and lost 828-898 on the five one-mode ones."""
    rec = _twin(_random_square(seed, 2.0), {"n_modes": modes}, seed=seed)
    truth, noise = _truth(ONE), mlfit.noise_start([rec])
    prof = profile_modes(ONE, [rec], _start(truth) | noise, fixed=SENSORS, nominal=truth | noise)
    gain = float(prof.loglik[1] - prof.loglik[0])
    assert prof.settings == (1, 2) and prof.best == modes
    assert gain > 1000.0 if modes == 2 else gain < 3.0
    _assert_linear(prof.fit_at(modes), truth)


@pytest.mark.parametrize(("modes", "delay", "seed"), [(1, 2, 21), (2, 0, 22), (1, 0, 23)])
def test_a_units_linear_model_takes_its_modes_and_delay_by_profile(modes, delay, seed):
    """A unit's records through the engine (fit_unit) from a one-mode, undelayed sheet 10 % off: a twin under a
    random +-0.8 V square with ``modes`` link modes and the command ``delay`` samples late. The second mode and the
    delay each enter by the rule (Vuong's test at 1 %) exactly where the twin has them, the delay at the twin's
    setting; the linear model then is the fit with them, nothing at a bound, its parameters within 5 % of the
    rig's."""
    from harness.likelihood.rule import Rule
    from harness.likelihood.unit import fit_unit, linear_start

    rec = _twin(_ramped(_random_square(seed, 2.0)), {"n_modes": modes}, {"delay_samples": delay}, seed=seed)
    sheet = {k: 1.1 * v for k, v in linear_start(ONE).items() if not k.startswith("sensor.")}
    unit = fit_unit(ONE, [rec], sheet | SENSORS, SENSORS, {}, rule=Rule())
    tests = {x.name: x for x in unit.effects}
    assert tests["second_mode"].test.enters == (modes == 2), tests["second_mode"].test
    assert tests["delay"].test.enters == (delay > 0), tests["delay"].test
    assert (
        tests["delay"].test.law == "vuong"
        and tests["delay"].settings == {"daq.delay_samples": delay or 1}
        or (not delay)
    )
    if delay:
        assert tests["delay"].settings == {"daq.delay_samples": delay}
    assert set(unit.structure) == {n for n, on in (("second_mode", modes == 2), ("delay", delay > 0)) if on}
    assert not unit.findings and not unit.fit.at_bounds().keys() - {"noise.hub_torque", "noise.link_torque"}
    for name, want in _truth(ONE).items():
        assert unit.fit.estimates[name].value == pytest.approx(want, rel=0.05), name


def test_a_delay_of_tens_of_samples_is_found_by_the_units_profile():
    """A command reaching the drive 20 samples (40 ms) late, as a PC-based DAQ's can (the twin's DAQ delays it),
    under a sheet that says none: the unit's profile (every sample to 50 ms, on a coarse grid and then around its
    best, each fit from its neighbour's) enters the delay at 20, and the linear model then comes back within 5 % of
    the rig's with nothing at a bound. The 25 delays (1-25 samples) are searched on every second one, then beside
    the grid's best."""
    from harness.likelihood.effects import profile_settings, search_order
    from harness.likelihood.rule import Rule
    from harness.likelihood.unit import fit_unit, linear_start

    assert profile_settings("delay", ONE, 0, TS) == tuple(range(1, 26))
    assert profile_settings("delay", ONE, 1, 0.02) == (0, 2, 3)
    assert search_order(tuple(range(1, 26))) == ((1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25), 2)
    rec = _twin(_ramped(_random_square(31, 2.0)), ONE, {"delay_samples": 20}, seed=31)
    sheet = {k: 1.1 * v for k, v in linear_start(ONE).items() if not k.startswith("sensor.")}
    unit = fit_unit(ONE, [rec], sheet | SENSORS, SENSORS, {}, rule=Rule())
    delay = next(x for x in unit.effects if x.name == "delay")
    assert delay.test.enters and delay.settings == {"daq.delay_samples": 20}, delay.test
    assert "delay" in unit.structure and not unit.findings
    assert "  the linear model with: delay (each entered by the rule)" in unit.summary()
    for name, want in _truth(ONE).items():
        assert unit.fit.estimates[name].value == pytest.approx(want, rel=0.05), name


def test_a_gauges_low_pass_is_nested_in_the_units_linear_model():
    """The DAQ's gauge amplifier low-passing the deflection with a time constant of 30 ms, under a sheet that gives
    none: the unit's gauge low-pass, nested at none, enters, at 0.03 s within 2 % (measured 0.02999), and the linear
    model with it comes back within 5 % of the rig's, the gauge's gain (free) within 2 % of 1. (With the filter taken
    as a continuous one, half a sample apart from the DAQ's: 0.0282 s and the link's damping +31 %.)"""
    from harness.likelihood.rule import Rule
    from harness.likelihood.unit import fit_unit, linear_start

    rec = _twin(_ramped(_random_square(41, 3.0)), ONE, {"gauge_tau": 0.03}, seed=41)
    sheet = {k: 1.1 * v if not k.startswith("sensor.") else v for k, v in linear_start(ONE).items()}
    held = {"sensor.theta_gain": 1.0}  # the hub's reading calibrated (in open loop its gain trades with the drive's)
    unit = fit_unit(ONE, [rec], sheet, held, {}, rule=Rule())
    low = next(x for x in unit.effects if x.name == "gauge_lowpass")
    assert low.test.enters and "gauge_lowpass" in unit.structure, low.test
    assert unit.fit.estimates["sensor.gauge_tau"].value == pytest.approx(0.03, rel=0.02)
    assert unit.fit.estimates["sensor.alpha_gauge_gain"].value == pytest.approx(1.0, rel=0.02)
    assert not unit.findings
    for name, want in _truth(ONE).items():
        assert unit.fit.estimates[name].value == pytest.approx(want, rel=0.05), name


@pytest.mark.parametrize(("cubic", "seed"), [(0.06, 41), (0.0, 42)])
def test_a_gauges_nonlinearity_is_nested_where_the_bridge_bends(cubic, seed):
    """A gauge that bends its reading by ``daq.gauge_cubic`` (the DAQ's a (1 + c (a / 10 deg)^2)), 1.2 V random
    squares over 4 s: its nested fit, from inside and from none, comes back within 2 % (measured 0.06011) and enters
    by the chi-square's rule (its null inside its range); on the straight gauge it stays out, within 0.002 of none
    (measured 6.6e-5), and the gauge's gain is that of the linear fit within 0.5 %. The verdict
    (:func:`harness.diagnosis.decide.decide`) is gauge_nonlinearity, and none on the straight gauge."""
    rec = _twin(_ramped(_random_square(seed, 4.0, 1.2)), ONE, {"gauge_cubic": cubic}, seed=seed)
    sheet = {k: 1.1 * v if not k.startswith("sensor.") else v for k, v in linear_start(ONE).items()}
    unit = fit_unit(ONE, [rec], sheet, {"sensor.theta_gain": 1.0}, {}, rule=Rule())
    bend = next(x for x in unit.effects if x.name == "gauge_nonlinearity")
    assert bend.test.law == "chi-square" and bend.test.critical >= 6.63
    value = bend.fit.estimates["daq.gauge_cubic"].value
    if cubic:
        assert bend.test.enters and value == pytest.approx(cubic, rel=0.02), bend.line()
        assert bend.fit.estimates["sensor.alpha_gauge_gain"].value == pytest.approx(1.0, rel=0.005)
        assert unit.final is bend.fit and decide(unit).verdict == "gauge_nonlinearity", decide(unit)
    else:
        assert not bend.test.enters and abs(value) < 0.002, bend.line()
        assert not any(x.test.enters for x in unit.effects), unit.summary()
        assert unit.final is None and decide(unit) == Decision("none", (), None, "no effect enters and the residuals "
                                                               "are white")  # fmt: skip
        _assert_the_verdicts_order(unit)


def _assert_the_verdicts_order(unit) -> None:
    """On a unit with no effect: a finding makes it unexplained (bound) before anything else; residuals not white on
    one record channel of two, at p below half the rule's level (Bonferroni), unexplained (not_white), at p just
    above it not; an ADC's lattice the sheet lacks, quantization; a missing force of a shape no effect draws,
    unexplained (shape)."""
    from dataclasses import replace

    from harness.likelihood.force import MissingForce

    rule = Rule(white=0.01)
    assert decide(replace(unit, findings=("drive gain ends at its lower bound",)), rule).unexplained == "bound"
    grey = {r: {"theta": 0.0049, "alpha": 0.5} for r in unit.whiteness}
    assert decide(replace(unit, whiteness=grey), rule).unexplained == "not_white"
    fine = {r: {"theta": 0.0051, "alpha": 0.5} for r in unit.whiteness}
    assert decide(replace(unit, whiteness=fine), rule).verdict == "none"
    assert decide(replace(unit, lattice_bits=10), rule).verdict == "quantization"
    offset = MissingForce("offset", 0.05, "V", 0.0, 100)
    assert decide(replace(unit, missing_force=offset), rule).unexplained == "shape"
