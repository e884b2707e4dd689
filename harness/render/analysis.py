"""What the report and the viewer compute from a loaded run (:class:`harness.render.load.RunResults`), as data
objects that the figures and tables take: no plotting here, and no model math of its own (transfer functions and
responses come from :mod:`harness.ident.lti`, the filter H(z) from :mod:`harness.ident.preprocess`, residual tests
from :mod:`harness.ident.armax`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.signal import coherence, csd, lfilter, welch

from ..diagnosis.replays import Replay
from ..ident import armax, lti
from ..ident.calibration import alpha_deg, theta_deg
from ..ident.identify import PreparedExperiment
from ..ident.preprocess import filter_coefficients, filter_response
from .load import RunResults

__all__ = [
    "MIN_COHERENCE",
    "RESID_LAGS",
    "Estimates",
    "MeasuredFRF",
    "best_per_dataset",
    "bode_curves",
    "bode_grid",
    "estimates",
    "measured_frf",
    "record_angles",
    "replay_fits",
    "residual_tests",
    "tip_from_filtered",
    "zoom_window",
]

RESID_LAGS = 25
MIN_COHERENCE = 0.8  # measured FRF points kept where the coherence u -> y_f reaches this


def bode_grid(Ts: float, n: int = 300) -> np.ndarray:
    """Log-spaced frequencies [Hz] from 0.01 Hz (or 1e-3 of Nyquist) up to 0.999 Nyquist."""
    nyq = 0.5 / Ts
    return np.logspace(math.log10(min(0.01, 1e-3 * nyq)), math.log10(0.999 * nyq), n)


def tip_from_filtered(y_f: np.ndarray, af: float, y0: float = 0.0) -> np.ndarray:
    """Invert H(z): the angle [deg] whose filtered difference is ``y_f`` [deg/sample], at rest at ``y0`` [deg]."""
    b, a = filter_coefficients(af)
    return y0 + lfilter(a, b, np.asarray(y_f, dtype=float))


@dataclass(frozen=True)
class MeasuredFRF:
    """Nonparametric frequency response u [V] -> tip angle y [deg] of one dataset at ``f_hz`` [Hz] (complex
    ``response`` [deg/V]), where the coherence ``coherence`` reaches MIN_COHERENCE."""

    dataset: str
    f_hz: np.ndarray
    response: np.ndarray
    coherence: np.ndarray

    @property
    def mag_db(self) -> np.ndarray:
        return 20.0 * np.log10(np.abs(self.response))

    def phase_deg(self, near: float) -> np.ndarray:
        """Unwrapped phase [deg], on the 360-deg branch whose first point is nearest ``near`` [deg]."""
        ph = np.degrees(np.unwrap(np.angle(self.response)))
        return ph + 360.0 * np.round((near - ph[0]) / 360.0)


def measured_frf(p: PreparedExperiment, af: float) -> MeasuredFRF | None:
    """The H1 estimate (Welch, Hann, 50 % overlap) of u_d -> y_f divided by H(z), at the frequencies where the
    coherence reaches MIN_COHERENCE; None when the record is too short or nowhere coherent."""
    if p.y_f.size < 64:
        return None
    fs = 1.0 / p.Ts
    nper = min(256, p.y_f.size // 4)
    f, puu = welch(p.u_d, fs=fs, nperseg=nper)
    _, puy = csd(p.u_d, p.y_f, fs=fs, nperseg=nper)
    _, coh = coherence(p.u_d, p.y_f, fs=fs, nperseg=nper)
    keep = (f > 0) & (puu > 0) & (coh >= MIN_COHERENCE)
    if not keep.any():
        return None
    mag, phase = filter_response(af, f[keep], p.Ts)
    return MeasuredFRF(p.name, f[keep], (puy[keep] / puu[keep]) / (mag * np.exp(1j * phase)), coh[keep])


def residual_tests(res: RunResults) -> dict[str, armax.ResidTest]:
    """The selected model's residual whiteness and independence tests (99 %) per dataset, up to RESID_LAGS."""
    if res.selected is None:
        return {}
    m = res.selected[0]
    return {
        name: armax.resid(m, p.u_d, p.y_f, lags=min(RESID_LAGS, p.y_f.size // 2 - 1))
        for name, p in res.prepared.items()
    }


def zoom_window(t: np.ndarray, r: np.ndarray, width: float) -> tuple[float, float]:
    """The ``width`` [s] window [t0, t1] [s] where the residual ``r`` has the most energy."""
    n = max(2, min(t.size, int(round(width / (t[1] - t[0])))))
    energy = np.convolve(r**2, np.ones(n), "valid")
    k = int(np.argmax(energy))
    return float(t[k]), float(t[k + n - 1])


@dataclass(frozen=True)
class Estimates:
    """Free parameters of an ARMAX model (``names`` a1.., b<nk>.., c1..) with their estimates and one standard
    deviation (square root of the covariance diagonal); on a dataset of N samples the loss V (mean squared
    one-step prediction error), FPE = V (1 + d/N)/(1 - d/N) and AIC = N ln V + 2 d, as MATLAB's fpe/aic."""

    names: list[str]
    values: np.ndarray
    std: np.ndarray
    N: int
    loss: float
    fpe: float
    aic: float


def estimates(m: armax.ArmaxModel, N: int) -> Estimates | None:
    """The free parameters of ``m`` with their deviations and information criteria on N samples; None when the
    model carries no covariance."""
    names = [f"a{i}" for i in range(1, m.na + 1)]
    names += [f"b{i}" for i in range(m.nk, m.nk + m.nb)] + [f"c{i}" for i in range(1, m.nc + 1)]
    values = np.concatenate([m.A[1:], m.B[m.nk :], m.C[1:]])
    std = m.std
    if std.size != len(names) or values.size != len(names) or not np.isfinite(std).any():
        return None
    V, d = float(m.loss) if m.loss is not None else math.nan, m.n_params
    ok = math.isfinite(V) and V > 0 and N > d
    fpe = V * (1 + d / N) / (1 - d / N) if ok else math.nan
    aic = N * math.log(V) + 2 * d if ok else math.nan
    return Estimates(names, values, std, N, V, fpe, aic)


def best_per_dataset(grid: pd.DataFrame) -> pd.DataFrame:
    """Per dataset, the grid row with the highest mean cross-validation fit (``cv_mean``) among those that were
    cross-validated (the survivors, or a dataset's fallback when none survived); indexed by dataset. Empty when
    the grid has no cross-validation column."""
    if "cv_mean" not in grid.columns:
        return grid.iloc[0:0]
    g = grid[pd.to_numeric(grid["cv_mean"], errors="coerce").notna()]
    if g.empty:
        return g
    idx = g.groupby("dataset", sort=False)["cv_mean"].idxmax()
    return g.loc[idx.to_numpy()].set_index("dataset")


def bode_curves(res: RunResults, f_hz: np.ndarray) -> dict[str, lti.BodeData]:
    """Bode data of G = B/A / H(z) (u [V] -> tip angle [deg]) of every model of the run at ``f_hz`` [Hz]."""
    return {name: lti.bode_data(lti.with_integrator(m, res.af), f_hz) for name, (m, _) in res.models.items()}


def replay_fits(rp: Replay) -> dict[str, float]:
    """Fit [%] of each stage's replay to the record, as the diagnosis pools it per experiment: 100 (1 - sqrt(mean
    over channels of ||y_rec - y_sim||^2 / ||y_rec - mean||^2)), the residual over the samples valid on both sides,
    the record's spread over all (channels with no motion skipped)."""
    out = {}
    for stage, sim in rp.sim.items():
        qs = []
        for ch, rec in rp.record.items():
            ok = np.isfinite(rec) & np.isfinite(sim[ch])
            if rp.sst[ch] > 0:
                qs.append(float(np.sum((rec[ok] - sim[ch][ok]) ** 2)) / rp.sst[ch])
        out[stage] = 100.0 * (1.0 - math.sqrt(float(np.mean(qs)))) if qs else math.nan
    return out


def record_angles(res: RunResults, name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """theta and alpha of experiment ``name`` as measured: in degrees through the run's calibration (theta
    unwrapped), else the sensor volts; and their unit ("deg" or "V")."""
    df = res.records[name]
    if res.calibration is None:
        return df["theta_v"].to_numpy(dtype=float), df["alpha_v"].to_numpy(dtype=float), "V"
    return theta_deg(df["theta_v"], res.calibration), alpha_deg(df["alpha_v"], res.calibration), "deg"
