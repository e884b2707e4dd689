"""The gauge's delay behind the hub angle (harness.diagnosis.gauge), read from records of the twin whose DAQ delays it
and of the independent simulator (tests/indeprig.py); the real records' in tests/test_real_records.py."""

from __future__ import annotations

import numpy as np
import pytest
from indeprig import IndepRig, mode_frequencies, simulate

from harness import spec as specmod
from harness.diagnosis.experiments import RigExperiment
from harness.diagnosis.gauge import gauge_delay
from harness.fmu.build import build_all
from harness.fmu.cosim import Rig

KP, KE = 35.5145, -3.3636  # deg/V: the DAQ's default pot and gauge gains


def _cu_records(daq: dict[str, float], n_records: int = 2) -> dict[str, RigExperiment]:
    """The CU arm at 1 kHz under its lab's state feedback, +-17 deg squares of period 10 s (8 s each), read through
    a DAQ with ``daq`` (2 mV of noise on both channels unless it says otherwise)."""
    sheet = specmod.load("cu_flexible_arm")
    Ts, n = 1e-3, 8000
    t = np.arange(n) * Ts
    out = {}
    fmus = build_all()
    with Rig(fmus["flexjoint"], fmus["daq"], fmus["controller"]) as rig:
        for i in range(n_records):
            ref = np.radians(np.where((t + 2.5 * i) % 10 < 5, 17.19, -17.19))
            dq = {"noise_theta": 0.002, "noise_alpha": 0.002, "seed": i + 1, **daq}
            res = rig.run_closed(ref, Ts, sheet.controller.fmu_parameters(1 / Ts), plant=sheet.plant, daq=dq)
            th, al = res["theta_v"] * KP, res["alpha_v"] * KE
            out[f"r{i}"] = RigExperiment(f"r{i}", "square", Ts, t, res["u"], th, al, res["theta_v"], res["alpha_v"])
    return out


@pytest.mark.parametrize("delay", [0, 40])
def test_the_gauges_delay_is_read_from_alpha_against_theta(delay):
    """A gauge read 40 ms late is found to the sample, and none where there is none; the link's clamped frequency
    comes with it (the sheet's 1.8 Hz with the tip mass: the twin's Ks is set for it)."""
    g = gauge_delay(_cu_records({"gauge_delay": delay}))
    assert g.samples == delay and g.seconds == pytest.approx(delay * 1e-3)
    assert g.link_hz == pytest.approx(1.8, rel=0.03)
    assert g.fit_pct > 95.0
    assert (g.fit_pct - g.fit_none_pct > 20.0) if delay else g.fit_pct == g.fit_none_pct
    assert g.records == ("r0", "r1")


def test_a_command_delay_is_not_the_gauges():
    """A command delay of 20 samples moves both channels alike: the gauge is on time (a delay there gains less than
    MIN_GAIN_PCT)."""
    g = gauge_delay(_cu_records({"delay_samples": 20}, 1))
    assert g.samples == 0 and g.fit_pct > 95.0 and g.records == ("r0",)


def test_a_record_too_short_is_not_read():
    """Under MIN_RECORD_S the delay cannot be told from the link's start: nothing is read, and it says so."""
    (x,) = _cu_records({"gauge_delay": 40}, 1).values()
    short = RigExperiment("short", "square", x.Ts, x.t[:900], x.u[:900], x.theta[:900], x.alpha[:900],
                          x.theta_v[:900], x.alpha_v[:900])  # fmt: skip
    g = gauge_delay({"short": short})
    assert g.samples == 0 and g.records == () and "1 s" in g.describe()


@pytest.mark.parametrize(
    "rig",
    [IndepRig(), IndepRig(n_modes=3, coulomb_torque=0.03, backlash=0.004, delay_samples=3)],
    ids=["textbook", "three modes, friction, play, command delay"],
)
def test_the_gauges_delay_on_the_independent_simulator(rig):
    """tests/indeprig.py's rig (an Euler-Bernoulli link with its gauge on the root curvature, its own drive, friction
    and play, none of our FMUs), 8 s of +-1 V steps of 0.1 s at 500 Hz: the gauge read on time is on time, and its
    readings shifted by 15 samples read 15 late (measured: the link fit 97.9 / 86.3 % either way, 47 % on time)."""
    Ts, n = 0.002, 4000
    u = np.repeat(np.random.default_rng(3).choice([-1.0, 1.0], n // 50), 50)
    r = simulate(rig, u, Ts, seed=1)
    th = r["theta_v"] * rig.pot_gain
    for shift in (0, 15):
        al = r["alpha_v"] * rig.gauge_Ke
        al = np.concatenate([np.full(shift, al[0]), al[: n - shift]])
        x = RigExperiment("steps", "prbs", Ts, r["t"], u, th, al, r["theta_v"], r["alpha_v"])
        g = gauge_delay({"steps": x})
        assert g.samples == shift and g.fit_pct > 85.0
        assert g.link_hz == pytest.approx(mode_frequencies(rig, "clamped")[0], rel=0.01)  # 2.94 Hz
