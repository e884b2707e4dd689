"""Prediction-error ARMAX identification (SISO), simulation, prediction, MATLAB-style fit and residual tests.

Model (q^-1 the backward shift, sample time Ts in seconds)::

    A(q) y(t) = B(q) u(t) + C(q) e(t)
    A = 1 + a1 q^-1 + .. + a_na q^-na          (monic, length na + 1)
    B = b_nk q^-nk + .. + b_(nk+nb-1) q^-(nk+nb-1)  (stored with its nk leading zeros, length nk + nb)
    C = 1 + c1 q^-1 + .. + c_nc q^-nc          (monic, length nc + 1)

Parameter vector order everywhere (``cov``, ``std``): [a1..a_na, b_nk..b_(nk+nb-1), c1..c_nc].

Initial conditions: like MATLAB's ``armax``/``pem`` with ``InitialCondition='zero'``, every signal before the
first sample (y, u and the prediction error e) is taken as zero, and the ARMAX loss is averaged over all N
samples. With ``nc = 0`` the model is ARX, estimated like MATLAB's ``arx``: least squares over the rows
t = n0..N-1, n0 = max(na, nk + nb - 1), so no fictitious zero samples enter (on the DaISY robot-arm data the
zero-padded variant gives a different, unstable ARX(6,6)). Predictors, simulations and fits always start from
zero initial conditions unless ``ic="e"``.
"""

from __future__ import annotations

import math
import numbers
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats
from scipy.signal import lfilter

__all__ = [
    "ArmaxModel",
    "FitResult",
    "IntegratorWarning",
    "ResidTest",
    "compare",
    "compare_report",
    "estimate",
    "fit_onestep",
    "fit_percent",
    "generate",
    "predict",
    "resid",
    "simulate",
]

INTEGRATOR_POLE = 0.999  # a real pole of A at or beyond this: the data integrate (estimate warns)
_C_RADIUS_MAX = 0.999  # roots of C reflected/clipped to this radius (predictor filter 1/C stays stable)
_SCHUR_MARGIN = 1e-8  # a reflection coefficient this close to 1: C's roots are taken by np.roots to tell


# ----------------------------------------------------------------------------------------------- model
@dataclass
class ArmaxModel:
    """An identified (or given) ARMAX model; coefficients at full double precision.

    ``A``, ``C`` monic, ``B`` with ``nk`` leading zeros (length nk + nb); ``Ts`` in seconds; ``loss`` is the mean
    squared one-step prediction error V on the estimation data (units of y squared); ``noise_variance`` is
    sum(e^2) / (N - n_params); ``cov`` the parameter covariance (order [a.., b.., c..]); ``fit_onestep`` the
    one-step prediction fit on the estimation data in percent.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    na: int
    nb: int
    nc: int
    nk: int
    Ts: float = 1.0
    loss: float = math.nan
    noise_variance: float = math.nan
    cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    fit_onestep: float = math.nan
    n_iter: int = 0
    converged: bool = True

    def __post_init__(self) -> None:
        self.A = np.asarray(self.A, dtype=float)
        self.B = np.asarray(self.B, dtype=float)
        self.C = np.asarray(self.C, dtype=float)
        self.cov = np.asarray(self.cov, dtype=float)
        if self.A.shape != (self.na + 1,) or self.A[0] != 1.0:
            raise ValueError(f"A must be monic of length na + 1 = {self.na + 1}, got {self.A.tolist()}")
        if self.C.shape != (self.nc + 1,) or self.C[0] != 1.0:
            raise ValueError(f"C must be monic of length nc + 1 = {self.nc + 1}, got {self.C.tolist()}")
        if self.B.shape != (self.nk + self.nb,) or np.any(self.B[: self.nk] != 0.0):
            raise ValueError(f"B must have length nk + nb = {self.nk + self.nb} with {self.nk} leading zeros")

    @property
    def theta(self) -> np.ndarray:
        """Free parameters [a1..a_na, b.., c1..c_nc]."""
        return np.concatenate([self.A[1:], self.B[self.nk :], self.C[1:]])

    @property
    def n_params(self) -> int:
        """Number of free parameters na + nb + nc."""
        return self.na + self.nb + self.nc

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of the parameters (sqrt of the covariance diagonal), order [a.., b.., c..]."""
        if self.cov.size == 0:
            return np.full(self.n_params, math.nan)
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    @property
    def poles(self) -> np.ndarray:
        """Roots of A(z) (z-plane poles of B/A, excluding poles at the origin)."""
        return np.roots(self.A) if self.na > 0 else np.zeros(0, dtype=complex)

    @property
    def stable(self) -> bool:
        """True when every root of A lies strictly inside the unit circle."""
        return bool(self.na == 0 or np.max(np.abs(self.poles)) < 1.0)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict; floats kept as Python floats (repr round trip is exact); non-finite as strings."""
        return {
            "A": _floats(self.A),
            "B": _floats(self.B),
            "C": _floats(self.C),
            "na": self.na,
            "nb": self.nb,
            "nc": self.nc,
            "nk": self.nk,
            "Ts": _float(self.Ts),
            "loss": _float(self.loss),
            "noise_variance": _float(self.noise_variance),
            "cov": [_floats(row) for row in self.cov],
            "fit_onestep": _float(self.fit_onestep),
            "n_iter": self.n_iter,
            "converged": self.converged,
            "stable": self.stable,  # informative; recomputed from A, ignored by from_dict
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ArmaxModel:
        """Inverse of :meth:`to_dict` (bit-exact)."""
        try:
            n = int(d["na"]) + int(d["nb"]) + int(d["nc"])
            cov = [[float(x) for x in row] for row in d.get("cov", [])]
            return cls(
                A=np.array([float(x) for x in d["A"]]),
                B=np.array([float(x) for x in d["B"]]),
                C=np.array([float(x) for x in d["C"]]),
                na=int(d["na"]),
                nb=int(d["nb"]),
                nc=int(d["nc"]),
                nk=int(d["nk"]),
                Ts=float(d.get("Ts", 1.0)),
                loss=float(d.get("loss", "nan")),
                noise_variance=float(d.get("noise_variance", "nan")),
                cov=np.array(cov, dtype=float).reshape((n, n) if cov else (0, 0)),
                fit_onestep=float(d.get("fit_onestep", "nan")),
                n_iter=int(d.get("n_iter", 0)),
                converged=bool(d.get("converged", True)),
            )
        except KeyError as exc:
            raise ValueError(f"ARMAX model dict lacks the key {exc}") from None


def _float(x: float) -> float | str:
    x = float(x)
    return x if math.isfinite(x) else repr(x)


def _floats(a: np.ndarray) -> list[float | str]:
    return [_float(x) for x in np.asarray(a, dtype=float).ravel()]


# ----------------------------------------------------------------------------------------------- helpers
def _check_signals(u: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    u = np.asarray(u, dtype=float)
    y = np.asarray(y, dtype=float)
    if u.ndim != 1 or y.ndim != 1:
        raise ValueError(f"u and y must be 1-D arrays, got shapes {u.shape} and {y.shape}")
    if u.size != y.size:
        raise ValueError(f"u and y must have equal length, got {u.size} and {y.size}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise ValueError("u and y must be finite (no NaN or inf)")
    return u, y


def _check_u(u: Any) -> np.ndarray:
    u = np.asarray(u, dtype=float)
    if u.ndim != 1:
        raise ValueError(f"u must be a 1-D array, got shape {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError("u must be finite (no NaN or inf)")
    return u


def _check_orders(na: int, nb: int, nc: int, nk: int) -> tuple[int, int, int, int]:
    out = []
    for name, v in (("na", na), ("nb", nb), ("nc", nc), ("nk", nk)):
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 0:
            raise ValueError(f"order {name} must be an integer >= 0, got {v!r}")
        out.append(int(v))
    if out[0] + out[1] + out[2] == 0:
        raise ValueError("na + nb + nc must be >= 1 (nothing to estimate)")
    return out[0], out[1], out[2], out[3]


def _shift_cols(out: np.ndarray, col: int, x: np.ndarray, lags: range, sign: float) -> None:
    """Write sign * x(t - lag) (zero before t = 0) into columns col, col+1, .. of out."""
    n = x.size
    for j, lag in enumerate(lags):
        c = out[:, col + j]
        if lag >= n:
            c[:] = 0.0
            continue
        c[:lag] = 0.0
        c[lag:] = x[: n - lag] if sign > 0 else -x[: n - lag]


def _regressors(y: np.ndarray, u: np.ndarray, e: np.ndarray | None, na: int, nb: int, nc: int, nk: int) -> np.ndarray:
    """Zero-padded regressor matrix phi with e(t) = y(t) - phi(t) theta, columns [-y lags, u lags, e lags]."""
    phi = np.empty((y.size, na + nb + nc))
    _shift_cols(phi, 0, y, range(1, na + 1), -1.0)
    _shift_cols(phi, na, u, range(nk, nk + nb), 1.0)
    if nc:
        if e is None:
            raise ValueError("an ARMAX regressor with nc > 0 needs the residuals e")
        _shift_cols(phi, na + nb, e, range(1, nc + 1), 1.0)
    return phi


def _lstsq(phi: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares via column-scaled normal equations, SVD fallback when ill-conditioned (cond > 1e12)."""
    scale = np.sqrt(np.einsum("ij,ij->j", phi, phi))
    scale[scale == 0.0] = 1.0
    ps = phi / scale
    r = ps.T @ ps
    g = ps.T @ y
    try:
        if np.linalg.cond(r) > 1e12:
            raise np.linalg.LinAlgError
        x = np.linalg.solve(r, g)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(ps, y, rcond=None)[0]
    return x / scale


def _polys(theta: np.ndarray, na: int, nb: int, nc: int, nk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    A = np.concatenate([[1.0], theta[:na]])
    B = np.concatenate([np.zeros(nk), theta[na : na + nb]])
    C = np.concatenate([[1.0], theta[na + nb :]])
    return A, B, C


def _pred_error(A: np.ndarray, B: np.ndarray, C: np.ndarray, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    """e = (A y - B u) / C with zero initial conditions."""
    n = y.size
    v = np.convolve(y, A)[:n]
    if B.size and np.any(B):
        v -= np.convolve(u, B)[:n]
    if C.size == 1:
        return v
    return lfilter([1.0], C, v)


def _inside(C: np.ndarray, radius: float) -> bool:
    """Whether every root of the monic ``C`` lies within ``radius``, clear of it: the Schur-Cohn step-down of C with
    its roots scaled by 1 / radius keeps every reflection coefficient below 1 - _SCHUR_MARGIN. False also where a
    root may sit on the circle; the caller then takes the roots themselves."""
    a = [float(c) / radius**i for i, c in enumerate(C)]
    for m in range(len(a) - 1, 0, -1):
        k = a[m]
        if abs(k) >= 1.0 - _SCHUR_MARGIN:
            return False
        d = 1.0 - k * k
        a = [(a[i] - k * a[m - i]) / d for i in range(m)]
    return True


def _stabilize(C: np.ndarray) -> np.ndarray:
    """Reflect roots of the monic C outside the unit circle to 1/conj(r) (as MATLAB does), then clip radii
    above _C_RADIUS_MAX to it so that 1/C stays a stable, not nearly marginal, filter."""
    if C.size <= 1 or _inside(C, _C_RADIUS_MAX):
        return C
    r = np.roots(C)
    mag = np.abs(r)
    if np.all(mag <= _C_RADIUS_MAX):
        return C
    big = mag > 1.0
    r[big] = 1.0 / np.conj(r[big])
    mag = np.abs(r)
    clip = mag > _C_RADIUS_MAX
    r[clip] *= _C_RADIUS_MAX / mag[clip]
    return np.real(np.poly(r))


def _fit(y: np.ndarray, yhat: np.ndarray) -> float:
    den = np.linalg.norm(y - np.mean(y))
    if den == 0.0:
        raise ValueError("y is constant: the fit percentage is undefined")
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / den))


def fit_percent(y: Any, yhat: Any) -> float:
    """MATLAB ``compare`` fit: 100 (1 - ||y - yhat|| / ||y - mean(y)||), in percent."""
    y = np.asarray(y, dtype=float)
    yhat = np.asarray(yhat, dtype=float)
    if y.shape != yhat.shape:
        raise ValueError(f"y and yhat must have the same shape, got {y.shape} and {yhat.shape}")
    if not np.all(np.isfinite(yhat)):
        return math.nan
    return _fit(y, yhat)


# ----------------------------------------------------------------------------------------------- estimation
def _hannan_rissanen(y: np.ndarray, u: np.ndarray, na: int, nb: int, nc: int, nk: int) -> np.ndarray:
    """Start values: long ARX for the innovations, then least squares on [y, u, e_hat] lags."""
    n = y.size
    long = max(10, 3 * max(na, nb + nk, nc))
    long = min(long, max(1, (n - 1) // 6))
    nb_long = long if nb else 0
    phi = _regressors(y, u, None, long, nb_long, 0, nk if nb else 1)
    th = _lstsq(phi, y)
    e_hat = y - phi @ th
    phi = _regressors(y, u, e_hat, na, nb, nc, nk)
    return _lstsq(phi, y)


def _jacobian(
    y: np.ndarray, u: np.ndarray, e: np.ndarray, C: np.ndarray, na: int, nb: int, nc: int, nk: int
) -> np.ndarray:
    """psi = d yhat / d theta = phi / C (phi built from y, u, e): the analytic gradient regressors."""
    rows = np.vstack([y, u, e]) if nc else np.vstack([y, u])
    f = lfilter([1.0], C, rows, axis=-1) if C.size > 1 else rows
    return _regressors(f[0], f[1], f[2] if nc else None, na, nb, nc, nk)


def estimate(
    u: Any,
    y: Any,
    na: int,
    nb: int,
    nc: int,
    nk: int = 1,
    Ts: float = 1.0,
    *,
    max_iter: int = 50,
    tol: float = 1e-8,
) -> ArmaxModel:
    """Prediction-error ARMAX estimate of A(q) y = B(q) u(t - nk) + C(q) e from one input and output.

    Start: Hannan-Rissanen (long ARX innovations, then least squares on y, u, e lags). Iterations: damped
    Gauss-Newton (step halving) with the analytic gradient psi = phi / C, Levenberg-Marquardt when halving
    fails; C kept stable by reflecting its roots into the unit circle. When the start has an unstable A a
    second start with A's roots reflected is also iterated and the lower loss wins. ``nc = 0`` gives ARX by
    plain least squares. Zero initial conditions.

    Parameters
    ----------
    u, y : array_like
        Input and output, the same length.
    na, nb, nc : int
        Orders of A, B and C.
    nk : int
        Input delay [samples].
    Ts : float
        Sample period [s]; it only labels the model.
    max_iter : int
        Iterations per start.
    tol : float
        Stop when the relative decrease of the loss falls below it (``converged``).

    Returns
    -------
    ArmaxModel
        A, B, C at full precision, the loss, the noise variance, the parameter covariance, the one-step fit.
    """
    u, y = _check_signals(u, y)
    na, nb, nc, nk = _check_orders(na, nb, nc, nk)
    if isinstance(Ts, bool) or not (isinstance(Ts, numbers.Real) and math.isfinite(Ts) and Ts > 0):
        raise ValueError(f"Ts must be a positive finite number of seconds, got {Ts!r}")
    if max_iter < 0 or not tol > 0:
        raise ValueError(f"max_iter must be >= 0 and tol > 0, got {max_iter} and {tol}")
    n = y.size
    p = na + nb + nc
    need = 2 * p + max(na, nb + nk, nc) + 10
    if n < need:
        raise ValueError(f"need at least {need} samples for ARMAX({na},{nb},{nc},{nk}), got {n}")
    ynorm = float(np.dot(y, y))
    if ynorm == 0.0:
        raise ValueError("y is identically zero: nothing to identify")

    if nc == 0:
        # ARX as MATLAB's arx: regression rows t = n0..N-1 only, no fictitious zero samples
        n0 = max(na, nk + nb - 1)
        psi = _regressors(y, u, None, na, nb, 0, nk)[n0:]
        theta = _lstsq(psi, y[n0:])
        e = y[n0:] - psi @ theta
        n_iter, converged = 0, True
        A, B, C = _polys(theta, na, nb, nc, nk)
    else:
        theta, n_iter, converged = _pem(y, u, na, nb, nc, nk, max_iter, tol)
        A, B, C = _polys(theta, na, nb, nc, nk)
        e = _pred_error(A, B, C, y, u)
        psi = _jacobian(y, u, e, C, na, nb, nc, nk)
    V = float(np.dot(e, e) / e.size)
    lam = float(np.dot(e, e) / max(e.size - p, 1))
    cov = lam * np.linalg.pinv(psi.T @ psi)
    model = ArmaxModel(A=A, B=B, C=C, na=na, nb=nb, nc=nc, nk=nk, Ts=float(Ts))
    fit1 = _fit(y, predict(model, u, y, 1))
    model.loss, model.noise_variance, model.cov, model.fit_onestep = V, lam, cov, fit1
    model.n_iter, model.converged = n_iter, converged
    integrator = [z.real for z in model.poles if abs(z.imag) < 1e-6 and z.real >= INTEGRATOR_POLE]
    if integrator:
        warnings.warn(
            f"ARMAX({na},{nb},{nc},{nk}) has a pole at {max(integrator):.8f}: y integrates u (a raw angle?), and "
            "such a model simulates a drift (compare gives nan or a meaningless fit); differentiate and low-pass y "
            "first (harness.prepare on a run, or harness.ident.preprocess.preprocess)",
            IntegratorWarning,
            stacklevel=2,
        )
    return model


def _reflect_start(theta: np.ndarray, na: int, nb: int, nc: int, nk: int) -> np.ndarray | None:
    """Start with the unstable roots of A reflected into the unit circle (B rescaled to keep |B/A|)."""
    if na == 0:
        return None
    r = np.roots(np.concatenate([[1.0], theta[:na]]))
    big = np.abs(r) >= 1.0
    if not np.any(big):
        return None
    gain = float(np.prod(np.abs(r[big])))
    r[big] = 1.0 / np.conj(r[big])
    a = np.real(np.poly(r))[1:]
    return np.concatenate([a, theta[na : na + nb] / gain, theta[na + nb :]])


def _pem(
    y: np.ndarray, u: np.ndarray, na: int, nb: int, nc: int, nk: int, max_iter: int, tol: float
) -> tuple[np.ndarray, int, bool]:
    """Hannan-Rissanen start (and, when its A is unstable, a second start with A reflected), then
    Gauss-Newton from each; the lowest loss wins. Returns (theta, total iterations, converged)."""
    th0 = _hannan_rissanen(y, u, na, nb, nc, nk)
    best: tuple[float, np.ndarray, bool] | None = None
    total = 0
    for start in (th0, _reflect_start(th0, na, nb, nc, nk)):
        if start is None:
            continue
        th, it, conv = _gauss_newton(start, y, u, na, nb, nc, nk, max_iter, tol)
        total += it
        e = _pred_error(*_polys(th, na, nb, nc, nk), y, u)
        V = float(np.dot(e, e))
        if best is None or V < best[0]:
            best = (V, th, conv)
    if best is None:
        raise ValueError("no starting point for the prediction-error search")
    return best[1], total, best[2]


def _gauss_newton(
    theta: np.ndarray, y: np.ndarray, u: np.ndarray, na: int, nb: int, nc: int, nk: int, max_iter: int, tol: float
) -> tuple[np.ndarray, int, bool]:
    """Minimise mean(e^2) over theta; returns (theta, iterations, converged)."""
    n = y.size
    A, B, C = _polys(theta, na, nb, nc, nk)
    Cs = _stabilize(C)
    if Cs is not C:
        theta = np.concatenate([theta[: na + nb], Cs[1:]])
        C = Cs
    e = _pred_error(A, B, C, y, u)
    V = float(np.dot(e, e)) / n
    for it in range(1, max_iter + 1):
        psi = _jacobian(y, u, e, C, na, nb, nc, nk)
        scale = np.sqrt(np.einsum("ij,ij->j", psi, psi))
        scale[scale == 0.0] = 1.0
        ps = psi / scale
        R = ps.T @ ps
        g = ps.T @ e  # e(theta + d) ~ e - psi d  =>  GN step d = R^-1 g (scaled)
        accepted = False
        for lm in (0.0, 1e-3, 1e-1, 10.0):
            try:
                step = np.linalg.solve(R + lm * np.eye(R.shape[0]), g) / scale
            except np.linalg.LinAlgError:
                step = np.linalg.lstsq(ps, e, rcond=None)[0] / scale
            mu = 1.0
            for _ in range(12 if lm == 0.0 else 4):
                cand = theta + mu * step
                Ac, Bc, Cc = _polys(cand, na, nb, nc, nk)
                Cs = _stabilize(Cc)
                if Cs is not Cc:
                    cand = np.concatenate([cand[: na + nb], Cs[1:]])
                    Cc = Cs
                ec = _pred_error(Ac, Bc, Cc, y, u)
                Vc = float(np.dot(ec, ec)) / n
                if Vc < V:
                    accepted = True
                    break
                mu *= 0.5
            if accepted:
                break
        if not accepted:
            return theta, it, True  # no descent direction left at working precision: a minimum
        rel = (V - Vc) / V
        theta, e, V, C = cand, ec, Vc, Cc
        if rel < tol:
            return theta, it, True
    return theta, max_iter, False


# ----------------------------------------------------------------------------------------------- use of models
def generate(model: ArmaxModel, u: Any, e: Any) -> np.ndarray:
    """Output of the ARMAX model for input u and innovations e: y = B/A u + C/A e (zero initial state)."""
    u = _check_u(u)
    e = _check_u(e)
    if e.size != u.size:
        raise ValueError(f"u and e must have equal length, got {u.size} and {e.size}")
    b = model.B if model.B.size else np.zeros(1)
    return lfilter(b, model.A, u) + lfilter(model.C, model.A, e)


def _free_responses(model: ArmaxModel, n: int) -> np.ndarray:
    """Columns: responses of B/A (DF-II transposed realisation, order max(na, nk+nb-1)) to unit initial states."""
    order = max(model.A.size, model.B.size) - 1
    if order == 0:
        return np.zeros((n, 0))
    b = model.B if model.B.size else np.zeros(1)
    zi = np.eye(order)
    out, _ = lfilter(b, model.A, np.zeros((order, n)), axis=-1, zi=zi)
    return out.T


def simulate(model: ArmaxModel, u: Any, y0: Any = None, ic: str = "z") -> np.ndarray:
    """Noise-free infinite-horizon simulation y_sim = B/A u.

    Parameters
    ----------
    model : ArmaxModel
        The model.
    u : array_like
        Input.
    y0 : array_like, optional
        The measured output, required with ``ic="e"`` (same length as ``u``).
    ic : {"z", "e"}
        Zero initial state, or the initial state of a state-space realisation of B/A estimated by least squares
        so that y_sim best matches ``y0``.

    Returns
    -------
    numpy.ndarray
        The simulated output.
    """
    u = _check_u(u)
    b = model.B if model.B.size else np.zeros(1)
    ys = lfilter(b, model.A, u)
    if ic == "z":
        return ys
    if ic != "e":
        raise ValueError(f"ic must be 'z' (zero) or 'e' (estimated), got {ic!r}")
    if y0 is None:
        raise ValueError("ic='e' needs the measured output y0 to estimate the initial state from")
    u, y0 = _check_signals(u, y0)
    obs = _free_responses(model, u.size)
    if obs.shape[1] == 0:
        return ys
    x0 = np.linalg.lstsq(obs, y0 - ys, rcond=None)[0]
    return ys + obs @ x0


def predict(model: ArmaxModel, u: Any, y: Any, k: int = 1) -> np.ndarray:
    """The k-step-ahead predictor yhat(t | t - k), zero initial conditions.

    C/A = F_k + q^-k G_k/A with F_k the first k impulse-response terms of C/A; then
    yhat = (F_k B u + (C - F_k A) y) / C. k = 1 gives yhat = y - e.

    Parameters
    ----------
    model : ArmaxModel
        The model.
    u, y : array_like
        Input and measured output, the same length.
    k : int
        Prediction horizon [samples], >= 1.

    Returns
    -------
    numpy.ndarray
        The prediction, in the unit of ``y``.
    """
    u, y = _check_signals(u, y)
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise ValueError(f"prediction horizon k must be an integer >= 1, got {k!r}")
    imp = np.zeros(k)
    imp[0] = 1.0
    F = lfilter(model.C, model.A, imp)
    fb = np.convolve(F, model.B) if model.B.size else np.zeros(1)
    fa = np.convolve(F, model.A)
    m = max(fa.size, model.C.size)
    ny = np.zeros(m)
    ny[: model.C.size] += model.C
    ny[: fa.size] -= fa
    ny[:k] = 0.0  # exact cancellation of the first k terms (removes rounding)
    return lfilter(fb, model.C, u) + lfilter(ny, model.C, y)


def fit_onestep(model: ArmaxModel, u: Any, y: Any) -> float:
    """One-step-ahead prediction fit in percent (not the simulation fit)."""
    u, y = _check_signals(u, y)
    return _fit(y, predict(model, u, y, 1))


@dataclass
class FitResult:
    """Simulation fit of a model on data: ``fit`` in percent (nan when ``stable`` is False), ``ic`` 'z'/'e'."""

    fit: float
    ic: str
    stable: bool
    yhat: np.ndarray | None = None

    @property
    def status(self) -> str:
        """'ok' or 'unstable'."""
        return "ok" if self.stable else "unstable"

    def __str__(self) -> str:
        return f"{self.fit:.2f} %" if self.stable else "unstable"


def compare_report(model: ArmaxModel, u: Any, y: Any, ic: str = "z") -> FitResult:
    """MATLAB ``compare`` (infinite horizon) fit with status; an unstable A gives fit nan, status 'unstable'."""
    u, y = _check_signals(u, y)
    if ic not in ("z", "e"):
        raise ValueError(f"ic must be 'z' (zero) or 'e' (estimated), got {ic!r}")
    if not model.stable:
        _fit(y, y)  # still reject constant y
        return FitResult(math.nan, ic, False, None)
    yhat = simulate(model, u, y, ic)
    return FitResult(_fit(y, yhat), ic, True, yhat)


def compare(model: ArmaxModel, u: Any, y: Any, ic: str = "z") -> float:
    """Simulation fit in percent, as MATLAB's ``compare``: 100 (1 - ||y - yhat|| / ||y - mean y||).

    Parameters
    ----------
    model : ArmaxModel
        The model; its simulation (infinite horizon), not its one-step prediction, is scored.
    u, y : array_like
        Input and measured output, the same length.
    ic : {"z", "e"}
        Initial state: zero, or estimated by least squares from ``y``.

    Returns
    -------
    float
        The fit [%]; NaN for a model whose A is unstable (no number like -1e40).
    """
    return compare_report(model, u, y, ic).fit


class IntegratorWarning(UserWarning):
    """An estimated A has a real pole at 1 or beyond: the output integrates the input, unprocessed."""


@dataclass
class ResidTest:
    """Residual correlation test at the 99 % level.

    ``acf[k]`` normalised autocorrelation of e at lag k = 0..lags; ``ccf[j]`` normalised cross-correlation
    r_eu(tau) = sum e(t + tau) u(t) / sqrt(..) for tau = lags_ccf[j] in -lags..lags; ``bound`` = 2.58/sqrt(N).
    ``white``/``independent``: at most ``allowed`` lags outside ``bound`` (binomial 99 % allowance for chance
    excursions) and none beyond ``bound_family_acf`` / ``bound_family_ccf`` (Bonferroni 99 % over all lags),
    so a correct model is flagged in about 1 % of data sets, not in 1 - 0.99^lags of them.
    """

    lags: int
    acf: np.ndarray
    ccf: np.ndarray
    lags_ccf: np.ndarray
    bound: float
    bound_family_acf: float
    bound_family_ccf: float
    allowed_acf: int
    allowed_ccf: int
    n_out_acf: int
    n_out_ccf: int
    white: bool
    independent: bool
    residuals: np.ndarray


def _xcorr(a: np.ndarray, b: np.ndarray, lags: int) -> np.ndarray:
    """sum_t a(t + tau) b(t) for tau = -lags..lags (biased, no normalisation)."""
    full = np.correlate(a, b, mode="full")  # index n-1 is lag 0
    n = a.size
    return full[n - 1 - lags : n + lags]


def resid(model: ArmaxModel, u: Any, y: Any, lags: int = 25) -> ResidTest:
    """Residual tests: whiteness of the one-step prediction errors and their independence from the input.

    Parameters
    ----------
    model : ArmaxModel
        The model.
    u, y : array_like
        Input and measured output.
    lags : int
        Lags of the auto- and cross-correlations tested.

    Returns
    -------
    ResidTest
        The correlations, their 99 % bound 2.58/sqrt(N), how many lags fall outside it, and the two verdicts.
    """
    u, y = _check_signals(u, y)
    n = y.size
    if isinstance(lags, bool) or not isinstance(lags, int | np.integer) or not 1 <= lags < n // 2:
        raise ValueError(f"lags must be an integer in 1..{n // 2 - 1}, got {lags!r}")
    e = y - predict(model, u, y, 1)
    ec = e - e.mean()
    uc = u - u.mean()
    r_ee = _xcorr(ec, ec, lags)[lags:]
    r_uu0 = float(np.dot(uc, uc))
    if r_ee[0] == 0.0:
        raise ValueError("residuals are identically zero: correlation test undefined")
    acf = r_ee / r_ee[0]
    if r_uu0 > 0:
        ccf = _xcorr(ec, uc, lags) / math.sqrt(r_ee[0] * r_uu0)
    else:
        ccf = np.zeros(2 * lags + 1)
    bound = 2.58 / math.sqrt(n)
    m_ccf = 2 * lags + 1
    fam_acf = stats.norm.ppf(1 - 0.005 / lags) / math.sqrt(n)
    fam_ccf = stats.norm.ppf(1 - 0.005 / m_ccf) / math.sqrt(n)
    allowed_acf = int(stats.binom.ppf(0.99, lags, 0.01))
    allowed_ccf = int(stats.binom.ppf(0.99, m_ccf, 0.01))
    out_acf = int(np.sum(np.abs(acf[1:]) > bound))
    out_ccf = int(np.sum(np.abs(ccf) > bound))
    white = out_acf <= allowed_acf and bool(np.all(np.abs(acf[1:]) <= fam_acf))
    indep = out_ccf <= allowed_ccf and bool(np.all(np.abs(ccf) <= fam_ccf))
    return ResidTest(
        lags=int(lags),
        acf=acf,
        ccf=ccf,
        lags_ccf=np.arange(-lags, lags + 1),
        bound=bound,
        bound_family_acf=float(fam_acf),
        bound_family_ccf=float(fam_ccf),
        allowed_acf=allowed_acf,
        allowed_ccf=allowed_ccf,
        n_out_acf=out_acf,
        n_out_ccf=out_ccf,
        white=white,
        independent=indep,
        residuals=e,
    )
