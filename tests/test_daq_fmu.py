"""The daq FMU (sensors, converters, noise, sample-and-hold) against the formulas of fmus/daq/readme.md."""

from __future__ import annotations

import numpy as np
import pytest
from fmpy.fmi1 import FMICallException
from scipy.signal import lfilter

KP, KE = 35.5145, -3.3636  # deg/V, lab 1's calibration
OUT = ["u_plant", "theta_v", "alpha_v"]


def pot_volts(deg: np.ndarray, kp: float = KP, deadband: float = 8.0, offset: float = 0.0) -> np.ndarray:
    """The potentiometer: wrap to [-180, 180), dead band holds the track end."""
    w = np.mod(np.asarray(deg) + 180.0, 360.0) - 180.0
    edge = 180.0 - deadband / 2
    return np.where(np.abs(w) > edge, np.sign(w) * edge, w) / kp + offset


def test_pot_wrap_and_dead_band(fmu_runner):
    deg = np.linspace(150.0, 210.0, 61)  # 1 deg per sample through +180
    res = fmu_runner["daq"].run(None, {"theta": np.radians(deg)}, OUT, 0.02, len(deg))
    v = res["theta_v"]
    np.testing.assert_allclose(v, pot_volts(deg), atol=1e-12)
    assert v[deg == 170.0][0] == pytest.approx(170 / KP, rel=1e-12)
    dead = (deg > 176.0) & (deg < 184.0)
    np.testing.assert_allclose(v[dead & (deg < 180)], 176 / KP, rtol=1e-12)  # wiper off the track: held
    np.testing.assert_allclose(v[dead & (deg >= 180)], -176 / KP, rtol=1e-12)
    jumps = np.flatnonzero(np.diff(v) < -1.0)
    assert len(jumps) == 1 and deg[jumps[0] + 1] == 180.0  # one jump from + to - at the wrap
    assert v[jumps[0]] == pytest.approx(4.9557, abs=1e-4) and v[jumps[0] + 1] == pytest.approx(-4.9557, abs=1e-4)
    # several turns and negative angles wrap the same way; offset adds everywhere
    deg2 = np.array([-725.0, -190.0, -179.0, 0.0, 359.0, 539.0])
    res = fmu_runner["daq"].run({"pot_offset": 0.1}, {"theta": np.radians(deg2)}, OUT, 0.02, len(deg2))
    np.testing.assert_allclose(res["theta_v"], pot_volts(deg2, offset=0.1), atol=1e-12)


def test_pot_linearity_error_and_gauge_gain_drift(fmu_runner):
    """The out-of-library sensor errors, inside the DAQ so that a controller reads them: the pot's bow is
    pot_bow x 180 deg sin(pi w / 180) on the track (0 at the centre and the ends, largest at +-90 deg); the gauge's
    reading about its offset grows by gauge_drift x t. Off (0) they leave the readings bit for bit."""
    n, Ts = 200, 0.02
    deg = np.linspace(-170.0, 170.0, n)
    alpha = 2.0 * np.sin(np.linspace(0.0, 6.0, n))
    t = np.arange(n) * Ts
    inputs = {"theta": np.radians(deg), "alpha_gauge": np.radians(alpha)}
    off = fmu_runner["daq"].run({"gauge_offset": 0.2}, inputs, OUT, Ts, n)
    on = fmu_runner["daq"].run({"gauge_offset": 0.2, "pot_bow": 0.015, "gauge_drift": 0.05}, inputs, OUT, Ts, n)
    bowed = deg + 0.015 * 180.0 * np.sin(np.pi * deg / 180.0)
    np.testing.assert_allclose(on["theta_v"], bowed / KP, rtol=0, atol=1e-12)
    assert np.max(np.abs(on["theta_v"] - off["theta_v"])) * KP == pytest.approx(2.7, abs=0.01)  # 1.5 % of 180 deg
    np.testing.assert_allclose(on["alpha_v"], 0.2 + (off["alpha_v"] - 0.2) * (1.0 + 0.05 * t), rtol=0, atol=1e-12)
    np.testing.assert_allclose(off["theta_v"], pot_volts(deg), rtol=0, atol=1e-12)  # off: the pot as it was
    zero = fmu_runner["daq"].run({"gauge_offset": 0.2, "pot_bow": 0.0, "gauge_drift": 0.0}, inputs, OUT, Ts, n)
    for c in OUT:
        np.testing.assert_array_equal(zero[c], off[c])


def test_adc_and_dac_quantisation_steps_equal_the_lsb(fmu_runner):
    n = 400
    deg = np.linspace(-20.0, 20.0, n)
    u = np.linspace(-3.0, 3.0, n)
    res = fmu_runner["daq"].run({"adc_bits": 12, "dac_bits": 8}, {"theta": np.radians(deg), "u": u}, OUT, 0.02, n)
    adc_lsb, dac_lsb = 20.0 / 4096, 20.0 / 256
    v = res["theta_v"]
    np.testing.assert_allclose(v / adc_lsb, np.round(v / adc_lsb), atol=1e-9)  # on the LSB grid
    steps = np.diff(np.unique(v))
    np.testing.assert_allclose(steps, adc_lsb, rtol=1e-9)  # a slow ramp visits every code
    assert np.abs(v - pot_volts(deg)).max() <= adc_lsb / 2 + 1e-12
    up = res["u_plant"]
    np.testing.assert_allclose(np.diff(np.unique(up)), dac_lsb, rtol=1e-9)
    assert np.abs(up - u).max() <= dac_lsb / 2 + 1e-12


def test_clamps(fmu_runner):
    u = np.array([-12.0, -7.0, 3.0, 7.0, 12.0])
    res = fmu_runner["daq"].run({"out_limit": 5.0}, {"u": u}, OUT, 0.02, len(u))
    np.testing.assert_array_equal(res["u_plant"], [-5.0, -5.0, 3.0, 5.0, 5.0])
    res = fmu_runner["daq"].run(None, {"u": u}, OUT, 0.02, len(u))
    np.testing.assert_array_equal(res["u_plant"], [-10.0, -7.0, 3.0, 7.0, 10.0])
    # the ADC clamps to its range
    res = fmu_runner["daq"].run({"adc_bits": 16, "pot_offset": 8.0}, {"theta": np.radians(150.0)}, OUT, 0.02, 2)
    assert res["theta_v"][-1] == 10.0


def test_delay_in_samples(fmu_runner):
    """u_plant after doStep(t, h) is the command over [t + h, ...): with delay_samples = d the command of d samples
    before the sample holding t + h (zeros before the first), the command of a sample being the last u set within
    it. So at h = Ts the command set at t_k reaches the plant over [t_k+d, t_k+d+1)."""
    rng = np.random.default_rng(3)
    u = rng.uniform(-5, 5, 50)
    res = fmu_runner["daq"].run({"delay_samples": 1}, {"u": u}, OUT, 0.02, len(u))
    assert res["init"]["u_plant"] == 0.0
    np.testing.assert_array_equal(res["u_plant"], u)  # after the step at t_k: u_k, for [t_k+1, t_k+2)
    res = fmu_runner["daq"].run({"delay_samples": 2}, {"u": u}, OUT, 0.02, len(u))
    assert res["u_plant"][0] == 0.0
    np.testing.assert_array_equal(res["u_plant"][1:], u[:-1])
    # delay counts samples, not communication steps; at Ts/4 a sample's command is the u set in its last quarter
    uq = rng.uniform(-5, 5, 200)  # a new value at every communication step
    res = fmu_runner["daq"].run({"delay_samples": 3}, {"u": uq}, OUT, 0.005, len(uq))
    k_end = np.arange(1, uq.size + 1) // 4  # the sample holding t + h after step j
    want = np.where(k_end >= 3, uq[np.clip(4 * (k_end - 3) + 3, 0, None)], 0.0)
    np.testing.assert_array_equal(res["u_plant"], want)
    assert np.all(res["u_plant"][:11] == 0.0) and res["u_plant"][11] == uq[3]  # from t_3 = 12 steps on


@pytest.mark.parametrize("model", ["daq", "controller"])
def test_a_step_between_sample_instants_is_an_error(fmu_runner, model):
    """Every sample instant must be a communication point: 0.015 s at 50 Hz is refused with the rates in the
    message; whole fractions and multiples of the period run."""
    inputs, out = ({"theta": 0.1}, ["theta_v"]) if model == "daq" else ({"ref": 0.1}, ["u"])
    with pytest.raises(FMICallException):
        fmu_runner[model].run({"sample_rate": 50.0}, inputs, out, 0.015, 3)
    assert "communication step 0.015 s does not fit sample_rate = 50 Hz" in fmu_runner[model].messages[-1]
    for h in (0.02, 0.005, 0.02 / 3, 0.04):
        fmu_runner[model].run({"sample_rate": 50.0}, inputs, out, h, 3)


def test_sample_and_hold_with_comm_step_quarter_period(fmu_runner):
    n = 200
    t = np.arange(n) * 0.005
    deg = 30 * np.sin(2 * np.pi * 1.3 * t)  # changes at every communication step
    alpha = np.radians(2 * np.cos(2 * np.pi * 0.7 * t))
    u = np.sin(2 * np.pi * 0.9 * t)
    res = fmu_runner["daq"].run(None, {"u": u, "theta": np.radians(deg), "alpha_gauge": alpha}, OUT, 0.005, n)
    held = np.repeat(np.arange(0, n, 4), 4)  # index of the last sample instant k / 50 Hz at or before t
    np.testing.assert_allclose(res["theta_v"], pot_volts(deg[held]), atol=1e-12)
    np.testing.assert_allclose(res["alpha_v"], np.degrees(alpha[held]) / KE, atol=1e-12)
    np.testing.assert_array_equal(res["u_plant"], u)  # without delay the DAC writes u as soon as it is set
    # ExitInitializationMode outputs the sample of the initial inputs
    assert res["init"]["theta_v"] == pytest.approx(pot_volts(deg[0]), abs=1e-12)
    assert res["init"]["alpha_v"] == pytest.approx(np.degrees(alpha[0]) / KE, abs=1e-12)
    assert res["init"]["u_plant"] == u[0]


def test_gauge_gain_offset_and_cubic(fmu_runner):
    deg = np.array([-10.0, -5.0, 0.0, 3.0, 10.0])
    res = fmu_runner["daq"].run(
        {"gauge_cubic": 0.05, "gauge_offset": 0.2}, {"alpha_gauge": np.radians(deg)}, OUT, 0.02, len(deg)
    )
    bridge = deg / KE  # the bridge's reading; its zero error (0.2 V) is electrical, outside the nonlinearity
    np.testing.assert_allclose(res["alpha_v"], 0.2 + bridge * (1 + 0.05 * (deg / 10) ** 2), rtol=1e-12)
    assert (res["alpha_v"][-1] - 0.2) / bridge[-1] - 1 == pytest.approx(0.05, rel=1e-9)  # 5 % at 10 deg
    assert res["alpha_v"][2] == pytest.approx(0.2, rel=1e-12)


def test_gauge_low_pass_is_a_first_order_lag_taken_at_the_samples(fmu_runner):
    """The gauge amplifier's low-pass (gauge_tau) against scipy's filter of the sampled readings, at a communication
    step of a quarter sample (one filter step per sample, not per call), and its gain and phase at 1.5 Hz against
    those of the analog RC filter 1 / (1 + j w tau) (its lag less half a sample: each sample's reading enters at
    once)."""
    fs, tau, n = 200.0, 0.05, 1600
    t = np.arange(n) / (4 * fs)
    deg = 3.0 + 5.0 * np.sin(2 * np.pi * 1.5 * t)
    res = fmu_runner["daq"].run(
        {"sample_rate": fs, "gauge_tau": tau}, {"alpha_gauge": np.radians(deg)}, OUT, 0.25 / fs, n
    )
    v = deg[::4] / KE  # the samples' readings without the filter
    c = np.exp(-1.0 / (fs * tau))
    y, _ = lfilter([1 - c], [1, -c], v, zi=[c * v[0]])  # starts in steady state at the first sample
    np.testing.assert_allclose(res["alpha_v"], np.repeat(y, 4), rtol=0, atol=1e-12)
    assert res["init"]["alpha_v"] == pytest.approx(v[0], abs=1e-12)
    w, k = 2 * np.pi * 1.5, np.arange(n // 8, n // 4)  # the second half: the start has died out (8 tau)
    ts = k / fs
    basis = np.column_stack([np.sin(w * ts), np.cos(w * ts), np.ones(k.size)])
    a, b, _ = np.linalg.lstsq(basis, y[k] - 3.0 / KE, rcond=None)[0]
    gain, phase = np.hypot(a, b) / abs(5.0 / KE), np.arctan2(b, a) - (np.pi if KE < 0 else 0.0)
    assert gain == pytest.approx(1 / np.hypot(1, w * tau), rel=5e-3)
    phase = (phase + np.pi) % (2 * np.pi) - np.pi
    assert -phase == pytest.approx(np.arctan(w * tau) - w / (2 * fs), abs=1e-3)  # the sample's own reading enters


def test_gauge_delay_reads_the_gauge_whole_samples_late(fmu_runner):
    """gauge_delay = d: the reading of sample k is the gauge's of sample k - d (the first sample's before it), at a
    communication step of a third of a sample; with the low-pass too, the lagged readings delayed; theta on time.
    0 leaves the readings bit for bit."""
    fs, d, n = 100.0, 7, 300
    t = np.arange(n) / (3 * fs)
    deg = 2.0 + 4.0 * np.sin(2 * np.pi * 1.3 * t)
    inputs = {"alpha_gauge": np.radians(deg), "theta": np.radians(deg)}
    run = fmu_runner["daq"].run
    base = run({"sample_rate": fs}, inputs, OUT, 1 / (3 * fs), n)
    late = run({"sample_rate": fs, "gauge_delay": d}, inputs, OUT, 1 / (3 * fs), n)
    v = base["alpha_v"][::3]
    np.testing.assert_array_equal(late["alpha_v"][::3], np.concatenate([np.full(d, v[0]), v[:-d]]))
    np.testing.assert_array_equal(late["theta_v"], base["theta_v"])
    assert late["init"]["alpha_v"] == base["init"]["alpha_v"]
    lag = run({"sample_rate": fs, "gauge_tau": 0.05}, inputs, OUT, 1 / (3 * fs), n)["alpha_v"][::3]
    both = run({"sample_rate": fs, "gauge_tau": 0.05, "gauge_delay": d}, inputs, OUT, 1 / (3 * fs), n)
    np.testing.assert_array_equal(both["alpha_v"][::3], np.concatenate([np.full(d, lag[0]), lag[:-d]]))
    zero = run({"sample_rate": fs, "gauge_delay": 0}, inputs, OUT, 1 / (3 * fs), n)
    np.testing.assert_array_equal(zero["alpha_v"], base["alpha_v"])


def test_seeded_noise(fmu_runner):
    n = 4000
    run = fmu_runner["daq"].run
    params = {"noise_theta": 0.01, "noise_alpha": 0.02, "seed": 5}
    a = run(params, {"theta": 0.1, "alpha_gauge": 0.0}, OUT, 0.02, n)
    b = run(params, {"theta": 0.1, "alpha_gauge": 0.0}, OUT, 0.02, n)
    c = run({**params, "seed": 6}, {"theta": 0.1, "alpha_gauge": 0.0}, OUT, 0.02, n)
    assert a["theta_v"].tobytes() == b["theta_v"].tobytes()
    assert a["alpha_v"].tobytes() == b["alpha_v"].tobytes()
    assert not np.any(a["theta_v"] == c["theta_v"])
    e_t = a["theta_v"] - pot_volts(np.degrees(0.1))
    e_a = a["alpha_v"]
    assert np.std(e_t) == pytest.approx(0.01, rel=0.05)
    assert np.std(e_a) == pytest.approx(0.02, rel=0.05)
    assert abs(np.mean(e_t)) < 4 * 0.01 / np.sqrt(n)
    assert np.mean(np.abs(e_t) < 0.01) == pytest.approx(0.6827, abs=0.03)  # Gaussian
    assert abs(np.corrcoef(e_t, e_a)[0, 1]) < 0.06  # two independent streams
    assert abs(np.corrcoef(e_t[1:], e_t[:-1])[0, 1]) < 0.06  # white
    # the noise of sample k does not depend on the communication step
    q = run(params, {"theta": 0.1, "alpha_gauge": 0.0}, OUT, 0.005, 400)
    np.testing.assert_array_equal(q["theta_v"][::4], a["theta_v"][:100])


def test_an_instance_draws_each_seed_s_noise_as_a_fresh_one_whatever_it_ran_before(fmus):
    """The DAQ keeps each stream's deviates across fmi2Reset (a fit replays the same draws): one instance that has
    run more seeds than it keeps, and a seed's record longer than it kept before, reads the bytes fresh
    instances read."""
    from harness.fmu.cosim import Rig

    u = 0.3 * np.sin(np.arange(9000) * 0.01)
    noise = {"noise_theta": 0.01, "noise_alpha": 0.02}

    def fresh(seed: int, n: int) -> np.ndarray:
        with Rig(fmus["flexjoint"], fmus["daq"]) as rig:
            r = rig.run(u[:n], 0.001, daq={**noise, "seed": seed})
        return np.stack([r["theta_v"], r["alpha_v"]])

    expected = {(s, n): fresh(s, n) for s, n in ((0, 3000), (0, 9000), (7, 9000))}
    with Rig(fmus["flexjoint"], fmus["daq"]) as rig:

        def reused(seed: int, n: int) -> np.ndarray:
            r = rig.run(u[:n], 0.001, daq={**noise, "seed": seed})
            return np.stack([r["theta_v"], r["alpha_v"]])

        assert reused(0, 3000).tobytes() == expected[(0, 3000)].tobytes()
        assert reused(0, 9000).tobytes() == expected[(0, 9000)].tobytes()  # longer than it kept
        for seed in range(1, 20):  # more streams than it keeps: seed 0's tables are taken by others
            reused(seed, 2000)
        assert reused(0, 9000).tobytes() == expected[(0, 9000)].tobytes()
        assert reused(7, 9000).tobytes() == expected[(7, 9000)].tobytes()
    assert expected[(0, 9000)][:, :3000].tobytes() == expected[(0, 3000)].tobytes()


def test_parameters_set_again_by_the_same_names_take_the_new_values(fmus):
    """An instance keeps how it sets a tuple of parameter names (their types and value references) for the next call
    with the same names: each call sets its own values, in any order of the names, Integer and Real alike, and a
    name the FMU does not have is one line listing those it has."""
    from harness.fmu.binding import FMUError, load

    daq = load(fmus["daq"])
    try:
        for values in ({"adc_bits": 12, "noise_theta": 0.1}, {"adc_bits": 10, "noise_theta": 0.2},
                       {"noise_theta": 0.3, "adc_bits": 8}, {"adc_bits": 10, "noise_theta": 0.2}):  # fmt: skip
            daq.reset()
            daq.set_parameters(values)
            assert daq.get(list(values)) == values
        with pytest.raises(FMUError, match="unknown parameter 'adc_bit'; valid: adc_bits, adc_range, dac_bits"):
            daq.set_parameters({"adc_bits": 12, "adc_bit": 1})
    finally:
        daq.free()


@pytest.mark.parametrize(
    "params, name",
    [
        ({"sample_rate": 0.0}, "sample_rate"),
        ({"delay_samples": -1}, "delay_samples"),
        ({"adc_bits": -2}, "adc_bits"),
        ({"pot_deadband": 400.0}, "pot_deadband"),
        ({"noise_theta": -0.1}, "noise_theta"),
        ({"gauge_gain": float("inf")}, "gauge_gain"),
        ({"gauge_tau": -0.01}, "gauge_tau"),
        ({"gauge_delay": -3}, "gauge_delay"),
    ],
)
def test_invalid_parameter_is_an_fmi_error(fmu_runner, params, name):
    run = fmu_runner["daq"]
    run.messages.clear()
    with pytest.raises(FMICallException, match="fmi2ExitInitializationMode"):
        run.run(params, {"u": 0.0}, OUT, 0.02, 1)
    assert any(f"parameter {name} " in m for m in run.messages), run.messages


def test_comb_static_tip_torque_through_the_twin(fmu_runner):
    """Plant (hub clamped) + DAQ coupled as the master does: gauge reads the static deflection."""
    from harness.fmu.plant import PlantParams, mass_stiffness

    tau, h, n = 0.01, 0.02, 200
    plant_par = {"n_modes": 2, "hub_locked": 1, "zeta_link": 0.7}
    K = mass_stiffness(PlantParams(**plant_par))[1]
    static = tau * np.sum(1 / np.diag(K)[1:])  # a_i = tau / k_i
    with (
        fmu_runner["flexjoint"].instance(plant_par, {"tau_tip": tau}) as plant,
        fmu_runner["daq"].instance({"adc_bits": 16}) as daq,
    ):
        for k in range(n):
            theta, alpha_gauge = plant.get("theta", "alpha_gauge")
            daq.set(u=0.0, theta=theta, alpha_gauge=alpha_gauge)
            daq.step(k * h, h)
            (u_plant,) = daq.get("u_plant")
            plant.set(u=u_plant, tau_tip=tau)
            plant.step(k * h, h)
        alpha, alpha_gauge = plant.get("alpha", "alpha_gauge")
        (alpha_v,) = daq.get("alpha_v")
    assert alpha == pytest.approx(static, rel=1e-8)
    assert alpha_gauge == pytest.approx(alpha, rel=1e-8)
    assert abs(alpha_v - np.degrees(alpha) / KE) <= 20 / 2**16 / 2 + 1e-12


def test_reset_starts_a_fresh_run(fmu_runner):
    params = {"delay_samples": 2, "noise_theta": 0.01, "seed": 9}
    u = [1.0, 2.0, 3.0, 4.0]
    runs = []
    with fmu_runner["daq"].instance(params) as h:
        for _ in range(2):
            out = []
            for k, uk in enumerate(u):
                h.set(u=uk, theta=0.2)
                h.step(k * 0.02, 0.02)
                out.append(h.get("u_plant", "theta_v"))
            runs.append(np.array(out))
            h.fmu.reset()  # back to instantiated: parameters keep their start values until set again
            daq = fmu_runner["daq"]
            h.fmu.setInteger([daq.vr("delay_samples"), daq.vr("seed")], [2, 9])
            h.fmu.setReal([daq.vr("noise_theta")], [0.01])
            h.fmu.setupExperiment(startTime=0.0)
            h.fmu.enterInitializationMode()
            h.fmu.exitInitializationMode()
    np.testing.assert_array_equal(runs[0], runs[1])
    np.testing.assert_array_equal(runs[0][:, 0], [0.0, 1.0, 2.0, 3.0])  # after step k: u_(k-1)


def test_readings_hold_between_sample_instants_whatever_is_set(fmu_runner):
    """The preview of a sample (the feedthrough theta -> theta_v) happens at its instant only: a master that sets
    the plant's angle mid-sample and then reads theta_v (Ecos transfers connection by connection) reads the held
    sample, not one taken from the wrong instant."""
    with fmu_runner["daq"].instance({"sample_rate": 50.0}) as h:
        h.set(theta=0.1)
        h.step(0.0, 0.005)
        (held,) = h.get("theta_v")
        assert held == pytest.approx(pot_volts(np.degrees(0.1)), abs=1e-12)
        h.set(theta=0.5)  # at 0.005 s; the next sample is at 0.02 s
        assert h.get("theta_v") == [held]
        for k in (1, 2, 3):
            h.step(k * 0.005, 0.005)
        h.set(theta=0.5)  # at 0.02 s: the preview of sample 1
        assert h.get("theta_v")[0] == pytest.approx(pot_volts(np.degrees(0.5)), abs=1e-12)
