"""Identified ARMAX models as python-control LTI objects: transfer functions, integrator, companion form, responses.

Conventions. ``harness.ident.armax`` polynomials are in q^-1 (A = [1, a1..], B with nk leading zeros). Here they
become discrete transfer functions in z with ``dt = Ts`` [s]: B(z^-1)/A(z^-1) with numerator and denominator
multiplied by the same power of z.

Preprocessing: the model was identified from u to the filtered difference yf = H(z) y with
``H(z) = (1 - af)(z - 1)/(z - af)``, 0 <= af < 1 (``harness.ident.preprocess.filter_coefficients``; af = 0 is
the plain difference 1 - z^-1). H does not divide by Ts, so its inverse multiplies by no Ts either:
``with_integrator(model, af) = B/A / H`` maps u to y exactly (a pole at z = 1 and a zero at z = af).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

import control
import numpy as np

from .armax import ArmaxModel
from .preprocess import filter_coefficients

__all__ = [
    "BodeData",
    "bode_data",
    "companion_ss",
    "poles",
    "square_response",
    "to_tf",
    "with_integrator",
    "zeros",
]


def _tf_qinv(num: np.ndarray, den: np.ndarray, dt: float) -> control.TransferFunction:
    """Transfer function from polynomials in z^-1 (index k = coefficient of z^-k)."""
    m = max(num.size, den.size)
    n_pad = np.zeros(m)
    d_pad = np.zeros(m)
    n_pad[: num.size] = num
    d_pad[: den.size] = den
    if not np.any(n_pad):
        n_pad = np.zeros(1)
    lead = d_pad[np.flatnonzero(d_pad)[0]]  # monic denominator
    return control.tf(n_pad / lead, d_pad / lead, dt)


def to_tf(model: ArmaxModel) -> control.TransferFunction:
    """The identified deterministic part B/A as a discrete transfer function in z, dt = Ts."""
    return _tf_qinv(model.B, model.A, model.Ts)


def with_integrator(model: ArmaxModel, af: float) -> control.TransferFunction:
    """B/A / H(z): undoes the differentiation and the low-pass of the preprocessing, so it maps u to y."""
    hn, hd = filter_coefficients(af)
    return _tf_qinv(np.convolve(model.B, hd), np.convolve(model.A, hn), model.Ts)


def _siso_tf(sys: Any) -> control.TransferFunction:
    """A SISO transfer function of an ArmaxModel, a transfer function or a state-space system."""
    sys = _lti(sys)
    if isinstance(sys, control.StateSpace):
        sys = control.ss2tf(sys)
    if not isinstance(sys, control.TransferFunction):
        raise ValueError(f"expected an ArmaxModel or a python-control LTI system, got {type(sys).__name__}")
    return sys


def _lti(sys: Any) -> control.LTI:
    """A SISO python-control LTI system of an ArmaxModel or of an LTI system (ValueError otherwise)."""
    if isinstance(sys, ArmaxModel):
        return to_tf(sys)
    if not isinstance(sys, control.LTI):
        raise ValueError(f"expected an ArmaxModel or a python-control LTI system, got {type(sys).__name__}")
    if sys.ninputs != 1 or sys.noutputs != 1:
        raise ValueError(f"only SISO systems are supported, got {sys.noutputs}x{sys.ninputs}")
    return sys


def companion_ss(tf: Any) -> control.StateSpace:
    """Controllable companion form (lab 1's eq. 10) of a SISO transfer function.

    den = z^n + a1 z^(n-1) + .. + an (normalised monic): A has first row [-a1 .. -an] and ones on the
    subdiagonal, B = e1, C = [c1 .. cn] with num - D den = c1 z^(n-1) + .. + cn, D the direct term.
    """
    g = _siso_tf(tf)
    num = np.atleast_1d(np.asarray(g.num[0][0], dtype=float))
    den = np.atleast_1d(np.asarray(g.den[0][0], dtype=float))
    nz = np.flatnonzero(den)
    if nz.size == 0:
        raise ValueError("transfer function has a zero denominator")
    den = den[nz[0] :] / den[nz[0]]
    num = num / g.den[0][0][nz[0]]
    n = den.size - 1
    if num.size > den.size and np.any(num[: num.size - den.size]):
        raise ValueError("transfer function is improper (numerator degree above denominator degree)")
    num = num[-(n + 1) :] if num.size > n + 1 else np.concatenate([np.zeros(n + 1 - num.size), num])
    d = num[0]
    c = num[1:] - d * den[1:]
    a = np.zeros((n, n))
    if n:
        a[0, :] = -den[1:]
        a[1:, :-1] = np.eye(n - 1)
    b = np.zeros((n, 1))
    if n:
        b[0, 0] = 1.0
    return control.ss(a, b, c.reshape(1, n), np.array([[d]]), g.dt)


def poles(sys: Any) -> np.ndarray:
    """Poles (z-plane for discrete systems) of an ArmaxModel's B/A or of an LTI system."""
    return np.asarray(control.poles(_lti(sys)))


def zeros(sys: Any) -> np.ndarray:
    """Transmission zeros of an ArmaxModel's B/A or of an LTI system."""
    return np.asarray(control.zeros(_lti(sys)))


@dataclass
class BodeData:
    """Frequency response at ``f_hz`` [Hz]: ``response`` complex, ``mag`` (abs), ``mag_db``, ``phase_deg``
    (unwrapped, degrees)."""

    f_hz: np.ndarray
    response: np.ndarray
    mag: np.ndarray
    mag_db: np.ndarray
    phase_deg: np.ndarray


def bode_data(sys: Any, f_hz: Any) -> BodeData:
    """Frequency response of a SISO system at the frequencies ``f_hz`` [Hz] (below Nyquist when discrete)."""
    g = _lti(sys)
    f = np.atleast_1d(np.asarray(f_hz, dtype=float))
    if f.ndim != 1 or f.size == 0 or not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError("f_hz must be a non-empty 1-D array of finite frequencies >= 0 Hz")
    w = 2 * math.pi * f
    if g.isdtime(strict=True):
        nyq = 0.5 / g.dt
        if np.any(f > nyq):
            raise ValueError(f"frequencies above the Nyquist frequency {nyq:g} Hz for dt = {g.dt:g} s")
        x = np.exp(1j * w * g.dt)
    else:
        x = 1j * w
    h = np.asarray(g(x), dtype=complex).reshape(f.shape)
    mag = np.abs(h)
    with np.errstate(divide="ignore"):
        mag_db = 20 * np.log10(mag)
    return BodeData(f, h, mag, mag_db, np.degrees(np.unwrap(np.angle(h))))


def _time_grid(g: control.LTI, T: Any, n_cont: int = 2001) -> np.ndarray:
    if np.ndim(T) == 0:
        T = float(T)
        if not (math.isfinite(T) and T > 0):
            raise ValueError(f"T must be a positive final time in seconds, got {T!r}")
        if g.isdtime(strict=True):
            return g.dt * np.arange(int(math.floor(T / g.dt + 1e-9)) + 1)
        return np.linspace(0.0, T, n_cont)
    t = np.asarray(T, dtype=float)
    if t.ndim != 1 or t.size < 2 or not np.all(np.diff(t) > 0):
        raise ValueError("T must be a final time or an increasing 1-D array of times [s]")
    return t


def square_response(sys: Any, f_hz: float, amplitude: float, T: float) -> tuple[np.ndarray, ...]:
    """Response to a square wave of frequency ``f_hz`` [Hz] and ``amplitude`` (+amplitude first half period),
    from zero state over [0, T] s. Returns (t, u, y)."""
    g = _lti(sys)
    if not (isinstance(f_hz, numbers.Real) and math.isfinite(f_hz) and f_hz > 0):
        raise ValueError(f"f_hz must be a positive frequency in Hz, got {f_hz!r}")
    n_cont = max(2001, int(200 * f_hz * float(T)) + 1) if np.ndim(T) == 0 and float(T) > 0 else 2001
    t = _time_grid(g, T, n_cont)
    half_periods = np.floor(2.0 * f_hz * t + 1e-9)  # a sample on a switching instant takes the new level
    u = float(amplitude) * np.where(half_periods % 2 == 0, 1.0, -1.0)
    r = control.forced_response(g, T=t, U=u)
    return t, u, np.asarray(r.outputs).reshape(-1)
