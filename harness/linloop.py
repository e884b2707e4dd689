"""The loop as a linear discrete-time system: the design model of a rig, a controller as an LTI system, their loop.

:func:`design_model` samples the rig's linear model (:func:`harness.fmu.plant.state_space`: its modes, effects off)
with a zero-order hold at the loop's period and adds the DAQ's linear dynamics, so that the model is the loop as the
controller sees it: the command's delay (``delay_samples`` states holding the past commands), the gauge amplifier's
low-pass (``gauge_tau``) and the gauge's reading delay (``gauge_delay`` states). Its outputs are the angles as the
controller reads them [rad]: each sensor's reading per true angle (the DAQ's gain against the controller's
calibration) scales its channel, and the states are taken in those units (the hub's angle and rate times the hub
sensor's gain, every mode times the gauge's), so that a state weight is a weight on what the lab reads. States:
``theta, a_1..a_n, theta_dot, a_dot_1..a_dot_n`` (the plant's; ``a_i`` mode i's share of alpha), then the gauge's
filter and delay, then the command's delay.

:func:`controller_lti` writes a controller of :mod:`harness.rig.controller` as x_c+ = A x_c + B (r, theta, alpha),
u = C x_c + D (r, theta, alpha) (its clamp left out: the linear loop); :func:`closed_loop` joins the two,
:func:`step_response` runs it, :func:`disk_margin` measures the loop broken at the plant's input with python-control's
``disk_margins`` rule (balanced: skew 0) on the loop's frequency response (:class:`Frequencies`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from scipy.linalg import expm

from .diagnosis.rigmodel import combos
from .fmu.plant import PlantParams, gauge_weights, state_space
from .rig.controller import Controller
from .spec import fmu_value
from .twin import RigTables

__all__ = [
    "DesignModel",
    "Frequencies",
    "LoopLTI",
    "dare",
    "kalman_gain",
    "lqr_gain",
    "closed_loop",
    "controller_lti",
    "design_model",
    "disk_margin",
    "step_response",
]


@dataclass(frozen=True, eq=False)
class DesignModel:
    """x_(k+1) = Phi x_k + Gamma u_k, (theta, alpha) as read [rad] = C x_k, at ``Ts`` [s]; ``n_modes`` link modes,
    ``n_plant`` = 2 (1 + n_modes) states of the plant (the first ones), ``gamma_plant`` their input column (the
    plant's own, where the command enters it after the DAQ's delay); ``alpha_row``: alpha as read per modal state
    (the gauge's weight of each mode); ``drive_gain`` [rad/(V s)] and ``drive_tau`` [s] of the rigid drive as read
    (:mod:`harness.diagnosis.rigmodel`); ``gains``: each sensor's reading per true angle (theta, alpha)."""

    Phi: np.ndarray
    Gamma: np.ndarray
    C: np.ndarray
    Ts: float
    n_modes: int
    n_plant: int
    gamma_plant: np.ndarray
    alpha_row: np.ndarray
    drive_gain: float
    drive_tau: float
    gains: tuple[float, float]

    @property
    def n(self) -> int:
        return self.Phi.shape[0]

    def plant_only(self) -> DesignModel:
        """The plant's states alone (the DAQ's delays and filter left out)."""
        k = self.n_plant
        return replace(self, Phi=self.Phi[:k, :k], Gamma=self.gamma_plant, C=self.C[:, :k])

    def outputs_z(self) -> np.ndarray:
        """Cz: z = (theta, alpha, theta_dot, alpha_dot) as read = Cz x."""
        m = self.n_modes
        Cz = np.zeros((4, self.n))
        Cz[0, 0] = 1.0
        Cz[1, 1 : 1 + m] = self.alpha_row
        Cz[2, 1 + m] = 1.0
        Cz[3, 2 + m : 2 + 2 * m] = self.alpha_row
        return Cz

    def weights(self, q: tuple[float, float, float, float]) -> np.ndarray:
        """The state weight Q = Cz' diag(q) Cz on z = (theta, alpha, theta_dot, alpha_dot) as read."""
        Cz = self.outputs_z()
        return Cz.T @ np.diag(q) @ Cz


def plant_params(plant: dict[str, Any], n_modes: int | None = None) -> Any:
    """A plant table (FMU names; other keys ignored) as :class:`harness.fmu.plant.PlantParams`, the hub free;
    ``n_modes``: the link modes to keep (default the table's)."""
    names = {f.name for f in fields(PlantParams)}
    kept = {k: v for k, v in plant.items() if k in names} | {"hub_locked": 0}
    return PlantParams(**kept | ({"n_modes": int(n_modes)} if n_modes is not None else {}))


def design_model(tables: RigTables, Ts: float, n_modes: int | None = None) -> DesignModel:
    """The rig ``tables`` as the controller at period ``Ts`` [s] sees it (see the module docstring); ``n_modes``:
    link modes to keep (default the plant's own)."""
    p = plant_params(tables.plant, n_modes)
    plant = {f.name: getattr(p, f.name) for f in fields(PlantParams)}
    A, B, Cc, _ = state_space(p)
    m = int(p.n_modes)
    N = 1 + m
    g_th = tables.calibration["theta_gain"] / fmu_value(tables.daq, "daq", "pot_gain")
    g_al = tables.calibration["alpha_gain"] / fmu_value(tables.daq, "daq", "gauge_gain")
    T = np.diag([g_th] + [g_al] * m + [g_th] + [g_al] * m)  # states as read
    A = T @ A @ np.linalg.inv(T)
    B = T @ B[:, :1]
    C = np.vstack([Cc[0], Cc[5]]) @ np.diag([1 / g_th] + [1 / g_al] * m + [1 / g_th] + [1 / g_al] * m)
    C = np.diag([g_th, g_al]) @ C
    n = A.shape[0]
    M = expm(np.block([[A, B], [np.zeros((1, n + 1))]]) * Ts)
    Phi, Gam = M[:n, :n], M[:n, n:]
    gamma_plant = Gam.copy()
    # the DAQ: the gauge's low-pass and reading delay on alpha, the command's delay
    tau = fmu_value(tables.daq, "daq", "gauge_tau")
    n_gd = int(fmu_value(tables.daq, "daq", "gauge_delay"))
    n_ud = int(fmu_value(tables.daq, "daq", "delay_samples"))
    Phi, Gam, C = _gauge_filter(Phi, Gam, C, math.exp(-Ts / tau) if tau > 0 else None)
    for _ in range(n_gd):
        Phi, Gam, C = _delay_output(Phi, Gam, C)
    for _ in range(n_ud):
        Phi, Gam, C = _delay_input(Phi, Gam, C)
    c = combos(plant)
    g, c_g = gauge_weights(p)
    drive = (c["rig.drive_gain"] * g_th, c["rig.drive_tau"])
    return DesignModel(Phi, Gam, C, Ts, m, 2 * N, gamma_plant, c_g * g, *drive, (g_th, g_al))


def _gauge_filter(
    Phi: np.ndarray, Gam: np.ndarray, C: np.ndarray, e: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """alpha read through y_k = e y_(k-1) + (1 - e) w_k (the gauge amplifier's low-pass), None: no filter."""
    if e is None:
        return Phi, Gam, C
    n = Phi.shape[0]
    ca = C[1]
    Phi2 = np.zeros((n + 1, n + 1))
    Phi2[:n, :n] = Phi
    Phi2[n, :n] = (1 - e) * ca @ Phi
    Phi2[n, n] = e
    Gam2 = np.vstack([Gam, (1 - e) * ca @ Gam])
    C2 = np.zeros((2, n + 1))
    C2[0, :n] = C[0]
    C2[1, n] = 1.0
    return Phi2, Gam2, C2


def _delay_output(Phi: np.ndarray, Gam: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """alpha read one sample later: a state holding the alpha the model read before."""
    n = Phi.shape[0]
    Phi2 = np.zeros((n + 1, n + 1))
    Phi2[:n, :n] = Phi
    Phi2[n, :n] = C[1]
    C2 = np.zeros((2, n + 1))
    C2[0, :n] = C[0]
    C2[1, n] = 1.0
    return Phi2, np.vstack([Gam, [[0.0]]]), C2


def _delay_input(Phi: np.ndarray, Gam: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The command reaching the plant one sample later: a state holding the last command."""
    n = Phi.shape[0]
    Phi2 = np.zeros((n + 1, n + 1))
    Phi2[:n, :n] = Phi
    Phi2[:n, n:] = Gam
    Gam2 = np.zeros((n + 1, 1))
    Gam2[n, 0] = 1.0
    return Phi2, Gam2, np.hstack([C, np.zeros((2, 1))])


@dataclass(frozen=True, eq=False)
class LoopLTI:
    """A discrete LTI system x+ = A x + B w, z = C x + D w."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray


def controller_lti(c: Controller, Ts: float) -> LoopLTI:
    """The controller as an LTI system from (r, theta, alpha) [rad] to u [V] (its clamp left out; the velocity
    filters and the estimator from rest)."""
    a = math.exp(-2.0 * math.pi * c.cutoff * Ts)
    f = (1.0 - a) / Ts
    if c.kind == "state_feedback":  # states: last theta, last alpha, v_theta, v_alpha
        k0, k1, k2, k3 = c.K
        kv = np.array([k2, k3])
        A = np.zeros((4, 4))
        A[2:, 2:] = a * np.eye(2)
        A[2:, :2] = -f * np.eye(2)
        B = np.zeros((4, 3))
        B[:2, 1:] = np.eye(2)
        B[2:, 1:] = f * np.eye(2)
        C = np.zeros((1, 4))
        C[0, 2:] = -kv * a
        C[0, :2] = kv * f
        D = np.array([[k0, -k0 - k2 * f, -k1 - k3 * f]])
        return LoopLTI(A, B, C, D)
    if c.kind == "pid":  # states: last theta, v_theta, integral
        A = np.array([[0.0, 0.0, 0.0], [-f, a, 0.0], [0.0, 0.0, 1.0]])
        B = np.array([[0.0, 1.0, 0.0], [0.0, f, 0.0], [Ts, -Ts, 0.0]])
        C = np.array([[c.kd * f, -c.kd * a, c.ki]])
        D = np.array([[c.kp, -c.kp - c.kd * f, 0.0]])
        return LoopLTI(A, B, C, D)
    e = c.estimator  # lqg: states x_hat_(k-1), u_(k-1)
    assert e is not None
    Phi, Gam, Cm, L = (np.asarray(x, dtype=float) for x in (e.A, e.B, e.C, e.L))
    K, Nr = np.asarray(e.K, dtype=float), np.asarray(e.N, dtype=float)
    n = Phi.shape[0]
    Gam = Gam.reshape(n, 1)
    IL = np.eye(n) - L @ Cm
    pred = np.hstack([IL @ Phi, IL @ Gam])  # x_hat_k = pred @ (x_hat_(k-1), u_(k-1)) + L y_k
    Cu = -K @ pred
    Du = np.concatenate([[K @ Nr], -K @ L])
    A = np.vstack([pred, Cu])
    By = np.vstack([L, -K @ L])
    B = np.hstack([np.vstack([np.zeros((n, 1)), [[K @ Nr]]]), By])
    return LoopLTI(A, B, Cu.reshape(1, -1), Du.reshape(1, 3))


def closed_loop(model: DesignModel, c: Controller) -> LoopLTI:
    """The loop from the reference r [rad] to (theta, alpha as read [rad], u [V]); its state (plant, controller)."""
    k = controller_lti(c, model.Ts)
    Br, By = k.B[:, :1], k.B[:, 1:]
    Dr, Dy = k.D[:, :1], k.D[:, 1:]
    n, m = model.n, k.A.shape[0]
    A = np.block([[model.Phi + model.Gamma @ Dy @ model.C, model.Gamma @ k.C], [By @ model.C, k.A]])
    B = np.vstack([model.Gamma @ Dr, Br])
    C = np.vstack([np.hstack([model.C, np.zeros((2, m))]), np.hstack([Dy @ model.C, k.C])])
    D = np.vstack([np.zeros((2, 1)), Dr])
    assert A.shape == (n + m, n + m)
    return LoopLTI(A, B, C, D)


def spectral_radius(loop: LoopLTI) -> float:
    """The largest |eigenvalue| of the loop: below 1 when it is stable."""
    return float(np.max(np.abs(np.linalg.eigvals(loop.A))))


def step_response(loop: LoopLTI, ref_rad: np.ndarray) -> np.ndarray:
    """The loop's (theta, alpha [rad], u [V]) from rest for the reference ``ref_rad``, shape (3, n)."""
    x = np.zeros(loop.A.shape[0])
    out = np.empty((3, ref_rad.size))
    A, b, C, d = loop.A, loop.B[:, 0], loop.C, loop.D[:, 0]
    for i, r in enumerate(ref_rad):
        out[:, i] = C @ x + d * r
        x = A @ x + b * r
        if not np.isfinite(x[0]) or abs(x[0]) > 1e6:
            out[:, i:] = np.inf
            break
    return out


def dare(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, tol: float = 1e-13, iters: int = 64) -> np.ndarray:
    """The stabilising solution X of the discrete algebraic Riccati equation X = A'XA - A'XB (R + B'XB)^-1 B'XA + Q
    by the structure-preserving doubling algorithm (quadratic convergence; no inverse of A, so delay states are fine):
    A_(k+1) = A_k W^-1 A_k, G_(k+1) = G_k + A_k W^-1 G_k A_k', H_(k+1) = H_k + A_k' H_k W^-1 A_k, W = I + G_k H_k,
    from A, B R^-1 B', Q; H_k -> X. scipy's ``solve_discrete_are`` gives the same X (to 1e-13 here) in 30x the
    time, which a search over hundreds of weights pays. Raises ValueError when it does not converge."""
    n = A.shape[0]
    Ak, Gk, Hk, eye = A.copy(), B @ np.linalg.solve(R, B.T), Q.copy(), np.eye(n)
    for _ in range(iters):
        W = eye + Gk @ Hk
        WA, WG = np.linalg.solve(W, Ak), np.linalg.solve(W, Gk)
        Hn = Hk + Ak.T @ Hk @ WA
        Gk, Ak = Gk + Ak @ WG @ Ak.T, Ak @ WA
        if not np.all(np.isfinite(Hn)):
            break
        if float(np.linalg.norm(Hn - Hk, 1)) <= tol * max(float(np.linalg.norm(Hn, 1)), 1e-300):
            return 0.5 * (Hn + Hn.T)
        Hk = Hn
    raise ValueError("the Riccati equation has no stabilising solution for these weights")


def lqr_gain(Phi: np.ndarray, Gamma: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The discrete LQR gain K (u = -K x) of x+ = Phi x + Gamma u for the weights Q, R: K = (R + G'XG)^-1 G'X Phi
    (python-control's ``dlqr``)."""
    X = dare(Phi, Gamma, Q, R)
    return np.linalg.solve(R + Gamma.T @ X @ Gamma, Gamma.T @ X @ Phi)


def kalman_gain(Phi: np.ndarray, C: np.ndarray, Qw: np.ndarray, Rv: np.ndarray) -> np.ndarray:
    """The steady-state Kalman gain in current form, L = P C' (C P C' + Rv)^-1, P the a priori covariance of x+ = Phi
    x + w, y = C x + v (cov Qw, Rv): the dual Riccati equation."""
    P = dare(Phi.T, C.T, Qw, Rv)
    return P @ C.T @ np.linalg.inv(C @ P @ C.T + Rv)


class Frequencies:
    """The plant's frequency response on ``points`` frequencies log-spaced from 0.01 rad/s to just below the Nyquist
    frequency, computed once per model: every controller's loop is then one product (:meth:`disk_margin`)."""

    def __init__(self, model: DesignModel, points: int = 2000) -> None:
        self.model = model
        self.omega = np.logspace(-2, math.log10(0.999 * math.pi / model.Ts), points)
        self.z = np.exp(1j * self.omega * model.Ts)
        self.P = _response(model.Phi, model.Gamma, model.C, np.zeros((2, 1)), self.z)  # (points, 2, 1)

    def loop(self, c: Controller) -> np.ndarray:
        """L(e^(j w Ts)) of the loop broken at the plant's input: -K(z) P(z), K the controller from (theta, alpha)
        to u (the loop is u = -L u)."""
        k = controller_lti(c, self.model.Ts)
        K = _response(k.A, k.B[:, 1:], k.C, k.D[:, 1:], self.z)  # (points, 1, 2)
        return -(K @ self.P)[:, 0, 0]

    def disk_margin(self, c: Controller) -> dict[str, float]:
        """The balanced disk margin (skew 0) of the loop: alpha = 1 / max |(S - T) / 2| = 2 / max |(1 - L) / (1 + L)|,
        the gain margin (1 + alpha/2) / (1 - alpha/2) [dB] (infinite from alpha = 2) and the phase margin 2 atan(alpha /
        2) [deg], python-control's ``disk_margins`` on the same frequencies; all 0 when the loop is unstable."""
        if spectral_radius(closed_loop(self.model, c)) >= 1.0:
            return {"disk_margin": 0.0, "gain_margin_db": 0.0, "phase_margin_deg": 0.0}
        L = self.loop(c)
        a = 2.0 / float(np.max(np.abs((1.0 - L) / (1.0 + L))))
        gm = 20.0 * math.log10((1.0 + a / 2.0) / (1.0 - a / 2.0)) if a < 2.0 else math.inf
        return {"disk_margin": a, "gain_margin_db": gm, "phase_margin_deg": math.degrees(2.0 * math.atan(a / 2.0))}


def _response(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, z: np.ndarray) -> np.ndarray:
    """C (zI - A)^-1 B + D at every z: shape (len(z), outputs, inputs)."""
    n = A.shape[0]
    if n == 0:
        return np.broadcast_to(D, (z.size, *D.shape)).astype(complex)
    M = z[:, None, None] * np.eye(n) - A
    return C @ np.linalg.solve(M, np.broadcast_to(B, (z.size, *B.shape))) + D


def disk_margin(model: DesignModel, c: Controller, points: int = 2000) -> dict[str, float]:
    """:meth:`Frequencies.disk_margin` of ``c`` on ``model`` over ``points`` frequencies."""
    return Frequencies(model, points).disk_margin(c)
