"""The best linear approximation (BLA) of a periodic multisine experiment and the simulated FRF against it.

Pure functions: numpy arrays in, the :class:`BLA` dataclass or JSON-safe dicts (Python floats, ints, str, bool,
lists) out; NaN marks "undefined" (written as null). Frequencies in Hz, G in units of y per unit of u (complex),
levels in dB relative to the mean output power at the excited lines. Also the frequency bands and the JSON-safe
number helpers :mod:`harness.diagnosis.where` shares.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..ident.preprocess import as_signal
from ..rig.signals import MultisineLines

__all__ = [
    "BLA",
    "DEFAULT_BAND_EDGES_HZ",
    "NAN",
    "band_edges",
    "bla",
    "db10",
    "frf_gap",
    "json_float",
    "json_floats",
    "positive",
    "safe_ratio",
]

DEFAULT_BAND_EDGES_HZ: tuple[float, ...] = (0.0, 0.5, 2.0, 5.0, 10.0)
NAN = float("nan")


# --- input checks and small helpers


def positive(name: str, x: Any) -> float:
    """``x`` as a positive finite float, or ValueError naming ``name``."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {x!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {x!r}")
    return v


def json_float(x: Any) -> float:
    """Plain Python float (NaN for None / non-finite stays NaN)."""
    if x is None:
        return NAN
    v = float(x)
    return v if math.isfinite(v) else NAN


def json_floats(a: np.ndarray) -> list[float]:
    """Plain Python floats of an array (non-finite as NaN)."""
    return [json_float(v) for v in np.asarray(a, dtype=np.float64)]


def safe_ratio(num: float, den: float) -> float:
    """num / den, NaN when den <= 0 or either is not finite."""
    return float(num / den) if den > 0 and math.isfinite(num) and math.isfinite(den) else NAN


def db10(x: float) -> float:
    """10 log10(x) [dB] of a power ratio, NaN when x <= 0 or not finite."""
    return 10.0 * math.log10(x) if x > 0 and math.isfinite(x) else NAN


# --- frequency


def band_edges(Ts: float, bands_hz: Sequence[float] | None = None) -> np.ndarray:
    """Band edges [Hz]: ``bands_hz`` (increasing, from >= 0 to <= Nyquist) or the defaults 0, 0.5, 2, 5, 10 Hz
    and Nyquist (defaults at or above Nyquist are dropped)."""
    Ts = positive("Ts", Ts)
    nyq = 0.5 / Ts
    if bands_hz is None:
        edges = np.array([f for f in DEFAULT_BAND_EDGES_HZ if f < nyq] + [nyq])
    else:
        edges = as_signal("bands_hz", bands_hz)
        if edges.size < 2 or np.any(np.diff(edges) <= 0) or edges[0] < 0:
            raise ValueError(f"bands_hz must be >= 2 increasing band edges >= 0 Hz, got {list(edges)}")
        if edges[-1] > nyq * (1 + 1e-9):
            raise ValueError(f"band edge {edges[-1]} Hz is above the Nyquist frequency {nyq} Hz")
    return edges


# --- best linear approximation


@dataclass(frozen=True)
class BLA:
    """Best linear approximation at the excited lines of a periodic multisine experiment.

    ``freqs`` [Hz] of the excited lines, ``G`` (unit of y per unit of u, complex), ``var_noise`` and
    ``var_nl``: variances of G from noise (period-to-period) and from stochastic nonlinear distortion
    (interpolated from the non-excited detection lines), in |G|^2 units. Levels in dB relative to the mean
    output power at the excited lines: ``odd_level_db`` / ``even_level_db`` (mean power at the odd / even
    detection lines; NaN without such lines) and ``noise_level_db`` (mean noise variance of the averaged
    output spectrum). ``odd_freqs``/``odd_db`` and ``even_freqs``/``even_db``: per detection line, same
    reference. ``Ts`` [s], ``n_periods``: periods averaged (the first is dropped).
    """

    freqs: np.ndarray
    G: np.ndarray
    var_noise: np.ndarray
    var_nl: np.ndarray
    odd_level_db: float
    even_level_db: float
    noise_level_db: float
    Ts: float
    n_periods: int
    odd_freqs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    odd_db: np.ndarray = field(default_factory=lambda: np.zeros(0))
    even_freqs: np.ndarray = field(default_factory=lambda: np.zeros(0))
    even_db: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def sigma(self) -> np.ndarray:
        """Total standard deviation of G, sqrt(var_noise + var_nl)."""
        return np.sqrt(self.var_noise + self.var_nl)

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe: magnitude [dB], unwrapped phase [deg], variances, levels, detection lines."""
        mag = np.abs(self.G)
        with np.errstate(divide="ignore"):
            mag_db = 20.0 * np.log10(mag)
        phase = np.degrees(np.unwrap(np.angle(self.G))) if self.G.size else np.zeros(0)
        return {
            "freqs_hz": json_floats(self.freqs),
            "mag_db": json_floats(mag_db),
            "phase_deg": json_floats(phase),
            "var_noise": json_floats(self.var_noise),
            "var_nl": json_floats(self.var_nl),
            "odd_level_db": json_float(self.odd_level_db),
            "even_level_db": json_float(self.even_level_db),
            "noise_level_db": json_float(self.noise_level_db),
            "Ts": json_float(self.Ts),
            "n_periods": int(self.n_periods),
            "odd_lines": {"freqs_hz": json_floats(self.odd_freqs), "level_db": json_floats(self.odd_db)},
            "even_lines": {"freqs_hz": json_floats(self.even_freqs), "level_db": json_floats(self.even_db)},
        }


def _nearest_mean(target: np.ndarray, src_bins: np.ndarray, src_vals: np.ndarray, k: int = 4) -> np.ndarray:
    """Mean of ``src_vals`` at the ``k`` source bins nearest to each target bin (NaN without sources)."""
    if src_bins.size == 0:
        return np.full(target.size, NAN)
    k = min(k, src_bins.size)
    dist = np.abs(target[:, None].astype(np.float64) - src_bins[None, :].astype(np.float64))
    near = np.argpartition(dist, k - 1, axis=1)[:, :k]
    return src_vals[near].mean(axis=1)


def bla(u: np.ndarray, y: np.ndarray, period_samples: int, lines: MultisineLines) -> BLA:
    """Best linear approximation G = Y / U at the excited lines of a periodic multisine experiment.

    The record is cut into whole periods of ``period_samples``; the first is dropped (transient), an
    incomplete tail is ignored; at least 2 periods must remain. U, Y are the period DFTs averaged over the M
    remaining periods. ``var_noise`` = sum_m |Y_m - G U_m|^2 / ((M - 1) M |U|^2) (covers input and output
    noise). ``var_nl``: the noise-corrected output power at the nearest 4 non-excited detection lines (odd
    ones for an odd multisine, whose excited lines only odd nonlinearities reach; all of them otherwise),
    divided by |U|^2. Integrating outputs (angles) drift with any DC error and leak into all lines: prefer a
    differentiated output.
    """
    ps = period_samples
    if isinstance(ps, bool) or not isinstance(ps, (int, np.integer)) or ps < 2:
        raise ValueError(f"period_samples must be an integer >= 2, got {period_samples!r}")
    P = int(ps)
    if not isinstance(lines, MultisineLines):
        raise ValueError(
            f"lines must be a MultisineLines (harness.rig.signals.multisine_lines), got {type(lines).__name__}"
        )
    if lines.period_samples != P:
        raise ValueError(f"lines were designed for a period of {lines.period_samples} samples, not {P}")
    u = as_signal("u", u)
    y = as_signal("y", y, u.size)
    M = u.size // P - 1
    if M < 2:
        raise ValueError(
            f"BLA needs at least 3 whole periods of {P} samples (the first is dropped), got {u.size} samples"
        )
    U = np.fft.rfft(u[P : P * (M + 1)].reshape(M, P), axis=1)
    Y = np.fft.rfft(y[P : P * (M + 1)].reshape(M, P), axis=1)
    Ub, Yb = U.mean(axis=0), Y.mean(axis=0)
    exc = np.asarray(lines.excited, dtype=np.int64)
    odd = np.asarray(lines.odd_detection, dtype=np.int64)
    even = np.asarray(lines.even_detection, dtype=np.int64)
    if exc.size == 0:
        raise ValueError("the multisine has no excited lines")
    if np.any(np.abs(Ub[exc]) == 0):
        raise ValueError("the input has no power at some excited line: u does not match the multisine lines")
    G = Yb[exc] / Ub[exc]
    resid = Y[:, exc] - G[None, :] * U[:, exc]
    var_noise = np.sum(np.abs(resid) ** 2, axis=0) / ((M - 1) * M * np.abs(Ub[exc]) ** 2)
    var_yb = np.sum(np.abs(Y - Yb[None, :]) ** 2, axis=0) / ((M - 1) * M)  # noise variance of Yb per bin
    det = odd if np.all(exc % 2 == 1) else np.union1d(odd, even)
    p_det = np.abs(Yb[det]) ** 2 - var_yb[det]  # noise-corrected; clipped at 0 after local averaging
    var_nl = np.maximum(_nearest_mean(exc, det, p_det), 0.0) / np.abs(Ub[exc]) ** 2
    var_nl = np.where(np.isfinite(var_nl), var_nl, 0.0)
    p_exc = float(np.mean(np.abs(Yb[exc]) ** 2))

    def level(bins: np.ndarray) -> float:
        return db10(float(np.mean(np.abs(Yb[bins]) ** 2)) / p_exc) if bins.size and p_exc > 0 else NAN

    def per_line(bins: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return 10.0 * np.log10(np.abs(Yb[bins]) ** 2 / p_exc) if p_exc > 0 else np.full(bins.size, NAN)

    all_lines = np.union1d(exc, np.union1d(odd, even))
    noise_db = db10(float(np.mean(var_yb[all_lines])) / p_exc) if p_exc > 0 else NAN
    df = lines.df
    return BLA(
        freqs=exc * df,
        G=G,
        var_noise=var_noise,
        var_nl=var_nl,
        odd_level_db=level(odd),
        even_level_db=level(even),
        noise_level_db=noise_db,
        Ts=float(lines.Ts),
        n_periods=M,
        odd_freqs=odd * df,
        odd_db=per_line(odd),
        even_freqs=even * df,
        even_db=per_line(even),
    )


def frf_gap(bla_real: BLA, G_sim: np.ndarray, bands_hz: Sequence[float] | None = None) -> dict[str, Any]:
    """Simulated FRF ``G_sim`` (complex, at ``bla_real.freqs``) against the measured BLA.

    Per line: ``err_db`` = 20 log10 |G_sim / G|, ``err_deg`` = angle(G_sim / G) in (-180, 180], and
    ``bound_db`` = 20 log10(1 + 2 sigma / |G|), the BLA's 2-sigma uncertainty (sigma^2 = var_noise + var_nl).
    A line "exceeds" when |G_sim - G| > 2 sigma. ``bands``: per band (edges as :func:`band_edges`) the lines,
    those exceeding, the RMS of err_db and the largest |err_deg|.
    """
    if not isinstance(bla_real, BLA):
        raise ValueError(f"bla_real must be a BLA, got {type(bla_real).__name__}")
    Gs = np.asarray(G_sim, dtype=np.complex128)
    if Gs.shape != bla_real.G.shape:
        want = bla_real.G.shape
        raise ValueError(f"G_sim has shape {Gs.shape}, expected {want} (one value per excited line)")
    if not np.all(np.isfinite(Gs)):
        raise ValueError("G_sim contains NaN or inf")
    G = bla_real.G
    sig = bla_real.sigma
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = Gs / G
        err_db = 20.0 * np.log10(np.abs(rel))
        err_deg = np.degrees(np.angle(rel))
        bound_db = 20.0 * np.log10(1.0 + 2.0 * sig / np.abs(G))
    exceeds = np.abs(Gs - G) > 2.0 * sig
    f = bla_real.freqs
    edges = band_edges(bla_real.Ts, bands_hz)
    which = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, edges.size - 2)
    bands = []
    for b in range(edges.size - 1):
        sel = which == b
        n = int(sel.sum())
        bands.append(
            {
                "lo_hz": json_float(edges[b]),
                "hi_hz": json_float(edges[b + 1]),
                "n_lines": n,
                "n_exceed": int(exceeds[sel].sum()),
                "rms_err_db": json_float(math.sqrt(float(np.mean(err_db[sel] ** 2)))) if n else NAN,
                "max_abs_err_deg": json_float(np.max(np.abs(err_deg[sel]))) if n else NAN,
            }
        )
    dist = np.abs(Gs - G) / np.where(sig > 0, sig, np.inf)
    worst = int(np.argmax(np.where(np.isfinite(dist), dist, np.abs(Gs - G))))
    return {
        "freqs_hz": json_floats(f),
        "err_db": json_floats(err_db),
        "err_deg": json_floats(err_deg),
        "bound_db": json_floats(bound_db),
        "exceeds_hz": json_floats(f[exceeds]),
        "n_lines": int(f.size),
        "n_exceed": int(exceeds.sum()),
        "share_exceed": float(exceeds.mean()),
        "worst": {
            "freq_hz": json_float(f[worst]),
            "err_db": json_float(err_db[worst]),
            "err_deg": json_float(err_deg[worst]),
        },
        "bands": bands,
    }
