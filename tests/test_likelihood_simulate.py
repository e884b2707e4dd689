"""The parametric bootstrap's draws (harness.likelihood.simulate): the fitted model's records, and what the filter
keeps on them."""

from __future__ import annotations

import numpy as np
from test_force_shapes import _multisine
from test_likelihood import TS, _truth
from test_likelihood_effects import ONE, _readings_of, _simulate

from harness.likelihood.model import Noise, rig_model
from harness.likelihood.record import Record
from harness.likelihood.simulate import draw_records, whiteness_scale

QUIET = {"noise.theta": 0.0, "noise.alpha": 0.0, "noise.hub_torque": 0.0, "noise.link_torque": 0.0}


def test_a_draw_without_noise_replays_the_fmus_stick_slip():
    """Without noise, a draw of the one-mode rig with Coulomb friction of 0.03 N m under a multisine that reverses
    the hub many times replays the plant FMU's event-located stick-slip: the gauge within 5e-5 deg of its +-3 deg
    (measured 3.2e-5; the friction moves it by degrees), where the filter's own 1 ms steps are off by more than 1e-4
    deg (1.2e-4: their impulse on the link up to a step late); a draw of the linear rig is the sampled model's replay
    exactly."""
    u = _multisine(5, 1.2, 4.0)
    y = _readings_of(u, ONE | {"coulomb_torque": 0.03}, {})
    rec = Record("r", TS, u, y, np.ones((u.size, 2), bool))
    values = _truth(ONE) | QUIET | {"plant.coulomb_torque": 0.03}
    drawn = draw_records(ONE, values, rec, 0, np.random.default_rng(0), draws=2)
    assert drawn.shape == (2, u.size, 2) and np.array_equal(drawn[0], drawn[1])
    assert np.abs(drawn[0, :, 1] - y[:, 1]).max() < 5e-5
    free = _readings_of(u, ONE, {})
    assert np.abs(free[:, 1] - y[:, 1]).max() > 1.0
    coarse = rig_model(ONE, _truth(ONE) | {"plant.coulomb_torque": 0.03}, Noise(0.0, 0.0)).discretise(TS)
    x, out = np.zeros(coarse.A.shape[0]), np.empty(u.size)
    for k in range(u.size):  # the filter's steps, its friction held over each
        out[k] = coarse.C[1] @ x
        for _ in range(coarse.substeps):
            x = coarse.A @ x + coarse.B @ [u[k], 1.0]
            x += np.clip(-x[coarse.speed] / coarse.hub[coarse.speed], -0.03, 0.03) * coarse.hub
    assert np.abs(out - y[:, 1]).max() > 1e-4
    linear = draw_records(ONE, _truth(ONE) | QUIET, rec, 0, np.random.default_rng(0), draws=1)[0]
    np.testing.assert_allclose(linear, _simulate(rig_model(ONE, _truth(ONE), Noise(0.0, 0.0)), u), atol=1e-9)


def test_the_filter_of_a_linear_model_keeps_nothing_on_its_draws():
    """The linear rig's filter is exact: on records its model draws (noise as a twin's, 20 mV of each reading, a
    lattice of 0.05 deg on the hub), the Ljung-Box statistic's mean over 10 draws is its white value within 35 %
    (the mean of 10 chi-squares of 20 degrees of freedom: +-20 % at one standard deviation), the scale at least 1."""
    u = _multisine(6, 1.2, 4.0)
    rec = Record("r", TS, u, np.zeros((u.size, 2)), np.ones((u.size, 2), bool), (0.05, 0.0))
    values = _truth(ONE) | {"noise.theta": 0.07, "noise.alpha": 0.007, "noise.hub_torque": 1e-3,
                            "noise.link_torque": 1e-4}  # fmt: skip
    scale = whiteness_scale(ONE, values, [rec], 0)
    assert set(scale) == {"r"} and set(scale["r"]) == {"theta", "alpha"}
    for c, v in scale["r"].items():
        assert 1.0 <= v < 1.35, (c, v)
    assert whiteness_scale(ONE, values, [rec], 0) == scale  # seeded: the same every time
