"""Records as labs log them: a gauge with its own zero, a link still ringing when the record starts, a gauge zeroed on
the record's quietest stretch (or not, where the link never rests), and the independent simulator's tip mass and
command offset against the twin's."""

from __future__ import annotations

import math

import indeprig
import numpy as np
import pandas as pd
import pytest

from harness.diagnosis.bands import parameter_draws
from harness.diagnosis.experiments import fit_ring
from harness.fmu.plant import PlantParams, mass_stiffness
from harness.rig.records import ImportOptions, import_records
from harness.rundir import read_dataset


def test_a_ring_at_the_start_is_read_with_its_amplitude_phase_and_offset():
    """A damped 1.9 Hz ring about a gauge zero of 3.1 deg, drifting 0.2 deg/s, in 1.5 s of 1 kHz samples with 0.01
    deg of noise: its offset, amplitude and phase at t = 0 (the replay's start) come back within a few noise RMS."""
    rng = np.random.default_rng(3)
    t = np.arange(1500) * 1e-3
    w, decay, a, b = 2 * math.pi * 1.9, 0.3, 0.8, -0.45
    y = 3.1 + 0.2 * t + np.exp(-decay * t) * (a * np.cos(w * t) + b * np.sin(w * t)) + rng.normal(0, 0.01, t.size)
    ring = fit_ring(y, 1e-3)
    assert ring is not None
    assert ring.offset_deg == pytest.approx(3.1, abs=0.01) and ring.a_deg == pytest.approx(a, abs=0.01)
    assert ring.omega == pytest.approx(w, rel=0.005) and ring.decay == pytest.approx(decay, abs=0.05)
    start = ring.start()
    assert math.degrees(start["alpha_start"]) == pytest.approx(3.1 + a, abs=0.01)
    assert math.degrees(start["alpha_dot_start"]) == pytest.approx(0.2 + w * b - decay * a, rel=0.03)
    assert fit_ring(y[:500], 1e-3) is None  # 0.5 s holds less than 1.5 periods of 1.9 Hz: no ring read


def _record_csv(path, alpha: np.ndarray, theta: np.ndarray) -> None:
    n = alpha.size
    t = np.arange(n) * 1e-3
    pd.DataFrame({"t": t, "u": np.zeros(n), "theta": theta, "alpha": alpha}).to_csv(path, index=False)


def test_zero_alpha_takes_the_quietest_stretch_not_the_first_sample(tmp_path):
    """A record that starts with its link ringing (1 deg, 2 Hz, decaying in 2 s) about a gauge zero of 4 deg: zeroed
    on its first 0.1 s it kept a bias of a point on the swing; zeroed on its quietest 0.25 s at rest it is zeroed
    within the noise, and the note says where."""
    rng = np.random.default_rng(1)
    t = np.arange(6000) * 1e-3
    alpha = 4.0 + np.exp(-t / 0.4) * np.cos(2 * math.pi * 2 * t) + rng.normal(0, 0.005, t.size)
    _record_csv(tmp_path / "r.csv", alpha, np.zeros(t.size) + rng.normal(0, 0.01, t.size))
    notes = []
    opts = ImportOptions(units={"theta": "deg", "alpha": "deg"}, zero_alpha=True)
    import_records([tmp_path / "r.csv"], tmp_path / "run", opts, note=notes.append)
    d = read_dataset(tmp_path / "run" / "data" / "r.parquet")
    assert abs(float(np.median(d["alpha"].to_numpy()[-1000:]))) < 0.005
    assert any("alpha zeroed: it read 3.99" in n and "quietest 0.25 s" in n for n in notes), notes


def test_zero_alpha_on_a_link_that_never_rests_is_one_warning_and_the_record_as_read(tmp_path):
    """A link ringing for the whole record (0.7 deg at 1.8 Hz, undamped): no stretch at rest, one warning line, the
    deflection left as read (the diagnosis fits each record's gauge offset)."""
    t = np.arange(5000) * 1e-3
    alpha = 2.5 + 0.7 * np.sin(2 * math.pi * 1.8 * t)
    _record_csv(tmp_path / "r.csv", alpha, np.zeros(t.size))
    notes = []
    opts = ImportOptions(units={"theta": "deg", "alpha": "deg"}, zero_alpha=True)
    import_records([tmp_path / "r.csv"], tmp_path / "run", opts, note=notes.append)
    warned = [n for n in notes if n.startswith("warning: ")]
    assert len(warned) == 1 and "the link never rests" in warned[0], notes
    d = read_dataset(tmp_path / "run" / "data" / "r.parquet")
    assert d["alpha"].to_numpy() == pytest.approx(alpha, abs=1e-9)
    assert not any("alpha zeroed" in n for n in notes)


def test_the_independent_rigs_tip_mass_gives_the_twins_link_frequency():
    """The independent simulator's beam (its own quadrature of the clamped-free shapes) with the CU arm's 50 g tip
    mass: its first clamped and free link frequencies within 0.5 % of the twin's analytic model's."""
    plant = PlantParams(Kg=48.4, kt=0.0107, km=0.0107, Rm=3.29, eta_g=1.0, eta_m=1.0, Jeq=0.002, m_link=0.06,
                        L_link=0.45, m_tip=0.05, Ks=2.2448, n_modes=1)  # fmt: skip
    M, K = mass_stiffness(plant)[:2]
    clamped = math.sqrt(K[1, 1] / M[1, 1]) / (2 * math.pi)
    free = math.sqrt(max(np.linalg.eigvals(np.linalg.solve(M, K)).real)) / (2 * math.pi)
    rig = indeprig.IndepRig.from_Ks(2.2448, m_link=0.06, L_link=0.45, m_tip=0.05, Jeq=0.002)
    assert indeprig.mode_frequencies(rig, "clamped")[0] == pytest.approx(clamped, rel=0.005)
    assert indeprig.mode_frequencies(rig, "free")[0] == pytest.approx(free, rel=0.005)
    assert clamped == pytest.approx(1.8, rel=0.01)  # the lab sheet's 1.8 Hz


def test_parameter_draws_follow_the_covariance_and_stay_physical():
    """Draws of a fit's parameters: the first is the fit, the log-normal spread of a log-scale one and the normal
    spread of an offset are the covariance's, and a friction's breakaway is kept >= 1 (the FMU's range)."""
    over = {"plant.Ks": 2.0, "plant.u_offset": -0.1, "plant.stiction_ratio": 1.05, "daq.delay_samples": 1}
    names, log = ["plant.Ks", "plant.u_offset", "plant.stiction_ratio"], [True, False, False]
    cov = np.diag([0.05**2, 0.01**2, 0.1**2])
    draws = parameter_draws(over, names, log, cov, 4000, 0)
    assert draws[0] == over and all(d["daq.delay_samples"] == 1 for d in draws)
    ks = np.log([d["plant.Ks"] / 2.0 for d in draws[1:]])
    u = np.array([d["plant.u_offset"] for d in draws[1:]])
    assert np.std(ks) == pytest.approx(0.05, rel=0.05) and np.std(u) == pytest.approx(0.01, rel=0.05)
    assert min(d["plant.stiction_ratio"] for d in draws) == 1.0
