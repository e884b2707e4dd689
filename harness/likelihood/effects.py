"""The effects the likelihood engine fits beside the linear rig, each a nested extension of it.

Continuous effects are parameters of :func:`harness.likelihood.fit.fit` (:data:`harness.likelihood.model.EFFECTS`):
Coulomb friction at the hub and the gear's play ``plant.backlash`` [rad], in the filter itself (the play as an
impact / dead-zone hybrid, the plant FMU's, on two more states), the strain gauge's cubic nonlinearity
``daq.gauge_cubic``, in the filter's reading of the gauge (an extended Kalman filter's update; its null inside its
range, :data:`INTERIOR`), and
the amplifier's output limit ``plant.amp_limit`` [V], a transformation of the filter's input (the command is known:
the drive sees clip(u + u_offset, +-L), as the plant FMU clamps it;
:meth:`harness.likelihood.model.StochasticModel.inputs`). The limit is searched as the share ``peak / L`` of the
records' largest |command| (:func:`command_peak`, the limit's nominal value): its null, no sample clipped, is the
wall at 1.

Integer effects are chosen by profile likelihood (:func:`profile_delay`, :func:`profile_modes`): the model fitted at
each setting, the setting whose maximised log-likelihood is highest. The command's transport delay
``daq.delay_samples`` shifts the filter's input by whole samples (the null: none); a second link mode
``plant.n_modes`` 2 adds the link's second clamped-free mode, its frequency (beta_2 / beta_1)^2 times the first's and
its gauge weight from the beam's shapes (:mod:`harness.fmu.plant`): the same free parameters, so the two fits'
log-likelihoods compare as they are. The one-mode model is not the two-mode one at a parameter's value (with two
modes the gauge's static calibration reads the first 1.22 times as strongly): the choice is a profile over the model's
structure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .fit import MLFit, fit
from .record import Record

__all__ = [
    "COARSE",
    "DELAY_SPAN",
    "FRICTION_SHAPE",
    "FRICTION_SHAPE_EFFECT",
    "INTERIOR",
    "NESTED",
    "PLAY",
    "PROFILED",
    "SENSOR_NESTED",
    "SHAPE",
    "NestedStart",
    "Profile",
    "command_peak",
    "nested_start",
    "profile_delay",
    "profile_settings",
    "search_order",
    "profile_modes",
]

# the continuous effects a unit's linear fit is extended by, one at a time: diagnosis.json's name -> the parameter
NESTED = {"coulomb_friction": "plant.coulomb_torque", "saturation": "plant.amp_limit",
          "gauge_nonlinearity": "daq.gauge_cubic", "backlash": "plant.backlash"}  # fmt: skip
# the nested effects whose null lies inside their range (either sign), not at a wall: their LR's law is chi-square
INTERIOR = ("gauge_nonlinearity",)
GAUGE_CUBIC = 0.05  # where the gauge's nonlinearity is searched from inside, and its scale
# the sensors' dynamics nested in the linear model (its structure, not an effect): the name -> the parameter
SENSOR_NESTED = {"gauge_lowpass": "sensor.gauge_tau"}
GAUGE_TAU = 0.02  # s: where the gauge's low-pass is searched from inside, and its scale
# friction's shape beside its Coulomb level, where its search starts (and the Stribeck speed's scale [rad/s]): a
# breakaway half again the Coulomb level, falling over 0.05 rad/s (the independent simulator's and a servo's order)
FRICTION_SHAPE = {"plant.stiction_ratio": 1.5, "plant.stribeck_speed": 0.05}
FRICTION_SHAPE_EFFECT = "friction_shape"  # its name among a unit's effects (not a verdict: friction's own refinement)
PLAY = 0.002  # rad: the gear play's scale (a small one: the rule's calibration's), searched from 1.5 times it

# the missing force's shape (harness.likelihood.force.SHAPES) each nested effect draws when the model lacks it
SHAPE = {"coulomb_friction": "friction", "saturation": "limit"}
# the integer effects, chosen by profile likelihood against the sheet's setting: diagnosis.json's name -> the parameter
PROFILED = {"delay": "daq.delay_samples", "second_mode": "plant.n_modes"}
DELAY_SPAN = 0.05  # the command delays a unit's profile tries: every whole sample up to this [s] (a DAQ's, a PC's)
COARSE = 10  # ... first on a grid of about this many, then every sample around the best


@dataclass(frozen=True)
class Profile:
    """An integer effect's profile likelihood: the parameter ``name`` (``daq.delay_samples``, ``plant.n_modes``),
    the ``settings`` tried (the first the null), and the maximum-likelihood ``fits`` at each."""

    name: str
    settings: tuple[int, ...]
    fits: tuple[MLFit, ...]

    @property
    def loglik(self) -> np.ndarray:
        """The maximised log-likelihood [nats] at each setting."""
        return np.array([f.loglik for f in self.fits])

    @property
    def best(self) -> int:
        """The setting whose log-likelihood is highest."""
        return self.settings[int(np.argmax(self.loglik))]

    @property
    def gain(self) -> float:
        """The best setting's log-likelihood over the null's (the first setting) [nats]."""
        return float(np.max(self.loglik) - self.loglik[0])

    def fit_at(self, setting: int) -> MLFit:
        """The fit at ``setting``."""
        return self.fits[self.settings.index(setting)]


def command_peak(records: Sequence[Record]) -> float:
    """The records' largest |command| [V]: the amplifier limit's nominal value (its search's null wall)."""
    peak = max((float(np.max(np.abs(r.u))) for r in records if r.n), default=0.0)
    if not peak > 0.0:
        raise ValueError("the records' command is zero throughout: no amplifier limit can show")
    return peak


@dataclass(frozen=True)
class NestedStart:
    """Where a nested fit starts: inside the effect (``inside``) and at its ``null`` (the linear rig), and the
    ``nominal`` value its search is scaled by, in the effect parameter's unit."""

    inside: float
    null: float
    nominal: float


def nested_start(name: str, records: Sequence[Record], drive: float) -> NestedStart:
    """Where the nested fit of effect ``name`` (:data:`NESTED`) starts, for ``records`` and the drive's torque per
    volt ``drive`` [N m/V]: friction from the torque of 20 mV of command and from none, scaled by the torque of 0.1 V;
    a limit from 0.9 of the records' peak command and from the peak (no sample clipped), scaled by the peak; the
    gauge's low-pass (:data:`SENSOR_NESTED`) from :data:`GAUGE_TAU` and from none, scaled by it; the gauge's
    nonlinearity from :data:`GAUGE_CUBIC` and from none; a gear's play from 1.5 :data:`PLAY` and from none, scaled
    by :data:`PLAY`."""
    if name == "coulomb_friction":
        return NestedStart(0.02 * drive, 0.0, 0.1 * drive)
    if name == "saturation":
        peak = command_peak(records)
        return NestedStart(0.9 * peak, peak, peak)
    if name == "gauge_lowpass":
        return NestedStart(GAUGE_TAU, 0.0, GAUGE_TAU)
    if name == "gauge_nonlinearity":
        return NestedStart(GAUGE_CUBIC, 0.0, GAUGE_CUBIC)
    if name == "backlash":
        return NestedStart(1.5 * PLAY, 0.0, PLAY)
    raise ValueError(f"no nested fit for the effect {name!r}; known: {', '.join({**NESTED, **SENSOR_NESTED})}")


def profile_settings(name: str, plant: Mapping[str, Any], delay: int, Ts: float) -> tuple[int, ...]:
    """The settings of the integer effect ``name`` (:data:`PROFILED`) tried against the sheet's: every whole-sample
    delay [samples] up to :data:`DELAY_SPAN` at the sample time ``Ts`` [s] (at least 3) other than the sheet's
    ``delay``; a second mode where the sheet's ``plant`` has one."""
    if name == "delay":
        top = max(3, int(DELAY_SPAN / Ts + 1e-9))
        return tuple(d for d in range(top + 1) if d != delay)
    if name == "second_mode":
        return (2,) if int(plant.get("n_modes", 1)) == 1 else ()
    raise ValueError(f"no profile for the effect {name!r}; known: {', '.join(PROFILED)}")


def search_order(settings: Sequence[int]) -> tuple[tuple[int, ...], int]:
    """How a profile over many ``settings`` is searched: a coarse grid of about :data:`COARSE` of them (every
    ``step``-th, the last included), then every setting within ``step`` of the coarse grid's best. Returns the grid
    and the step."""
    step = max(1, len(settings) // COARSE)
    grid = tuple(sorted({*settings[::step], settings[-1]}))
    return grid, step


def profile_delay(
    plant: Mapping[str, Any],
    records: Sequence[Record],
    start: Mapping[str, float],
    delays: Sequence[int] = (0, 1, 2, 3),
    **kwargs: Any,
) -> Profile:
    """The command's delay by profile likelihood: :func:`harness.likelihood.fit.fit` of ``start`` over ``records``
    at each of ``delays`` [samples] (``kwargs``: its other arguments).

    Returns
    -------
    Profile
        ``best`` the delay whose likelihood is highest.
    """
    if not delays or min(delays) < 0:
        raise ValueError(f"delays must be whole samples >= 0, got {tuple(delays)}")
    settings = tuple(int(d) for d in delays)
    fits = tuple(fit(plant, records, start, delay=d, **kwargs) for d in settings)
    return Profile("daq.delay_samples", settings, fits)


def profile_modes(
    plant: Mapping[str, Any],
    records: Sequence[Record],
    start: Mapping[str, float],
    modes: Sequence[int] = (1, 2),
    **kwargs: Any,
) -> Profile:
    """The link's modes by profile likelihood: :func:`harness.likelihood.fit.fit` of ``start`` over ``records`` with
    the plant's ``n_modes`` at each of ``modes`` (``kwargs``: the fit's other arguments, ``delay`` among them).

    Returns
    -------
    Profile
        ``best`` the number of modes whose likelihood is highest; ``gain`` the second mode's log-likelihood over
        the one-mode model's.
    """
    if not modes or min(modes) < 1:
        raise ValueError(f"modes must be whole numbers >= 1, got {tuple(modes)}")
    settings = tuple(int(m) for m in modes)
    fits = tuple(fit({**plant, "n_modes": m}, records, start, **kwargs) for m in settings)
    return Profile("plant.n_modes", settings, fits)
