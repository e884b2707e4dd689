"""The likelihood engine (harness.likelihood): the compiled filter against the exact Gaussian likelihood and the
smoother against the exact conditional mean of a small model written out in full; the stochastic model against the
plant FMU; the rig's linear parameters and its noise recovered by maximum likelihood from twins run through the FMUs,
open and closed loop (the logged command as the input: no controller replayed)."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import multivariate_normal

from harness import spec as specmod
from harness.diagnosis import rigmodel
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig
from harness.fmu.modeldesc import bundled_model
from harness.likelihood import fit as mlfit
from harness.likelihood.kalman import Discrete, kalman_filter, smooth
from harness.likelihood.model import Noise, rig_model
from harness.likelihood.record import Record
from harness.likelihood.unit import fit_run, write_likelihood
from harness.likelihood.whiteness import ljung_box
from harness.rig.campaign import run_campaign
from harness.rig.controller import Controller

DAQ = bundled_model("daq").parameters()
KP, KE = DAQ["pot_gain"].start, DAQ["gauge_gain"].start  # deg/V: the readings' calibration
PLANT = {"n_modes": 2}  # the textbook rig with its second mode, no effect
NOISE_V = 0.002  # V rms on both channels
TS = 2e-3


def _small_model(rng: np.random.Generator) -> tuple[Discrete, np.ndarray, np.ndarray]:
    """A random stable 3-state, 2-reading, 1-input model with its start (x0, P0)."""
    A = np.array([[0.9, 0.2, 0.0], [-0.2, 0.9, 0.1], [0.0, 0.0, 0.95]]) + 0.02 * rng.standard_normal((3, 3))
    L = 0.3 * rng.standard_normal((3, 3))
    model = Discrete(A=A, B=rng.standard_normal((3, 1)), Q=L @ L.T + 0.01 * np.eye(3),
                     C=rng.standard_normal((2, 3)), r=np.array([0.2, 0.5]))  # fmt: skip
    L0 = rng.standard_normal((3, 3))
    return model, rng.standard_normal(3), L0 @ L0.T + np.eye(3)


def _joint(model: Discrete, x0: np.ndarray, P0: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ...]:
    """The exact joint Gaussian of the states x_0..x_{n-1} and readings y_0..y_{n-1}, written out: means and
    covariances (states stacked, readings stacked), Cov(x, y)."""
    n, nx = u.shape[0], model.A.shape[0]
    Ak = [np.linalg.matrix_power(model.A, k) for k in range(n + 1)]
    mx = np.zeros((n, nx))
    m = x0.copy()
    for k in range(n):
        mx[k] = m
        m = model.A @ m + model.B @ u[k]
    Sx = np.zeros((n * nx, n * nx))
    for k in range(n):
        for j in range(n):
            c = Ak[k] @ P0 @ Ak[j].T
            for i in range(min(k, j)):
                c += Ak[k - 1 - i] @ model.Q @ Ak[j - 1 - i].T
            Sx[k * nx : (k + 1) * nx, j * nx : (j + 1) * nx] = c
    Cbig = np.kron(np.eye(n), model.C)
    my = (mx @ model.C.T).ravel()
    Sy = Cbig @ Sx @ Cbig.T + np.kron(np.eye(n), np.diag(model.r))
    return mx.ravel(), Sx, my, Sy, Sx @ Cbig.T


def test_the_filter_gives_the_exact_gaussian_likelihood_and_the_smoother_the_exact_conditional_mean():
    """On a random 3-state model over 40 samples, a fifth of its readings masked: the compiled filter's
    log-likelihood is the multivariate normal density of the measured readings (scipy, the model written out as one
    Gaussian), and the RTS smoother's states are the exact conditional mean E[x | y], to 1e-9."""
    rng = np.random.default_rng(7)
    model, x0, P0 = _small_model(rng)
    n = 40
    u = rng.standard_normal((n, 1))
    mx, Sx, my, Sy, Sxy = _joint(model, x0, P0, u)
    y = rng.multivariate_normal(my, Sy).reshape(n, 2)
    mask = rng.random((n, 2)) > 0.2
    f = kalman_filter(model, u, y, mask, x0, P0, keep=True)
    on = mask.ravel()
    want = multivariate_normal(my[on], Sy[np.ix_(on, on)]).logpdf(y.ravel()[on])
    assert f.loglik == pytest.approx(want, rel=1e-11)
    assert np.all(f.s[~mask] == 0) and np.all(f.s[mask] > 0)
    xs, _ = smooth(model, f)
    cond = mx + Sxy[:, on] @ np.linalg.solve(Sy[np.ix_(on, on)], y.ravel()[on] - my[on])
    np.testing.assert_allclose(xs.ravel(), cond, rtol=0, atol=1e-9 * np.abs(cond).max())


def test_the_filter_says_what_it_cannot_take():
    rng = np.random.default_rng(1)
    model, x0, P0 = _small_model(rng)
    u, y = np.zeros((5, 1)), np.zeros((5, 2))
    with pytest.raises(ValueError, match="do not match 5 samples of 2 channels"):
        kalman_filter(model, u, y[:4], np.ones((4, 2), bool), x0, P0)
    big = Discrete(A=np.eye(40), B=np.zeros((40, 1)), Q=np.eye(40), C=np.zeros((2, 40)), r=np.ones(2))
    with pytest.raises(ValueError, match="at most 32 states"):
        kalman_filter(big, u, y, np.ones((5, 2), bool), np.zeros(40), np.eye(40))
    bad = Discrete(A=model.A, B=model.B, Q=model.Q, C=model.C, r=np.array([0.0, -1.0]))
    assert math.isnan(kalman_filter(bad, u, y, np.ones((5, 2), bool), x0, 0 * P0).loglik)
    with pytest.raises(ValueError, match="not a number"):
        Record("r", TS, np.array([0.0, np.inf]), np.zeros((2, 2)), np.ones((2, 2), bool))


def _truth(plant: dict) -> dict[str, float]:
    """The plant's linear parameters as the engine names them (sensors read true)."""
    return rigmodel.combos(plant) | {
        "plant.Ks": rigmodel.plant_value(plant, "Ks"),
        "plant.zeta_link": rigmodel.plant_value(plant, "zeta_link"),
    }


def _readings(out: dict[str, np.ndarray]) -> np.ndarray:
    """The DAQ's volts as a user's calibrated degrees (the pot's and the gauge's own gains and offsets)."""
    th = (out["theta_v"] - DAQ["pot_offset"].start) * KP
    al = (out["alpha_v"] - DAQ["gauge_offset"].start) * KE
    return np.column_stack([th, al])


def test_the_stochastic_model_replays_the_plant_fmu():
    """Without noise, the sampled model's response to a chirp from rest is the plant and DAQ FMUs' readings (RK4
    inside the FMU against the matrix exponential of harness.fmu.plant's matrices): the hub within 1e-6 deg of its
    37 deg travel (measured 2.8e-7), the gauge within 2e-5 deg of its 27 deg (measured 9.5e-6)."""
    n = 2500
    t = np.arange(n) * TS
    u = 1.5 * np.sin(2 * np.pi * (0.3 + 1.5 * t) * t)
    with Rig(build_all()["flexjoint"], build_all()["daq"]) as rig:
        y = _readings(rig.run(u, TS, plant=PLANT))
    model = rig_model(PLANT, _truth(PLANT), Noise(0.0, 0.0))
    d = model.discretise(TS)
    x = np.zeros(d.A.shape[0])
    sim = np.empty((n, 2))
    for k in range(n):
        sim[k] = d.C @ x
        x = d.A @ x + d.B @ np.array([u[k], 1.0])
    assert np.ptp(y[:, 0]) > 30 and np.ptp(y[:, 1]) > 20
    np.testing.assert_allclose(sim[:, 0], y[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(sim[:, 1], y[:, 1], rtol=0, atol=2e-5)


def _twin(closed: bool, seed: int, bits: int = 0) -> Record:
    """A 5 s twin record at 500 Hz through the FMUs, 2 mV of noise on both channels, an ADC of ``bits`` over +-10 V
    (0: none): open loop, a random square command of +-0.8 V; closed loop, the closed_loop spec's state feedback on a
    +-20 deg square reference, its logged command the record's."""
    n = 2500
    rng = np.random.default_rng(seed)
    daq = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "seed": seed, "adc_bits": bits}
    fmus = build_all()
    if closed:
        t = np.arange(n) * TS
        ref = np.radians(np.where(t % 2.0 < 1.0, 20.0, -20.0))
        ctrl = Controller(K=[9.231, -18.769, 1.203, -0.041], cutoff=15.0).fmu_parameters(1 / TS)
        with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as rig:
            out = rig.run_closed(ref, TS, ctrl, plant=PLANT, daq=daq)
    else:
        u = 0.8 * np.where(np.cumsum(rng.random(n) < 0.015) % 2 == 0, 1.0, -1.0)
        with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
            out = rig.run(u, TS, plant=PLANT, daq=daq)
    y = _readings(out)
    assert np.abs(y[:, 0]).max() < 170  # the pot on its track
    lsb = 20.0 / 2**bits if bits else 0.0
    return Record("closed" if closed else "open", TS, out["u"], y, np.ones((n, 2), bool), (lsb * KP, lsb * abs(KE)))


@pytest.mark.parametrize(
    ("closed", "bits"), [(False, 0), (True, 0), (True, 8)], ids=["open_loop", "closed_loop", "closed_loop_8bit"]
)
def test_maximum_likelihood_recovers_the_twins_parameters_and_noise(closed, bits):
    """From a start 15-25 % off, the drive's gain and time constant, the inertia ratio, the link's stiffness and
    damping each within 0.5 % and inside its 99.9 % interval (3.29 standard errors; on campaign seeds 1-8 the errors
    over their standard errors, the intervals from the Fisher information, spread as a unit normal's: sd 1.02, 77 of 80
    within 1.96, 79 within 2.6, one at -3.3), nothing at a bound but a
    noise at its floor, and the innovations white (lag-one autocorrelation under 0.1, unit variance).

    Without a lattice, each reading's noise within 5 % of the DAQ's 2 mV (0.071 and 0.0067 deg) and no torque noise
    (the FMUs have none: the intensities end below 1e-6 N m sqrt(s)). Through an 8-bit ADC (a lattice of 2.8 deg on
    the hub, 0.26 deg on the gauge; the hub's noise a fortieth of its step) the readings' cells are the likelihood's:
    the hub's noise within 10 %, the gauge's at its floor (a noise far below its step is not in the data), the torques
    below 1e-4 N m sqrt(s), the residuals randomised across their cells. As
    points with a lattice's q^2 / 12 (the filter before cells, seeds 1-2) the drive gain came out 1.8 % low at 12
    standard errors, a white hub torque of 1.6e-4 N m sqrt(s) took its place, and the hub's innovations had a lag-one
    autocorrelation of 0.43-0.47."""
    rec = _twin(closed, seed=1, bits=bits)
    truth = _truth(PLANT)
    off = dict(zip(truth, (1.15, 0.85, 1.2, 0.8, 1.25), strict=True))
    start = {k: v * off[k] for k, v in truth.items()} | mlfit.noise_start([rec])
    fixed = {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0}
    res = mlfit.fit(PLANT, [rec], start, fixed=fixed, nominal=truth | mlfit.noise_start([rec]))
    assert res.converged, res.message
    for name, want in truth.items():
        e, b = res.estimates[name], mlfit.BOUNDS[name]
        se = (b.to_x(e.ci95[1], want) - b.to_x(e.ci95[0], want)) / (2 * 1.96)
        assert e.value == pytest.approx(want, rel=5e-3), name
        assert abs(b.to_x(e.value, want)) < 3.29 * se, (name, want, e)
    assert res.estimates["noise.theta"].value == pytest.approx(NOISE_V * KP, rel=0.1 if bits else 0.05)
    if not bits:
        assert res.estimates["noise.alpha"].value == pytest.approx(NOISE_V * abs(KE), rel=0.05)
    for name in mlfit.TORQUES:
        assert res.estimates[name].value < (1e-4 if bits else 1e-6), name
    assert not {k: v for k, v in res.at_bounds().items() if not (k.startswith("noise.") and v == "lower")}
    z = mlfit.filter_record(PLANT, res.values() | fixed, rec).standardised(np.array(rec.lattice))[50:]
    for j in range(2):
        assert abs(np.corrcoef(z[:-1, j], z[1:, j])[0, 1]) < 0.1
        assert np.std(z[:, j]) == pytest.approx(1.0, abs=0.1)


def test_a_reading_on_a_lattice_is_scored_by_its_cell():
    """One reading of a scalar state N(0.3, 0.5^2) plus noise of 0.1 on a lattice of step 0.4 read as 0.4: its
    log-likelihood is log P(0.2 < z < 0.6) by the normal CDF (scipy); on a lattice a thousand times finer, a record's
    log-likelihood is the Gaussian one plus n log q (the density times the cell) within 1e-4."""
    from scipy.stats import norm

    one = Discrete(A=np.eye(1), B=np.zeros((1, 1)), Q=np.zeros((1, 1)), C=np.eye(1), r=np.array([0.01]),
                   q=np.array([0.4]))  # fmt: skip
    f = kalman_filter(one, np.zeros((1, 1)), np.array([[0.4]]), np.ones((1, 1), bool), np.array([0.3]), np.eye(1) / 4)
    sd = math.sqrt(0.25 + 0.01)
    assert f.loglik == pytest.approx(math.log(norm.cdf(0.6, 0.3, sd) - norm.cdf(0.2, 0.3, sd)), rel=1e-12)
    rng = np.random.default_rng(3)
    model, x0, P0 = _small_model(rng)
    n, step = 40, 1e-3 * np.sqrt(model.r)
    u = rng.standard_normal((n, 1))
    y = np.round(rng.standard_normal((n, 2)) / step) * step
    mask = np.ones((n, 2), bool)
    plain = kalman_filter(model, u, y, mask, x0, P0).loglik
    fine = kalman_filter(Discrete(model.A, model.B, model.Q, model.C, model.r, q=step), u, y, mask, x0, P0).loglik
    assert fine == pytest.approx(plain + n * np.log(step).sum(), abs=1e-4)


def _nominal_twin(
    tmp_path, coulomb: float = 0.0, amp_limit: float = 0.0, names: tuple[str, ...] = ("prbs_b010", "square_030")
) -> tuple[Path, specmod.Spec]:
    """The nominal rig's campaign (its calibration and ``names``, by default a PRBS and a square wave, 30 s at 50 Hz;
    a multisine 40 s) logged through a 12-bit ADC with 2 mV of noise, with Coulomb friction ``coulomb`` [N m] and an
    amplifier limit ``amp_limit`` [V] (0: none), and a sheet for it that is off and has neither: Ks 1.6 for 1.3, Beq
    0.006 for 0.004, Jeq 0.0025 for 0.00208."""
    raw = specmod.load("nominal").raw
    raw["daq"] = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "adc_bits": 12}
    raw["plant"] = {**raw["plant"], "coulomb_torque": coulomb, "amp_limit": amp_limit}
    raw["experiment"] = [{**e, "duration": 40.0 if e["signal"] == "multisine" else 30.0}
                         for e in raw["experiment"] if e["name"] in names]  # fmt: skip
    real = specmod.from_dict(raw, str(specmod.resolve_path("nominal")))
    run_campaign(real, tmp_path / "real", workers=1)
    sheet = {**raw, "plant": {**raw["plant"], "Ks": 1.6, "Beq": 0.006, "Jeq": 0.0025, "coulomb_torque": 0.0,
                              "amp_limit": 0.0}}  # fmt: skip
    return tmp_path / "real", specmod.from_dict(sheet, str(specmod.resolve_path("nominal")))


def test_a_units_linear_model_is_fitted_from_an_off_sheet_with_nothing_at_a_bound(tmp_path):
    """The nominal twin's two records (3000 readings each on a 12-bit lattice) fitted from a sheet 15-50 % off
    (:func:`_nominal_twin`), the priors the sheet's uncertainty: the drive's gain and time constant, the inertia
    ratio, the link's stiffness and damping within 1 % of the rig's and inside 3.29 standard errors, the sensors'
    gains within 0.5 % of 1, the torques' noise at its floor, nothing at a bound, no finding, no missing force,
    residuals white (lag-one autocorrelation within +-0.1, Ljung-Box at 1 % on every record and channel)."""
    run, sheet = _nominal_twin(tmp_path)
    unit = fit_run(run, sheet)
    assert unit.fit.converged, unit.fit.message
    assert not unit.findings
    truth = _truth({"n_modes": 1})
    for name, want in truth.items():
        e, b = unit.fit.estimates[name], mlfit.BOUNDS[name]
        se = (b.to_x(e.ci95[1], want) - b.to_x(e.ci95[0], want)) / (2 * 1.96)
        assert e.value == pytest.approx(want, rel=0.01), name
        assert abs(b.to_x(e.value, want)) < 3.29 * se, (name, want, e)
    for name in ("sensor.theta_gain", "sensor.alpha_gauge_gain"):
        assert unit.fit.estimates[name].value == pytest.approx(1.0, abs=5e-3)
    assert not {k: v for k, v in unit.fit.at_bounds().items() if not (k.startswith("noise.") and v == "lower")}
    assert all(abs(r) < 0.1 for chans in unit.lag_one.values() for r in chans.values()), unit.lag_one
    assert all(p >= 0.01 for chans in unit.whiteness.values() for p in chans.values()), unit.whiteness
    assert unit.missing_force.shape == "none"
    effects = {x.name: x for x in unit.effects}  # none enters (measured: friction 0 at its bound, LR -0.002; the
    friction, limit = effects["coulomb_friction"], effects["saturation"]  # limit at its null)
    assert not effects["second_mode"].test.enters and not effects["delay"].test.enters and unit.structure == ()
    assert friction.fit.estimates["plant.coulomb_torque"].value < 1e-3 and not friction.test.enters, friction
    assert limit.fit.estimates["plant.amp_limit"].at == "lower" and not limit.test.enters, limit
    play = effects["backlash"]
    assert play.fit.estimates["plant.backlash"].value < 2e-5 and not play.test.enters, play
    lines = unit.summary()
    assert "  nothing at a bound: effects may be tried" in lines and "  missing force: none" in lines
    assert not any(x.startswith("  not white at: ") for x in lines)  # no band, no stretch flagged
    doc = json.loads(write_likelihood(tmp_path, unit).read_text())["where"]
    assert set(doc) == set(unit.records) and {"bands", "windows"} <= set(doc[unit.records[0]]["alpha"])
    assert unit.drawn_without is None and unit.curve is None
    assert len(lines) <= 16 and max(map(len, lines)) <= 100  # a line per effect tried


def test_a_units_friction_is_fitted_as_a_nested_model_from_its_linear_fit(tmp_path):
    """The nominal twin with Coulomb friction of 0.03 N m, its sheet off and without friction: the linear fit
    finds nothing at a bound (its drive's gain 16 % low, the inertia ratio 7 % low, the residuals of two of four
    channels not white), and the friction fitted from it comes back within 2 % (measured 0.02996; its command in
    volts too), the linear parameters refitted beside it within 2 % of the rig's (the link's damping -1.3 %, the
    others within 0.2 %), its likelihood-ratio statistic over the linear model in the thousands (measured 10 603);
    likelihood.json and the summary hold it."""
    from harness.fmu.plant import PlantParams, motor_constants

    run, sheet = _nominal_twin(tmp_path, coulomb=0.03)
    unit = fit_run(run, sheet)
    assert not unit.findings
    friction = next(x for x in unit.effects if x.name == "coulomb_friction")
    e = friction.fit.estimates["plant.coulomb_torque"]
    assert e.value == pytest.approx(0.03, rel=0.02) and e.ci95[0] < e.value < e.ci95[1]
    assert friction.lr > 1000 and friction.test.enters and friction.fit.converged
    G, _ = motor_constants(PlantParams(n_modes=1))
    assert e.value / friction.drive == pytest.approx(0.03 / G, rel=0.02)
    for name, want in _truth({"n_modes": 1}).items():
        assert friction.fit.estimates[name].value == pytest.approx(want, rel=0.02), name
    doc = json.loads(write_likelihood(tmp_path, unit).read_text())["effects"]["coulomb_friction"]

    def doc_all(path):
        return json.loads((path / "likelihood.json").read_text())

    assert doc["parameters"]["plant.coulomb_torque"]["fitted"] == e.value
    assert doc["likelihood"]["lr"] == friction.lr and doc["likelihood"]["k"] == friction.fit.k
    assert doc["likelihood"]["enters"] and doc["likelihood"]["critical"] >= 5.41 and doc["likelihood"]["p"] < 1e-9
    assert unit.drawn_without == "coulomb_friction" and unit.missing_force.shape == "friction"
    mf = unit.missing_force  # sized by the nested friction; the force drawn without it reads 0.0297 (measured)
    assert mf.sized_by == "coulomb_friction" and mf.size == e.value and mf.dead_band_v == e.value / friction.drive
    assert mf.picture_size == pytest.approx(0.03, rel=0.05)
    assert unit.curve is not None and unit.curve.x == "speed" and max(unit.curve.ys) == e.value
    assert doc_all(tmp_path)["missing_force"]["drawn_without"] == "coulomb_friction"
    line = next(x for x in unit.summary() if x.startswith("  coulomb_friction"))
    assert f"{e.value:.4g} N m = {e.value / friction.drive:.3g} V" in line and len(line) <= 100
    grey = {f"record_{i:02d}": {"theta": 0.0, "alpha": 0.0} for i in range(30)}
    long = dataclasses.replace(unit, findings=("the spec's hub and drive (motor, gear) " * 4,) * 7, whiteness=grey,
                               records=tuple(grey))  # fmt: skip
    lines = long.summary()
    assert max(map(len, lines)) <= 100 and sum(x.startswith("  finding: ") for x in lines) == 5, lines
    assert any(x.startswith("  residuals white (Ljung-Box, 0.01): 0 of 60 record channels; not: ") for x in lines)


def test_diagnose_says_which_engines_it_knows():
    """A misspelt --engine: a usage error naming the two engines, exit 2, before anything loads."""
    r = subprocess.run([sys.executable, "-m", "harness.cli", "diagnose", "--real", ".", "--engine", "kalman"],
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 2 and "--engine 'kalman': replay or likelihood" in r.stderr, r.stderr


@pytest.mark.parametrize(
    ("n", "flat", "says"),
    [(100, False, "record rec: 100 readings, too short for the filter to settle"),
     (1000, True, "the gauge readings (alpha) have no third differences on any record")],
    ids=["too_short", "noise_undetermined"],
)  # fmt: skip
def test_diagnose_refuses_records_the_likelihood_engine_cannot_fit(tmp_path, n, flat, says):
    """A record of 100 samples at 50 Hz (the shortest the import takes; the filter settles after a few, the whiteness
    test needs 100 more), or a gauge channel that never changes: one line that says which, exit 2, no
    diagnosis.json."""
    from harness.ident.calibration import Calibration
    from harness.rig.records import ImportOptions, import_records

    rng = np.random.default_rng(1)
    t = np.arange(n) / 50.0
    u = np.where(np.sin(2 * np.pi * 0.5 * t) >= 0, 1.0, -1.0)
    theta = 20.0 * np.sin(2 * np.pi * 0.4 * t) + rng.normal(0, 0.05, n)
    alpha = np.zeros(n) if flat else rng.normal(0, 0.05, n)
    path = tmp_path / "rec.csv"
    pd.DataFrame({"t": t, "u": u, "theta_deg": theta, "alpha_deg": alpha}).to_csv(path, index=False)
    import_records([path], tmp_path / "run", ImportOptions(calibration=Calibration(Kp=KP, Ke=KE)))
    args = ["diagnose", "--real", str(tmp_path / "run"), "--engine", "likelihood", "--out", str(tmp_path / "out")]
    r = subprocess.run([sys.executable, "-m", "harness.cli", *args], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and says in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "out" / "diagnosis.json").exists()


@pytest.mark.parametrize("coulomb", [0.03, 0.0], ids=["coulomb_0.03", "friction_free"])
def test_the_missing_force_draws_friction_against_the_hubs_speed(coulomb):
    """A twin under a +-1 V square command (10 s at 500 Hz, 2 mV of noise) with Coulomb friction of 0.03 N m that the
    model lacks, the rig's linear parameters given: the smoothed missing force is the friction, -0.03 N m while the
    hub turns forward and +0.03 backward (its median within 5 %; measured 0.2 %), and the records want it (a
    random walk's intensity above zero, a log-likelihood gain). On the same twin without friction: no force (an
    intensity of zero, the force under 1e-4 N m). The classifier names them friction, its size and its dead band in
    volts within 5 %, and none; some samples, under a tenth, lie at rest."""
    from harness.fmu.plant import PlantParams, motor_constants
    from harness.likelihood.force import classify, force_picture

    n = 5000
    u = np.where(np.arange(n) * TS % 2.0 < 1.0, 1.0, -1.0)
    with Rig(build_all()["flexjoint"], build_all()["daq"]) as rig:
        out = rig.run(u, TS, plant={**PLANT, "coulomb_torque": coulomb}, daq={"noise_theta": NOISE_V,
                      "noise_alpha": NOISE_V, "seed": 1})  # fmt: skip
    rec = Record("square", TS, u, _readings(out), np.ones((n, 2), bool))
    values = _truth(PLANT) | {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0, "noise.theta": NOISE_V * KP,
                              "noise.alpha": NOISE_V * abs(KE)}  # fmt: skip
    pic = force_picture(PLANT, values, [rec])
    tr = pic.traces[0]
    forward, backward = np.median(tr.force[tr.speed > 20.0]), np.median(tr.force[tr.speed < -20.0])
    named = classify(pic)
    if coulomb:
        assert pic.intensity > 0 and pic.gain > 100
        assert forward == pytest.approx(-coulomb, rel=0.05) and backward == pytest.approx(coulomb, rel=0.05)
        assert named.shape == "friction" and named.size == pytest.approx(coulomb, rel=0.05)
        G, _ = motor_constants(PlantParams(**PLANT))
        assert named.dead_band_v == pytest.approx(coulomb / G, rel=0.05)
    else:
        assert pic.intensity == 0 and pic.gain == 0
        assert np.abs(tr.force).max() < 1e-4
        assert named.shape == "none" and named.size == 0
    assert 0 < named.samples_near_zero < n // 10


def _white_share(bits: int, seeds: range) -> tuple[int, int]:
    """Of closed-loop twins through a ``bits`` ADC (``seeds``), filtered at their true parameters: how many have
    both channels' residuals white by Ljung-Box at 1 % with the readings' cells, and how many with the lattice taken
    as points of q^2 / 12 more noise."""
    cells = points = 0
    truth = _truth(PLANT) | {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0, "noise.theta": NOISE_V * KP,
                             "noise.alpha": NOISE_V * abs(KE)}  # fmt: skip
    for seed in seeds:
        rec = _twin(True, seed, bits)
        z = mlfit.filter_record(PLANT, truth, rec).standardised(np.array(rec.lattice))[50:]
        cells += all(ljung_box(z[:, j]).white for j in range(2))
        flat = Record(rec.name, rec.Ts, rec.u, rec.y, rec.mask)
        wider = {f"noise.{c}": math.hypot(truth[f"noise.{c}"], q / math.sqrt(12.0))
                 for c, q in zip(("theta", "alpha"), rec.lattice, strict=True)}  # fmt: skip
        z = mlfit.filter_record(PLANT, truth | wider, flat).standardised()[50:]
        points += all(ljung_box(z[:, j]).white for j in range(2))
    return cells, points


def test_a_quantised_twins_residuals_are_white_with_its_cells_and_not_as_points():
    """Ten closed-loop twins through a 10-bit ADC (the hub's lattice 0.69 deg, ten times its noise), filtered at
    their true parameters: with the readings' cells the residuals pass Ljung-Box (20 lags, 1 %) on at least 9 of 10
    (measured 10); with the lattice as points of q^2 / 12 on none (measured 0)."""
    cells, points = _white_share(10, range(1, 11))
    assert cells >= 9 and points == 0


@pytest.mark.open(
    reason=(
        "issue 63 open: through an 8-bit ADC (the hub's lattice 2.8 deg, forty times its noise) 7 of 10 twins are "
        "white with cells (as points: 0); on the other three the residuals blow up after a reference step (up to 37 "
        "sd on the gauge): at rest the moment-matched cells shrink the state's variance where the true posterior is "
        "a cell's width"
    ),
)
def test_an_8bit_twins_residuals_are_white_with_its_cells():
    cells, _ = _white_share(8, range(1, 11))
    assert cells >= 9


def test_ljung_box_holds_its_level_on_white_noise_and_rejects_an_ar1():
    """On 400 series of 1000 independent normals (a tenth of them masked at random) the test rejects at 1 % on 0-12
    of them (measured 3; on 3000 series 1.13 %, unmasked 0.93 %); on an AR(1) of coefficient 0.2 it rejects every
    one of 50."""
    rng = np.random.default_rng(11)
    z = rng.standard_normal((400, 1000))
    z[rng.random(z.shape) < 0.1] = np.nan
    assert sum(not ljung_box(s).white for s in z) <= 12
    e = rng.standard_normal((50, 1000))
    ar = np.zeros_like(e)
    for k in range(1, 1000):
        ar[:, k] = 0.2 * ar[:, k - 1] + e[:, k]
    assert not any(ljung_box(s).white for s in ar)
    with pytest.raises(ValueError, match="too few"):
        ljung_box(np.ones(10))


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_a_units_amplifier_limit_is_fitted_as_a_nested_model_from_its_linear_fit(tmp_path):
    """The nominal twin under a square wave of 1.5 V and a multisine through an amplifier that clips at 1.2 V, its
    sheet off and without a limit: the limit nested on the linear fit comes back within 2 % (measured 1.2004 V), the
    linear parameters beside it within 2 % (measured 0.07 %), its likelihood-ratio statistic over the linear model
    large (18 506); the friction nested on the same fit stays at none (LR 0). Under the PRBS and the square alone
    (commands of two levels, where a limit is a gain) it was fitted at its null, the drive's gain 20 % low. The
    searches' trials far off (an exponential that overflows) warn nobody: their likelihood is NaN."""
    run, sheet = _nominal_twin(tmp_path, amp_limit=1.2, names=("square_030", "multisine"))
    unit = fit_run(run, sheet)
    assert not unit.findings
    effects = {x.name: x for x in unit.effects}
    friction, limit = effects["coulomb_friction"], effects["saturation"]
    e = limit.fit.estimates["plant.amp_limit"]
    assert e.value == pytest.approx(1.2, rel=0.02) and limit.lr > 100 and limit.test.enters
    for name, want in _truth({"n_modes": 1}).items():
        assert limit.fit.estimates[name].value == pytest.approx(want, rel=0.02), name
    assert friction.fit.estimates["plant.coulomb_torque"].value < 1e-3 and not friction.test.enters
    assert unit.drawn_without == "saturation" and unit.curve is not None and unit.curve.x == "u"


def test_a_gauge_read_late_is_put_back_in_time():
    """The DAQ's gauge reading 10 samples (20 ms) late on the open-loop twin: with its readings put back in time
    (Record.gauge_late) the linear parameters come back as on time (within 0.5 %, 3.29 standard errors), and the
    fit gains on the record read as logged (measured: 3 857 nats; as logged the link's stiffness 19 % low, the
    inertia ratio 14 % low and its damping 16 times the rig's)."""
    n, late = 2500, 10
    rng = np.random.default_rng(3)
    u = 0.8 * np.where(np.cumsum(rng.random(n) < 0.015) % 2 == 0, 1.0, -1.0)
    daq = {"noise_theta": NOISE_V, "noise_alpha": NOISE_V, "seed": 3, "gauge_delay": late}
    with Rig(build_all()["flexjoint"], build_all()["daq"]) as rig:
        out = rig.run(u, TS, plant=PLANT, daq=daq)
    logged = Record("late", TS, out["u"], _readings(out), np.ones((n, 2), bool))
    back = logged.gauge_late(late)
    assert np.array_equal(back.y[: n - late, 1], logged.y[late:, 1]) and not back.mask[n - late :, 1].any()
    truth = _truth(PLANT)
    start = {k: 1.1 * v for k, v in truth.items()} | mlfit.noise_start([logged])
    fixed = {"sensor.theta_gain": 1.0, "sensor.alpha_gauge_gain": 1.0}
    fits = [mlfit.fit(PLANT, [r], start, fixed=fixed, nominal=truth | mlfit.noise_start([r])) for r in (back, logged)]
    for name, want in truth.items():
        e, b = fits[0].estimates[name], mlfit.BOUNDS[name]
        se = (b.to_x(e.ci95[1], want) - b.to_x(e.ci95[0], want)) / (2 * 1.96)
        assert e.value == pytest.approx(want, rel=5e-3), name
        assert abs(b.to_x(e.value, want)) < 3.29 * se, (name, want, e)
    assert fits[0].loglik - fits[1].loglik > 100
