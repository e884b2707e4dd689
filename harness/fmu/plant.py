"""Analytic linear model of the flexible-joint rig: the test oracle of the flexjoint FMU, and the campaign's
nominal link stiffness (the comb calibration's tip torques, ``harness.rig.campaign``).

Independent of the C code of ``fmus/flexjoint`` (same physics, other route: the beam integrals are
computed here by root finding and numerical quadrature of the clamped-free mode shapes).

All SI, angles in rad.  Coordinates: hub (load shaft) angle ``theta`` and ``a_i``, the tip-angle
contribution of assumed mode ``i`` (``alpha = sum a_i``), mode shapes normalised to ``phi_i(L) = +2``
and ``int_0^L phi_i^2 dx = L``.  State order of :func:`state_space`:
``[theta, a_1..a_n, theta_dot, a_dot_1..a_dot_n]``; inputs ``[u (V), tau_tip (N.m)]``; outputs
``[theta, alpha, y, theta_dot, alpha_dot, alpha_gauge]``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, make_dataclass
from functools import cache
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.integrate import quad
from scipy.linalg import eigh
from scipy.optimize import brentq

from .modeldesc import bundled_model

OUTPUTS = ("theta", "alpha", "y", "theta_dot", "alpha_dot", "alpha_gauge")
INPUTS = ("u", "tau_tip")


FLEXJOINT = bundled_model("flexjoint")  # the parameter table: names, types, defaults and ranges
MIN_EXCLUSIVE = ("Rm", "kt", "Kg", "eta_g", "eta_m", "Jeq", "m_link", "L_link", "Ks", "internal_step")
# FMI bounds are inclusive; these parameters divide or scale the dynamics, so their min (0) is invalid as well


def _bounds(name: str, lo: float | None, hi: float | None) -> str:
    """The valid range as text: ``> 0``, ``>= 1``, ``(0, 1]``, ``[0.05, 0.95]``."""
    if hi is None:
        return f"{'>' if name in MIN_EXCLUSIVE else '>='} {lo:g}"
    return f"in {'(' if name in MIN_EXCLUSIVE else '['}{lo:g}, {hi:g}]"


def _validate(self: Any) -> None:
    """Raise ValueError (one line naming the parameter) for values the FMU would reject: not finite, an Integer
    that is not one, outside the range of modelDescription.xml (min excluded for :data:`MIN_EXCLUSIVE`), an initial
    hub speed on a clamped hub."""
    for name, v in FLEXJOINT.parameters().items():
        value = getattr(self, name)
        if not math.isfinite(value):
            raise ValueError(f"invalid parameter {name} = {value}: must be finite")
        if v.type == "Integer" and int(value) != value:
            raise ValueError(f"invalid parameter {name} = {value}: must be an integer")
        lo = -math.inf if v.min is None else v.min
        hi = math.inf if v.max is None else v.max
        if not lo <= value <= hi or (name in MIN_EXCLUSIVE and value == lo):
            raise ValueError(f"invalid parameter {name} = {value}: must be {_bounds(name, v.min, v.max)}")
    if self.hub_locked and self.theta_dot_start != 0.0:
        raise ValueError(
            f"invalid parameter theta_dot_start = {self.theta_dot_start}: must be 0 with hub_locked = 1 "
            "(the hub is clamped)"
        )


def _to_dict(self: Any) -> dict[str, float | int]:
    """The parameters as {FMU name: value}."""
    return asdict(self)


# names, types and defaults of the flexjoint FMU's parameters (the textbook rig, effects off), SI units as declared
# in its modelDescription.xml
if TYPE_CHECKING:  # what the class made below looks like to a type checker: one attribute per FMU parameter

    @dataclass
    class PlantParams:
        """Parameters of the flexjoint FMU by name, defaults from its modelDescription.xml."""

        def __init__(self, **values: float) -> None: ...
        def __getattr__(self, name: str) -> float: ...
        def validate(self) -> None: ...
        def to_dict(self) -> dict[str, float | int]: ...

else:
    PlantParams = make_dataclass(
        "PlantParams",
        [(n, int if v.type == "Integer" else float, field(default=v.start)) for n, v in FLEXJOINT.parameters().items()],
        namespace={"validate": _validate, "to_dict": _to_dict, "__module__": __name__},
    )
    PlantParams.__doc__ = "Parameters of the flexjoint FMU by name, defaults from its modelDescription.xml."


# ------------------------------------------------------------------ beam (dimensionless)


@cache
def beam_roots(n: int) -> tuple[float, ...]:
    """The first n roots beta_i L of the clamped-free frequency equation cos(x) cosh(x) + 1 = 0."""
    roots = []
    for i in range(1, n + 1):
        guess = (2 * i - 1) * math.pi / 2
        roots.append(brentq(lambda x: math.cos(x) * math.cosh(x) + 1.0, guess - 1.0, guess + 1.0, xtol=1e-15))
    return tuple(roots)


def _shape(bl: float, xi: float, deriv: int = 0) -> float:
    """Un-normalised clamped-free mode shape (or its 2nd derivative in xi) at xi = x / L."""
    s = (math.cosh(bl) + math.cos(bl)) / (math.sinh(bl) + math.sin(bl))
    z = bl * xi
    if deriv == 0:
        return math.cosh(z) - math.cos(z) - s * (math.sinh(z) - math.sin(z))
    if deriv == 2:
        return bl**2 * (math.cosh(z) + math.cos(z) - s * (math.sinh(z) + math.sin(z)))
    raise ValueError(f"deriv must be 0 or 2, got {deriv}")


@cache
def beam_integrals(n: int) -> dict[str, np.ndarray]:
    """Dimensionless integrals of the tip-normalised shapes phi_i (phi_i(1) = 2), by quadrature.

    Returns ``mass`` = int_0^1 phi_i phi_j dxi (n x n, ~identity), ``first`` = int_0^1 xi phi_i dxi,
    ``tip`` = phi_i(1) / 2 (~1), ``curv`` = phi_i''(0) (second derivative in xi).
    """
    bls = beam_roots(n)
    scale = [2.0 / _shape(bl, 1.0) for bl in bls]

    def phi(i: int, xi: float) -> float:
        return scale[i] * _shape(bls[i], xi)

    opts = {"epsabs": 1e-14, "epsrel": 1e-13, "limit": 200}
    mass = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            mass[i, j] = quad(lambda x, i=i, j=j: phi(i, x) * phi(j, x), 0, 1, **opts)[0]
    first = np.array([quad(lambda x, i=i: x * phi(i, x), 0, 1, **opts)[0] for i in range(n)])
    tip = np.array([phi(i, 1.0) / 2.0 for i in range(n)])
    curv = np.array([scale[i] * _shape(bls[i], 0.0, deriv=2) for i in range(n)])
    return {"mass": mass, "first": first, "tip": tip, "curv": curv}


# ------------------------------------------------------------------ rig model


def motor_constants(p: PlantParams) -> tuple[float, float]:
    """(G [N.m/V], Bemf [N.m.s/rad]): load-shaft motor torque per volt and back-EMF damping."""
    G = p.eta_g * p.Kg * p.eta_m * p.kt / p.Rm
    return G, G * p.Kg * p.km


def link_inertia(p: PlantParams) -> float:
    """Rigid inertia of the bare link about the hub Jl = m L^2 / 3 [kg.m2] (by quadrature of rho x^2).

    Without the tip mass: Jl defines the link's stiffness through Ks (w_1 = sqrt(Ks / Jl)); the tip mass's
    m_tip L^2 enters the mass matrix (:func:`mass_stiffness`), not this number."""
    return p.m_link / p.L_link * quad(lambda x: x * x, 0.0, p.L_link)[0]


def clamped_frequencies_rad(p: PlantParams) -> np.ndarray:
    """Clamped (hub fixed) natural frequencies of the bare link, w_i = w_1 (beta_i / beta_1)^2 [rad/s],
    w_1 = sqrt(Ks / Jl).

    These fix the modal stiffnesses k_i = J_i w_i^2 (the beam's EI, independent of the tip mass); the clamped
    frequencies with a tip mass are row 1 of :func:`mode_frequencies` (equal to these when m_tip = 0)."""
    bls = np.array(beam_roots(int(p.n_modes)))
    return math.sqrt(p.Ks / link_inertia(p)) * (bls / bls[0]) ** 2


def mass_stiffness(p: PlantParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, K, D) for the coordinates [theta, a_1..a_n] with the hub free (rigid gear).

    M [kg.m2], K [N.m/rad], D [N.m.s/rad]; D holds Beq plus the motor's back-EMF damping on theta
    and the modal damping 2 zeta J_i w_i on each a_i. A tip mass m_tip moves with L (theta' + sum a_i'): its
    kinetic energy adds m_tip L^2 to every entry of M.
    """
    p.validate()
    n = int(p.n_modes)
    m, L = p.m_link, p.L_link
    ints = beam_integrals(n)
    Jl = link_inertia(p)
    Jmode = m * L**2 / 4.0 * ints["mass"]  # q_i = L a_i / 2, int rho phi_i phi_j (L/2)^2
    b = m * L**2 / 2.0 * ints["first"]  # (m/L)(L/2) int x phi_i dx
    w = clamped_frequencies_rad(p)
    N = n + 1
    M = np.zeros((N, N))
    M[0, 0] = p.Jeq + Jl
    M[0, 1:] = M[1:, 0] = b
    M[1:, 1:] = Jmode
    M += p.m_tip * L**2  # the tip mass: its velocity L (theta' + sum a_i') couples every coordinate
    K = np.zeros((N, N))
    K[1:, 1:] = np.diag(np.diag(Jmode) * w**2)
    _, Bemf = motor_constants(p)
    D = np.zeros((N, N))
    D[0, 0] = p.Beq + Bemf
    D[1:, 1:] = np.diag(2.0 * p.zeta_link * np.diag(Jmode) * w)
    return M, K, D


def gauge_weights(p: PlantParams) -> tuple[np.ndarray, float]:
    """(g, c_g): root-curvature weight of each a_i relative to mode 1, and the static calibration factor.

    alpha_gauge = c_g * sum g_i a_i; c_g makes a static tip load (hub clamped) read the static deflection.
    """
    ints = beam_integrals(int(p.n_modes))
    g = ints["curv"] / ints["curv"][0]
    M, K, _ = mass_stiffness(p)
    a_static = np.linalg.solve(K[1:, 1:], ints["tip"])  # unit tip torque
    return g, float(a_static.sum() / (g @ a_static))


def state_space(p: PlantParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C, D) of the linear rig (effects off: friction, backlash, saturation ignored).

    States [theta, a_1..a_n, theta_dot, a_dot_1..n] (rad, rad/s); inputs [u (V), tau_tip (N.m)];
    outputs [theta, alpha, y, theta_dot, alpha_dot, alpha_gauge] (rad, rad/s).  With hub_locked = 1
    the hub rows are zero (theta stays at its initial value) and the link vibrates clamped.
    """
    M, K, Dm = mass_stiffness(p)
    N = M.shape[0]
    G, _ = motor_constants(p)
    F = np.zeros((N, 2))  # generalised forces per input
    F[0, 0] = G
    F[0, 1] = 1.0
    F[1:, 1] = beam_integrals(int(p.n_modes))["tip"]
    Minv = np.linalg.inv(M)
    if p.hub_locked:
        Minv = np.zeros((N, N))
        Minv[1:, 1:] = np.linalg.inv(M[1:, 1:])
    A = np.zeros((2 * N, 2 * N))
    A[:N, N:] = np.eye(N)
    A[N:, :N] = -Minv @ K
    A[N:, N:] = -Minv @ Dm
    B = np.zeros((2 * N, 2))
    B[N:, :] = Minv @ F
    g, c_g = gauge_weights(p)
    C = np.zeros((len(OUTPUTS), 2 * N))
    C[0, 0] = 1.0
    C[1, 1:N] = 1.0
    C[2, :N] = 1.0
    C[3, N] = 1.0
    C[4, N + 1 :] = 1.0
    C[5, 1:N] = c_g * g
    return A, B, C, np.zeros((len(OUTPUTS), 2))


@dataclass(frozen=True)
class GearPlay:
    """The rig with its gear's teeth apart (in the play, ``backlash`` > 0): the hub side and the motor side move
    on their own, as the flexjoint FMU splits them (``Jm_share`` of Jeq and of Beq on the motor side).

    ``A`` (2N x 2N) and ``tip`` (2N) are the hub side's dynamics in :func:`state_space`'s states: its inertia
    Jeq (1 - Jm_share) with the link, its viscous friction Beq (1 - Jm_share), no drive; ``tip`` is a tip torque's
    input column. ``hub`` (2N) is a unit torque on the hub side's effect on the derivatives (its velocity rows: the
    first column of the hub side's inverse mass matrix), so that an impulse P through the gear moves the velocities
    by P ``hub[N:]``. The motor side's speed w obeys Jm w' = G v - (Bemf + Bm) w: ``Jm`` [kg m2], ``damping``
    Bemf + Bm [N m s/rad] and ``drive`` G [N m/V]."""

    A: np.ndarray
    tip: np.ndarray
    hub: np.ndarray
    Jm: float
    damping: float
    drive: float


def gear_play(p: PlantParams) -> GearPlay:
    """The rig ``p`` in its gear's play (:class:`GearPlay`): the hub side from :func:`mass_stiffness` with the hub
    side's inertia and friction and no back-EMF, the motor side's constants."""
    hub_side = PlantParams(**(p.to_dict() | {"Jeq": (1.0 - p.Jm_share) * p.Jeq, "Beq": (1.0 - p.Jm_share) * p.Beq}))
    M, K, D = mass_stiffness(hub_side)
    G, Bemf = motor_constants(p)
    D[0, 0] -= Bemf  # the motor is on the other side of the play
    N = M.shape[0]
    Minv = np.linalg.inv(M)
    A = np.zeros((2 * N, 2 * N))
    A[:N, N:] = np.eye(N)
    A[N:, :N] = -Minv @ K
    A[N:, N:] = -Minv @ D
    F = np.zeros(N)
    F[0] = 1.0
    F[1:] = beam_integrals(int(p.n_modes))["tip"]
    tip, hub = np.zeros(2 * N), np.zeros(2 * N)
    tip[N:], hub[N:] = Minv @ F, Minv[:, 0]
    Jm = p.Jm_share * p.Jeq
    return GearPlay(A=A, tip=tip, hub=hub, Jm=Jm, damping=Bemf + p.Jm_share * p.Beq, drive=G)


def mode_frequencies(p: PlantParams) -> np.ndarray:
    """Undamped flexible-mode frequencies [Hz], shape (2, n_modes): row 0 free hub, row 1 clamped hub.

    Free hub: generalised eigenvalues of (K, M) without the rigid-body zero (damping, back-EMF included, ignored);
    clamped: those of the link block (hub row and column removed), w_i / (2 pi) when m_tip = 0 and below them
    otherwise (the tip mass couples and lowers the modes).
    """
    M, K, _ = mass_stiffness(p)

    lam = np.sort(eigh(K, M, eigvals_only=True))[1:]  # drop the rigid-body mode
    free = np.sqrt(np.maximum(lam, 0.0)) / (2 * math.pi)
    clamped = np.sqrt(np.sort(eigh(K[1:, 1:], M[1:, 1:], eigvals_only=True))) / (2 * math.pi)
    return np.vstack([free, clamped])


def ks_for_first_mode(p: PlantParams, f1_hz: float) -> float:
    """The link stiffness Ks [N.m/rad] that puts the first clamped mode (hub held, as a lab sheet measures it) at
    ``f1_hz`` [Hz] with ``p``'s link, tip mass and modes: the clamped frequencies scale with sqrt(Ks) (K is linear
    in Ks, M does not depend on it)."""
    if not (math.isfinite(f1_hz) and f1_hz > 0):
        raise ValueError(f"first mode must be a frequency > 0 Hz, got {f1_hz}")
    f0 = float(mode_frequencies(p)[1, 0])
    return float(p.Ks * (f1_hz / f0) ** 2)


def sliding_friction(p: PlantParams, w: float) -> float:
    """Friction torque [N.m] against a hub sliding at the speed ``w`` [rad/s] (its magnitude; the sign is the
    sliding direction's): Fc + (Fs - Fc) exp(-(w / stribeck_speed)^2), Fc alone when stribeck_speed is 0."""
    fc = p.coulomb_torque
    if p.stribeck_speed == 0:
        return fc
    return fc + (p.stiction_ratio - 1.0) * fc * math.exp(-((w / p.stribeck_speed) ** 2))


def steady_speed(p: PlantParams, V: float) -> float:
    """Steady hub speed [rad/s] for a constant command V [V], starting from rest.

    Effects off this is eta_g Kg eta_m kt V / (Rm Beq + eta_g eta_m kt km Kg^2); the amplifier's input offset, its limit
    and the friction (breakaway, Coulomb level and Stribeck drop) are applied when set (zero if the hub cannot break
    away; with a Stribeck drop, the first speed from rest where the drive equals friction and damping).
    """
    p.validate()
    v = float(V) + p.u_offset
    if p.amp_limit > 0:
        v = min(max(v, -p.amp_limit), p.amp_limit)
    G, Bemf = motor_constants(p)
    drive, damping = abs(G * v), p.Beq + Bemf
    if drive <= p.stiction_ratio * p.coulomb_torque:
        return 0.0
    w = (drive - p.coulomb_torque) / damping  # the Coulomb level's speed, where the net torque is <= 0

    def net(s: float) -> float:
        return drive - sliding_friction(p, s) - damping * s

    if p.stribeck_speed > 0:
        grid = np.linspace(0.0, w, 4001)
        first = int(np.argmax([net(s) <= 0.0 for s in grid[1:]])) + 1  # the first grid speed past the root
        w = float(brentq(net, grid[first - 1], grid[first], xtol=1e-15)) if net(grid[first]) < 0 else grid[first]
    return math.copysign(w, G * v)


def dead_zone_voltage(p: PlantParams) -> float:
    """Smallest constant command [V] that breaks the hub away from rest: Fs Rm / (eta_g Kg eta_m kt)."""
    p.validate()
    G, _ = motor_constants(p)
    return p.stiction_ratio * p.coulomb_torque / G
