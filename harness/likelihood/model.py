"""The rig as a stochastic model: the plant's linear equations, the DAQ's sensors, process and measurement noise.

In continuous time, with the state ``x = [theta, a_1..a_n, theta_dot, a_dot_1..a_dot_n, b_alpha]`` (rad, rad/s,
deg: the plant's coordinates of :func:`harness.fmu.plant.state_space` and the record's gauge offset, a constant;
with the gauge's low-pass ``sensor.gauge_tau`` its output ``gauge`` [deg] before ``b_alpha``)::

    dx = (A x + B [u, 1]) dt + G dW          W: white torques on the hub and at the link's tip [N m sqrt(s)]
    y_k = C x(t_k) + v_k                      y: the readings theta, alpha [deg]; v_k white, var sigma^2

The command ``u`` [V] is held over each sample (zero-order hold; the second input, a constant 1, carries the
amplifier's input offset ``plant.u_offset``). The readings are the sensors' gains (``sensor.theta_gain``,
``sensor.alpha_gauge_gain``: reading per true angle) times the hub angle and the gauge's root-curvature deflection;
a record's theta offset is its hub's start, its gauge offset the state ``b_alpha``. A gauge amplifier with a
first-order low-pass of time constant tau reads its state ``gauge``, d gauge / dt = (alpha - gauge) / tau; sampled,
it is the DAQ FMU's filter of the sampled deflection, g_k = (1 - a) g_(k-1) + a alpha_k with a = 1 - exp(-Ts / tau),
the state holding g_(k-1) (:meth:`StochasticModel.discretise`; with friction's substeps, a substep's filter). The
rig's linear parameters are
those the recalibration fits (:data:`harness.diagnosis.recalibrate.LINEAR`, mapped to the plant by
:func:`harness.diagnosis.rigmodel.to_plant`); the noise's are :class:`Noise`'s.

:meth:`StochasticModel.discretise` gives the exact sampled model (the matrix exponential for A and B, Van Loan's
for the process noise's covariance): the filter's input.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from scipy.linalg import expm

from ..diagnosis import rigmodel
from ..diagnosis.recalibrate import LINEAR, Bound
from ..fmu import plant as plantmod
from .kalman import Discrete

__all__ = ["EFFECTS", "NOISE", "SENSORS", "LimitBound", "Noise", "StochasticModel", "rig_model"]

DEG = 180.0 / math.pi

# the noise's parameters, each as a factor of a start the data give (harness.likelihood.fit.noise_start); the torques'
# searched as variances from none
NOISE: dict[str, Bound] = {
    "noise.theta": Bound(1e-3, 1e3, "deg", "hub angle reading's white noise (rms)", part="noise"),
    "noise.alpha": Bound(1e-3, 1e3, "deg", "gauge reading's white noise (rms)", part="noise"),
    "noise.hub_torque": Bound(
        0.0, 1e3, "N m sqrt(s)", "white torque on the hub (intensity)", part="noise", square=True
    ),
    "noise.link_torque": Bound(
        0.0, 1e3, "N m sqrt(s)", "white torque at the link's tip (intensity)", part="noise", square=True
    ),
    "noise.hub_force": Bound(
        0.0, 1e3, "N m/sqrt(s)", "the missing force's random walk (intensity)", part="noise", square=True
    ),
}

FRICTION_STEP = 1e-3  # s: the longest step over which the filter holds a friction torque (kalman.c's substeps)
STRIBECK_STEP = 2.5e-4  # s: ... where the friction falls with speed (a step samples the drop as a hub reverses)

# the sensors' dynamics beyond their gains: the gauge amplifier's first-order low-pass (the DAQ's gauge_tau), its
# time constant searched as the square of its ratio to a nominal (a slope at none), none its null
SENSORS: dict[str, Bound] = {
    "sensor.gauge_tau": Bound(0.0, 50.0, "s", "the gauge's low-pass time constant", part="sensor", square=True),
}


@dataclass(frozen=True)
class LimitBound(Bound):
    """A limit [V] searched as a tenth of the share ``nominal / value`` of its nominal value, the records' largest
    |command| (:func:`harness.likelihood.effects.command_peak`), the share from ``lo`` (1: the limit at the peak, no
    sample clipped: the null, a wall the search reaches) to ``hi`` (the limit at 1 / hi of the peak). A step of the
    search's differences is then a share of the limit (the gradient's, 1e-5, about 1e-4 of it), and a limit within
    about 1 % of the peak ends at the wall. A value of 0 (the FMU's "none") is the null."""

    scale: float = 0.1

    def to_x(self, value: float, nominal: float) -> float:
        """A tenth of the share nominal / value, the share at least ``lo`` (0 or a limit beyond the peak: the
        null)."""
        return self.scale * (max(nominal / value, self.lo) if value > 0 else self.lo)

    def from_x(self, x: float, nominal: float) -> float:
        """The limit nominal / share (at the wall ``lo``: the peak)."""
        return nominal / max(x / self.scale, self.lo)

    def x_range(self) -> tuple[float, float]:
        """The coordinate's walls."""
        return (self.scale * self.lo, self.scale * self.hi)


# the effects, each a nested extension of the linear rig (off at its null), in the plant FMU's names and units.
# Friction is searched as the square of its ratio to a nominal size (a step of the search's differences is then a
# share of the size); the amplifier's limit as the share of the records' peak command over it (LimitBound: its
# nominal is that peak), the null no limit. The command's delay (daq.delay_samples) and a second link mode
# (plant.n_modes) are integers, chosen by profile likelihood (harness.likelihood.effects). The gauge's nonlinearity
# (the DAQ's gauge_cubic: a reading a (1 + c (a / 10 deg)^2) of the deflection a [deg]) is searched as itself: either
# sign bends a bridge, its null none inside its range.
EFFECTS: dict[str, Bound] = {
    "plant.coulomb_torque": Bound(0.0, 1e3, "N m", "Coulomb friction at the hub", part="effect", square=True),
    "plant.amp_limit": LimitBound(1.0, 20.0, "V", "the amplifier's output limit", part="effect"),
    "daq.gauge_cubic": Bound(-0.3, 0.3, "1", "the strain gauge's cubic nonlinearity", log=False, part="effect"),
    "plant.backlash": Bound(0.0, 1e3, "rad", "the gear's play at the load shaft", part="effect", square=True),
    # friction's shape beside its Coulomb level (the plant FMU's Karnopp law): the breakaway over the Coulomb level
    # (1: none, its null a wall) and the speed over which the sliding friction falls from it (Stribeck's)
    "plant.stiction_ratio": Bound(1.0, 3.0, "1", "breakaway over Coulomb friction", log=False, part="effect"),
    "plant.stribeck_speed": Bound(0.1, 10.0, "rad/s", "Stribeck speed of the friction drop", part="effect"),
}


@dataclass(frozen=True)
class Noise:
    """The model's noise: each reading's white noise [deg rms], the intensities of the white torques on the hub
    and at the link's tip [N m sqrt(s)] (a torque of intensity q held over a sample of Ts has the rms q / sqrt(Ts)),
    and that of the missing force's random walk [N m / sqrt(s)] (a model with the force state,
    :func:`rig_model`'s ``force``)."""

    theta: float
    alpha: float
    hub_torque: float = 0.0
    link_torque: float = 0.0
    hub_force: float = 0.0

    @classmethod
    def from_values(cls, values: Mapping[str, float]) -> Noise:
        """The noise from parameters named as in :data:`NOISE` (``noise.theta``, ...)."""
        return cls(**{f.name: float(values[f"noise.{f.name}"]) for f in fields(cls) if f"noise.{f.name}" in values})


@dataclass(frozen=True)
class StochasticModel:
    """The rig in continuous time (the module docstring's equations): ``A`` (nx x nx), ``B`` (nx x 2: the command
    [V] and the constant input), ``G`` (nx x 2: the hub's and the tip's white torques), ``C`` (2 x nx: theta and
    alpha [deg]), its ``noise``, the state names ``states``, the link's first free-hub frequency ``w1`` [rad/s] (the
    scale of its start's uncertainty) and the drive's torque per volt ``drive`` [N m/V] (its force's scale). With the
    missing force, ``G`` has a third column: the force's random walk. ``coulomb`` [N m] is the Coulomb friction at
    the hub (0: none; the filter's, :class:`harness.likelihood.kalman.Discrete`'s ``friction``), ``breakaway`` [N m]
    the torque the stuck hub holds (0: the Coulomb level) and ``stribeck`` [rad/s] the speed over which the sliding
    friction falls from it to the Coulomb level (0: at once), ``shaped`` whether the model has friction's shape at all
    (then on the finer steps of :data:`STRIBECK_STEP`, its breakaway at none too: a shape and its null one filter);
    ``limit`` [V] the amplifier's output limit on the command plus its input offset ``offset`` [V] (0: none;
    :meth:`inputs`);
    ``gauge_tau`` [s] the gauge's low-pass (0: none; the state ``gauge``, sampled as the DAQ filters:
    :meth:`discretise`); ``cubic`` [1/deg^2] the gauge reading's bend, its reading L (offset apart) read as
    L + cubic L^3 (0: none; with the low-pass, taken on its output where the DAQ bends its input). ``play`` [rad]
    is the gear's play (0: none): two more states, ``gap`` (the motor side's angle ahead of the hub's, within
    +-play / 2) and ``motor_speed``; ``A``, ``B`` and ``G`` are then the teeth in contact's (the rig as one body: the
    gap held, the motor's speed the hub's), ``loose`` the (A, B, G) of the two sides apart (:class:`harness.fmu.plant.
    GearPlay`) and ``impact`` (nx x nx) the plastic impact that closes the play, momentum kept, the gap left to be
    set at +-play / 2 (:meth:`discretise`)."""

    A: np.ndarray
    B: np.ndarray
    G: np.ndarray
    C: np.ndarray
    noise: Noise
    states: tuple[str, ...]
    w1: float
    drive: float
    coulomb: float = 0.0
    breakaway: float = 0.0
    stribeck: float = 0.0
    shaped: bool = False
    limit: float = 0.0
    offset: float = 0.0
    gauge_tau: float = 0.0
    cubic: float = 0.0
    play: float = 0.0
    loose: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    impact: np.ndarray | None = None

    def inputs(self, u: np.ndarray) -> np.ndarray:
        """The filter's inputs (n x 2) for the command ``u`` [V] as the plant receives it: ``[u, 1]`` (the offset
        rides on the constant input); with a limit L the amplifier's output clip(u + offset, -L, L) as the plant FMU
        clamps it, written ``[clip(u + offset, -L, L) - offset, 1]`` on the same ``B``."""
        u = np.asarray(u, dtype=float)
        if self.limit > 0.0:
            u = np.clip(u + self.offset, -self.limit, self.limit) - self.offset
        return np.column_stack([u, np.ones(u.shape[0])])

    def discretise(self, Ts: float, step: float = FRICTION_STEP) -> Discrete:
        """The model sampled every ``Ts`` [s] with the inputs held over each sample: A_d = exp(A Ts), B_d its
        integral on B, Q_d = int_0^Ts exp(A s) G W G' exp(A' s) ds (Van Loan), r the readings' variances. With
        friction or a play, the steps are substeps of at most ``step`` [s] (the hub sticks and slides, the teeth
        part and meet, within a sample; the filter's :data:`FRICTION_STEP`, with friction's shape
        :data:`STRIBECK_STEP`); with a play, the sides apart sampled as well (``kalman.c``'s header)."""
        if self.shaped:
            step = min(step, STRIBECK_STEP)
        substeps = max(1, math.ceil(Ts / step - 1e-9)) if self.coulomb > 0.0 or self.play > 0.0 else 1
        Ts /= substeps
        C = self.C
        if self.gauge_tau > 0.0:  # the DAQ's filter at the samples: g_k = (1 - a) g_(k-1) + a alpha_k, read g_k
            i = self.states.index("gauge")
            a = 1.0 - math.exp(-Ts / self.gauge_tau)
            C = C.copy()
            C[1, :i], C[1, i] = a * self.gauge_tau * self.A[i, :i], 1.0 - a
        Ad, Bd, Q = self._sampled(self.A, self.B, self.G, Ts)
        bend = None
        if self.cubic != 0.0:  # the gauge's reading without its offset bends
            bend = np.zeros_like(C)
            bend[1] = C[1]
            bend[1, self.states.index("b_alpha")] = 0.0
        loose = None if self.loose is None else self._sampled(*self.loose, Ts)
        return Discrete(A=Ad, B=Bd, Q=Q, C=C, r=np.array([self.noise.theta**2, self.noise.alpha**2]),
                        friction=self.coulomb, breakaway=self.breakaway, stribeck=self.stribeck,
                        hub=Bd[:, 0] / self.drive, speed=self.states.index("theta_dot"),
                        substeps=substeps, cubic=None if bend is None else np.array([0.0, self.cubic]), bend=bend,
                        play=self.play, gap=self.states.index("gap") if self.play > 0.0 else 0, loose=loose,
                        impact=self.impact)  # fmt: skip

    def _sampled(
        self, A: np.ndarray, B: np.ndarray, G: np.ndarray, Ts: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A_d, B_d, Q_d) of the continuous (A, B, G) over ``Ts`` [s] with this model's noise (:meth:`discretise`);
        with the gauge's low-pass, its state the DAQ's filter of the sampled deflection."""
        nx, nu = B.shape
        M = np.zeros((nx + nu, nx + nu))
        M[:nx, :nx], M[:nx, nx:] = A, B
        E = expm(M * Ts)
        W = np.diag([self.noise.hub_torque**2, self.noise.link_torque**2, self.noise.hub_force**2][: G.shape[1]])
        V = np.zeros((2 * nx, 2 * nx))
        V[:nx, :nx], V[:nx, nx:], V[nx:, nx:] = -A, G @ W @ G.T, A.T
        F = expm(V * Ts)
        Q = F[nx:, nx:].T @ F[:nx, nx:]
        Ad, Bd = E[:nx, :nx], E[:nx, nx:]
        if self.gauge_tau > 0.0:
            i = self.states.index("gauge")
            a = 1.0 - math.exp(-Ts / self.gauge_tau)
            Ad, Bd = Ad.copy(), Bd.copy()
            Ad[i, :], Bd[i, :], Q[i, :], Q[:, i] = 0.0, 0.0, 0.0, 0.0
            Ad[i, :i], Ad[i, i] = a * self.gauge_tau * A[i, :i], 1.0 - a
        return Ad, Bd, 0.5 * (Q + Q.T)


def rig_model(
    plant: Mapping[str, Any], values: Mapping[str, float], noise: Noise, force: bool = False
) -> StochasticModel:
    """The stochastic model of the rig ``plant`` (a spec's plant table, FMU defaults for the rest) with the linear
    parameters ``values`` (any of :data:`harness.diagnosis.recalibrate.LINEAR`; the others keep the plant's) and
    ``noise``; with ``force``, the missing force: a torque on the hub [N m], the state ``d``, a random walk of
    intensity ``noise.hub_force`` (CTSM's systematic model improvement: what the model lacks, estimated as a state).

    Parameters
    ----------
    plant : mapping
        The plant FMU's parameters by name (``Ks``, ``zeta_link``, ``n_modes``, ...).
    values : mapping
        Linear parameters by their diagnosis names (``rig.drive_gain``, ``plant.Ks``, ``sensor.theta_gain``, ...),
        the sensors' dynamics (:data:`SENSORS`: ``sensor.gauge_tau``) and effects (:data:`EFFECTS`:
        ``plant.coulomb_torque``, ``plant.amp_limit``, ``daq.gauge_cubic``; off when not given, whatever the
        plant's table says: the model is the linear rig plus the effects named).
    noise : Noise
        The readings' and the torques' noise.
    force : bool
        Add the missing force's state.

    Returns
    -------
    StochasticModel
    """
    unknown = sorted(set(values) - set(LINEAR) - set(EFFECTS) - set(SENSORS))
    if unknown:
        raise ValueError(f"not a linear parameter or an effect of the rig: {', '.join(unknown)}")
    table = {k: v for k, v in plant.items() if not isinstance(v, str)}
    table |= rigmodel.to_plant({k: v for k, v in values.items() if k in rigmodel.COMBOS}, table)
    table |= {k.removeprefix("plant."): float(v) for k, v in values.items() if k in ("plant.Ks", "plant.zeta_link")}
    p = plantmod.PlantParams(**{k: table[k] for k in plantmod.FLEXJOINT.parameters() if k in table})
    A, B, Cp, _ = plantmod.state_space(p)
    G_volt, _ = plantmod.motor_constants(p)
    tau = float(values.get("sensor.gauge_tau", 0.0))
    lowpass = tau > 0.0
    n2 = A.shape[0]
    ib = n2 + int(lowpass)  # the gauge offset's state, after the gauge's low-pass
    nx = ib + 1 + int(force)  # and the missing force
    hub = B[:, 0] / G_volt  # a unit torque on the hub
    gauge = DEG * float(values.get("sensor.alpha_gauge_gain", 1.0)) * Cp[5]  # the gauge's reading of the plant
    Ax = np.zeros((nx, nx))
    Ax[:n2, :n2] = A
    if lowpass:
        Ax[n2, :n2], Ax[n2, n2] = gauge / tau, -1.0 / tau
    if force:
        Ax[:n2, -1] = hub
    u_offset = float(values.get("plant.u_offset", table.get("u_offset", 0.0)))
    Bx = np.zeros((nx, 2))
    Bx[:n2, 0], Bx[:n2, 1] = B[:, 0], B[:, 0] * u_offset
    Gx = np.zeros((nx, 2 + int(force)))
    Gx[:n2, 0], Gx[:n2, 1] = hub, B[:, 1]  # on the hub; at the tip
    if force:
        Gx[-1, 2] = 1.0
    Cx = np.zeros((2, nx))
    Cx[0, :n2] = DEG * float(values.get("sensor.theta_gain", 1.0)) * Cp[0]
    if lowpass:
        Cx[1, n2] = 1.0
    else:
        Cx[1, :n2] = gauge
    Cx[1, ib] = 1.0
    n = int(p.n_modes)
    states = ("theta", *(f"a_{i + 1}" for i in range(n)), "theta_dot", *(f"a_dot_{i + 1}" for i in range(n)))
    states += ("gauge",) * lowpass + (("b_alpha", "d") if force else ("b_alpha",))
    w1 = float(plantmod.mode_frequencies(p)[0, 0]) * 2.0 * math.pi
    coulomb = float(values.get("plant.coulomb_torque", 0.0))
    breakaway = coulomb * float(values.get("plant.stiction_ratio", 1.0))
    stribeck = float(values.get("plant.stribeck_speed", 0.0)) if breakaway > coulomb else 0.0
    shaped = coulomb > 0.0 and "plant.stiction_ratio" in values
    limit = float(values.get("plant.amp_limit", 0.0))
    # the DAQ's a (1 + c (a / 10)^2) of the deflection a [deg], read as L = g a (g: the gauge's gain)
    cubic = float(values.get("daq.gauge_cubic", 0.0)) / (100.0 * float(values.get("sensor.alpha_gauge_gain", 1.0)) ** 2)
    model = StochasticModel(A=Ax, B=Bx, G=Gx, C=Cx, noise=noise, states=states, w1=w1, drive=G_volt, coulomb=coulomb,
                            breakaway=breakaway, stribeck=stribeck, shaped=shaped, limit=limit, offset=u_offset,
                            gauge_tau=tau, cubic=cubic)  # fmt: skip
    play = float(values.get("plant.backlash", 0.0))
    return _with_play(model, plantmod.gear_play(p), play, u_offset) if play > 0.0 else model


def _with_play(rigid: StochasticModel, gear: plantmod.GearPlay, play: float, u_offset: float) -> StochasticModel:
    """``rigid`` with the gear's ``play`` [rad] (:class:`StochasticModel`'s ``loose`` and ``impact``): the states
    ``gap`` and ``motor_speed`` added; in contact the gap held and the motor's speed the hub's; apart, the hub side
    ``gear`` without the drive (the gauge, its offset and the missing force as in contact), the motor side
    driven."""
    nr, n2 = rigid.A.shape[0], gear.A.shape[0]
    N, nx = n2 // 2, nr + 2
    ig, iw = nr, nr + 1  # the gap, the motor's speed

    def widen(M: np.ndarray) -> np.ndarray:  # the rows of the two new states, none yet
        out = np.zeros((nx, M.shape[1]))
        out[:nr] = M
        return out

    A, B, G = (widen(M) for M in (rigid.A, rigid.B, rigid.G))
    A = np.column_stack([A, np.zeros((nx, 2))])
    A[iw], B[iw], G[iw] = A[N], B[N], G[N]  # in contact the motor turns with the hub
    Af, Bf, Gf = A.copy(), np.zeros_like(B), np.zeros_like(G)
    Af[:n2, :n2] = gear.A
    if "d" in rigid.states:  # the missing force acts on the hub side
        Af[:n2, rigid.states.index("d")] = gear.hub
        Gf[rigid.states.index("d"), 2] = 1.0
    Gf[:n2, 0], Gf[:n2, 1] = gear.hub, gear.tip
    Af[iw] = 0.0
    Af[ig, iw], Af[ig, N] = 1.0, -1.0
    Af[iw, iw] = -gear.damping / gear.Jm
    Bf[iw, 0], Bf[iw, 1] = gear.drive / gear.Jm, gear.drive / gear.Jm * u_offset
    # the plastic impact: an impulse P = (w_m - theta_dot) / (1 / Jm + hub[N]) through the gear moves the hub side's
    # velocities by P hub[N:], the motor's speed becomes the hub's; the gap is then set (zero here)
    impact = np.eye(nx)
    c = 1.0 / (1.0 / gear.Jm + gear.hub[N])
    impact[N:n2, iw] += gear.hub[N:] * c
    impact[N:n2, N] -= gear.hub[N:] * c
    impact[iw] = impact[N]
    impact[ig] = 0.0
    return replace(rigid, A=A, B=B, G=G, C=np.column_stack([rigid.C, np.zeros((2, 2))]), play=play,
                   states=(*rigid.states, "gap", "motor_speed"), loose=(Af, Bf, Gf), impact=impact)  # fmt: skip
