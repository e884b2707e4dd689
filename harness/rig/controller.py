"""The closed loop's controller: its law, the controller FMU's parameters, and the law run on sampled data.

Real rigs are run under feedback; the logged command is this law's output, computed every sample from the
measured angles. Three kinds, as lab controllers are written:

- ``state_feedback``: u = K (x_ref - x) on x = (theta, alpha, theta_dot, alpha_dot), x_ref = (ref, 0, 0, 0),
  K = (k_theta, k_alpha, k_theta_dot, k_alpha_dot) [V/rad, V/rad, V s/rad, V s/rad];
- ``pid``: u = kp e + ki I - kd theta_dot on e = ref - theta (derivative on the measurement, so a square
  reference gives no kick), I the integral of e (forward Euler, held while the output is limited)
  [V/rad, V/(rad s), V s/rad];
- ``lqg``: a steady-state Kalman filter in current form on y = (theta, alpha) and state feedback on its estimate
  (:class:`Estimator`): x_bar_k = A x_hat_(k-1) + B u_(k-1) (the first sample: X0 y_0), x_hat_k = x_bar_k +
  L (y_k - C x_bar_k), u_k = K (N ref_k - x_hat_k), u_(k-1) the command written (after the clamp); at most
  :data:`NX_MAX` states.

Velocities are filtered differences, as lab controllers compute them: v_k = a v_{k-1} + (1 - a) (x_k - x_{k-1})
/ Ts with a = exp(-2 pi cutoff Ts) and v_0 = 0 (a first-order low-pass at ``cutoff`` [Hz] on the backward
difference). The output is clamped to +-``u_limit`` [V] (0: no limit). A record may log its reference ahead of the
command that used it (a lab's logger and controller in different loops): ``ref_delay`` samples, the controller then
acting on ref_(k - ref_delay); the co-simulation feeds the controller FMU the reference so delayed. Angles enter in
volts, as the DAQ reads them, and are converted with the controller's own calibration: theta [deg] = theta_gain
(theta_v - theta_offset), alpha [deg] = alpha_gain (alpha_v - alpha_offset).

:func:`law` is the same computation in numpy: the controller FMU's test oracle, and what identifies a controller
from a record.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

__all__ = [
    "CUTOFFS",
    "IDENTIFIABLE",
    "KINDS",
    "NX_MAX",
    "Estimator",
    "MAX_REF_DELAY_S",
    "R2_MIN",
    "Controller",
    "command_r2",
    "delayed",
    "filtered_rate",
    "identify_controller",
    "law",
    "output_limit",
    "parse_controller",
]

KINDS = {"state_feedback": 1, "pid": 2, "lqg": 3}  # kind name -> the FMU's Integer parameter ``kind``
IDENTIFIABLE = ("state_feedback", "pid")  # the kinds identify_controller fits to a record's command
NX_MAX = 10  # the LQG's largest number of states: NX_MAX in fmus/controller/config.h
ESTIMATOR_SHAPES = {"A": ("n", "n"), "B": ("n",), "C": (2, "n"), "L": ("n", 2), "K": ("n",), "N": ("n",),
                    "X0": ("n", 2)}  # fmt: skip


@dataclass(frozen=True)
class Estimator:
    """An LQG controller's arrays (see the module docstring), nested lists of floats: ``A`` (n x n), ``B`` (n),
    ``C`` (2 x n, rows theta and alpha as read [rad]), ``L`` (n x 2, the Kalman gain in current form), ``K`` (n,
    [V per unit of state]), ``N`` (n, the state per rad of reference), ``X0`` (n x 2, the first estimate per rad read).
    """

    A: list[list[float]]
    B: list[float]
    C: list[list[float]]
    L: list[list[float]]
    K: list[float]
    N: list[float]
    X0: list[list[float]]

    def __post_init__(self) -> None:
        n = len(self.B)
        if not 1 <= n <= NX_MAX:
            raise ValueError(f"controller estimator: {n} states; an LQG has 1 to {NX_MAX}")
        for name, shape in ESTIMATOR_SHAPES.items():
            a = np.asarray(getattr(self, name), dtype=float)
            want = tuple(n if d == "n" else d for d in shape)
            if a.shape != want:
                raise ValueError(f"controller estimator {name}: shape {a.shape}, expected {want} (n = {n} states)")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"controller estimator {name}: must be finite numbers")

    @property
    def n(self) -> int:
        return len(self.B)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(getattr(self, k), dtype=float) for k in ESTIMATOR_SHAPES}

    def fmu_parameters(self) -> dict[str, float | int]:
        """The controller FMU's lqg_ parameters: lqg_n and each array's elements by name (``lqg_A[i,j]``, ``lqg_B[i]``,
        1-based)."""
        out: dict[str, float | int] = {"lqg_n": self.n}
        for k, a in self.arrays().items():
            if a.ndim == 1:
                out |= {f"lqg_{k}[{i + 1}]": float(v) for i, v in enumerate(a)}
            else:
                out |= {
                    f"lqg_{k}[{i + 1},{j + 1}]": float(a[i, j]) for i in range(a.shape[0]) for j in range(a.shape[1])
                }
        return out


@dataclass(frozen=True)
class Controller:
    """A controller as a spec or a record names it. ``K`` (state feedback) or ``kp``/``ki``/``kd`` (PID) as in
    the module docstring; ``cutoff`` [Hz] of the velocity filter; ``u_limit`` [V] (0: none); ``sample_rate``
    [Hz] (None: the data's); ``ref_delay`` [samples] of the reference it acts on behind the logged one; ``alpha_bias``
    [deg] the zero error of the deflection it reads (a record's gauge offset, removed from its data); ``alpha_gain``
    [deg/V] the gauge calibration it converts alpha_v with (None: the DAQ's gauge_gain, a calibration that is right);
    ``source`` "spec", "given" or "identified" (then ``r2`` of the least-squares fit of the logged command)."""

    kind: str = "state_feedback"
    K: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])
    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    cutoff: float = 50.0
    u_limit: float = 0.0
    sample_rate: float | None = None
    ref_delay: int = 0
    alpha_bias: float = 0.0
    alpha_gain: float | None = None
    source: str = "spec"
    r2: float | None = None
    estimator: Estimator | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"controller kind {self.kind!r} unknown; valid: {', '.join(KINDS)}")
        if isinstance(self.estimator, dict):
            object.__setattr__(self, "estimator", Estimator(**self.estimator))
        if (self.kind == "lqg") != (self.estimator is not None):
            raise ValueError("an lqg controller has an estimator (A, B, C, L, K, N, X0), and only an lqg one")
        if len(self.K) != 4:
            raise ValueError(f"controller K must have 4 gains (theta, alpha, theta_dot, alpha_dot), got {len(self.K)}")
        vals = [*self.K, self.kp, self.ki, self.kd, self.cutoff, self.u_limit, self.alpha_bias]
        if not all(math.isfinite(float(v)) for v in vals):
            raise ValueError("controller gains, cutoff and u_limit must be finite numbers")
        if self.alpha_gain is not None and not (math.isfinite(float(self.alpha_gain)) and self.alpha_gain != 0):
            raise ValueError(f"controller alpha_gain must be a finite, nonzero deg/V, got {self.alpha_gain}")
        if not self.cutoff > 0:
            raise ValueError(f"controller cutoff must be > 0 Hz, got {self.cutoff}")
        if self.u_limit < 0:
            raise ValueError(f"controller u_limit must be >= 0 V (0: none), got {self.u_limit}")
        if int(self.ref_delay) != self.ref_delay or self.ref_delay < 0:
            raise ValueError(f"controller ref_delay must be a whole number of samples >= 0, got {self.ref_delay}")

    def fmu_parameters(self, sample_rate: float) -> dict[str, Any]:
        """Parameters of the controller FMU (fmus/controller) at ``sample_rate`` [Hz] unless the controller
        has its own; the angle calibration (theta_gain ...) is the caller's to add (``alpha_gain`` when the controller
        has its own), and with it ``alpha_bias`` (returned as such: :meth:`harness.fmu.cosim.Rig.run_closed` turns it
        into the FMU's alpha_offset)."""
        k = [float(v) for v in self.K]
        own = {"alpha_gain": float(self.alpha_gain)} if self.alpha_gain is not None else {}
        return {
            "kind": KINDS[self.kind],
            "sample_rate": float(self.sample_rate or sample_rate),
            "k_theta": k[0],
            "k_alpha": k[1],
            "k_theta_dot": k[2],
            "k_alpha_dot": k[3],
            "kp": float(self.kp),
            "ki": float(self.ki),
            "kd": float(self.kd),
            "cutoff": float(self.cutoff),
            "u_limit": float(self.u_limit),
            "alpha_bias": float(self.alpha_bias),
            **own,
            **(self.estimator.fmu_parameters() if self.estimator is not None else {}),
        }

    def to_dict(self) -> dict[str, Any]:
        """Plain content (for manifest.json and diagnosis.json), None fields left out."""
        return {k: v for k, v in asdict(self).items() if v is not None}


def delayed(ref: np.ndarray, n: int) -> np.ndarray:
    """``ref`` delayed by ``n`` samples, its first value held before it."""
    ref = np.asarray(ref, dtype=float)
    n = int(n)
    return ref.copy() if n <= 0 else np.concatenate([np.full(min(n, ref.size), ref[0]), ref[: max(ref.size - n, 0)]])


def filtered_rate(x: np.ndarray, Ts: float, cutoff: float) -> np.ndarray:
    """Velocity of samples ``x`` at ``Ts`` [s] as a lab controller computes it: the backward difference through a
    first-order low-pass at ``cutoff`` [Hz], v_0 = 0 (units of x per second)."""
    x = np.asarray(x, dtype=float)
    a = math.exp(-2.0 * math.pi * cutoff * Ts)
    d = np.zeros_like(x)
    d[1:] = np.diff(x) / Ts
    v = np.empty_like(x)
    acc = 0.0
    for k in range(x.size):  # a scalar recursion: scipy.signal.lfilter would need its own initial conditions
        acc = a * acc + (1.0 - a) * d[k]
        v[k] = acc
    return v


def law(c: Controller, ref: np.ndarray, theta: np.ndarray, alpha: np.ndarray, Ts: float) -> np.ndarray:
    """The command u [V] a controller computes at every sample from the reference and the measured angles, all in
    rad at ``Ts`` [s] (the controller FMU's computation, in numpy)."""
    ref, theta, alpha = (np.asarray(v, dtype=float) for v in (ref, theta, alpha))
    ref = delayed(ref, c.ref_delay)
    alpha = alpha + math.radians(c.alpha_bias)
    th_dot = filtered_rate(theta, Ts, c.cutoff)
    lim = c.u_limit if c.u_limit > 0 else math.inf
    if c.estimator is not None:
        return _lqg_law(c.estimator, ref, theta, alpha, lim)
    if c.kind == "state_feedback":
        k = c.K
        u = k[0] * (ref - theta) - k[1] * alpha - k[2] * th_dot - k[3] * filtered_rate(alpha, Ts, c.cutoff)
        return np.clip(u, -lim, lim)
    e = ref - theta
    u = np.empty_like(e)
    integral = 0.0
    for i in range(e.size):
        raw = c.kp * e[i] + c.ki * integral - c.kd * th_dot[i]
        u[i] = min(max(raw, -lim), lim)
        if u[i] == raw:  # integrate only while the output is not limited (anti-windup)
            integral += Ts * e[i]
    return u


def _lqg_law(e: Estimator, ref: np.ndarray, theta: np.ndarray, alpha: np.ndarray, lim: float) -> np.ndarray:
    """An LQG's commands (the module docstring) on the samples [rad]: the FMU's recursion in numpy."""
    a = e.arrays()
    y = np.column_stack([theta, alpha])
    u = np.empty(theta.size)
    x_hat, u_prev = np.zeros(e.n), 0.0
    for k in range(theta.size):
        x_bar = a["X0"] @ y[k] if k == 0 else a["A"] @ x_hat + a["B"] * u_prev
        x_hat = x_bar + a["L"] @ (y[k] - a["C"] @ x_bar)
        u_prev = u[k] = min(max(float(a["K"] @ (a["N"] * ref[k] - x_hat)), -lim), lim)
    return u


R2_MIN = 0.9  # below this R^2 an identified controller is not trusted for a closed-loop replay
CUTOFFS = (5.0, 10.0, 15.0, 25.0, 50.0, 100.0)  # Hz: velocity-filter cutoffs tried when identifying a controller
MAX_REF_DELAY_S = 0.02  # s: reference delays tried when identifying a controller, up to this


def _regressors(
    kind: str, ref: np.ndarray, theta: np.ndarray, alpha: np.ndarray, Ts: float, cutoff: float
) -> np.ndarray:
    """The columns u is regressed on: state feedback (ref - theta, -alpha, -theta_dot, -alpha_dot); PID (e,
    integral of e, -theta_dot)."""
    th_dot = filtered_rate(theta, Ts, cutoff)
    e = ref - theta
    if kind == "state_feedback":
        return np.column_stack([e, -alpha, -th_dot, -filtered_rate(alpha, Ts, cutoff)])
    integral = np.concatenate([[0.0], np.cumsum(e[:-1]) * Ts])
    return np.column_stack([e, integral, -th_dot])


def output_limit(u: np.ndarray) -> float:
    """The command's clamp [V] when the record shows one (at least 3 samples at the same largest |u|: a free
    signal does not return to its exact peak), else 0."""
    top = float(np.max(np.abs(u)))
    at = np.isclose(np.abs(u), top, rtol=0.0, atol=1e-9 * max(top, 1.0))
    return top if top > 0 and np.count_nonzero(at) >= 3 else 0.0


def parse_controller(text: str) -> Controller:
    """A controller from its command-line form (``flexjoint predict --controller``).

    Parameters
    ----------
    text : str
        ``KIND:NAME=VALUE;...``: ``state_feedback:K=9.2,-18.8,1.2,0;cutoff=15;u_limit=10`` (gains on theta, alpha
        [V/rad] and their rates [V s/rad]) or ``pid:kp=12;ki=40;kd=0.8;cutoff=30``. An lqg controller's arrays are
        given as a ``[controller]`` table instead (a design's controller.toml).

    Returns
    -------
    Controller
        The controller, its ``source`` "given".

    Raises
    ------
    ValueError
        One line naming what is malformed.
    """
    kind, sep, rest = str(text).partition(":")
    kind = kind.strip()
    if kind == "lqg":
        raise ValueError(f"--controller {text!r}: an lqg controller's arrays are given as a [controller] table: "
                         "--controller-from FILE (a design's controller.toml)")  # fmt: skip
    if not sep or kind not in KINDS:
        raise ValueError(f"--controller {text!r}: expected KIND:NAME=VALUE;... with KIND one of state_feedback, pid, "
                         "e.g. state_feedback:K=9.2,-18.8,1.2,0;cutoff=15")  # fmt: skip
    common = ("cutoff", "u_limit", "ref_delay", "alpha_bias")
    names = {"state_feedback": ("K", *common), "pid": ("kp", "ki", "kd", *common)}[kind]
    args: dict[str, Any] = {"kind": kind, "source": "given"}
    for item in [s for s in rest.split(";") if s.strip()]:
        name, eq, value = (p.strip() for p in item.partition("="))
        if not eq or name not in names:
            raise ValueError(f"--controller {text!r}: {name!r} is not a {kind} setting; valid: {', '.join(names)}")
        try:
            nums = [float(v) for v in value.split(",")]
        except ValueError:
            raise ValueError(f"--controller {text!r}: {name}={value!r} is not a number") from None
        args[name] = nums if name == "K" else int(nums[0]) if name == "ref_delay" else nums[0]
        if (name == "K") != (len(nums) > 1) and name != "K":
            raise ValueError(f"--controller {text!r}: {name} takes one number")
    return Controller(**args)


def command_r2(c: Controller, ref: np.ndarray, theta: np.ndarray, alpha: np.ndarray, u: np.ndarray, Ts: float) -> float:
    """R^2 of a logged command ``u`` [V] by controller ``c``'s :func:`law` on ``ref``, ``theta``, ``alpha`` [rad] at
    ``Ts`` [s], over the samples where u is not at its clamp (:func:`output_limit`); NaN when u does not move there.
    How well a given controller explains a record (an identified one carries its own ``r2``)."""
    u = np.asarray(u, dtype=float)
    lim = output_limit(u)
    free = np.abs(u) < lim if lim > 0 else np.ones(u.size, dtype=bool)
    sst = float(np.sum((u[free] - np.mean(u[free])) ** 2)) if free.any() else 0.0
    if sst == 0.0:
        return math.nan
    resid = u[free] - law(c, ref, theta, alpha, Ts)[free]
    return 1.0 - float(np.sum(resid**2)) / sst


def identify_controller(
    ref: np.ndarray,
    theta: np.ndarray,
    alpha: np.ndarray,
    u: np.ndarray,
    Ts: float,
    kind: str = "state_feedback",
    cutoff: float | None = None,
    ref_delay: int | None = None,
    rounds: int = 5,
) -> Controller:
    """The controller that computed a record's command: least squares of ``u`` on the regressors of ``kind`` (state
    feedback: ref - theta, -alpha and the filtered rates; PID: e, its integral, -theta_dot), the velocity filter's
    cutoff and the reference's logging delay chosen by R^2 over :data:`CUTOFFS` and 0..MAX_REF_DELAY_S. It holds
    where the logged command's clamp is not exact (an amplifier's measured output, noise on the log): a sample
    enters the least squares only while the fit's own unclamped
    command there stays inside the largest logged |u| (and, for an exact clamp, u is not at it), refitted ``rounds``
    times; censoring on the regressors, not on u, leaves the gains unbiased. A PID's integral is the law's, held
    over the samples at the clamp (anti-windup). ``ref``, ``theta``, ``alpha`` [rad],
    ``u`` [V], ``Ts`` [s]; ``cutoff`` [Hz] and ``ref_delay`` [samples] given or chosen by R^2 as there.
    ``u_limit``: the exact clamp (:func:`output_limit`), else the median |u| where the fit's command passes the
    largest logged one (when at least 3 samples and 0.2 % of them do), else 0. ``r2`` over the samples fitted."""
    if kind not in IDENTIFIABLE:
        raise ValueError(
            f"controller kind {kind!r} cannot be identified from a record; valid: {', '.join(IDENTIFIABLE)}"
        )
    ref, theta, alpha, u = (np.asarray(v, dtype=float) for v in (ref, theta, alpha, u))
    if not ref.size == theta.size == alpha.size == u.size:
        raise ValueError("ref, theta, alpha and u must have the same length")
    lim = output_limit(u)
    top = lim if lim > 0 else float(np.max(np.abs(u)))
    if lim > 0:
        base = np.abs(u) < lim
    else:  # a clamp blurred by noise: start without the samples within 3 sigma of the peak (sigma: of u's noise)
        d2 = np.diff(u, 2)
        sigma = 1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / math.sqrt(6.0) if u.size > 2 else 0.0
        base = np.abs(u) < top - 3.0 * sigma if sigma > 0 else np.ones(u.size, dtype=bool)
    if base.sum() < 10 or float(np.ptp(u[base])) == 0.0:
        raise ValueError("the command does not move: no controller can be identified from it")
    nyquist = 0.5 / Ts
    tried = [cutoff] if cutoff is not None else [c for c in CUTOFFS if c < nyquist] or [0.5 * nyquist]
    delays = range(0, int(round(MAX_REF_DELAY_S / Ts)) + 1) if ref_delay is None else [ref_delay]
    best: tuple[float, float, int, np.ndarray, np.ndarray] | None = None
    for c in tried:
        X0 = _regressors(kind, ref, theta, alpha, Ts, c)
        for dly in delays:
            X = X0.copy()
            X[:, 0] = e = delayed(ref, dly) - theta
            keep, clamped = base, ~base
            for _ in range(max(1, rounds)):
                if kind == "pid":  # the law's integral: held while the output is limited (anti-windup)
                    X[:, 1] = np.concatenate([[0.0], np.cumsum(np.where(clamped, 0.0, e)[:-1]) * Ts])
                k, *_ = np.linalg.lstsq(X[keep], u[keep], rcond=None)
                p = X @ k
                was, clamped = clamped, (np.abs(u) >= lim if lim > 0 else np.abs(p) >= top)
                new = ~clamped & (np.abs(p) < top)
                if new.sum() < 10 or (np.array_equal(new, keep) and np.array_equal(was, clamped)):
                    break
                keep = new
            if kind == "pid":
                X[:, 1] = np.concatenate([[0.0], np.cumsum(np.where(clamped, 0.0, e)[:-1]) * Ts])
            k, *_ = np.linalg.lstsq(X[keep], u[keep], rcond=None)
            sst = float(np.sum((u[keep] - np.mean(u[keep])) ** 2))
            if sst == 0.0:
                continue
            r2 = 1.0 - float(np.sum((u[keep] - X[keep] @ k) ** 2)) / sst
            if best is None or r2 > best[0]:
                best = (r2, c, dly, k, X @ k)
    if best is None:
        raise ValueError("the command does not move: no controller can be identified from it")
    r2, c, dly, k, p = best
    if lim == 0.0:
        beyond = np.abs(p) >= top
        if beyond.sum() >= max(3, 0.002 * u.size):
            lim = float(np.median(np.abs(u[beyond])))
    gains = [float(v) for v in k]
    found = Controller(cutoff=c, u_limit=lim, ref_delay=dly, source="identified", r2=r2)
    if kind == "state_feedback":
        return replace(found, K=gains)
    return replace(found, kind="pid", kp=gains[0], ki=gains[1], kd=gains[2])
