"""The real rig's experiments, ready to be re-simulated: loaded, converted to degrees, masked, split in folds.

Every non-calibration experiment of the real run becomes a :class:`RigExperiment`: its command, its calibrated
angles (theta unwrapped), its raw volts, the sim spec's per-experiment overrides and the samples that can be
compared. Where the pot's wiper is off its track (its dead band around the wrap: the reading sticks at a track
end) or the ADC clips, a sample says nothing about the shaft: such samples carry no residual
(:data:`DEADBAND_GUARD` deg of margin). The experiments are split into two folds for 2-fold cross-fitting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_filter

from .. import spec as specmod
from ..behaviour import reference_steps
from ..ident.calibration import Calibration, alpha_deg, theta_deg
from ..rig.controller import R2_MIN
from ..rig.signals import MultisineLines, multisine_lines
from ..rundir import DataError, ExperimentEntry, Manifest, RunDir, read_dataset, sample_time
from .result import Folds

__all__ = [
    "CHANNELS",
    "DEADBAND_GUARD",
    "FIT_SECONDS",
    "MAX_BLOCKS",
    "MIN_FOLD_SAMPLES",
    "MIN_FOLD_SECONDS",
    "REPLAYS",
    "SHOOTING_SECONDS",
    "SCREEN_SECONDS",
    "RigExperiment",
    "block_count",
    "block_cuts",
    "block_length",
    "blocks",
    "command_period",
    "fold_experiments",
    "fold_steps",
    "halves",
    "load_experiments",
    "masked_share",
    "measured_state",
    "one_rate",
    "pot_track_ends",
    "shown_period",
    "signal_period",
    "split_folds",
    "split_point",
    "valid_samples",
]

CHANNELS = ("theta", "alpha")
REPLAYS = {
    "open": "the logged command replayed open loop",
    "closed": "the reference replayed through the controller FMU in closed loop",
    "shooting": "the logged command replayed open loop in windows restarted from the measured state",
}  # how an experiment is re-simulated
SHOOTING_SECONDS = 1.0  # s: window of the multiple-shooting replay
FIT_SECONDS = 20.0  # s: parameters are fitted on the first 20 s of each experiment (scored on all of it)
SCREEN_SECONDS = 12.0  # s: candidates are screened on the first 12 s of each experiment
DEADBAND_GUARD = 1.5  # deg: samples this close to a pot track end (its dead band) are not compared
START_SE = 5.0  # a record starts in motion when its first hub rate is this many of its standard errors (and more)
LINK_START_SHARE = 0.1  # ... or its link is deflected by this share of its largest deflection
SMOOTH_SECONDS = 0.02  # s: window of the smoothed rates of the measured state (a multiple-shooting start)
START_WINDOWS = 4  # a record's start rates: a cubic over SMOOTH_SECONDS x 1, 2, 4, 8, the widest that agrees ...
START_AGREE = 3.0  # ... with every narrower one's slope within this many of that one's standard errors
RING_SECONDS = 2.0  # s: a record's first stretch, where its link's ring at the start is read, is at most this long
RING_PERIODS = 1.5  # ... and holds at least this many periods of what it shows


@dataclass
class RigExperiment:
    """One experiment of the real rig ready to be re-simulated: command ``u`` [V] at ``Ts`` [s], real
    ``theta``/``alpha`` [deg] (calibrated, theta unwrapped), raw volts, ``sst`` per channel [deg^2] (sum of
    squares about the mean), the sim spec's per-experiment ``plant``/``daq`` overrides, ``kind`` (signal),
    ``period`` (samples of a periodic command, 0 if none), ``lines`` (the multisine line design of a periodic
    campaign experiment, for its BLA; None otherwise) and ``valid`` per channel (samples that measure the
    shaft). A closed-loop record has its reference ``ref`` [deg] and ``controller`` (a
    :class:`harness.rig.controller.Controller` as a dict); ``replay`` says how it is re-simulated (:data:`REPLAYS`)
    and ``replay_reason`` why; ``encoder``: theta was read by an encoder (no pot wrap or dead band);
    ``lattice_deg``: the angle step [deg] per channel a record was written on (from its import). The fit
    window (first FIT_SECONDS) and the screening window (first SCREEN_SECONDS) have their own sample counts and
    sums of squares. ``record``: the record it is (a part of); ``measured_start``: where a part cut from an open-loop
    record starts; ``quiet``: the channels that do not move beyond their noise (:meth:`moves`); ``faulty``: the samples
    an import masked in either channel (a sensor pinned at a rail or stuck: never a quiet point, its stillness is the
    sensor's), None where it masked none."""

    name: str
    kind: str
    Ts: float
    t: np.ndarray
    u: np.ndarray
    theta: np.ndarray
    alpha: np.ndarray
    theta_v: np.ndarray
    alpha_v: np.ndarray
    plant: dict[str, Any] = field(default_factory=dict)
    daq: dict[str, Any] = field(default_factory=dict)
    period: int = 0
    role: str = "identification"
    lines: MultisineLines | None = None
    sst: dict[str, float] = field(init=False)
    n_fit: int = 0
    sst_fit: dict[str, float] = field(default_factory=dict)
    n_screen: int = 0
    sst_screen: dict[str, float] = field(default_factory=dict)
    valid: dict[str, np.ndarray] = field(default_factory=dict)
    ref: np.ndarray | None = None
    controller: dict[str, Any] | None = None
    replay: str = "open"
    replay_reason: str = "an open-loop experiment: its command replayed as logged"
    encoder: bool = False
    lattice_deg: dict[str, float] | None = None
    record: str = ""
    measured_start: dict[str, float] | None = None
    quiet: frozenset[str] = frozenset()
    faulty: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.record = self.record or self.name
        self.n_fit = min(self.u.size, max(16, int(round(FIT_SECONDS / self.Ts))))
        for c in CHANNELS:
            self.valid.setdefault(c, np.ones(self.u.size, dtype=bool))
        self.n_screen = min(self.n_fit, max(16, int(round(SCREEN_SECONDS / self.Ts))))
        self.sst = self._sst(self.u.size)
        self.sst_fit, self.sst_screen = self._sst(self.n_fit), self._sst(self.n_screen)

    def _sst(self, n: int) -> dict[str, float]:
        ys = (self.theta[:n], self.alpha[:n])
        return {c: float(np.sum((y - y.mean()) ** 2)) for c, y in zip(CHANNELS, ys, strict=True)}

    @cached_property
    def start_state(self) -> dict[str, float]:
        """The state a replay starts from, as the sensors read it (plant parameters alpha_start [rad of the
        gauge's reading, its offset included], theta_dot_start, alpha_dot_start [rad/s]; the replay converts them
        with the fitted gains and the record's gauge offset, :func:`harness.diagnosis.simulation.true_state`).

        A part cut from a record starts where the record was (:attr:`measured_start`). Otherwise the link's state
        comes from its ring at the start (:attr:`link_ring`: amplitude and phase from the data), where the record's
        first stretch holds one; else from a cubic through its first SMOOTH_SECONDS where it is deflected there
        (from the median reading) by more than LINK_START_SHARE of its largest deflection and START_SE standard
        errors. The hub's rate is set where it is above the hub rate's RMS over the record and START_SE of its
        standard errors (a record cut from a longer run; one driven from rest by its reference's step has no rate
        at its first sample: the cubic's slope there is its noise). The link's state is read ``gauge_delay``
        samples on (the DAQ's, when the gauge reads late)."""
        if self.measured_start is not None:
            return dict(self.measured_start)
        head = max(6, int(round(SMOOTH_SECONDS / self.Ts)))
        lag = int(self.daq.get("gauge_delay", 0))
        if self.u.size < 4 * head + lag:
            return {}
        t = np.arange(head) * self.Ts
        x = measured_state(self)
        v0, se = (abs(v) for v in _cubic_start(t, x[:head, 0], 1))
        moving = v0 > START_SE * se and v0 > float(np.sqrt(np.mean(x[:, 2] ** 2)))
        state = {"theta_dot_start": _start_rate(x[:, 0], self.Ts)} if moving else {}
        ring = self.link_ring
        if ring is not None:
            return {**state, **ring.start()}
        rest = float(np.median(x[:, 1]))  # the gauge's zero as the record shows it: an offset is no deflection
        a0, se_a = (abs(v) for v in _cubic_start(t, x[lag : lag + head, 1] - rest, 0))
        deflected = a0 > START_SE * se_a and a0 > LINK_START_SHARE * float(np.max(np.abs(x[:, 1] - rest)))
        if not (moving or deflected):
            return {}
        rates = {"theta_dot_start": _start_rate(x[:, 0], self.Ts), "alpha_dot_start": _start_rate(x[lag:, 1], self.Ts)}
        return {"alpha_start": float(x[lag, 1]), **rates}

    @property
    def link_start(self) -> tuple[float, float]:
        """The link's deflection from rest [deg] and its rate [deg/s] at the first sample, as the gauge reads them
        (:attr:`start_state` less the record's rest reading :attr:`alpha_rest`; 0 where the record starts at rest):
        where a closed loop's replay starts the link, before a fit moves it."""
        s = self.start_state
        a = math.degrees(s["alpha_start"]) - self.alpha_rest if "alpha_start" in s else 0.0
        return a, math.degrees(s.get("alpha_dot_start", 0.0))

    @cached_property
    def link_ring(self) -> Ring | None:
        """The link's ring over the record's first stretch, where the rig starts undriven (a closed loop's hub within
        LINK_START_SHARE of its reference's range from its reference, an open loop's command at 0) until its
        reference, or command, first changes (at most RING_SECONDS), read ``gauge_delay`` samples on:
        :func:`fit_ring`; None where the rig starts driven or that stretch is too short to hold RING_PERIODS periods
        of what it shows."""
        lag = int(self.daq.get("gauge_delay", 0))
        drive = self.ref if self.ref is not None else self.u
        scale = max(float(np.max(np.abs(drive))), 1e-12)
        if self.ref is not None:
            driven = abs(float(self.ref[0] - self.theta[0])) > LINK_START_SHARE * max(float(np.ptp(self.ref)), 1e-12)
        else:
            driven = abs(float(self.u[0])) > 1e-9 * scale
        if driven:
            return None
        moved = np.flatnonzero(np.abs(drive - drive[0]) > 1e-9 * scale)
        end = min(int(moved[0]) if moved.size else drive.size, int(round(RING_SECONDS / self.Ts)), self.u.size - lag)
        return fit_ring(self.alpha[lag : lag + end], self.Ts) if end > 0 else None

    @cached_property
    def alpha_rest(self) -> float:
        """The gauge's reading of the link at rest [deg] as the record shows it (its offset: where a replay's gauge
        offset starts): the ring's centre where the record starts with one (:attr:`link_ring`), else the median of
        alpha over the record's quietest QUIET_SECONDS (:func:`_quietness`)."""
        ring = self.link_ring
        if ring is not None:
            return ring.offset_deg
        w = max(1, int(round(QUIET_SECONDS / self.Ts)))
        if self.u.size <= w:
            return float(np.median(self.alpha))
        i = int(np.argmin(_quietness(self)[w // 2 : self.u.size - w // 2])) if self.u.size > w else 0
        return float(np.median(self.alpha[i : i + w]))

    def moves(self, channel: str, which: str = "all") -> bool:
        """Does ``channel`` move over window ``which`` (:meth:`window`) beyond its noise (not one of :attr:`quiet`,
        which the diagnosis marks from the noise floor: a channel whose variance is within twice its noise's carries
        nothing a model can fit)?"""
        return self.window(which)[1][channel] > 0 and channel not in self.quiet

    def window(self, which: str) -> tuple[int, dict[str, float]]:
        """(samples, sst per channel) of a window: "all", "fit" (first FIT_SECONDS), "screen" (SCREEN_SECONDS)."""
        if which == "fit":
            return self.n_fit, self.sst_fit
        if which == "screen":
            return self.n_screen, self.sst_screen
        return self.u.size, self.sst

    @property
    def peak_command_v(self) -> float:
        """max |u| [V]."""
        return float(np.max(np.abs(self.u)))


@dataclass(frozen=True)
class Ring:
    """A link ringing freely over a record's first stretch, as the gauge reads it [deg]: alpha(t) = offset_deg +
    drift_deg_s t + exp(-decay t) (a_deg cos(omega t) + b_deg sin(omega t)), ``omega`` [rad/s], ``decay`` [1/s]
    (the drift: what the hub's slow motion deflects the link by)."""

    offset_deg: float
    drift_deg_s: float
    a_deg: float
    b_deg: float
    omega: float
    decay: float

    def start(self) -> dict[str, float]:
        """The link's state at t = 0 as the gauge reads it, as plant parameters: alpha_start [rad] (the offset
        included) and alpha_dot_start [rad/s]."""
        return {
            "alpha_start": math.radians(self.offset_deg + self.a_deg),
            "alpha_dot_start": math.radians(self.drift_deg_s + self.omega * self.b_deg - self.decay * self.a_deg),
        }


def _ring_basis(t: np.ndarray, omega: float, decay: float) -> np.ndarray:
    env = np.exp(-decay * t)
    return np.column_stack([np.ones_like(t), t, env * np.cos(omega * t), env * np.sin(omega * t)])


def fit_ring(y: np.ndarray, Ts: float) -> Ring | None:
    """A damped sinusoid about an offset and a drift fitted to ``y`` [deg] sampled at ``Ts`` [s] (:class:`Ring`):
    the frequency of the largest peak of its detrended spectrum (zero-padded) among those of which it holds at least
    RING_PERIODS periods, then frequency and decay by least squares with the offset, drift and amplitudes solved
    linearly at each step. None when ``y`` is too short for that (or holds fewer than 16 samples)."""
    n = y.size
    if n < 16 or np.ptp(y) <= 0:
        return None
    t = np.arange(n) * Ts
    flat = y - np.polyval(np.polyfit(t, y, 1), t)
    spec = np.abs(np.fft.rfft(flat * np.hanning(n), 8 * n))
    f = np.fft.rfftfreq(8 * n, Ts)
    ok = np.flatnonzero(f * n * Ts >= RING_PERIODS)
    if not ok.size:
        return None
    omega0 = 2.0 * math.pi * float(f[ok[int(np.argmax(spec[ok]))]])

    def resid(p: np.ndarray) -> np.ndarray:
        basis = _ring_basis(t, p[0], p[1])
        return basis @ np.linalg.lstsq(basis, y, rcond=None)[0] - y

    fit = least_squares(resid, [omega0, 0.0], bounds=([0.5 * omega0, -0.5 * omega0], [2.0 * omega0, omega0]))
    omega, decay = (float(v) for v in fit.x)
    c, d, a, b = (float(v) for v in np.linalg.lstsq(_ring_basis(t, omega, decay), y, rcond=None)[0])
    return Ring(c, d, a, b, omega, decay) if omega * n * Ts >= 2.0 * math.pi * RING_PERIODS else None


def command_period(u: np.ndarray, hint: int = 0) -> int:
    """Period [samples] of a command repeated at least 3 times (``hint`` tried first), 0 when none."""
    n = u.size
    tol = 1e-9 * max(float(np.max(np.abs(u))), 1e-12)
    cands = [hint] if hint > 0 else []
    cands += [p for p in range(16, n // 3 + 1) if n % p == 0]
    for p in cands:
        if 0 < p <= n // 3 and np.all(np.abs(u[p:] - u[:-p]) <= tol) and np.ptp(u[:p]) > 0:
            return p
    return 0


def pot_track_ends(readings: list[np.ndarray]) -> tuple[float, float] | None:
    """(lowest, highest) pot reading [deg] over the records when the shaft went round (the readings reach both
    ends of the track, beyond +-150 deg), else None: in the pot's dead band the wiper is off the track and the
    reading sticks at a track end, so samples there say nothing about the shaft angle."""
    lo = min(float(np.min(r)) for r in readings)
    hi = max(float(np.max(r)) for r in readings)
    return (lo, hi) if lo < -150.0 and hi > 150.0 else None


def valid_samples(
    reading: np.ndarray, ends: tuple[float, float] | None, volts: np.ndarray, adc_range: float
) -> np.ndarray:
    """Samples that measure the shaft: not within DEADBAND_GUARD [deg] of a track end of the pot (``reading``,
    the wrapped pot angle [deg]) and not clipped at the ADC's range [V] (``volts``)."""
    ok = np.abs(volts) < (1.0 - 1e-6) * adc_range
    if ends is not None:
        ok &= (reading > ends[0] + DEADBAND_GUARD) & (reading < ends[1] - DEADBAND_GUARD)
    return ok


def _loop(x: RigExperiment, e: ExperimentEntry, df: Any, replay: str) -> None:
    """How experiment ``x`` is replayed (``replay`` "auto" or one of :data:`REPLAYS`): a closed-loop record with
    its controller in closed loop, one without (or with a controller too poorly identified) by multiple shooting,
    an open-loop one as logged."""
    if "ref" in df.columns:
        x.ref = df["ref"].to_numpy(float)
    x.controller = e.controller if e.loop == "closed" else None
    closed_record = x.ref is not None or e.loop == "closed"
    trusted = x.controller is not None and (x.controller.get("r2") is None or x.controller["r2"] >= R2_MIN)
    if replay == "auto":
        if trusted and x.ref is not None:
            x.replay, x.replay_reason = "closed", f"a closed-loop record with its controller ({_source(e)})"
        elif closed_record:
            x.replay = "shooting"
            why = f"its identified controller explains too little (R^2 {x.controller['r2']:.3f} < {R2_MIN})" if (
                x.controller is not None) else "no controller known"  # fmt: skip
            x.replay_reason = f"a closed-loop record, {why}: an open-loop replay would drift"
        return
    if replay == "closed" and (x.controller is None or x.ref is None):
        raise DataError(f"experiment {x.name!r}: closed-loop replay needs a reference and a controller; it has none")
    x.replay, x.replay_reason = replay, "as asked (--replay)"


def _source(e: ExperimentEntry) -> str:
    c = e.controller or {}
    src = str(c.get("source", "spec"))
    return f"{src}, R^2 {c['r2']:.3f}" if c.get("r2") is not None else src


def load_experiments(
    real: Path, cal: Calibration, sim: specmod.Spec, adc_range: float, replay: str = "auto"
) -> dict[str, RigExperiment]:
    """Every non-calibration experiment of run ``real`` as a :class:`RigExperiment` (manifest order), converted
    with ``cal``, with the sim spec's per-experiment overrides and the samples that can be compared marked valid
    (pot dead band and clipping at the ADC's ``adc_range`` [V] masked; an encoder has neither dead band nor wrap;
    the samples an import masked, a channel pinned at a rail or stuck: the manifest's ``masked``).
    ``replay``: "auto" (closed-loop records in closed loop where their controller is known, else by multiple
    shooting; open-loop ones as logged) or one of :data:`REPLAYS` for every experiment."""
    manifest = Manifest.load(real)
    exps = [e for e in manifest.experiments if e.role != "calibration"]
    if not exps:
        raise DataError(f"{real}: no identification or analysis experiments to diagnose")
    raw_spec = manifest.spec if manifest.kind == "campaign" else None
    sim_exps = {e.name: e for e in sim.all_experiments()}
    run = RunDir(real)
    out: dict[str, RigExperiment] = {}
    for e in exps:
        df = read_dataset(run.dataset(e.name))
        Ts = sample_time(df)
        u = df["u"].to_numpy(float)
        th_v, al_v = df["theta_v"].to_numpy(float), df["alpha_v"].to_numpy(float)
        th, al = theta_deg(th_v, cal), alpha_deg(al_v, cal)
        table: dict[str, Any] = next(
            (d for d in raw_spec.get("experiment", []) if d.get("name") == e.name), {}) if raw_spec else {}  # fmt: skip
        multisine = table.get("signal") == "multisine"
        hint = int(round(float(table["period"]) / Ts)) if multisine and "period" in table else 0
        se = sim_exps.get(e.name)
        x = RigExperiment(
            name=e.name,
            kind=e.signal or "imported",
            Ts=Ts,
            t=df["t"].to_numpy(float),
            u=u,
            theta=th,
            alpha=al,
            theta_v=th_v,
            alpha_v=al_v,
            plant=dict(se.plant) if se else {},
            daq=dict(se.daq) if se else {},
            period=command_period(u, hint),
            role=e.role,
            encoder=e.theta_sensor == "encoder",
            lattice_deg=e.lattice_deg,
        )
        _loop(x, e, df, replay)
        if x.encoder and e.counts_per_rev:
            x.daq = {"theta_sensor": 1, "encoder_counts": float(e.counts_per_rev), **x.daq}
        if multisine and x.period:
            x.lines = multisine_lines(
                x.period,
                Ts,
                float(table["f_min"]),
                float(table["f_max"]),
                odd=bool(table.get("odd", True)),
                seed=int(e.seed or 0),
                skip_one_per_group=bool(table.get("skip_one_per_group", True)),
            )
        out[e.name] = x
    readings = {n: theta_deg(x.theta_v, cal, unwrap=False) for n, x in out.items()}
    ends = pot_track_ends([r for n, r in readings.items() if not out[n].encoder] or [np.zeros(1)])
    masked = {e.name: e.masked or {} for e in exps}
    for n, x in out.items():
        x.valid = {
            "theta": valid_samples(readings[n], None if x.encoder else ends, x.theta_v, adc_range),
            "alpha": valid_samples(np.zeros(1), None, x.alpha_v, adc_range),
        }
        for c, spans in masked[n].items():
            for a, b in spans:
                x.valid[c][a:b] = False
        if masked[n]:
            x.faulty = np.isin(np.arange(x.u.size), _spans(masked[n]))
    return out


def _spans(masked: dict[str, list[list[int]]]) -> np.ndarray:
    """The samples of [first, end) ranges per channel."""
    return np.concatenate([np.arange(a, b) for spans in masked.values() for a, b in spans])


def one_rate(experiments: dict[str, RigExperiment]) -> float:
    """The one sample interval [s] of the experiments; records at different rates raise a one-line DataError that
    names them with their rates (the diagnosis fits one rig to every record at one rate: one DAQ, a delay in samples,
    a noise floor per sample)."""
    rates: dict[float, list[str]] = {}
    for n, x in experiments.items():
        rate = next((r for r in rates if abs(r * x.Ts - 1.0) <= 1e-6), 1.0 / x.Ts)
        rates.setdefault(rate, []).append(n)
    if len(rates) > 1:
        said = "; ".join(f"{', '.join(repr(n) for n in names)} at {r:.6g} Hz" for r, names in sorted(rates.items()))
        raise DataError(
            f"records at different sample rates ({said}): the diagnosis replays every record on one rig at one rate; "
            "import and diagnose each rate's records as a run of its own"
        )
    return 1.0 / next(iter(rates))


def masked_share(experiments: dict[str, RigExperiment]) -> dict[str, float]:
    """Share of the real samples per channel not compared (pot dead band, ADC clipping, a fault found at import)."""
    n = sum(x.u.size for x in experiments.values())
    return {c: float(sum(int(np.sum(~x.valid[c])) for x in experiments.values())) / n for c in CHANNELS}


def mark_quiet(experiments: dict[str, RigExperiment], sigma: dict[str, float]) -> None:
    """Each experiment's channels that do not move beyond their noise ``sigma`` [deg RMS per channel], in place
    (:attr:`RigExperiment.quiet`): a channel whose variance is within twice its noise's carries nothing a model can
    fit."""
    for x in experiments.values():
        x.quiet = frozenset(c for c in sigma if x.sst[c] <= 2.0 * x.u.size * sigma[c] ** 2)


def moving_records(
    records: dict[str, RigExperiment], sigma: dict[str, float]
) -> tuple[dict[str, RigExperiment], list[str]]:
    """The records in which something moves beyond the noise ``sigma`` (:func:`mark_quiet`), and the names of those
    set aside, in which nothing does (a hub held by its friction under a weak drive: nothing for a model to fit, and
    a fold of such records alone nothing to fit on). None moving: a one-line DataError."""
    mark_quiet(records, sigma)
    still = [n for n, x in records.items() if not any(x.moves(c) for c in CHANNELS)]
    if len(still) == len(records):
        raise DataError(f"nothing moves beyond its noise in any record ({', '.join(still)}): nothing to diagnose")
    return {n: x for n, x in records.items() if n not in still}, still


def split_folds(experiments: dict[str, RigExperiment]) -> tuple[list[str], list[str]]:
    """Two folds A, B of experiment names for 2-fold cross-fitting (fit on A, score on B, and back): within each
    signal kind (sorted by peak |u|, then name) the experiments alternate between the folds, the first of
    every other kind going to B, so both folds span the kinds and the command levels. One experiment: it is
    both folds (nothing can be held out; the diagnosis cuts a lone record in time into two halves before, one per
    fold: :func:`fold_experiments`)."""
    names = list(experiments)
    if len(names) == 1:
        return names, names
    kinds: dict[str, list[str]] = {}
    for n in names:
        kinds.setdefault(experiments[n].kind, []).append(n)
    a: list[str] = []
    b: list[str] = []
    for g, kind in enumerate(sorted(kinds)):
        grp = sorted(kinds[kind], key=lambda n: (round(experiments[n].peak_command_v, 6), n))
        for i, n in enumerate(grp):
            (a if (i + g) % 2 == 0 else b).append(n)
    if not b:  # every kind a singleton of the same parity
        b.append(a.pop())
    order = {n: i for i, n in enumerate(names)}
    return sorted(a, key=lambda n: order[n]), sorted(b, key=lambda n: order[n])


def _cubic_start(t: np.ndarray, y: np.ndarray, order: int) -> tuple[float, float]:
    """The value (order 0) or slope (1) at t[0] = 0 of a cubic through ``y``, and its standard error."""
    coef, cov = np.polyfit(t, y, 3, cov="unscaled")
    resid = y - np.polyval(coef, t)
    k = 3 - order
    se = math.sqrt(max(float(cov[k, k]) * float(np.sum(resid**2)) / (t.size - 4), 0.0))
    return float(coef[k]), se


def _start_rate(y: np.ndarray, Ts: float) -> float:
    """The rate [rad/s] of the angle ``y`` [rad] at its first sample: the slope of a cubic through its first
    SMOOTH_SECONDS x 2^j samples, the widest window (j < START_WINDOWS) whose slope lies within START_AGREE standard
    errors of every narrower window's (the intersection-of-confidence-intervals rule: a wider window averages the
    noise out, until the cubic misses an acceleration and its slope leaves the narrower ones')."""
    head = max(6, int(round(SMOOTH_SECONDS / Ts)))
    kept: list[tuple[float, float]] = []
    for j in range(START_WINDOWS):
        n = head << j
        if n > y.size:
            break
        rate, se = _cubic_start(np.arange(n) * Ts, y[:n], 1)
        if any(abs(rate - r) > START_AGREE * s for r, s in kept):
            break
        kept.append((rate, se))
    return kept[-1][0] if kept else 0.0


def measured_state(exp: RigExperiment) -> np.ndarray:
    """The measured state per sample, (n, 4): theta, alpha [rad] and their rates [rad/s] (Savitzky-Golay, cubic,
    over SMOOTH_SECONDS: differences of quantized angles are steps)."""
    w = max(5, int(round(SMOOTH_SECONDS / exp.Ts)) | 1)
    th, al = np.radians(exp.theta), np.radians(exp.alpha)
    if th.size <= w:
        return np.column_stack([th, al, np.gradient(th, exp.Ts), np.gradient(al, exp.Ts)])
    rates = [savgol_filter(x, w, 3, deriv=1, delta=exp.Ts) for x in (th, al)]
    return np.column_stack([th, al, *rates])


MIN_FOLD_SECONDS = 1.0  # s: each half or block of a lone record, a multiple-shooting window (import: 2x it at least)
MIN_FOLD_SAMPLES = 50  # samples in each half or block of a lone record, whatever the rate
SPLIT_ZONE = (0.4, 0.6)  # a lone record is split in this share of its length, at its quietest point
QUIET_SECONDS = 0.1  # s: the motion measure that picks the split point is averaged over this window
MAX_BLOCKS = 6  # a lone record is cut into at most this many blocks, 3 per fold
BLOCK_ZONE = 0.2  # a cut between a lone record's blocks is sought within this share of a block of its even place
START_STATE = ("theta_start", "alpha_start", "theta_dot_start", "alpha_dot_start")  # the plant's, [rad], [rad/s]
PERIOD_MISMATCH = 0.2  # a signal repeats with period p when its mean squared change over p is <= this x its variance


def _min_fold(x: RigExperiment) -> int:
    """The fewest samples a fold's part of a lone record holds: MIN_FOLD_SECONDS and MIN_FOLD_SAMPLES."""
    return max(MIN_FOLD_SAMPLES, math.ceil(MIN_FOLD_SECONDS / x.Ts - 1e-6))


def _quietness(x: RigExperiment) -> np.ndarray:
    """Per sample how far the rig is from rest: the rates of theta and alpha and the deflection alpha, each in
    units of its RMS, squared, summed and averaged over QUIET_SECONDS (small: a replay started there from the
    measured angle starts near rest)."""
    state = measured_state(x)
    alpha = state[:, 1] - np.median(state[:, 1])
    score = np.zeros(x.u.size)
    for z in (state[:, 2], alpha, state[:, 3]):
        rms = float(np.sqrt(np.mean(z**2)))
        if rms > 0:
            score += (z / rms) ** 2
    if x.faulty is not None and x.faulty.any():  # a sensor held still by its fault is not the rig at rest
        score[x.faulty] = 1e6 * (1.0 + float(np.max(score)))
    w = max(1, int(round(QUIET_SECONDS / x.Ts)))
    return np.convolve(score, np.ones(w) / w, mode="same")


def split_point(x: RigExperiment) -> int:
    """Where a lone record is cut in two (the first sample of its second half): a whole number of periods of a
    periodic command near the middle, else the quietest sample of the middle (SPLIT_ZONE) where the rates of
    theta and alpha and the deflection alpha are smallest (each in units of its RMS, averaged over QUIET_SECONDS),
    so the second half's replay, started from the measured angle, starts near rest; each half keeps at least
    MIN_FOLD_SECONDS and MIN_FOLD_SAMPLES. A record too short for that raises a one-line DataError."""
    n = x.u.size
    n_min = _min_fold(x)
    if n < 2 * n_min:
        raise DataError(
            f"experiment {x.name!r}: one record of {n} samples ({n * x.Ts:.4g} s) is too short for two folds; the "
            f"diagnosis splits a lone record in time and needs >= {MIN_FOLD_SECONDS:g} s and {MIN_FOLD_SAMPLES} "
            f"samples in each half ({2 * n_min} samples)"
        )
    lo, hi = max(math.ceil(SPLIT_ZONE[0] * n), n_min), min(math.floor(SPLIT_ZONE[1] * n), n - n_min)
    if lo > hi:
        return n // 2 if n_min <= n // 2 <= n - n_min else n_min
    if x.period:
        whole = [m for m in range(x.period, n, x.period) if lo <= m <= hi]
        if whole:
            return min(whole, key=lambda m: (abs(2 * m - n), m))
    return lo + int(np.argmin(_quietness(x)[lo : hi + 1]))


def signal_period(y: np.ndarray) -> int:
    """Period [samples] of a signal that repeats at least twice, up to noise, jitter or a different first stretch
    (a reference's lead-in): past the first lag where the signal no longer resembles itself (mean squared change
    y[k + p] - y[k] >= its variance), the first run of lags p whose mean squared change is within PERIOD_MISMATCH x
    its variance, and of those the one with the least; 0 when none."""
    n = y.size
    if n < 32 or np.ptp(y) <= 0:
        return 0
    z = y - y.mean()
    f = np.fft.rfft(z, 2 * n)
    r = np.fft.irfft(f * np.conj(f))[:n]  # sum_k z[k] z[k + p]
    c = np.r_[0.0, np.cumsum(z**2)]
    p = np.arange(n // 2 + 1)
    d = (c[n - p] + c[n] - c[p] - 2.0 * r[p]) / (n - p)  # mean (z[k + p] - z[k])^2 over the overlap
    apart = np.nonzero(d >= c[n] / n)[0]
    if not apart.size:
        return 0
    ok = np.nonzero((p > max(apart[0], 15)) & (d <= PERIOD_MISMATCH * c[n] / n))[0]
    if not ok.size:
        return 0
    run = ok[: int(np.argmax(np.diff(np.r_[ok, n]) > 1)) + 1]  # the first run of consecutive lags
    return int(run[np.argmin(d[run])])


def shown_period(x: RigExperiment) -> int:
    """The period [samples] a lone record shows: its periodic command's, else its reference's (closed loop) or its
    command's up to noise and jitter (:func:`signal_period`); 0 when it shows none."""
    if x.period:
        return x.period
    return signal_period(x.ref if x.ref is not None else x.u)


def block_cuts(x: RigExperiment, blocks: int) -> list[int]:
    """Where a lone record is cut into ``blocks`` blocks of about equal length: the first sample of each block
    after the first. A periodic command is cut at whole periods (its periods shared out evenly); otherwise each cut
    is the quietest sample (:func:`_quietness`) within BLOCK_ZONE of a block of its even place, every block keeping
    at least :func:`block_length` samples."""
    n = x.u.size
    if x.period:
        whole = n // x.period
        return [x.period * round(k * whole / blocks) for k in range(1, blocks)]
    short = block_length(x)
    zone = BLOCK_ZONE * n / blocks
    quiet = _quietness(x)
    cuts: list[int] = []
    for k in range(1, blocks):
        even = k * n / blocks
        lo = max(math.ceil(even - zone), (cuts[-1] if cuts else 0) + short)
        hi = min(math.floor(even + zone), n - (blocks - k) * short)
        cuts.append(lo + int(np.argmin(quiet[lo : hi + 1])))
    return cuts


def block_length(x: RigExperiment) -> int:
    """The fewest samples a block of a lone record holds: MIN_FOLD_SECONDS, MIN_FOLD_SAMPLES and a whole period
    of what it shows (:func:`shown_period`)."""
    return max(_min_fold(x), shown_period(x))


def repeats(x: RigExperiment) -> bool:
    """Does a closed-loop record repeat what it does: its reference shows a period (:func:`shown_period`) and the
    record is two blocks long or more (:func:`block_length`: a period of its reference or more each)?"""
    return x.replay == "closed" and shown_period(x) > 0 and x.u.size >= 2 * block_length(x)


def block_count(x: RigExperiment) -> int:
    """How many blocks a lone record is cut into for its folds: the most, an even number up to MAX_BLOCKS, that
    each hold :func:`block_length` samples (whole periods of a periodic command), where the record shows a period
    and its replay is pulled back to the record (closed loop, multiple shooting); else 2, two halves. A block
    without a period may hold no excitation (the CU record's 2.3 s between two reference steps: the replay's
    offset against a shaft at rest); an open-loop block starts without the states the record does not measure
    (a second mode, the friction's stick, the play), so each cut adds a start transient."""
    n = x.u.size
    if x.replay == "open" or not shown_period(x):
        return 2
    if x.period:
        most = (n // x.period) // max(1, math.ceil(_min_fold(x) / x.period))
    else:
        most = n // block_length(x)
    most = min(most, MAX_BLOCKS)
    return max(2, most - most % 2)


def _part(x: RigExperiment, a: int, b: int, bla: bool, state: np.ndarray) -> RigExperiment:
    """Samples a..b of a lone record as a pseudo-experiment named "<name> (0-4.87 s)": every array sliced alike
    (command, angles, volts, valid samples, reference), the replay, controller and sensor kept. Its replay starts
    at the measured angle (the simulation's own default); an open-loop part after the first starts from the
    measured state (``state``: :func:`measured_state` of the record: theta, alpha and their rates as the plant's
    start values, as read: :attr:`RigExperiment.measured_start`), since the rig may be moving there and nothing
    pulls an open-loop replay back; a closed-loop one
    at rest (its feedback does, and the measured rates at a quiet point are the noise's), a multiple-shooting one
    from the measured state at each window (its own restarts). A periodic command's period is kept when the part
    starts on a whole period and holds >= 2, its multisine lines when ``bla`` too (its BLA)."""
    s = slice(a, b)
    start = dict(zip(START_STATE, (float(v) for v in state[a]), strict=True)) if a > 0 and x.replay == "open" else {}
    name = f"{x.name} ({a * x.Ts:.4g}-{b * x.Ts:.4g} s)"
    periodic = x.period > 0 and a % x.period == 0 and (b - a) // x.period >= 2
    return replace(
        x,
        name=name,
        t=x.t[s],
        u=x.u[s],
        theta=x.theta[s],
        alpha=x.alpha[s],
        theta_v=x.theta_v[s],
        alpha_v=x.alpha_v[s],
        plant=dict(x.plant),
        daq=dict(x.daq),
        measured_start=start or None,
        period=x.period if periodic else 0,
        lines=x.lines if periodic and bla else None,
        valid={c: v[s] for c, v in x.valid.items()},
        ref=None if x.ref is None else x.ref[s],
        faulty=None if x.faulty is None else x.faulty[s],
    )


def _parts(x: RigExperiment, cuts: list[int]) -> dict[str, RigExperiment]:
    """A lone record cut at ``cuts`` into parts (:func:`_part`); a periodic command keeps its multisine lines
    when every part holds >= 3 whole periods."""
    edges = [0, *cuts, x.u.size]
    bla = bool(x.lines is not None and x.period > 0 and min(np.diff(edges)) // x.period >= 3)
    state = measured_state(x)
    return {p.name: p for p in (_part(x, a, b, bla, state) for a, b in zip(edges[:-1], edges[1:], strict=True))}


def halves(x: RigExperiment) -> tuple[dict[str, RigExperiment], int]:
    """A lone record as two pseudo-experiments, its halves in time cut at :func:`split_point`, named
    "<name> (0-4.87 s)" and "<name> (4.87-10 s)" (:func:`_part`); a periodic command keeps its multisine lines when
    each half holds >= 3 whole periods (its BLA), else only its period. Returns (halves, split sample)."""
    m = split_point(x)
    return _parts(x, [m]), m


def blocks(x: RigExperiment) -> tuple[dict[str, RigExperiment], list[int]]:
    """A lone record as :func:`block_count` pseudo-experiments, blocks in time cut at :func:`block_cuts`
    (:func:`_part`; two: :func:`halves`). Returns (blocks in time order, cut samples)."""
    count = block_count(x)
    if count == 2:
        parts, m = halves(x)
        return parts, [m]
    cuts = block_cuts(x, count)
    return _parts(x, cuts), cuts


def fold_experiments(experiments: dict[str, RigExperiment]) -> tuple[dict[str, RigExperiment], Folds]:
    """The experiments the diagnosis scores and its 2-fold cross-fit (:func:`split_folds`).

    A record that holds what it does twice over, a closed loop repeating its reference (:func:`repeats`), is cut in
    time at quiet points into blocks of about a period or more (:func:`blocks`) that alternate between the folds,
    each such record's first block going to the other fold than the previous one's: both folds then hold every
    record's conditions (its controller, its reference), and an effect that only one record exercises is fitted and
    held out on that record. The other experiments alternate whole (:func:`split_folds`). A lone record is cut in
    time into blocks alternating between the folds (A the 1st, 3rd, ...; B the 2nd, 4th, ...), so that its held-out
    figures are held out and do not hinge on one cut; where it shows no period, is replayed open loop or is too
    short for four blocks, into two halves, one per fold."""
    scheme = "2-fold cross-fit: fit on A score on B, and back"
    cut = [n for n, x in experiments.items() if repeats(x)]
    if len(experiments) != 1 and cut:
        whole = {n: x for n, x in experiments.items() if n not in cut}
        a, b = split_folds(whole) if len(whole) > 1 else (list(whole), [])
        out: dict[str, RigExperiment] = {}
        for n, x in experiments.items():
            if n not in cut:
                out[n] = x
                continue
            parts, _ = blocks(x)
            names = list(parts)
            first, second = (a, b) if cut.index(n) % 2 == 0 else (b, a)
            first += names[0::2]
            second += names[1::2]
            out.update(parts)
        order = {n: i for i, n in enumerate(out)}
        scheme += (f"; the closed-loop records that repeat their reference ({', '.join(map(repr, cut))}) each cut in "
                   "time into blocks of a period or more, alternating between the folds")  # fmt: skip
        return out, Folds(A=sorted(a, key=order.__getitem__), B=sorted(b, key=order.__getitem__), scheme=scheme)
    if len(experiments) != 1:
        a, b = split_folds(experiments)
        return experiments, Folds(A=a, B=b, scheme=scheme)
    (x,) = experiments.values()
    parts, cuts = blocks(x)
    names = list(parts)
    if len(names) == 2:
        scheme += f"; the lone record {x.name!r} split in time at {cuts[0] * x.Ts:.4g} s into two halves, one per fold"
        return parts, Folds(A=[names[0]], B=[names[1]], scheme=scheme)
    lengths = np.diff([0, *cuts, x.u.size]) * x.Ts
    at = "whole periods of its command" if x.period else "quiet points"
    scheme += (
        f"; the lone record {x.name!r} cut in time at {at} into {len(names)} blocks of "
        f"{lengths.min():.3g}-{lengths.max():.3g} s, alternating between the folds (A the 1st, 3rd, ...; B the "
        "2nd, 4th, ...)"
    )
    return parts, Folds(A=names[0::2], B=names[1::2], scheme=scheme)


def fold_steps(experiments: dict[str, RigExperiment], folds: Folds) -> tuple[int, int]:
    """How many steps of their references the closed-loop experiments of folds A and B hold
    (:func:`harness.behaviour.reference_steps`: a change of the reference within a part, not the level it starts at).
    A fold without one beside a fold with some: the fit on the first is scored on step responses it never saw."""

    def count(names: list[str]) -> int:
        parts = [experiments[n] for n in names]
        return sum(len(reference_steps(x.t, x.ref)) for x in parts if x.replay == "closed" and x.ref is not None)

    return count(folds.A), count(folds.B)
