"""Excitation signals for the flexible-joint rig.

Every generator returns a float64 array of ``n`` samples taken at ``Ts`` seconds, in volts (the amplifier
command). Sample ``k`` is at time ``t = k * Ts``. Random signals are deterministic per ``seed`` (numpy
``Generator`` with ``PCG64``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "MultisineLines",
    "SIGNAL_KINDS",
    "check_params",
    "chirp",
    "constant",
    "crest_factor",
    "generate",
    "multisine",
    "multisine_lines",
    "prbs",
    "ramp",
    "square",
    "step",
]

# Relative tolerance used when comparing sample times with switching instants (t0, square edges).
_TIME_EPS = 1e-9


def _check_n(n: int) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer number of samples, got {n!r}")
    return int(n)


def _check_ts(Ts: float) -> float:
    Ts = _finite("Ts", Ts)
    if Ts <= 0:
        raise ValueError(f"Ts must be > 0 seconds, got {Ts!r}")
    return Ts


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def _finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return v


def _time(n: int, Ts: float) -> np.ndarray:
    return np.arange(n, dtype=np.float64) * Ts


def constant(n: int, amplitude: float, *, offset: float = 0.0) -> np.ndarray:
    """Constant command ``offset + amplitude`` [V]."""
    n = _check_n(n)
    return np.full(n, _finite("offset", offset) + _finite("amplitude", amplitude), dtype=np.float64)


def prbs(n: int, B: float, amplitude: float, *, offset: float = 0.0, seed: int = 0) -> np.ndarray:
    """Random binary signal ``offset +- amplitude`` [V] with switching probability ``B`` per sample.

    The level is a two-state Markov chain: at every sample after the first it flips with probability B
    (0 < B <= 1), so the mean run length is 1/B samples. The first level is drawn at random (+ or -).
    Deterministic per ``seed`` (PCG64).
    """
    n = _check_n(n)
    B = _finite("B", B)
    if not 0.0 < B <= 1.0:
        raise ValueError(f"switching probability B must be in (0, 1], got {B!r}")
    amplitude = _finite("amplitude", amplitude)
    offset = _finite("offset", offset)
    rng = np.random.Generator(np.random.PCG64(_check_seed(seed)))
    first = 1 if rng.random() < 0.5 else 0
    flips = rng.random(n - 1) < B
    parity = (first + np.concatenate(([0], np.cumsum(flips)))) % 2
    level = np.where(parity == 1, 1.0, -1.0)
    return offset + amplitude * level


def square(
    n: int,
    Ts: float,
    f: float,
    amplitude: float,
    *,
    offset: float = 0.0,
    duty: float = 0.5,
    phase: float = 0.0,
) -> np.ndarray:
    """Square wave ``offset +- amplitude`` [V] of frequency ``f`` [Hz].

    High (``offset + amplitude``) for the first ``duty`` fraction of each period, starting at t = 0 when
    ``phase`` [rad] is 0; a phase of pi shifts the wave by half a period.
    """
    n, Ts = _check_n(n), _check_ts(Ts)
    f = _finite("f", f)
    if f <= 0:
        raise ValueError(f"square wave frequency f must be > 0 Hz, got {f!r}")
    duty = _finite("duty", duty)
    if not 0.0 < duty < 1.0:
        raise ValueError(f"duty must be in (0, 1), got {duty!r}")
    amplitude, offset = _finite("amplitude", amplitude), _finite("offset", offset)
    phase = _finite("phase", phase)
    cycles = np.arange(n, dtype=np.float64) * (Ts * f) + phase / (2.0 * math.pi)
    frac = np.mod(cycles + _TIME_EPS, 1.0)
    return offset + amplitude * np.where(frac < duty, 1.0, -1.0)


def step(n: int, Ts: float, t0: float, amplitude: float, *, offset: float = 0.0) -> np.ndarray:
    """Step from ``offset`` to ``offset + amplitude`` [V] at time ``t0`` [s] (sample k with k Ts >= t0)."""
    n, Ts = _check_n(n), _check_ts(Ts)
    t0 = _finite("t0", t0)
    amplitude, offset = _finite("amplitude", amplitude), _finite("offset", offset)
    t = _time(n, Ts)
    return offset + amplitude * (t >= t0 - _TIME_EPS * Ts).astype(np.float64)


def ramp(
    n: int,
    Ts: float,
    slope: float,
    *,
    t0: float = 0.0,
    offset: float = 0.0,
    limit: float | None = None,
) -> np.ndarray:
    """Ramp ``offset + slope * max(t - t0, 0)`` [V], ``slope`` in V/s.

    ``limit`` [V] is the level at which the ramp stops and holds; it must lie on the side the ramp moves to
    (above ``offset`` for a positive slope, below it for a negative one).
    """
    n, Ts = _check_n(n), _check_ts(Ts)
    slope, t0, offset = _finite("slope", slope), _finite("t0", t0), _finite("offset", offset)
    t = _time(n, Ts)
    x = offset + slope * np.maximum(t - t0, 0.0)
    if limit is not None:
        limit = _finite("limit", limit)
        if slope > 0:
            if limit < offset:
                raise ValueError(f"ramp limit {limit} V is below its offset {offset} V for a rising ramp")
            x = np.minimum(x, limit)
        elif slope < 0:
            if limit > offset:
                raise ValueError(f"ramp limit {limit} V is above its offset {offset} V for a falling ramp")
            x = np.maximum(x, limit)
    return x


def chirp(
    n: int,
    Ts: float,
    f0: float,
    f1: float,
    amplitude: float,
    *,
    method: str = "log",
    offset: float = 0.0,
) -> np.ndarray:
    """Swept sine ``offset + amplitude sin(phi(t))`` [V], ``f0`` [Hz] at t = 0 to ``f1`` [Hz] at the end.

    ``method`` is "log" (exponential sweep, constant time per decade) or "linear". Starts at ``offset``.
    """
    n, Ts = _check_n(n), _check_ts(Ts)
    f0, f1 = _finite("f0", f0), _finite("f1", f1)
    amplitude, offset = _finite("amplitude", amplitude), _finite("offset", offset)
    methods = {"log": "logarithmic", "linear": "linear"}
    if method not in methods:
        raise ValueError(f"unknown chirp method {method!r}; valid: {', '.join(methods)}")
    if f0 <= 0 or f1 <= 0:
        raise ValueError(f"chirp frequencies must be > 0 Hz, got f0={f0}, f1={f1}")
    nyquist = 0.5 / Ts
    if max(f0, f1) > nyquist:
        raise ValueError(f"chirp frequency {max(f0, f1)} Hz is above the Nyquist frequency {nyquist} Hz")
    if n < 2:
        return np.full(n, offset)
    t = _time(n, Ts)
    return offset + amplitude * np.cos(_sweep_phase(t, f0, float(t[-1]), f1, methods[method]) + np.deg2rad(-90.0))


def _sweep_phase(t: np.ndarray, f0: float, t1: float, f1: float, method: str) -> np.ndarray:
    """The phase [rad] of a sweep from ``f0`` [Hz] at t = 0 to ``f1`` at ``t1`` [s]: ``scipy.signal.chirp``'s
    "linear" and "logarithmic" phase, in its arithmetic (the same numbers; scipy.signal itself costs every command
    that reads a spec most of a second to import)."""
    if method == "linear":
        beta = (f1 - f0) / t1
        return 2 * np.pi * (f0 * t + 0.5 * beta * t * t)
    if f0 == f1:
        return 2 * np.pi * f0 * t
    beta = t1 / np.log(f1 / f0)
    return 2 * np.pi * beta * f0 * (pow(f1 / f0, t / t1) - 1.0)


@dataclass(frozen=True)
class MultisineLines:
    """Frequency lines of one period of a multisine, as DFT bin indices of one period.

    A bin ``k`` is at ``k * df`` Hz with ``df = 1 / (period_samples * Ts)``. For a record of ``P`` whole
    periods, the same line is bin ``k * P`` of the full-record DFT.
    ``excited``: lines carrying power. ``odd_detection``: odd lines in the band left unexcited (they reveal
    odd nonlinearities). ``even_detection``: even lines in the band (unexcited when ``odd``; reveal even
    nonlinearities).
    """

    period_samples: int
    Ts: float
    excited: np.ndarray
    odd_detection: np.ndarray
    even_detection: np.ndarray

    @property
    def df(self) -> float:
        """Frequency resolution of one period [Hz]."""
        return 1.0 / (self.period_samples * self.Ts)

    def freqs(self, which: str = "excited") -> np.ndarray:
        """Frequencies [Hz] of ``excited``, ``odd_detection`` or ``even_detection`` lines."""
        if which not in ("excited", "odd_detection", "even_detection"):
            raise ValueError(f"unknown line set {which!r}; valid: excited, odd_detection, even_detection")
        return getattr(self, which) * self.df


def _seed_streams(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Two independent PCG64 streams from one seed: line selection and phases."""
    lines_ss, phase_ss = np.random.SeedSequence(_check_seed(seed)).spawn(2)
    return np.random.Generator(np.random.PCG64(lines_ss)), np.random.Generator(np.random.PCG64(phase_ss))


def multisine_lines(
    period_samples: int,
    Ts: float,
    f_min: float,
    f_max: float,
    *,
    odd: bool = True,
    seed: int = 0,
    skip_one_per_group: bool = True,
) -> MultisineLines:
    """Design the lines of a (random-odd) multisine; same arguments and seed as :func:`multisine`.

    Candidate lines are bins k with f_min <= k df <= f_max, 1 <= k < period_samples / 2 (odd k only when
    ``odd``). With ``skip_one_per_group`` one line chosen at random in each group of 3 consecutive candidate
    lines is left out (an incomplete last group keeps all its lines).
    """
    N = _check_n(period_samples)
    Ts = _check_ts(Ts)
    f_min, f_max = _finite("f_min", f_min), _finite("f_max", f_max)
    if not 0.0 <= f_min <= f_max:
        raise ValueError(f"need 0 <= f_min <= f_max, got f_min={f_min} Hz, f_max={f_max} Hz")
    df = 1.0 / (N * Ts)
    k_lo = max(1, math.ceil(f_min / df - 1e-9))
    k_hi = min(math.floor(f_max / df + 1e-9), (N - 1) // 2)
    band = np.arange(k_lo, k_hi + 1, dtype=np.int64)
    cand = band[band % 2 == 1] if odd else band
    if cand.size == 0:
        raise ValueError(
            f"no {'odd ' if odd else ''}multisine line between {f_min} and {f_max} Hz "
            f"(resolution {df:.6g} Hz, Nyquist {0.5 / Ts:.6g} Hz): lengthen the period or widen the band"
        )
    rng_lines, _ = _seed_streams(seed)
    keep = np.ones(cand.size, dtype=bool)
    if skip_one_per_group:
        for g in range(cand.size // 3):
            keep[3 * g + int(rng_lines.integers(3))] = False
    excited = cand[keep]
    unexcited = np.setdiff1d(band, excited)
    return MultisineLines(
        period_samples=N,
        Ts=Ts,
        excited=excited,
        odd_detection=unexcited[unexcited % 2 == 1],
        even_detection=unexcited[unexcited % 2 == 0],
    )


def multisine(
    n: int,
    Ts: float,
    f_min: float,
    f_max: float,
    amplitude_rms: float,
    *,
    period_samples: int,
    odd: bool = True,
    seed: int = 0,
    skip_one_per_group: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Random-phase (odd) multisine [V] with flat amplitude spectrum, for the best linear approximation.

    One period of ``period_samples`` samples is repeated ``n / period_samples`` times (n must be a multiple).
    Lines are those of :func:`multisine_lines`; phases are uniform on [0, 2 pi). The signal has zero mean and
    RMS ``amplitude_rms`` [V]. Returns ``(x, excited_bins)`` with bins as DFT indices of one period.
    """
    n = _check_n(n)
    N = _check_n(period_samples)
    if n % N:
        raise ValueError(f"multisine length n={n} is not a multiple of period_samples={N}")
    amplitude_rms = _finite("amplitude_rms", amplitude_rms)
    if amplitude_rms < 0:
        raise ValueError(f"amplitude_rms must be >= 0 V, got {amplitude_rms}")
    lines = multisine_lines(N, Ts, f_min, f_max, odd=odd, seed=seed, skip_one_per_group=skip_one_per_group)
    _, rng_phase = _seed_streams(seed)
    phases = rng_phase.uniform(0.0, 2.0 * math.pi, lines.excited.size)
    spec = np.zeros(N // 2 + 1, dtype=np.complex128)
    spec[lines.excited] = np.exp(1j * phases)
    one = np.fft.irfft(spec, n=N)
    one *= amplitude_rms / math.sqrt(float(np.mean(one**2)))
    return np.tile(one, n // N), lines.excited.copy()


def crest_factor(x: np.ndarray) -> float:
    """Crest factor max|x - mean| / rms(x - mean) (dimensionless; sqrt(2) for a sine)."""
    x = np.asarray(x, dtype=np.float64)
    xc = x - x.mean()
    rms = math.sqrt(float(np.mean(xc**2)))
    if rms == 0.0:
        raise ValueError("crest factor of a constant signal is undefined")
    return float(np.max(np.abs(xc)) / rms)


# kind -> (required params, optional params with defaults)
_SPECS: dict[str, tuple[tuple[str, ...], dict[str, Any]]] = {
    "constant": (("amplitude",), {"offset": 0.0}),
    "prbs": (("B", "amplitude"), {"offset": 0.0}),
    "square": (("f", "amplitude"), {"offset": 0.0, "duty": 0.5, "phase": 0.0}),
    "step": (("t0", "amplitude"), {"offset": 0.0}),
    "ramp": (("slope",), {"t0": 0.0, "offset": 0.0, "limit": None}),
    "chirp": (("f0", "f1", "amplitude"), {"method": "log", "offset": 0.0}),
    "multisine": (
        ("f_min", "f_max", "amplitude_rms", "period"),
        {"odd": True, "skip_one_per_group": True},
    ),
}
SIGNAL_KINDS: tuple[str, ...] = tuple(_SPECS)


def _as_bool(name: str, value: Any) -> bool:
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise ValueError(f"{name} must be true or false, got {value!r}")


def check_params(kind: str, Ts: float, params: dict[str, Any]) -> None:
    """Validate a spec entry without knowing its length: names and values, as :func:`generate` would.

    Builds one multisine period (or 4 samples of the other kinds); raises ValueError on bad input.
    """
    n = 4
    if kind == "multisine" and isinstance(params, dict) and "period" in params:
        Ts_ = _check_ts(Ts)
        n = max(1, round(_finite("period", params["period"]) / Ts_))
    generate(kind, n, Ts, params, 0)


def generate(kind: str, n: int, Ts: float, params: dict[str, Any], seed: int = 0) -> np.ndarray:
    """Build an excitation of ``n`` samples at ``Ts`` s from a campaign spec entry.

    Parameters
    ----------
    kind : str
        One of :data:`SIGNAL_KINDS`: constant, prbs, square, step, ramp, chirp, multisine.
    n : int
        Number of samples; sample ``k`` is at ``t = k Ts``.
    Ts : float
        Sample period [s].
    params : dict
        The generator's keyword parameters (``{"B": 0.1, "amplitude": 1.0}`` for a PRBS); for "multisine",
        ``period`` is in seconds and must be a whole number of samples dividing ``n``.
    seed : int
        Drives "prbs" and "multisine"; ignored by the deterministic kinds.

    Returns
    -------
    numpy.ndarray
        The signal, float64, in the unit of its amplitude (V for a command, deg for a closed loop's reference).
    """
    if kind not in _SPECS:
        raise ValueError(f"unknown signal kind {kind!r}; valid: {', '.join(SIGNAL_KINDS)}")
    if not isinstance(params, dict):
        raise ValueError(f"signal parameters must be a table/dict, got {type(params).__name__}")
    required, optional = _SPECS[kind]
    valid = ", ".join((*required, *optional))
    unknown = sorted(set(params) - set(required) - set(optional))
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)} for signal {kind!r}; valid: {valid}")
    missing = [p for p in required if p not in params]
    if missing:
        raise ValueError(f"missing parameter(s) {', '.join(missing)} for signal {kind!r}; valid: {valid}")
    p = {**optional, **params}
    n, Ts = _check_n(n), _check_ts(Ts)
    if kind == "constant":
        return constant(n, p["amplitude"], offset=p["offset"])
    if kind == "prbs":
        return prbs(n, p["B"], p["amplitude"], offset=p["offset"], seed=seed)
    if kind == "square":
        return square(n, Ts, p["f"], p["amplitude"], offset=p["offset"], duty=p["duty"], phase=p["phase"])
    if kind == "step":
        return step(n, Ts, p["t0"], p["amplitude"], offset=p["offset"])
    if kind == "ramp":
        return ramp(n, Ts, p["slope"], t0=p["t0"], offset=p["offset"], limit=p["limit"])
    if kind == "chirp":
        return chirp(n, Ts, p["f0"], p["f1"], p["amplitude"], method=p["method"], offset=p["offset"])
    # multisine
    period = _finite("period", p["period"])
    period_samples = round(period / Ts)
    if period_samples < 1 or abs(period_samples * Ts - period) > 1e-6 * max(period, Ts):
        raise ValueError(f"multisine period {period} s is not a whole number of samples of Ts={Ts} s")
    x, _ = multisine(
        n,
        Ts,
        p["f_min"],
        p["f_max"],
        p["amplitude_rms"],
        period_samples=period_samples,
        odd=_as_bool("odd", p["odd"]),
        seed=seed,
        skip_one_per_group=_as_bool("skip_one_per_group", p["skip_one_per_group"]),
    )
    return x
