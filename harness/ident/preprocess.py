"""Preprocessing of identification data, as in lab 1.

The shaft/tip angle contains the plant's integrator. It is removed by differentiating the output and the
noise this amplifies is cut by a first-order low-pass, both in one filter

    H(z) = (1 - af) (z - 1) / (z - af) = (1 - af) (1 - z^-1) / (1 - af z^-1),   0 <= af < 1,

with DC gain 0, gain 2 (1 - af) / (1 + af) at Nyquist, a zero at z = 1 and a pole at z = af. ``af = 0`` is
the plain first difference y[k] - y[k-1]; ``af = 0.8`` is the labs' default. The input is detrended.

:func:`filter_coefficients` is the one definition of H in the package: the filter, its transfer function, its
frequency response and its inverse (``harness.ident.lti.with_integrator``) are built from it. The armax FMU
(``fmus/armax/model.c``) applies the inverse in C.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.signal import detrend as _scipy_detrend
from scipy.signal import lfilter, lfilter_zi

__all__ = [
    "as_signal",
    "detrend",
    "diff_filter",
    "filter_coefficients",
    "filter_response",
    "preprocess",
    "time_axis",
]

DETREND_KINDS = ("constant", "linear", "none")


def _check_af(af: float) -> float:
    try:
        af = float(af)
    except (TypeError, ValueError):
        raise ValueError(f"filter coefficient af must be a number in [0, 1), got {af!r}") from None
    if not (math.isfinite(af) and 0.0 <= af < 1.0):
        raise ValueError(f"filter coefficient af must be in [0, 1), got {af!r}")
    return af


def as_signal(name: str, x: Any, n: int | None = None) -> np.ndarray:
    """``x`` as a finite 1-D float array (of ``n`` samples when given), or ValueError naming ``name``."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array, got shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"{name} is empty")
    if n is not None and a.size != n:
        raise ValueError(f"{name} has {a.size} samples, expected {n} (same as the other signals)")
    if not np.all(np.isfinite(a)):
        bad = int(np.flatnonzero(~np.isfinite(a))[0])
        raise ValueError(f"{name} contains NaN or inf (first at sample {bad})")
    return a


def time_axis(t: Any) -> np.ndarray:
    """Sample times [s]: at least two, strictly increasing, finite."""
    t = as_signal("t", t)
    if t.size < 2 or np.any(np.diff(t) <= 0):
        raise ValueError("t must hold at least two strictly increasing times [s]")
    return t


def filter_coefficients(af: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """The preprocessing filter H(z) = (1 - af)(z - 1)/(z - af) as polynomials in z^-1.

    Parameters
    ----------
    af : float
        The filter's pole, in [0, 1).

    Returns
    -------
    b, a : numpy.ndarray
        ``b = (1 - af) [1, -1]``, ``a = [1, -af]``.
    """
    af = _check_af(af)
    return np.array([1.0 - af, -(1.0 - af)]), np.array([1.0, -af])


def diff_filter(y: np.ndarray, af: float = 0.8, *, initial: str = "zero") -> np.ndarray:
    """Differentiate and low-pass ``y`` with H(z) (output in units of y per sample, e.g. deg/sample).

    ``initial="zero"`` (the labs' MATLAB ``filter``): zero initial state, i.e. y was 0 before the record, so
    a nonzero y[0] gives a first output of (1 - af) y[0]. ``initial="rest"``: y was constant at y[0] before
    the record, so the output starts at 0. ``af = 0`` is the plain first difference.
    """
    b, a = filter_coefficients(af)
    y = as_signal("y", y)
    if initial == "zero":
        return lfilter(b, a, y)
    if initial == "rest":
        out, _ = lfilter(b, a, y, zi=lfilter_zi(b, a) * y[0])
        return out
    raise ValueError(f"unknown initial condition {initial!r}; valid: zero, rest")


def _check_Ts(Ts: float) -> float:
    Ts = float(Ts)
    if not (math.isfinite(Ts) and Ts > 0):
        raise ValueError(f"sample time Ts must be > 0 s, got {Ts!r}")
    return Ts


def filter_response(af: float, f_hz: ArrayLike, Ts: float) -> tuple[np.ndarray, np.ndarray]:
    """Frequency response of the preprocessing filter H(z).

    Parameters
    ----------
    af : float
        The filter's pole.
    f_hz : array_like
        Frequencies [Hz].
    Ts : float
        Sample period [s].

    Returns
    -------
    magnitude : numpy.ndarray
        The magnitude of H per sample (dimensionless).
    phase : numpy.ndarray
        The phase of H [rad].
    """
    b, a = filter_coefficients(af)
    z = np.exp(1j * 2.0 * math.pi * np.asarray(f_hz, dtype=np.float64) * _check_Ts(Ts))
    h = np.polyval(b, z) / np.polyval(a, z)
    return np.abs(h), np.angle(h)


def detrend(x: np.ndarray, kind: str = "constant") -> np.ndarray:
    """Remove the mean (``"constant"``), a least-squares line (``"linear"``) or nothing (``"none"``)."""
    if kind not in DETREND_KINDS:
        raise ValueError(f"unknown detrend kind {kind!r}; valid: {', '.join(DETREND_KINDS)}")
    x = as_signal("x", x)
    if kind == "none":
        return x.copy()
    return _scipy_detrend(x, type=kind)


def preprocess(
    u: np.ndarray,
    y: np.ndarray,
    af: float = 0.8,
    detrend_input: str = "constant",
    *,
    initial: str = "zero",
) -> tuple[np.ndarray, np.ndarray]:
    """Lab 1's pipeline: ``(u_d, y_f) = (detrend(u), H(z) y)``.

    u: command [V]; y: angle (e.g. deg). y_f is in units of y per sample. af in [0, 1) (0: plain first
    difference). ``initial`` as in :func:`diff_filter`.
    """
    af = _check_af(af)
    u = as_signal("u", u)
    y = as_signal("y", y)
    if u.shape != y.shape:
        raise ValueError(f"u and y must have the same length, got {u.size} and {y.size}")
    return detrend(u, detrend_input), diff_filter(y, af, initial=initial)
