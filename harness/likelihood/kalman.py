"""The Kalman filter through a record and the Rauch-Tung-Striebel smoother, for a sampled linear Gaussian model.

:func:`kalman_filter` runs ``fmus/master/kalman.c`` (built once into the FMU cache with the co-simulation's loops,
:func:`harness.fmu.build.build_master`): a loop in C, since a record holds 5 000-20 000 samples and a fit asks for
thousands of passes. The readings of a sample are taken one channel at a time (their noise is independent), so a
masked reading is skipped. A reading written on a lattice (an ADC's, an encoder's counts) is scored by its cell's
probability and conditions the state on its cell (moment matching, the C file's header), not as a point with
q^2 / 12 of noise: at rest a lattice's error is one constant, not white, and a point reading would count it as
information on every sample. :func:`smooth` runs in numpy: it is asked for once per fit, for the force picture.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from functools import cache

import numpy as np
from scipy.special import ndtr, ndtri

from ..fmu.build import build_master

__all__ = ["Discrete", "Filtered", "kalman_filter", "smooth"]


@dataclass(frozen=True)
class Discrete:
    """A sampled linear Gaussian model: x[k+1] = A x[k] + B u[k] + w[k], w ~ N(0, Q); z[k] = C x[k] + v[k],
    v ~ N(0, diag(r)); the reading y[k] is z[k], or the centre of its cell on a lattice of step ``q`` per channel
    (0: none). Units are the caller's (the rig's: :mod:`harness.likelihood.model`).

    With ``friction`` Fc > 0, friction acts on the state ``speed``: over each sample one torque f held, its effect on
    the state ``hub`` per unit (nx), the torque that brings the speed to rest where that is within +-Fs (stuck: Fs the
    ``breakaway``, Fc where that is less), else the sliding friction against the motion, Fc + (Fs - Fc)
    exp(-(v / ``stribeck``)^2) (Fc alone when ``stribeck`` is 0; ``fmus/master/kalman.c``'s header). With
    ``substeps`` > 1, A, B, Q and ``hub`` are a substep's, taken that many times per sample (the input held), the
    friction after each.

    A channel with ``cubic`` [1/unit^2] not 0 bends: z = C x + cubic (g x)^3 + v, ``bend``'s row g the part of the
    reading that bends (a strain gauge's bridge, its offset apart); the filter's update is then the extended Kalman
    filter's, the row linearised at the predicted state.

    With ``play`` > 0 the model has a gear's play: the state ``gap`` (within +-play / 2) says how far its teeth are
    apart. A, B, Q are then the teeth in contact's, ``loose`` the (A, B, Q) of the sides apart, and ``impact``
    (nx x nx) the plastic impact that brings them together (the gap left to be set): over each step the sides move
    apart, and where that would take the gap past +-play / 2 the teeth are in contact instead, the step taken from the
    state after the impact (``fmus/master/kalman.c``'s header)."""

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    C: np.ndarray
    r: np.ndarray
    q: np.ndarray | None = None
    friction: float = 0.0
    breakaway: float = 0.0
    stribeck: float = 0.0
    hub: np.ndarray | None = None
    speed: int = 0
    substeps: int = 1
    cubic: np.ndarray | None = None
    bend: np.ndarray | None = None
    play: float = 0.0
    gap: int = 0
    loose: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    impact: np.ndarray | None = None


@dataclass(frozen=True)
class Filtered:
    """The filter's pass through a record: the Gaussian log-likelihood ``loglik`` of the measured readings, each
    reading's innovation ``e``, its variance ``s`` and its term of the log-likelihood ``terms`` (n x ny; 0 where
    masked: the channels of a sample taken in turn, each given the ones before it), and, when kept, the predicted
    (``xp``, ``Pp``: before sample k's readings)
    and filtered (``xf``, ``Pf``: after them) states and covariances."""

    loglik: float
    e: np.ndarray
    s: np.ndarray
    terms: np.ndarray
    xp: np.ndarray | None = None
    Pp: np.ndarray | None = None
    xf: np.ndarray | None = None
    Pf: np.ndarray | None = None

    def standardised(self, q: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
        """The innovations as standard normal residuals (n x ny), NaN where a reading was masked: e / sqrt(s) for a
        plain reading; for one on a lattice of step ``q`` (per channel), a randomised quantile residual (Dunn and
        Smyth 1996): the predicted distribution's CDF drawn uniformly across the reading's cell (``seed``: the same
        draws every time), mapped through the normal quantile. Under the right model both are independent standard
        normals, so that a whiteness test holds its level on quantised records."""
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(self.s > 0, self.e / np.sqrt(self.s), np.nan)
            if q is None or not np.any(np.asarray(q) > 0):
                return z
            half = 0.5 * np.broadcast_to(np.asarray(q, dtype=float), z.shape) / np.sqrt(self.s)
            lo, hi = ndtr(z - half), ndtr(z + half)
            u = lo + np.random.default_rng(seed).random(z.shape) * (hi - lo)
            return np.where(half > 0, ndtri(np.clip(u, 1e-300, 1.0 - 1e-16)), z)


@cache
def _library() -> ctypes.CDLL:
    lib = ctypes.CDLL(str(build_master()))
    ptr, n = ctypes.c_void_p, ctypes.c_long
    lib.kalman_filter.restype = ctypes.c_double
    d = ctypes.c_double
    lib.kalman_filter.argtypes = [n, n, n, *[ptr] * 8, n, *[ptr] * 4, n, d, d, d, n, *[ptr] * 2,
                                  ctypes.c_double, n, *[ptr] * 4, *[ptr] * 7]  # fmt: skip
    lib.kalman_max_states.restype = ctypes.c_int
    return lib


def _ptr(a: np.ndarray | None) -> int | None:
    return None if a is None else a.__array_interface__["data"][0]


def _c(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def kalman_filter(
    model: Discrete,
    u: np.ndarray,
    y: np.ndarray,
    mask: np.ndarray,
    x0: np.ndarray,
    P0: np.ndarray,
    keep: bool = False,
) -> Filtered:
    """Run the Kalman filter of ``model`` through a record.

    Parameters
    ----------
    model : Discrete
        The sampled model (nx states, nu inputs, ny readings).
    u : ndarray, shape (n, nu)
        The inputs, each held over its sample.
    y : ndarray, shape (n, ny)
        The readings.
    mask : ndarray of bool, shape (n, ny)
        True where a reading measures (False: skipped, no update).
    x0, P0 : ndarray
        The state's mean (nx) and covariance (nx x nx) at the first sample, before its readings.
    keep : bool
        Keep the predicted and filtered states and covariances (the smoother's input).

    Returns
    -------
    Filtered
        ``loglik`` is NaN when an innovation's variance is not positive or a number is not finite.
    """
    A, B, Q, C, r = (_c(m) for m in (model.A, model.B, model.Q, model.C, model.r))
    nx, nu, ny = A.shape[0], B.shape[1], C.shape[0]
    q = _c(np.zeros(ny) if model.q is None else model.q)
    lib = _library()
    if nx > lib.kalman_max_states():
        raise ValueError(f"the filter takes at most {lib.kalman_max_states()} states, the model has {nx}")
    u, y, x0, P0 = _c(u).reshape(-1, nu), _c(y), _c(x0), _c(P0)
    n = u.shape[0]
    if y.shape != (n, ny) or mask.shape != (n, ny):
        raise ValueError(f"readings {y.shape} and mask {mask.shape} do not match {n} samples of {ny} channels")
    m = _c(mask, np.uint8)
    friction = model.friction if model.hub is not None else 0.0
    hub = _c(model.hub) if friction > 0.0 and model.hub is not None else None
    cubic = bend = None
    if model.cubic is not None and model.bend is not None and np.any(model.cubic):
        cubic, bend = _c(model.cubic), _c(model.bend).reshape(ny, nx)
    play, loose = 0.0, list[np.ndarray | None]([None] * 4)
    if model.play > 0.0 and model.loose is not None and model.impact is not None:
        play, loose = model.play, [_c(m) for m in (*model.loose, model.impact)]
    e, s, terms = np.empty((n, ny)), np.empty((n, ny)), np.empty((n, ny))
    kept = [np.empty((n, nx)), np.empty((n, nx, nx)), np.empty((n, nx)), np.empty((n, nx, nx))] if keep else [None] * 4
    ll = lib.kalman_filter(
        nx, ny, nu, _ptr(A), _ptr(B), _ptr(Q), _ptr(C), _ptr(r), _ptr(q), _ptr(x0), _ptr(P0), n, _ptr(u), _ptr(y),
        _ptr(m), _ptr(hub), model.speed, friction, max(model.breakaway, friction), model.stribeck, model.substeps,
        _ptr(cubic), _ptr(bend), play, model.gap, *(_ptr(k) for k in loose), _ptr(e), _ptr(s), _ptr(terms),
        *(_ptr(k) for k in kept),
    )  # fmt: skip
    return Filtered(float(ll), e, s, terms, *kept)


def smooth(model: Discrete, filtered: Filtered) -> tuple[np.ndarray, np.ndarray]:
    """The Rauch-Tung-Striebel smoother: each sample's state given the whole record.

    Parameters
    ----------
    model : Discrete
        The model the filter ran.
    filtered : Filtered
        A pass kept with ``keep=True``.

    Returns
    -------
    x, P : ndarray
        The smoothed states (n x nx) and their covariances (n x nx x nx).
    """
    if filtered.xp is None or filtered.Pp is None or filtered.xf is None or filtered.Pf is None:
        raise ValueError("the smoother needs the filter's states: run kalman_filter with keep=True")
    bent = model.cubic is not None and np.any(model.cubic)
    if model.friction > 0.0 or model.play > 0.0 or model.substeps != 1 or bent:
        raise ValueError("the smoother takes a linear model: one without friction, a play or a bent reading")
    xp, Pp, xf, Pf = filtered.xp, filtered.Pp, filtered.xf, filtered.Pf
    x, P = xf.copy(), Pf.copy()
    A = model.A
    for k in range(x.shape[0] - 2, -1, -1):
        # J = Pf A' Pp[k+1]^-1, by a least-squares solve: a state the record never moves has a singular Pp
        J = np.linalg.lstsq(Pp[k + 1], A @ Pf[k], rcond=None)[0].T
        x[k] = xf[k] + J @ (x[k + 1] - xp[k + 1])
        P[k] = Pf[k] + J @ (P[k + 1] - Pp[k + 1]) @ J.T
    return x, P
