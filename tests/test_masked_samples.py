"""Samples masked in a run's manifest (``masked``: a channel pinned at a rail or stuck, found at import) are left
out: the identification fits the longest stretch without any, the diagnosis compares none of them."""

from __future__ import annotations

import numpy as np
import pandas as pd

from harness import spec as specmod
from harness.diagnosis.experiments import load_experiments, split_point
from harness.ident.calibration import Calibration
from harness.ident.identify import prepare, run_masks, unmasked_stretch
from harness.rig.records import ImportOptions, import_records
from harness.rundir import Manifest, load_run

KP, KE = 35.5145, -3.3636
CAL = Calibration(Kp=KP, Ke=KE)
RATE = 50.0


def test_masked_samples_are_left_out_by_the_identification_and_the_diagnosis(tmp_path):
    n = 400
    t = np.arange(n) / RATE
    u = np.where(np.sin(2 * np.pi * 0.5 * t) >= 0, 1.0, -1.0)
    theta = 20.0 * np.sin(2 * np.pi * 0.4 * t) + np.random.default_rng(1).normal(0, 0.05, n)
    alpha = np.random.default_rng(2).normal(0, 0.05, n)
    path = tmp_path / "rec.csv"
    pd.DataFrame({"t": t, "u": u, "theta_deg": theta, "alpha_deg": alpha}).to_csv(path, index=False)
    run = tmp_path / "run"
    import_records([path], run, ImportOptions(calibration=CAL))
    assert run_masks(run) == {}
    m = Manifest.load(run)
    m.experiments[0].masked = {"theta": [[120, 150], [300, 310]]}
    m.write(run)
    assert run_masks(run) == {"rec": {"theta": [[120, 150], [300, 310]]}}
    assert unmasked_stretch(n, [[120, 150], [300, 310]]) == (150, 300)
    for output, size in (("y", 150), ("theta", 150), ("alpha", n)):  # alpha reads no masked sample
        (p,) = prepare(load_run(run), CAL, 0.8, output, run_masks(run)).values()
        assert p.u.size == size
        np.testing.assert_array_equal(p.u, u[150 : 150 + size] if size < n else u)
    (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
    assert np.flatnonzero(~x.valid["theta"]).tolist() == [*range(120, 150), *range(300, 310)]
    assert x.valid["alpha"].all()


def test_a_masked_stretch_is_never_a_quiet_point(tmp_path):
    """A sensor held still by its fault is not the rig at rest: the diagnosis cuts a lone record elsewhere, and reads
    the gauge's rest elsewhere (measured on the twin: a stuck alpha had been taken for the link's rest, the replay's
    gauge offset set from it, the held-out gap before any fit 0.0319 against the clean record's 0.0155; now 0.0170,
    alpha's residual 0.0882 deg RMS against 0.0883)."""
    n = 400
    t = np.arange(n) / RATE
    u = np.where(np.sin(2 * np.pi * 0.5 * t) >= 0, 1.0, -1.0)
    theta = 20.0 * np.sin(2 * np.pi * 0.4 * t) + np.random.default_rng(1).normal(0, 0.05, n)
    alpha = np.random.default_rng(2).normal(0, 0.05, n)
    alpha[170:230] = alpha[170]
    theta[170:230] = theta[170]
    path = tmp_path / "rec.csv"
    pd.DataFrame({"t": t, "u": u, "theta_deg": theta, "alpha_deg": alpha}).to_csv(path, index=False)
    run = tmp_path / "run"
    import_records([path], run, ImportOptions(calibration=CAL))
    assert Manifest.load(run).experiments[0].masked == {"theta": [[170, 230]], "alpha": [[170, 230]]}  # found stuck
    (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
    assert x.faulty is not None and np.flatnonzero(x.faulty).tolist() == list(range(170, 230))
    assert not 170 <= split_point(x) < 230 and x.alpha_rest != alpha[170]
    m = Manifest.load(run)
    m.experiments[0].masked = None
    m.write(run)
    (x,) = load_experiments(run, CAL, specmod.load("nominal"), 10.0).values()
    assert x.faulty is None and 170 <= split_point(x) < 230  # not masked, the still stretch is the quietest
