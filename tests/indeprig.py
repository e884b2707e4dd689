"""An independent simulator of the flexible-joint rig, for checking the diagnoser on data our FMUs did not make.

Nothing here uses the project's FMUs, ``harness.fmu.plant``, ``harness.fmu.cosim`` or ``harness.rig.controller``: the
beam, the drive train, the friction and backlash laws, the integrator (scipy's ``solve_ivp``), the DAQ and the closed
loop's controller are written anew, with other model structures than the twin's. Only the command signals
(``harness.rig.signals``), the experiment seeds and the run-directory format (``harness.rig.campaign``,
``harness.rundir``) are shared, since they are not the plant.

Physics (SI, angles in rad, all torques at the load shaft):

- Amplifier + DC motor + gearbox: ``V`` clipped at ``amp_limit`` (0 = off); torque
  ``tau = G (V - Kg km w_m)`` with ``G = motor_gain eta_g eta_m Kg kt / Rm`` [N m/V].
- Drive train: motor-side inertia ``Jm = Jm_fraction Jeq`` with viscous damping ``Beq`` and friction, hub inertia
  ``Jh = Jeq - Jm`` carrying the link. With ``backlash`` = 0 the two are one rigid inertia ``Jeq``.
- Backlash (total play b): a dead-band contact spring between the motor side and the hub,
  ``tau_c = k_c dz(phi, b/2) + c_c dphi/dt`` in contact (never pulling), ``phi = theta_m - theta``. Chosen
  ``k_c = contact_stiffness = 50 N m/rad`` (a ~42 Hz contact mode between Jm and the hub + link: well above the
  link's first modes and stiff enough that 0.05 N m of drive compresses it by 1e-3 rad, yet integrable) and
  ``c_c = 2 contact_zeta sqrt(k_c J_red)`` with ``contact_zeta = 0.3`` and ``J_red`` the reduced inertia of Jm
  and the hub + rigid link. The damping fades in over the first 1e-4 rad of penetration so that the contact
  torque is continuous at first touch.
- Friction on the motor side (gear train): Stribeck law with a smooth sign,
  ``F(v) = (Fc + (Fs - Fc) exp(-(v/vs)^2)) tanh(v/eps)``, ``Fc = coulomb_torque``, ``Fs = 1.3 Fc``,
  ``vs = 0.05 rad/s``, ``eps = 1e-4 rad/s`` (creep below breakaway ~ eps atanh(drive/Fs): hundredths of a degree
  in seconds, invisible to the pot). The tanh makes stiction stiff (dF/dv = Fs/eps, 3e5 1/s on Jeq). The twin's hub
  friction has the same law as a hybrid stuck/sliding model (``stiction_ratio``, ``stribeck_speed``; 0 there is no
  drop), so the two are checked against each other on a stick-slip record.
- Link: Euler-Bernoulli beam (EI, rhoA = m/L), clamped at the hub, assumed modes = the clamped-free shapes
  ``psi_i`` normalised to a unit tip deflection (``psi_i(L) = 1``, so q_i is mode i's tip deflection [m]).
  Displacement ``w(x) = x theta + sum psi_i(x) q_i``; mass matrix entries ``rhoA int x^2``, ``rhoA int x psi_i``,
  ``rhoA int psi_i psi_j``, stiffness ``EI int psi_i'' psi_j''``, all by Gauss-Legendre quadrature (64 nodes).
  Modal damping ``2 zeta_link sqrt(k_i m_i)``. A tip torque ``tau_tip`` [N m] is a tip force tau_tip / L.
- Outputs: hub angle theta, deflection ``alpha = w_tip / L = sum q_i / L``, and the gauge signal from the root
  curvature ``kappa0 = sum psi_i''(0) q_i``, scaled so that a static tip load reads alpha exactly.

DAQ: command sampled and held over each sample interval, DAC clamp +-``dac_limit``, ``delay_samples`` of
transport delay (zeros first). At t_k the sensors read the state at t_k (before command k acts, the twin's
convention). Pot: theta [deg] wrapped to [-180, 180), ``v = wrapped / pot_gain + pot_offset``, within
``pot_deadband``/2 of the wrap the wiper rests on the track end. Gauge: ``v = alpha_g / Ke (1 + gauge_cubic
(alpha_g/10)^2) + gauge_offset`` (alpha_g in deg). Seeded Gaussian noise, then an ADC with ``adc_bits`` over
+-``adc_range`` (codes -2^(bits-1) .. 2^(bits-1) - 1; 0 bits = ideal).

Integration: ``solve_ivp`` per stretch of constant input (so the held command never jumps inside a solver step),
``t_eval`` at the samples, ``max_step = Ts``. Smooth rigs (no friction, no play): DOP853. Friction or play: LSODA
(it switches to BDF when sticking or contact makes the system stiff) with the analytic Jacobian. rtol 1e-7, atol
rtol x (0.01 rad, 0.1 mm, 1 rad/s, 10 mm/s). Measured against rtol 1e-10 references on the blind campaign's
records: <= 1e-6 deg (smooth), ~2e-5 deg (friction + play); rtol 1e-6 left 1e-2 deg on friction + play (stick-slip
timing), which is why 1e-7. Both are far below the noise (0.07 deg on the pot, 0.007 deg on the gauge).

Closed loop (:func:`simulate_closed`): the controller is a lab controller written from the law's specification
(:class:`LabLaw`: state feedback u = K (x_ref - x) on (theta, alpha, theta_dot, alpha_dot) or PID on theta with the
derivative on the measurement and conditional-integration anti-windup; velocities by backward differences through a
first-order low-pass, v_0 = 0; output clamp). It reads its own DAQ's sampled volts (noise and ADC included) with the
rig's nominal calibration (pot gain, gauge Ke, offsets). The command of sample k is held over [t_k, t_k+1) (direct
feedthrough, the project's master's convention), then DAC clamp, delay and amplifier limit as in open loop. The
plant is stepped one sample at a time by the same ``solve_ivp`` stepping as :func:`integrate` (a closed loop's
command changes every sample, as a noisy open-loop command does). A 6 s record at 500 Hz takes ~0.4 s on a smooth
rig and ~1.3 s with friction and play. On a smooth rig DOP853 takes one step per sample: its states agree with the
exact zero-order-hold propagation of the same command to ~1e-12 deg (1e-8 deg with 3 modes); with friction and play,
rtol 1e-7 against 1e-10 differ by ~3e-5 deg. With a 12-bit ADC the loop is sensitive to which side of a code edge a
sample falls: a 1e-5 deg difference can flip a code and the two runs then differ by a few tenths of a degree, as two
runs of a real rig would, though each is an equally accurate solution.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp
from scipy.linalg import expm
from scipy.optimize import brentq

DEG = 180.0 / math.pi
MAX_MODES = 3
RTOL = 1e-7
METHOD = "DOP853"
METHOD_NONSMOOTH = "LSODA"
DIVERGED_ALPHA = math.radians(45.0)  # a closed loop whose link deflects more has diverged (the link would break)
CONTACT_RAMP = 1e-4  # rad of gear penetration over which the contact damping fades in
_QUAD_NODES = 64


# ------------------------------------------------------------------ beam


@cache
def clamped_free_roots(n: int) -> tuple[float, ...]:
    """beta_i L, i = 1..n: roots of 1 + cos(x) cosh(x) = 0 (1.8751, 4.6941, 7.8548), one in each ((i-1) pi, i pi)."""
    return tuple(
        float(brentq(lambda x: 1.0 + math.cos(x) * math.cosh(x), (i - 1) * math.pi, i * math.pi, xtol=1e-14))
        for i in range(1, n + 1)
    )


def _shape(bl: float, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Clamped-free shape at xi = x/L and its second derivative d2/dxi2, normalised to 1 at the tip."""
    r = (math.sinh(bl) - math.sin(bl)) / (math.cosh(bl) + math.cos(bl))
    z = bl * xi

    def raw(z: np.ndarray) -> np.ndarray:
        return np.cosh(z) - np.cos(z) - r * (np.sinh(z) - np.sin(z))

    def raw2(z: np.ndarray) -> np.ndarray:
        return bl**2 * (np.cosh(z) + np.cos(z) - r * (np.sinh(z) + np.sin(z)))

    tip = float(raw(np.array(bl)))
    return raw(z) / tip, raw2(z) / tip


@dataclass(frozen=True)
class Beam:
    """Assumed-modes matrices of the clamped link (mode shapes with unit tip deflection, q_i in m).

    J_rigid [kg m^2] = rhoA int x^2; coupling [kg m] = rhoA int x psi_i; mass [kg] = rhoA int psi_i psi_j;
    stiffness [N/m] = EI int psi_i'' psi_j''; curv0 [1/m] = psi_i''(0); beta_L the clamped-free roots.
    """

    J_rigid: float
    coupling: np.ndarray
    mass: np.ndarray
    stiffness: np.ndarray
    curv0: np.ndarray
    beta_L: tuple[float, ...]


@cache
def beam_matrices(EI: float, m: float, L: float, n: int) -> Beam:
    """Beam of flexural rigidity EI [N m^2], mass m [kg], length L [m] with n assumed modes (quadrature)."""
    xg, wg = np.polynomial.legendre.leggauss(_QUAD_NODES)
    xi = 0.5 * (xg + 1.0)  # nodes on [0, 1]
    dx = 0.5 * wg * L  # weights for int_0^L dx
    rhoA = m / L
    bls = clamped_free_roots(n)
    psi = np.empty((n, xi.size))
    psi2 = np.empty((n, xi.size))  # d2 psi / dx2 [1/m]
    curv0 = np.empty(n)
    for i, bl in enumerate(bls):
        s, s2 = _shape(bl, xi)
        psi[i], psi2[i] = s, s2 / L**2
        curv0[i] = _shape(bl, np.array([0.0]))[1][0] / L**2
    x = xi * L
    return Beam(
        J_rigid=float(rhoA * np.sum(dx * x * x)),
        coupling=rhoA * (psi * x) @ dx,
        mass=rhoA * (psi * dx) @ psi.T,
        stiffness=EI * (psi2 * dx) @ psi2.T,
        curv0=curv0,
        beta_L=bls,
    )


def ei_from_ks(Ks: float, L: float = 0.419) -> float:
    """EI [N m^2] whose first clamped mode gives the project's Ks [N m/rad]: w1^2 Jl = Ks, EI = 3 L Ks / (b1 L)^4."""
    return 3.0 * L * Ks / clamped_free_roots(1)[0] ** 4


# ------------------------------------------------------------------ rig


@dataclass(frozen=True)
class IndepRig:
    """The independent rig: defaults are the textbook rig (one mode, effects off, 2 mV noise on both channels)."""

    # amplifier, motor, gearbox
    Rm: float = 2.6  # armature resistance [ohm]
    kt: float = 7.68e-3  # torque constant [N m/A]
    km: float = 7.68e-3  # back-EMF constant [V s/rad]
    Kg: float = 70.0  # gear ratio [-]
    eta_g: float = 0.9  # gearbox efficiency [-]
    eta_m: float = 0.69  # motor efficiency [-]
    motor_gain: float = 1.0  # factor on eta_g eta_m (drive torque and back-EMF damping) [-]
    amp_limit: float = 0.0  # amplifier saturation [V], 0 = none
    u_offset: float = 0.0  # amplifier input offset [V]: it drives (held command + u_offset), then its limit
    # drive train
    Jeq: float = 2.08e-3  # motor side + hub inertia at the load shaft [kg m^2]
    Jm_fraction: float = 0.4  # share of Jeq on the motor side of the play [-]
    Beq: float = 0.004  # viscous damping, motor side [N m s/rad]
    backlash: float = 0.0  # total gear play [rad], 0 = rigid
    contact_stiffness: float = 50.0  # gear-contact spring k_c [N m/rad]
    contact_zeta: float = 0.3  # gear-contact damping ratio [-]
    coulomb_torque: float = 0.0  # Coulomb friction Fc [N m], 0 = none
    stribeck_ratio: float = 1.3  # Fs / Fc [-]
    stribeck_velocity: float = 0.05  # vs [rad/s]
    friction_eps: float = 1e-4  # velocity of the smooth sign tanh(v / eps) [rad/s]
    # link
    m_link: float = 0.065  # [kg]
    L_link: float = 0.419  # [m]
    m_tip: float = 0.0  # a point mass at the tip [kg]
    EI: float = ei_from_ks(1.3, 0.419)  # flexural rigidity [N m^2] (Ks_eq = 1.3 N m/rad)
    n_modes: int = 1  # assumed modes (1..3)
    zeta_link: float = 0.01  # modal damping ratio [-]
    # DAQ
    dac_limit: float = 10.0  # command clamp [V]
    delay_samples: int = 0  # transport delay of the command [samples]
    pot_gain: float = 35.5  # Kp [deg/V]
    pot_offset: float = 0.0  # [V]
    pot_deadband: float = 10.0  # [deg] around the wrap
    gauge_Ke: float = -3.36  # gauge calibration [deg/V]
    gauge_offset: float = 0.01  # [V]
    gauge_cubic: float = 0.0  # relative cubic term at 10 deg [-]
    pot_bow: float = 0.0  # pot linearity error: the track reads theta + pot_bow 180 sin(pi theta / 180) [-]
    gauge_drift: float = 0.0  # gauge gain drift about its offset: x (1 + gauge_drift t) [1/s]
    adc_bits: int = 0  # 0 = ideal
    adc_range: float = 10.0  # [V]
    noise_theta: float = 0.002  # pot noise [V rms]
    noise_alpha: float = 0.002  # gauge noise [V rms]

    @classmethod
    def from_Ks(cls, Ks: float, **kw: Any) -> IndepRig:
        """A rig whose link has the project's stiffness Ks [N m/rad] (first clamped mode sqrt(Ks / Jl))."""
        return cls(EI=ei_from_ks(Ks, float(kw.get("L_link", cls.L_link))), **kw)

    def validate(self) -> None:
        """Raise ValueError naming the first unusable parameter."""
        for f in fields(self):
            if not math.isfinite(getattr(self, f.name)):
                raise ValueError(f"IndepRig.{f.name} must be finite")
        for name in ("Rm", "kt", "Kg", "Jeq", "m_link", "L_link", "EI", "motor_gain", "pot_gain", "adc_range"):
            if not getattr(self, name) > 0:
                raise ValueError(f"IndepRig.{name} = {getattr(self, name)} must be > 0")
        for name in ("km", "Beq", "backlash", "coulomb_torque", "amp_limit", "zeta_link", "noise_theta", "m_tip"):
            if getattr(self, name) < 0:
                raise ValueError(f"IndepRig.{name} = {getattr(self, name)} must be >= 0")
        if self.noise_alpha < 0 or self.dac_limit <= 0 or self.gauge_Ke == 0:
            raise ValueError("IndepRig: need noise_alpha >= 0, dac_limit > 0, gauge_Ke != 0")
        if self.backlash > 0 and not (0.05 <= self.Jm_fraction <= 0.95 and self.contact_stiffness > 0):
            raise ValueError("IndepRig: backlash needs Jm_fraction in [0.05, 0.95] and contact_stiffness > 0")
        if self.coulomb_torque > 0 and not (self.stribeck_ratio >= 1 and self.stribeck_velocity > 0):
            raise ValueError("IndepRig: friction needs stribeck_ratio >= 1 and stribeck_velocity > 0")
        if self.coulomb_torque > 0 and not self.friction_eps > 0:
            raise ValueError("IndepRig.friction_eps must be > 0")
        if int(self.n_modes) != self.n_modes or not 1 <= self.n_modes <= MAX_MODES:
            raise ValueError(f"IndepRig.n_modes = {self.n_modes} must be an integer in 1..{MAX_MODES}")
        if int(self.delay_samples) != self.delay_samples or self.delay_samples < 0:
            raise ValueError(f"IndepRig.delay_samples = {self.delay_samples} must be an integer >= 0")
        if int(self.adc_bits) != self.adc_bits or not 0 <= self.adc_bits <= 32:
            raise ValueError(f"IndepRig.adc_bits = {self.adc_bits} must be an integer in 0..32")
        if not 0 <= self.pot_deadband < 360:
            raise ValueError(f"IndepRig.pot_deadband = {self.pot_deadband} must be in [0, 360)")


def motor_constants(rig: IndepRig) -> tuple[float, float]:
    """(G [N m/V], back-EMF damping [N m s/rad]) at the load shaft."""
    G = rig.motor_gain * rig.eta_g * rig.eta_m * rig.Kg * rig.kt / rig.Rm
    return G, G * rig.Kg * rig.km


def beam_of(rig: IndepRig) -> Beam:
    return beam_matrices(float(rig.EI), float(rig.m_link), float(rig.L_link), int(rig.n_modes))


def link_inertia(rig: IndepRig) -> float:
    """Rigid link inertia about the hub Jl = m L^2 / 3 [kg m^2]."""
    return rig.m_link * rig.L_link**2 / 3.0


def clamped_frequency_closed_form(rig: IndepRig) -> float:
    """First clamped-free frequency w1 = (b1 L)^2 sqrt(EI / (rhoA L^4)) [rad/s]."""
    return clamped_free_roots(1)[0] ** 2 * math.sqrt(rig.EI * rig.L_link / (rig.m_link * rig.L_link**4))


def equivalent_Ks(rig: IndepRig) -> float:
    """The project's Ks [N m/rad] for this link: w1^2 Jl, w1 the first clamped mode, Jl = m L^2 / 3."""
    return clamped_frequency_closed_form(rig) ** 2 * link_inertia(rig)


def mode_frequencies(rig: IndepRig, hub: str = "free") -> np.ndarray:
    """Undamped link-mode frequencies [Hz] of the assembled model: hub "free" (rigid gear, rigid-body mode
    dropped) or "clamped"."""
    b = beam_of(rig)
    if hub == "clamped":
        lam = np.linalg.eigvals(np.linalg.solve(b.mass + rig.m_tip, b.stiffness)).real
    elif hub == "free":
        n = int(rig.n_modes)
        M = np.zeros((n + 1, n + 1))
        M[0, 0] = rig.Jeq + b.J_rigid + rig.m_tip * rig.L_link**2
        M[0, 1:] = M[1:, 0] = b.coupling + rig.m_tip * rig.L_link
        M[1:, 1:] = b.mass + rig.m_tip
        K = np.zeros_like(M)
        K[1:, 1:] = b.stiffness
        lam = np.sort(np.linalg.eigvals(np.linalg.solve(M, K)).real)[1:]
    else:
        raise ValueError(f"hub must be 'free' or 'clamped', got {hub!r}")
    return np.sqrt(np.sort(np.maximum(lam, 0.0))) / (2 * math.pi)


def tip_compliance(rig: IndepRig) -> float:
    """Static deflection alpha [rad] per tip torque [N m] with the hub clamped (the assumed modes' statics)."""
    b = beam_of(rig)
    q = np.linalg.solve(b.stiffness, np.ones(int(rig.n_modes)) / rig.L_link)
    return float(q.sum() / rig.L_link)


def gauge_scale(rig: IndepRig) -> float:
    """c [rad m]: alpha_gauge = c kappa0 reads the deflection of a static tip load exactly."""
    b = beam_of(rig)
    q = np.linalg.solve(b.stiffness, np.ones(int(rig.n_modes)))
    return float(q.sum() / rig.L_link / (b.curv0 @ q))


# ------------------------------------------------------------------ equations of motion


class _Plant:
    """First-order form s' = A s + c(u, tau) + nonlinear torques, for one rig and hub condition.

    Coordinates: rigid gear [theta, q_1..q_n], backlash [theta_m, theta, q_1..q_n], hub locked [q_1..q_n];
    state s = [coordinates, their rates].
    """

    def __init__(self, rig: IndepRig, hub_locked: bool) -> None:
        rig.validate()
        b = beam_of(rig)
        n = int(rig.n_modes)
        self.locked = bool(hub_locked)
        self.play = (not self.locked) and rig.backlash > 0
        self.friction = (not self.locked) and rig.coulomb_torque > 0
        G, Bemf = motor_constants(rig)
        self.G = G
        nh = 0 if self.locked else (2 if self.play else 1)  # hub/motor coordinates
        N = nh + n
        self.N, self.nh, self.n = N, nh, n
        self.im = 0  # motor-side coordinate
        self.ih = 1 if self.play else 0  # hub coordinate
        M = np.zeros((N, N))
        K = np.zeros((N, N))
        D = np.zeros((N, N))
        M[nh:, nh:] = b.mass + rig.m_tip  # a tip mass moves with every mode's unit tip deflection
        K[nh:, nh:] = b.stiffness
        k_modal = np.diag(b.stiffness)
        D[nh:, nh:] = np.diag(2.0 * rig.zeta_link * np.sqrt(k_modal * np.diag(b.mass)))
        f_tip = np.zeros(N)
        f_tip[nh:] = 1.0 / rig.L_link  # tip force tau / L on each unit-tip-deflection mode
        if not self.locked:
            Jm = rig.Jm_fraction * rig.Jeq if self.play else rig.Jeq
            Jh = rig.Jeq - Jm if self.play else 0.0
            ih = self.ih
            M[0, 0] += Jm
            M[ih, ih] += Jh + b.J_rigid + rig.m_tip * rig.L_link**2
            M[ih, nh:] = M[nh:, ih] = b.coupling + rig.m_tip * rig.L_link
            D[0, 0] = rig.Beq + Bemf
            f_tip[ih] = 1.0
            if self.play:
                Jhub = Jh + b.J_rigid + rig.m_tip * rig.L_link**2
                self.k_c = rig.contact_stiffness
                self.c_c = 2.0 * rig.contact_zeta * math.sqrt(self.k_c * Jm * Jhub / (Jm + Jhub))
                self.half_play = 0.5 * rig.backlash
        Minv = np.linalg.inv(M)
        A = np.zeros((2 * N, 2 * N))
        A[:N, N:] = np.eye(N)
        A[N:, :N] = -Minv @ K
        A[N:, N:] = -Minv @ D
        self.A = A
        self.b_tip = np.concatenate([np.zeros(N), Minv @ f_tip])
        if not self.locked:
            self.b_motor = Minv[:, 0].copy()  # acceleration per unit torque on the motor coordinate
            self.b_contact = Minv[:, self.ih] - Minv[:, 0]  # per unit contact torque (+hub, -motor)
            self.b_u = np.concatenate([np.zeros(N), G * self.b_motor])
        if self.friction:
            self.Fc = rig.coulomb_torque
            self.Fs = rig.stribeck_ratio * rig.coulomb_torque
            self.vs = rig.stribeck_velocity
            self.eps = rig.friction_eps
        # absolute tolerance per unit rtol: 0.01 rad, 0.1 mm, 1 rad/s, 10 mm/s
        self.atol_per_rtol = np.concatenate([np.full(nh, 1e-2), np.full(n, 1e-4), np.full(nh, 1.0), np.full(n, 1e-2)])

    # -- nonlinear torques and their slopes
    def friction_torque(self, v: float) -> tuple[float, float]:
        """Stribeck friction F(v) [N m] and dF/dv at motor-side speed v [rad/s]."""
        e = math.exp(-((v / self.vs) ** 2))
        level = self.Fc + (self.Fs - self.Fc) * e
        th = math.tanh(v / self.eps)
        dlevel = (self.Fs - self.Fc) * e * (-2.0 * v / self.vs**2)
        return level * th, dlevel * th + level * (1.0 - th * th) / self.eps

    def contact_torque(self, phi: float, dphi: float) -> tuple[float, float, float]:
        """Contact torque [N m] on the hub and its slopes in phi and dphi (0 inside the play, never pulling).

        The damping fades in over the first ``CONTACT_RAMP`` of penetration, so the torque is continuous at
        first touch (an adaptive integrator would otherwise chase the jump c_c dphi down to tiny steps).
        """
        if phi > self.half_play:
            pen = phi - self.half_play
        elif phi < -self.half_play:
            pen = phi + self.half_play
        else:
            return 0.0, 0.0, 0.0
        r = abs(pen) / CONTACT_RAMP
        if r < 1.0:
            tau = self.k_c * pen + self.c_c * r * dphi
            d_phi = self.k_c + self.c_c * dphi * math.copysign(1.0 / CONTACT_RAMP, pen)
            d_dphi = self.c_c * r
        else:
            tau, d_phi, d_dphi = self.k_c * pen + self.c_c * dphi, self.k_c, self.c_c
        return (tau, d_phi, d_dphi) if tau * pen > 0 else (0.0, 0.0, 0.0)

    def functions(self, u: float, tau_tip: float) -> tuple[Callable, Callable]:
        """(rhs, jac) for a stretch of constant amplifier voltage u [V] and tip torque [N m]."""
        A, N = self.A, self.N
        c = self.b_tip * tau_tip
        if not self.locked:
            c = c + self.b_u * u
        if not (self.play or self.friction):
            return (lambda t, s: A @ s + c), (lambda t, s: A)
        play, friction, im, ih = self.play, self.friction, self.im, self.ih
        b_motor = self.b_motor if friction else None
        b_contact = self.b_contact if play else None
        zeros = np.zeros(N)
        # ds = A s + W (1, F, tau_c): the constant input, the friction and the contact torque in one product
        W = np.column_stack(
            [
                c,
                np.concatenate([zeros, -self.b_motor]) if friction else np.zeros(2 * N),
                np.concatenate([zeros, self.b_contact]) if play else np.zeros(2 * N),
            ]
        )
        friction_torque, contact_torque = self.friction_torque, self.contact_torque
        vm, vh = N + im, N + ih

        def rhs(t: float, s: np.ndarray) -> np.ndarray:
            F = friction_torque(s[vm])[0] if friction else 0.0
            tau_c = contact_torque(s[im] - s[ih], s[vm] - s[vh])[0] if play else 0.0
            return A @ s + W @ np.array((1.0, F, tau_c))

        def jac(t: float, s: np.ndarray) -> np.ndarray:
            J = A.copy()
            if friction:
                J[N:, N + im] -= self.friction_torque(s[N + im])[1] * b_motor
            if play:
                _, kp, kd = self.contact_torque(s[im] - s[ih], s[N + im] - s[N + ih])
                J[N:, im] += kp * b_contact
                J[N:, ih] -= kp * b_contact
                J[N:, N + im] += kd * b_contact
                J[N:, N + ih] -= kd * b_contact
            return J

        return rhs, jac


class _Stepper:
    """The per-stretch stepping shared by :func:`integrate` (open loop) and :func:`simulate_closed`: ``solve_ivp``
    over a stretch of constant input, DOP853 on a smooth plant, LSODA with the analytic Jacobian on one with
    friction or play, ``rtol`` and atol = rtol x the plant's scales, ``max_step = Ts``, and each stretch's first
    step the solver's last step of the previous one-sample stretch (offered, never imposed: the error control
    still rejects it)."""

    def __init__(self, plant: _Plant, Ts: float, rtol: float) -> None:
        self.plant, self.Ts, self.rtol = plant, Ts, rtol
        self.method = METHOD_NONSMOOTH if (plant.friction or plant.play) else METHOD
        self.atol = plant.atol_per_rtol * rtol
        self.h_last = Ts

    def advance(self, s0: np.ndarray, t: np.ndarray, drive: float, tau_tip: float) -> np.ndarray:
        """States at t[1:] [shape (len(t) - 1, 2N)] from ``s0`` at t[0], amplifier voltage ``drive`` [V] and tip
        torque ``tau_tip`` [N m] held over [t[0], t[-1]]."""
        rhs, jac = self.plant.functions(drive, tau_tip)
        one = t.size == 2  # one sample: the end point is a solver step, no interpolation needed
        sol = solve_ivp(
            rhs,
            (t[0], t[-1]),
            s0,
            method=self.method,
            t_eval=None if one else t[1:],
            rtol=self.rtol,
            atol=self.atol,
            max_step=self.Ts,
            first_step=min(self.h_last, t[-1] - t[0]),
            **({"jac": jac} if self.method in ("LSODA", "Radau", "BDF") else {}),
        )
        if not sol.success:
            raise RuntimeError(f"solve_ivp failed at t = {t[0]:.3f} s: {sol.message}")
        if one:
            self.h_last = float(sol.t[-1] - sol.t[-2])
            return sol.y[:, -1:].T
        return sol.y.T


def integrate(
    rig: IndepRig,
    u_amp: np.ndarray,
    Ts: float,
    tau_tip: np.ndarray | None = None,
    hub_locked: bool = False,
    rtol: float = RTOL,
) -> tuple[_Plant, np.ndarray]:
    """States at t_k = k Ts [shape (n, 2N)] from rest, with amplifier input u_amp[k] [V] (after delay and
    saturation) and tip torque tau_tip[k] [N m] held over [t_k, t_k+1). Absolute tolerances scale with rtol."""
    plant = _Plant(rig, hub_locked)
    n = u_amp.size
    tau = np.zeros(n) if tau_tip is None else np.asarray(tau_tip, dtype=float)
    S = np.zeros((n, 2 * plant.N))
    drive = np.zeros(n) if plant.locked else u_amp
    change = np.flatnonzero((np.diff(drive) != 0) | (np.diff(tau) != 0)) + 1
    starts = np.concatenate([[0], change])
    stops = np.concatenate([change, [n]])
    t = np.arange(n) * Ts
    stepper = _Stepper(plant, Ts, rtol)
    for k0, k1 in zip(starts, stops, strict=True):
        k_end = min(int(k1), n - 1)  # the state at t_n is not needed
        if k_end > k0:
            S[k0 + 1 : k_end + 1] = stepper.advance(S[k0], t[k0 : k_end + 1], float(drive[k0]), float(tau[k0]))
    return plant, S


# ------------------------------------------------------------------ DAQ


def pot_volts(theta_deg: np.ndarray, rig: IndepRig) -> np.ndarray:
    """Potentiometer voltage [V] for shaft angles [deg]: wrap to [-180, 180), track ends in the dead band, the
    track's linearity error (a sine bow of ``pot_bow`` x 180 deg)."""
    wrapped = np.mod(np.asarray(theta_deg, dtype=float) + 180.0, 360.0) - 180.0
    end = 180.0 - 0.5 * rig.pot_deadband
    wrapped = np.clip(wrapped, -end, end)
    wrapped = wrapped + rig.pot_bow * 180.0 * np.sin(np.radians(wrapped))
    return wrapped / rig.pot_gain + rig.pot_offset


def gauge_volts(alpha_deg: np.ndarray, rig: IndepRig, t: np.ndarray | float = 0.0) -> np.ndarray:
    """Strain-gauge bridge voltage [V] for a gauge-equivalent deflection [deg] at time ``t`` [s] (its gain drifts
    about the offset by ``gauge_drift`` per second)."""
    a = np.asarray(alpha_deg, dtype=float)
    bridge = a / rig.gauge_Ke * (1.0 + rig.gauge_cubic * (a / 10.0) ** 2)
    return bridge * (1.0 + rig.gauge_drift * np.asarray(t, dtype=float)) + rig.gauge_offset


def adc(v: np.ndarray, bits: int, full_scale: float) -> np.ndarray:
    """Two's-complement ADC over +-full_scale [V]: codes -2^(bits-1) .. 2^(bits-1) - 1 (bits 0 = ideal)."""
    if bits == 0:
        return np.asarray(v, dtype=float)
    lsb = 2.0 * full_scale / 2.0**bits
    half = 2.0 ** (bits - 1)
    return np.clip(np.floor(np.asarray(v) / lsb + 0.5), -half, half - 1) * lsb


def simulate(
    rig: IndepRig,
    u: np.ndarray,
    Ts: float,
    seed: int = 0,
    tau_tip: np.ndarray | None = None,
    hub_locked: bool = False,
    rtol: float = RTOL,
) -> dict[str, np.ndarray]:
    """Run one record: command u [V] sampled at Ts [s]; optional tip torque [N m] per sample; hub clamped or not;
    ``seed`` draws the noise; ``rtol`` of the integrator (default :data:`RTOL`).

    Returns arrays of len(u): t [s], u [V], u_plant [V] (held, clamped, delayed, saturated), theta_v, alpha_v [V]
    (measured at t_k), true theta, alpha [deg], and theta_m [deg] (motor side), theta_dot [deg/s], alpha_gauge [deg].
    """
    u = np.asarray(u, dtype=float)
    if u.ndim != 1 or u.size < 2 or not np.all(np.isfinite(u)):
        raise ValueError("u must be a 1-D array of at least 2 finite commands")
    if not Ts > 0:
        raise ValueError(f"Ts must be > 0, got {Ts}")
    rig.validate()
    n = u.size
    d = int(rig.delay_samples)
    u_dac = np.clip(u, -rig.dac_limit, rig.dac_limit)
    u_held = np.zeros(n)
    if d < n:
        u_held[d:] = u_dac[: n - d]
    u_in = u_held + rig.u_offset
    u_amp = np.clip(u_in, -rig.amp_limit, rig.amp_limit) if rig.amp_limit > 0 else u_in
    if tau_tip is not None:
        tau_tip = np.asarray(tau_tip, dtype=float)
        if tau_tip.shape != u.shape or not np.all(np.isfinite(tau_tip)):
            raise ValueError("tau_tip must be finite and as long as u")
    plant, S = integrate(rig, u_amp, Ts, tau_tip, hub_locked, rtol)
    out = _outputs(rig, plant, S)
    noise_theta, noise_alpha = _noise(rig, seed, n)
    theta_v = pot_volts(out["theta"], rig) + noise_theta
    alpha_v = gauge_volts(out["alpha_gauge"], rig, np.arange(n) * Ts) + noise_alpha
    return {
        "t": np.arange(n) * Ts,
        "u": u,
        "u_plant": u_amp,
        "theta_v": adc(theta_v, int(rig.adc_bits), rig.adc_range),
        "alpha_v": adc(alpha_v, int(rig.adc_bits), rig.adc_range),
        **out,
    }


def _outputs(rig: IndepRig, plant: _Plant, S: np.ndarray) -> dict[str, np.ndarray]:
    """theta, alpha, theta_m [deg], theta_dot [deg/s] and the gauge-equivalent alpha_gauge [deg] of states S."""
    N, nh = plant.N, plant.nh
    q = S[:, nh:N]
    if plant.locked:
        theta = theta_m = theta_dot = np.zeros(len(S))
    else:
        theta, theta_m, theta_dot = S[:, plant.ih], S[:, plant.im], S[:, N + plant.ih]
    alpha = q.sum(axis=1) / rig.L_link
    alpha_gauge = gauge_scale(rig) * (q @ beam_of(rig).curv0)
    return {
        "theta": theta * DEG,
        "alpha": alpha * DEG,
        "theta_m": theta_m * DEG,
        "theta_dot": theta_dot * DEG,
        "alpha_gauge": alpha_gauge * DEG,
    }


def _noise(rig: IndepRig, seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The measurement noise [V] of the pot and the gauge for ``n`` samples: two streams spawned from ``seed``."""
    rng_theta, rng_alpha = (np.random.default_rng(s) for s in np.random.SeedSequence(int(seed)).spawn(2))
    return rig.noise_theta * rng_theta.standard_normal(n), rig.noise_alpha * rng_alpha.standard_normal(n)


# ------------------------------------------------------------------ closed loop


@dataclass(frozen=True)
class LabLaw:
    """The closed loop's control law, written anew from its specification (the project's controller is not used).

    ``state_feedback``: u = K (x_ref - x) on x = (theta, alpha, theta_dot, alpha_dot) [rad, rad/s], x_ref = (ref,
    0, 0, 0). ``pid`` on e = ref - theta: u = kp e + ki I - kd theta_dot (derivative on the measurement), I the
    forward-Euler integral of e, not advanced at a sample whose output is clamped (conditional integration).
    Velocities: the backward difference through a first-order low-pass at ``cutoff`` [Hz], v_0 = 0. Output
    clamped to +-``u_limit`` [V] (0: none).
    """

    kind: str = "state_feedback"
    K: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    cutoff: float = 50.0
    u_limit: float = 0.0
    sample_rate: float | None = None

    @classmethod
    def of(cls, controller: Any) -> LabLaw:
        """From a spec's controller (any object with these attributes, e.g. ``harness.rig.controller.Controller``)
        or its dict (``to_dict()``, a manifest's ``controller``); other keys (source, r2) are ignored."""
        if isinstance(controller, LabLaw):
            return controller
        if isinstance(controller, Mapping):
            get = controller.get
        else:

            def get(name: str, default: Any = None) -> Any:
                return getattr(controller, name, default)

        law = cls(
            kind=str(get("kind", "state_feedback")),
            K=tuple(float(k) for k in get("K", (0.0,) * 4)),  # type: ignore[arg-type]
            **{k: float(get(k, getattr(cls, k))) for k in ("kp", "ki", "kd", "cutoff", "u_limit")},
            sample_rate=None if get("sample_rate") is None else float(get("sample_rate")),
        )
        if law.kind not in ("state_feedback", "pid"):
            raise ValueError(f"controller kind {law.kind!r} unknown; valid: state_feedback, pid")
        if len(law.K) != 4 or not all(math.isfinite(v) for v in (*law.K, law.kp, law.ki, law.kd, law.u_limit)):
            raise ValueError("controller: K must be 4 finite gains, kp, ki, kd and u_limit finite")
        if not (law.cutoff > 0 and math.isfinite(law.cutoff)) or law.u_limit < 0:
            raise ValueError(f"controller: need cutoff > 0 Hz and u_limit >= 0 V, got {law.cutoff}, {law.u_limit}")
        return law


def nominal_calibration(rig: IndepRig) -> tuple[float, float, float, float]:
    """The lab controller's angle calibration (theta_gain [deg/V], theta_offset [V], alpha_gain [deg/V],
    alpha_offset [V]): the rig's nominal pot gain and gauge Ke with their offsets (no cubic term, no dead band)."""
    return rig.pot_gain, rig.pot_offset, rig.gauge_Ke, rig.gauge_offset


class LabController:
    """A lab controller at ``Ts``: every sample it converts the DAQ's volts with its calibration and returns the
    command of :class:`LabLaw` (state carried from sample to sample: last angles, filtered velocities, integral)."""

    def __init__(self, law: LabLaw, Ts: float, calibration: tuple[float, float, float, float]) -> None:
        self.law, self.Ts = law, Ts
        self.th_gain, self.th_off, self.al_gain, self.al_off = calibration
        self.a = math.exp(-2.0 * math.pi * law.cutoff * Ts)
        self.lim = law.u_limit if law.u_limit > 0 else math.inf
        self.last: tuple[float, float] | None = None
        self.v_th = self.v_al = self.integral = 0.0

    def step(self, ref: float, theta_v: float, alpha_v: float) -> float:
        """Command u [V] at this sample from the reference [rad] and the sampled volts."""
        law, Ts, a = self.law, self.Ts, self.a
        th = math.radians(self.th_gain * (theta_v - self.th_off))
        al = math.radians(self.al_gain * (alpha_v - self.al_off))
        d_th, d_al = (0.0, 0.0) if self.last is None else ((th - self.last[0]) / Ts, (al - self.last[1]) / Ts)
        self.last = (th, al)
        self.v_th = a * self.v_th + (1.0 - a) * d_th
        self.v_al = a * self.v_al + (1.0 - a) * d_al
        if law.kind == "state_feedback":
            k = law.K
            raw = k[0] * (ref - th) - k[1] * al - k[2] * self.v_th - k[3] * self.v_al
            return min(max(raw, -self.lim), self.lim)
        e = ref - th
        raw = law.kp * e + law.ki * self.integral - law.kd * self.v_th
        u = min(max(raw, -self.lim), self.lim)
        if u == raw:
            self.integral += Ts * e
        return u


def zoh(rig: IndepRig, Ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rig without friction, play and limits sampled exactly with a zero-order hold at ``Ts``: (Ad, Bd, C) with
    s_k+1 = Ad s_k + Bd u_k (u the amplifier voltage [V]) and C s = (theta, alpha_gauge) [rad]; s as in
    :func:`integrate` (rigid gear)."""
    plant = _Plant(replace(rig, coulomb_torque=0.0, backlash=0.0), hub_locked=False)
    n2 = 2 * plant.N
    aug = np.zeros((n2 + 1, n2 + 1))
    aug[:n2, :n2], aug[:n2, n2] = plant.A, plant.b_u
    E = expm(aug * Ts)
    C = np.zeros((2, n2))
    C[0, plant.ih] = 1.0
    C[1, plant.nh : plant.N] = gauge_scale(rig) * beam_of(rig).curv0
    return E[:n2, :n2], E[:n2, n2], C


def closed_loop_poles(rig: IndepRig, controller: Any, Ts: float) -> np.ndarray:
    """Eigenvalues of the sampled closed loop linearised about rest: the rig without friction, play and limits
    (exact zero-order-hold discretisation), its command delay, the controller's velocity filters and integrator.

    Loop state z_k = (plant state s_k, angles read at k-1, velocities at k-1, integral, commands u_{k-1..k-d});
    the pot reads theta and the gauge alpha_gauge (the cubic term has no slope at rest)."""
    law = LabLaw.of(controller)
    Ad, Bd, C = zoh(rig, Ts)
    n2, d = Ad.shape[0], int(rig.delay_samples)
    a = math.exp(-2.0 * math.pi * law.cutoff * Ts)
    i_y, i_v, i_I, i_u = n2, n2 + 2, n2 + 4, n2 + 5  # block offsets in z
    nz = i_u + d
    y = np.zeros((2, nz))  # angles read at k
    y[:, :n2] = C
    v = a * np.eye(2, nz, i_v) + (1.0 - a) / Ts * (y - np.eye(2, nz, i_y))  # filtered velocities at k
    if law.kind == "state_feedback":
        F = -law.K[0] * y[0] - law.K[1] * y[1] - law.K[2] * v[0] - law.K[3] * v[1]
    else:
        F = -law.kp * y[0] + law.ki * np.eye(1, nz, i_I)[0] - law.kd * v[0]
    Phi = np.zeros((nz, nz))
    applied = F if d == 0 else np.eye(1, nz, i_u + d - 1)[0]  # the command acting over [t_k, t_k+1)
    Phi[:n2, :n2] = Ad
    Phi[:n2] += np.outer(Bd, applied)
    Phi[i_y : i_y + 2] = y
    Phi[i_v : i_v + 2] = v
    if law.kind == "pid":  # state feedback has no integral: its row stays zero (a pole at 0, not a spurious 1)
        Phi[i_I] = np.eye(1, nz, i_I)[0] - Ts * y[0]
    if d:
        Phi[i_u] = F
        Phi[i_u + 1 : i_u + d, i_u : i_u + d - 1] = np.eye(d - 1)
    return np.linalg.eigvals(Phi)


def check_stable(rig: IndepRig, controller: Any, Ts: float) -> None:
    """Raise ValueError (one line) when the controller destabilises the rig (a pole of
    :func:`closed_loop_poles` outside the unit circle)."""
    z = closed_loop_poles(rig, controller, Ts)
    worst = z[np.argmax(np.abs(z))]
    if abs(worst) > 1.0 + 1e-9:
        law = LabLaw.of(controller)
        f = abs(np.angle(worst)) / (2 * math.pi * Ts)
        where = f"{f:.2f} Hz" if f > 0 else "real"
        gains = f"K = {list(law.K)}" if law.kind == "state_feedback" else f"kp, ki, kd = {law.kp}, {law.ki}, {law.kd}"
        raise ValueError(
            f"controller ({law.kind}, {gains}) destabilises the rig: closed-loop pole |z| = {abs(worst):.4f} > 1 "
            f"({where}) at Ts = {Ts:g} s, rig linearised without friction, play and limits"
        )


def simulate_closed(
    rig: IndepRig,
    ref_rad: np.ndarray,
    Ts: float,
    controller: Any,
    seed: int = 0,
    rtol: float = RTOL,
    check: bool = True,
    start: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
    calibration: tuple[float, float, float, float] | None = None,
) -> dict[str, np.ndarray]:
    """Run one closed-loop record: the shaft tracks ``ref_rad`` [rad per sample at Ts] under ``controller`` (a
    spec's controller or its dict, :meth:`LabLaw.of`), from ``start`` (hub angle, tip deflection angle [rad] in the
    first mode, and their rates [rad/s]; default rest); ``seed`` draws the noise; ``calibration``: the one the lab
    controller converts its volts with (default :func:`nominal_calibration`: a lab that knows its gauge's offset).

    Sample by sample: at t_k the DAQ samples the state (noise, ADC, as :func:`simulate`); the controller converts
    those volts with :func:`nominal_calibration` and computes u_k, which after the DAC clamp, ``delay_samples`` and
    the amplifier limit is held over [t_k, t_k+1) (direct feedthrough, as the project's co-simulation master);
    the plant is integrated over that interval by the same stepping as :func:`integrate`.

    A controller that destabilises the rig is refused with a one-line ValueError: with ``check``, before the run
    on a smooth rig (:func:`check_stable`: there the linearisation is the rig, but for its limits); on a rig with
    friction or play, whose linearisation at rest is not defined (a stuck hub clamps the link, which can hold a
    loop the linear part would lose: the lab rig's LQR with a second mode and one sample of delay), when the run
    diverges: the link deflects more than :data:`DIVERGED_ALPHA` or the shaft strays more than half a turn from the
    reference (the pot wraps: the controller has lost the angle).

    Returns the keys of :func:`simulate` (``u`` the controller's command [V]) plus ``ref`` [deg].
    """
    ref = np.asarray(ref_rad, dtype=float)
    if ref.ndim != 1 or ref.size < 2 or not np.all(np.isfinite(ref)):
        raise ValueError("ref_rad must be a 1-D array of at least 2 finite angles")
    if not Ts > 0:
        raise ValueError(f"Ts must be > 0, got {Ts}")
    rig.validate()
    law = LabLaw.of(controller)
    if law.sample_rate is not None and abs(law.sample_rate * Ts - 1.0) > 1e-9:
        raise ValueError(f"controller sample_rate {law.sample_rate:g} Hz differs from the DAQ's {1 / Ts:g} Hz")
    if check and not (rig.coulomb_torque > 0 or rig.backlash > 0):
        check_stable(rig, law, Ts)
    n, d = ref.size, int(rig.delay_samples)
    plant = _Plant(rig, hub_locked=False)
    stepper = _Stepper(plant, Ts, rtol)
    ctl = LabController(law, Ts, calibration or nominal_calibration(rig))
    noise_theta, noise_alpha = _noise(rig, seed, n)
    bits, fs = int(rig.adc_bits), rig.adc_range
    t = np.arange(n) * Ts
    S = np.zeros((n, 2 * plant.N))
    S[0, plant.ih], S[0, plant.nh], S[0, plant.N + plant.ih], S[0, plant.N + plant.nh] = (
        start[0], rig.L_link * start[1], start[2], rig.L_link * start[3])  # fmt: skip
    if plant.play:
        S[0, plant.im], S[0, plant.N + plant.im] = start[0], start[2]
    u, u_amp, theta_v, alpha_v = (np.zeros(n) for _ in range(4))
    ih, curv = plant.ih, gauge_scale(rig) * beam_of(rig).curv0 * DEG  # alpha_gauge [deg] per modal coordinate
    amp = rig.amp_limit if rig.amp_limit > 0 else math.inf
    q_tip = np.zeros(2 * plant.N)  # alpha [rad] = q_tip @ s
    q_tip[plant.nh : plant.N] = 1.0 / rig.L_link
    for k in range(n):
        s = S[k]
        if abs(float(q_tip @ s)) > DIVERGED_ALPHA or abs(s[ih] - ref[k]) > math.pi:
            raise ValueError(
                f"closed loop diverged at t = {t[k]:.3f} s (theta {s[ih] * DEG:.1f} deg, reference "
                f"{ref[k] * DEG:.1f} deg, alpha {q_tip @ s * DEG:.1f} deg): the controller destabilises the rig"
            )
        theta_v[k] = adc(pot_volts(s[ih] * DEG, rig) + noise_theta[k], bits, fs)
        alpha_v[k] = adc(gauge_volts(curv @ s[plant.nh : plant.N], rig, k * Ts) + noise_alpha[k], bits, fs)
        u[k] = ctl.step(float(ref[k]), float(theta_v[k]), float(alpha_v[k]))
        held = min(max(u[k - d], -rig.dac_limit), rig.dac_limit) if k >= d else 0.0
        u_amp[k] = min(max(held + rig.u_offset, -amp), amp)
        if k + 1 < n:
            S[k + 1] = stepper.advance(s, t[k : k + 2], float(u_amp[k]), 0.0)[0]
    return {
        "t": t,
        "u": u,
        "u_plant": u_amp,
        "theta_v": theta_v,
        "alpha_v": alpha_v,
        **_outputs(rig, plant, S),
        "ref": ref * DEG,
    }


# ------------------------------------------------------------------ run directories


def comb_layout(
    params: dict[str, Any], duration: float, Ts: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The comb calibration's schedule as the project lays it out: comb angle -atan(l / D) per deflection l [cm],
    each reached by a raised-cosine ramp of ``ramp`` s and held ``hold`` s.

    Per sample: (target angle [deg], previous target [deg], ramp fraction 0..1, comb_angle [deg, NaN outside
    the holds]).
    """
    ls = np.asarray(params.get("deflections_cm", [-3.7, -3.05, -2.4, -1.8, -1.1, -0.5, 0, 0.6, 1.4, 2, 2.65, 3.3, 3.9]))
    D, hold, ramp = float(params.get("D_cm", 40.0)), float(params.get("hold", 3.0)), float(params.get("ramp", 1.0))
    n = int(round(duration / Ts))
    t = np.arange(n) * Ts
    angles = -np.degrees(np.arctan(ls / D))
    if ls.size * (hold + ramp) > duration + 1e-9:
        raise ValueError(f"comb: duration {duration} s too short for {ls.size} holds")
    target = np.full(n, angles[-1])
    before = np.full(n, angles[-1])
    frac = np.ones(n)
    comb = np.full(n, np.nan)
    prev = 0.0
    for i, a in enumerate(angles):
        t0 = i * (hold + ramp)
        up = (t >= t0) & (t < t0 + ramp)
        held = (t >= t0 + ramp) & (t < t0 + ramp + hold)
        target[up | held], before[up | held] = a, prev
        frac[up] = 0.5 * (1.0 - np.cos(np.pi * (t[up] - t0) / ramp))
        comb[held] = a
        prev = a
    return target, before, frac, comb


def comb_run(rig: IndepRig, params: dict[str, Any], duration: float, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """(tau_tip [N m], comb_angle [deg, NaN between holds]) for a comb on this rig's own beam statics."""
    target, before, frac, comb = comb_layout(params, duration, Ts)
    angle = np.radians(before + (target - before) * frac)
    return angle / tip_compliance(rig), comb


_OVERRIDABLE = {f.name for f in fields(IndepRig)}


def make_run(dest: Path, spec: Any, rig: IndepRig, seed: int) -> Path:
    """Write run directory ``dest`` for ``spec`` (a :class:`harness.spec.Spec`) simulated on ``rig``.

    Same layout as ``harness.rig.campaign.run_campaign``: ``data/<experiment>.parquet`` and ``manifest.json``. The
    spec's [plant]/[daq] tables describe the twin and are not applied (the rig replaces them); an experiment's
    own overrides are applied where their names are IndepRig fields. ``seed`` draws the measurement noise.
    A closed-loop experiment (``loop = "closed"``) runs under the spec's [controller] (:func:`simulate_closed`),
    its signal the theta reference [deg]: its dataset adds ``ref`` [deg], its ``u`` is the controller's command,
    and its manifest entry has ``loop`` "closed" and the ``controller`` (``to_dict()``).
    """
    import platform

    import scipy

    from harness import __version__
    from harness.rig.campaign import experiment_seed
    from harness.rig.signals import generate
    from harness.rundir import write_dataset, write_json

    dest = Path(dest)
    Ts = spec.Ts
    entries = []
    for exp in spec.all_experiments():
        n = int(round(exp.duration * spec.sample_rate))
        e_seed = experiment_seed(spec, exp)
        over = {k: v for k, v in {**exp.plant, **exp.daq}.items() if k in _OVERRIDABLE}
        r = replace(rig, **over) if over else rig
        noise_seed = int(np.random.SeedSequence([int(seed), e_seed]).generate_state(1)[0])
        entry = {"name": exp.name, "role": exp.role, "signal": exp.signal, "n": n, "seed": e_seed}
        if exp.signal == "comb":
            tau, comb = comb_run(r, exp.params, exp.duration, Ts)
            res = simulate(r, np.zeros(n), Ts, noise_seed, tau_tip=tau, hub_locked=True)
        elif exp.loop == "closed":
            if spec.controller is None:
                raise ValueError(f"experiment {exp.name!r} runs closed loop but the spec has no [controller]")
            ref = generate(exp.signal, n, Ts, exp.params, e_seed)  # the theta reference [deg]
            res = simulate_closed(r, np.radians(ref), Ts, spec.controller, noise_seed)
            res["ref"] = ref
            entry.update(loop="closed", controller=spec.controller.to_dict())
        else:
            res = simulate(r, generate(exp.signal, n, Ts, exp.params, e_seed), Ts, noise_seed)
        cols = {k: res[k] for k in ("t", "u", "theta_v", "alpha_v", "theta", "alpha")}
        if exp.signal == "comb":
            cols["tau_tip"], cols["comb_angle"] = tau, comb
        if exp.loop == "closed":
            cols["ref"] = res["ref"]
        write_dataset(dest / "data" / f"{exp.name}.parquet", cols)
        entries.append(entry)
    manifest = {
        "kind": "campaign",
        "generator": "tests/indeprig.py",
        "spec": spec.raw,
        "spec_file": Path(spec.path).name,
        "spec_sha256": spec.sha256(),
        "seed": spec.seed,
        "noise_seed": int(seed),
        "sample_rate": spec.sample_rate,
        "versions": {
            "harness": __version__,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
        },
        "experiments": entries,
    }
    write_json(dest / "manifest.json", manifest)
    return dest
