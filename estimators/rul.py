"""Remaining-useful-life prognosis of the friction drive (seed section 6).

From the filter's estimate ``x = [w1, w2, alpha, m]`` and covariance ``P`` at stream time t, the
plant model (seed eqs. 9-10, m constant) is propagated under an assumed future load until the
normalized deterioration ``Dn = 1 - alpha / alpha0`` reaches ``failure_dn``; RUL = t_f - t.

* Monte Carlo: ``n`` initial states ``x + L z``, ``z ~ N(0, I)``, ``L L^T = P`` (seed eq. 29;
  ``L`` from the eigen-decomposition of P so that a singular P is fine), each propagated by
  :func:`estimators.kernels.dekf_kernels.time_to_failure` (compiled, one loop over all
  trajectories). A trajectory with ``m <= 0`` never wears and one that does not reach the
  threshold within ``horizon_s`` is "not reached": the mean and standard deviation are then
  undefined (None), and a quantile q is defined only if at least a fraction q reached it.
* Deterministic bounds (section 6): optimistic from ``(alpha + c s_alpha, m - c s_m)``,
  pessimistic from ``(alpha - c s_alpha, m + c s_m)``, speeds at their estimates.
* Future load: a periodic piecewise-constant current (a square wave, a constant, a recorded
  profile, or the recently observed current binned by the filter), phased by stream time.
"""

from __future__ import annotations

import itertools
import math
import struct
from dataclasses import dataclass, replace
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AllowInfNan,
    Field,
    Strict,
    StrictInt,
    TypeAdapter,
    ValidationError,
    model_validator,
)

from estimators.base import ConfigError, EstimatorConfigModel, FloatArray
from estimators.checks import finite_or_none as _finite_or_none
from estimators.kernels import dekf_kernels as kern

#: Segment length used for a constant current (any length is exact; this one keeps the
#: per-segment wear small enough for the midpoint rule without extra subdivision).
CONSTANT_SEGMENT_S = 1.0


# ----------------------------------------------------------------------------- load laws
FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]


class SquareWaveLoad(EstimatorConfigModel):
    """Pulse current between ``low_a`` and ``high_a``; rising edges at ``t0_s + k period_s``
    (stream time), ``high_a`` during ``duty * period_s``."""

    kind: Literal["square_wave"] = Field(default="square_wave", description="load law")
    high_a: FiniteFloat = Field(default=20.0, description="current during the pulse, A")
    low_a: FiniteFloat = Field(default=0.0, description="current between pulses, A")
    period_s: FiniteFloat = Field(default=2.0, gt=0.0, description="period of the wave, s")
    duty: FiniteFloat = Field(default=0.5, gt=0.0, lt=1.0, description="fraction of the period at high_a")
    t0_s: FiniteFloat = Field(default=0.0, description="stream time of a rising edge, s")


class ConstantLoad(EstimatorConfigModel):
    """Constant current (the seed's own prognosis assumption, 20 A)."""

    kind: Literal["constant"] = Field(default="constant", description="load law")
    current_a: FiniteFloat = Field(default=20.0, description="the constant current, A")


class ProfileLoad(EstimatorConfigModel):
    """A recorded current profile repeated periodically: ``current_a[i]`` is held for
    ``durations_s[i]``; the profile starts at ``t0_s + k * sum(durations_s)`` (stream time)."""

    kind: Literal["profile"] = Field(default="profile", description="load law")
    durations_s: tuple[Annotated[FiniteFloat, Field(gt=0.0)], ...] = Field(
        min_length=1, max_length=100_000, description="duration of each segment, s"
    )
    current_a: tuple[FiniteFloat, ...] = Field(
        min_length=1, max_length=100_000, description="current held over each segment, A"
    )
    t0_s: FiniteFloat = Field(default=0.0, description="stream time at which a repetition starts, s")
    merge_tolerance_a: FiniteFloat = Field(
        default=0.0,
        ge=0.0,
        description="consecutive segments whose currents are within this of their run's first "
        "segment are propagated as one (duration-weighted mean current), A; 0: only equal "
        "currents (exact). The propagation's cost grows with the segments per period",
    )

    @model_validator(mode="after")
    def _same_length(self) -> ProfileLoad:
        if len(self.durations_s) != len(self.current_a):
            raise ValueError(
                "durations_s and current_a must be of equal length "
                f"(got {len(self.durations_s)} and {len(self.current_a)})"
            )
        return self


class ObservedLoad(EstimatorConfigModel):
    """The recently applied current: the filter bins the held current over ``bin_samples``
    stream samples into a ring of ``bins`` bins. ``model`` says how the ring becomes the future
    load:

    * ``"repeat"``: the ring (oldest bin first) is one period of the future load, starting now.
      Consecutive bins whose currents differ by at most ``merge_tolerance_a`` from the first of
      their run are merged.
    * ``"dwells"``: a load switching between two levels with random dwells (:func:`dwell_load`):
      the levels and the empirical distribution of the completed dwells at each level are read
      from the ring; the future period holds ``dwell_pairs`` dwells per level at the quantiles
      of that distribution, and the prognosis' interval carries the randomness of the future
      dwells and the sampling error of the observed ones. With ``dwell_record`` the mean dwells
      and their variances come from the stream's record of every dwell seen since its start
      (:class:`DwellRecord`, forgetting over ``dwell_memory_s``), and so does the shape of the
      distribution where the record holds more whole dwells than the ring."""

    kind: Literal["observed"] = Field(default="observed", description="load law")
    bin_samples: StrictInt = Field(default=20, ge=1, le=10_000_000, description="stream samples per bin")
    bins: StrictInt = Field(default=200, ge=1, le=10_000, description="bins in the ring (one period)")
    merge_tolerance_a: FiniteFloat = Field(
        default=0.05, ge=0.0, description="largest current difference merged into one segment, A"
    )
    model: Literal["repeat", "dwells"] = Field(
        default="repeat",
        description="'repeat': the ring is one period of the future load; 'dwells': two levels "
        "with the observed dwell distribution (random switching loads)",
    )
    dwell_pairs: StrictInt = Field(
        default=16, ge=2, le=256, description="dwells per level in the future period ('dwells')"
    )
    dwell_record: bool = Field(
        default=True,
        description="'dwells': the mean dwells and their variances from the stream's record of "
        "all dwells seen (with forgetting over dwell_memory_s and a stationarity check against "
        "the ring), not the ring's alone",
    )
    dwell_memory_s: FiniteFloat = Field(
        default=3600.0, gt=0.0, description="time constant of the dwell record's forgetting, s"
    )


LoadAssumption = Annotated[
    SquareWaveLoad | ConstantLoad | ProfileLoad | ObservedLoad, Field(discriminator="kind")
]
_LOAD_ADAPTER: TypeAdapter[SquareWaveLoad | ConstantLoad | ProfileLoad | ObservedLoad] = (
    TypeAdapter(LoadAssumption)
)


def parse_load(raw: Any, name: str = "rul_load") -> SquareWaveLoad | ConstantLoad | ProfileLoad | ObservedLoad:
    """Validate a JSON-like load assumption ``{"kind": ..., ...}``.

    Raises:
        ConfigError: unknown kind or field, non-finite numbers, non-positive period or
            durations, duty outside (0, 1), profile arrays of different lengths or empty
            (the message names the field, prefixed by ``name``).
    """
    try:
        return _LOAD_ADAPTER.validate_python(raw)
    except ValidationError as exc:
        parts = []
        for err in exc.errors(include_url=False):
            loc = [str(p) for p in err["loc"]]
            # drop the union tag pydantic puts first (the kind) from the location
            if loc and loc[0] in ("square_wave", "constant", "profile", "observed"):
                loc = loc[1:]
            parts.append(".".join([name, *loc]) + f": {err['msg']}")
        raise ConfigError("; ".join(parts)) from None


def load_to_dict(load: SquareWaveLoad | ConstantLoad | ProfileLoad | ObservedLoad) -> dict[str, Any]:
    """The load assumption as a JSON-serializable mapping (the form :func:`parse_load` takes)."""
    return load.model_dump(mode="json")


def merge_bins(
    durations: FloatArray, currents: FloatArray, tolerance_a: float
) -> tuple[FloatArray, FloatArray]:
    """Merge runs of consecutive bins whose currents are within ``tolerance_a`` of the run's
    first bin into one segment carrying their duration-weighted mean current."""
    out_d: list[float] = []
    out_c: list[float] = []
    start = 0
    n = durations.shape[0]
    for i in range(1, n + 1):
        if i == n or abs(currents[i] - currents[start]) > tolerance_a:
            d = durations[start:i]
            out_d.append(float(d.sum()))
            out_c.append(float(np.dot(d, currents[start:i]) / d.sum()))
            start = i
    return np.array(out_d), np.array(out_c)


def _rotate(
    durations: FloatArray, currents: FloatArray, phase_s: float
) -> tuple[FloatArray, FloatArray]:
    """The period starting ``phase_s`` into the profile: the rest of the segment holding the
    phase, the following segments, then the part of that segment before the phase."""
    ends = np.cumsum(durations)
    j = min(int(np.searchsorted(ends, phase_s, side="right")), durations.shape[0] - 1)
    into = phase_s - (ends[j] - durations[j])
    d = [ends[j] - phase_s, *durations[j + 1 :], *durations[:j], into]
    c = [currents[j], *currents[j + 1 :], *currents[:j], currents[j]]
    keep = [i for i, v in enumerate(d) if v > 0.0]
    return np.array([d[i] for i in keep]), np.array([c[i] for i in keep])


#: bins within this share of the level difference of a level count as at that level
DWELL_EDGE_SHARE = 0.05
#: fewest completed dwells at each level for the dwell model
MIN_DWELLS = 3
#: z of the stationarity check of the dwell record against the ring (repeated at every
#: prognosis on overlapping rings: 4 keeps false restarts rare)
DWELL_STATIONARITY_Z = 4.0
#: histogram of the whole dwells' lengths in the record: ``DWELL_HIST_BINS`` bins growing by
#: ``DWELL_HIST_FACTOR`` from ``DWELL_HIST_MIN_S`` (1 ms to about 17 min; longer dwells count
#: in the last bin, shorter in the first)
DWELL_HIST_BINS = kern.DW_HIST_BINS
DWELL_HIST_MIN_S = 1e-3
DWELL_HIST_FACTOR = math.sqrt(2.0)


@dataclass(frozen=True)
class DwellLoad:
    """A two-level switching load read from the observed current (:func:`dwell_load`).

    Attributes:
        durations_s, currents_a: one period of the future load from now (the level in force
            first), ``pairs`` dwells per level at the quantiles of the observed dwells.
        low_a, high_a: the levels.
        dwells: completed dwells observed at the low and the high level (in the ring, or the
            switches out of each level in the record when ``source`` is "record").
        cycle_mean_s, cycle_var_s2: mean and variance of a cycle (a low plus a high dwell).
        estimate_rel_var: relative variance of the mean cycle estimated from the observed
            dwells, ``cycle_var / (n cycle_mean^2)``, n the fewer of the two counts.
        renewal_var_s: the relative variance of the number of cycles in a future span T is
            ``renewal_var_s / T`` (renewal theory: ``T var / mean^3`` cycles^2 over
            ``(T / mean)^2``), i.e. ``cycle_var / cycle_mean``.
        source: "ring" (the dwells of the ring alone) or "record" (the stream's dwell record,
            :class:`DwellRecord`, for the mean dwells, their variances and counts).
    """

    durations_s: FloatArray
    currents_a: FloatArray
    low_a: float
    high_a: float
    dwells: tuple[int, int]
    cycle_mean_s: float
    cycle_var_s2: float
    estimate_rel_var: float
    renewal_var_s: float
    source: str = "ring"


def bin_levels(
    durations: FloatArray, currents: FloatArray, tolerance_a: float
) -> tuple[float, float, FloatArray] | None:
    """The two levels of binned current and each bin's share of time at the high level.

    The levels are the duration-weighted means of the bins within ``DWELL_EDGE_SHARE`` of the
    level difference of the 5 % and 95 % quantiles of the bin currents; a bin between them
    holds an edge and the share ``(I - low) / (high - low)`` of its time at the high level
    (exact for one edge in the bin). None when the levels are within ``tolerance_a``."""
    if durations.shape[0] < 4:
        return None
    lo_q, hi_q = np.quantile(currents, [0.05, 0.95])
    span = hi_q - lo_q
    if not span > tolerance_a:
        return None
    share = np.clip((currents - lo_q) / span, 0.0, 1.0)
    share = np.where(share <= DWELL_EDGE_SHARE, 0.0, np.where(share >= 1.0 - DWELL_EDGE_SHARE, 1.0, share))
    at_lo = share == 0.0
    at_hi = share == 1.0
    if not (at_lo.any() and at_hi.any()):
        return None
    low = float(np.dot(durations[at_lo], currents[at_lo]) / durations[at_lo].sum())
    high = float(np.dot(durations[at_hi], currents[at_hi]) / durations[at_hi].sum())
    return low, high, share


@dataclass(frozen=True)
class DwellRecord:
    """The stream's record of a two-level load's dwells over its whole history (with a slow
    exponential forgetting), which the 30 s or so of the ring cannot give: the mean dwell at
    each level is the ratio estimator ``time at the level / switches out of it`` (exact under
    censoring for exponential dwells and consistent for any renewal process), the variance of
    a dwell from the dwells seen whole.

    Attributes:
        t_s: end of the newest bin counted (NaN: nothing counted yet).
        level: level in force there (0 low, 1 high; NaN: none).
        run_s: time at that level since its last switch (NaN: the run began unseen).
        exposure_s, switches, n, sum_s, sum2_s2: per level (low, high): time at the level,
            switches out of it, completed dwells seen whole, their summed lengths and squares.
        restarts: times the stationarity check restarted the record from the ring.
        hist: per level, the counts of the whole dwells in the log-spaced bins
            (``DWELL_HIST_*``): the shape of the dwell distribution.
    """

    t_s: float = math.nan
    level: float = math.nan
    run_s: float = math.nan
    exposure_s: tuple[float, float] = (0.0, 0.0)
    switches: tuple[float, float] = (0.0, 0.0)
    n: tuple[float, float] = (0.0, 0.0)
    sum_s: tuple[float, float] = (0.0, 0.0)
    sum2_s2: tuple[float, float] = (0.0, 0.0)
    restarts: float = 0.0
    hist: tuple[tuple[float, ...], tuple[float, ...]] = (
        (0.0,) * DWELL_HIST_BINS,
        (0.0,) * DWELL_HIST_BINS,
    )

    def dwell_quantiles(self, lvl: int, q: FloatArray) -> FloatArray:
        """Quantiles of the whole dwells at a level from the histogram (log-linear within a
        bin)."""
        counts = np.asarray(self.hist[lvl], dtype=np.float64)
        cum = np.concatenate([[0.0], np.cumsum(counts)])
        edges = np.log(DWELL_HIST_MIN_S) + np.arange(DWELL_HIST_BINS + 1) * math.log(DWELL_HIST_FACTOR)
        # each occupied bin spreads its count evenly in log length over the bin
        full = np.flatnonzero(counts > 0.0)
        xp = np.column_stack([cum[full], cum[full + 1]]).ravel()
        fp = np.column_stack([edges[full], edges[full + 1]]).ravel()
        return np.asarray(np.exp(np.interp(q * cum[-1], xp, fp)), dtype=np.float64)

    def mean_dwell(self, lvl: int) -> float:
        """Mean dwell at a level (NaN before a switch out of it)."""
        sw = self.switches[lvl]
        return self.exposure_s[lvl] / sw if sw > 0.0 else math.nan

    def dwell_var(self, lvl: int) -> float:
        """Variance of a dwell at a level, from the dwells seen whole (NaN before two)."""
        n = self.n[lvl]
        if n < 2.0:
            return math.nan
        return max(0.0, (self.sum2_s2[lvl] - self.sum_s[lvl] ** 2 / n) / (n - 1.0))


def _walk_runs(
    durations: FloatArray, share: FloatArray, level: int, run: float
) -> tuple[list[tuple[int, float]], FloatArray, int, float]:
    """Walk bins from ``level`` with ``run`` already spent there: the completed runs (level,
    length; NaN where the run began unseen), the time at each level, the level in force at
    the end and the time spent there."""
    runs: list[tuple[int, float]] = []
    expo = np.zeros(2)
    for d, f in zip(durations, share, strict=True):
        here = d * (f if level else 1.0 - f)
        other = d - here
        expo[level] += here
        expo[1 - level] += other
        run += here
        if other > DWELL_EDGE_SHARE * d:
            runs.append((level, run))
            level = 1 - level
            run = other
    return runs, expo, level, run


def record_dwells(
    record: DwellRecord,
    durations: FloatArray,
    share: FloatArray,
    t_end_s: float,
    memory_s: float,
) -> DwellRecord:
    """Count into the record the bins of the ring (oldest first, the newest ending at
    ``t_end_s``; ``share`` the time share at the high level, :func:`bin_levels`) that end after
    the record's ``t_s``. If the ring reaches back to ``t_s`` the run under way continues;
    otherwise (a gap longer than the ring) the first run is censored. The sums are weighted
    by ``exp(-elapsed / memory_s)`` first."""
    ends = t_end_s - (np.cumsum(durations[::-1])[::-1] - durations)
    tol = 0.5 * float(durations.min())
    t0 = record.t_s
    new = ends > t0 + tol if math.isfinite(t0) else np.ones(ends.shape[0], dtype=bool)
    if not new.any():
        return record
    k = int(np.argmax(new))
    start = ends[k] - durations[k]
    if math.isfinite(t0) and math.isfinite(record.level) and abs(start - t0) <= tol:
        level, run = int(record.level), record.run_s
    else:
        level, run = int(share[k] >= 0.5), math.nan
    runs, expo, level, run = _walk_runs(durations[k:], share[k:], level, run)
    w = math.exp(-(t_end_s - t0) / memory_s) if math.isfinite(t0) else 1.0
    sw = np.array(record.switches) * w
    n = np.array(record.n) * w
    s1 = np.array(record.sum_s) * w
    s2 = np.array(record.sum2_s2) * w
    for lvl, length in runs:
        sw[lvl] += 1.0
        if math.isfinite(length):
            n[lvl] += 1.0
            s1[lvl] += length
            s2[lvl] += length * length
    hist = np.array(record.hist) * w
    for lvl, length in runs:
        if math.isfinite(length):
            hist[lvl, _hist_bin(length)] += 1.0
    ex = np.array(record.exposure_s) * w + expo
    return DwellRecord(
        t_s=float(ends[-1]),
        level=float(level),
        run_s=float(run),
        exposure_s=(float(ex[0]), float(ex[1])),
        switches=(float(sw[0]), float(sw[1])),
        n=(float(n[0]), float(n[1])),
        sum_s=(float(s1[0]), float(s1[1])),
        sum2_s2=(float(s2[0]), float(s2[1])),
        restarts=record.restarts,
        hist=(tuple(float(v) for v in hist[0]), tuple(float(v) for v in hist[1])),
    )


def _hist_bin(length_s: float) -> int:
    k = math.floor(math.log(max(length_s, DWELL_HIST_MIN_S) / DWELL_HIST_MIN_S) / math.log(DWELL_HIST_FACTOR))
    return min(max(k, 0), DWELL_HIST_BINS - 1)


def _cycle_stats(record: DwellRecord) -> tuple[float, float, float] | None:
    """Mean and variance of a cycle and the fewer switches of the two levels, from a record
    with at least ``MIN_DWELLS`` switches and two whole dwells at each level."""
    if min(record.switches) < MIN_DWELLS:
        return None
    means = [record.mean_dwell(0), record.mean_dwell(1)]
    var = [record.dwell_var(0), record.dwell_var(1)]
    if not all(math.isfinite(v) for v in (*means, *var)):
        return None
    return means[0] + means[1], var[0] + var[1], min(record.switches)


def check_stationary(
    record: DwellRecord, ring: DwellRecord
) -> bool:
    """Whether the ring's mean cycle agrees with the record's (the record then describes the
    load in force): ``|ln(mu_ring / mu_record)|`` within ``DWELL_STATIONARITY_Z`` standard
    deviations of the ring's estimate, ``cycle_var / (n_ring mu^2)``, times ``1 - f`` (the
    ring is a share f of the record, so their difference varies less). True when either
    lacks the dwells to say."""
    rec = _cycle_stats(record)
    if rec is None or min(ring.switches) < MIN_DWELLS:
        return True
    mu_ring = ring.mean_dwell(0) + ring.mean_dwell(1)
    mu, var, _ = rec
    f = min(sum(ring.exposure_s) / max(sum(record.exposure_s), 1e-300), 1.0)
    rel_var = var / (min(ring.switches) * mu * mu) * (1.0 - f)
    if not rel_var > 0.0:
        return True
    return abs(math.log(mu_ring / mu)) <= DWELL_STATIONARITY_Z * math.sqrt(rel_var)


def update_dwell_record(
    record: DwellRecord,
    durations: FloatArray,
    currents: FloatArray,
    t_end_s: float,
    tolerance_a: float,
    memory_s: float,
) -> DwellRecord:
    """The record after the ring ending at ``t_end_s`` (oldest bin first): its new bins counted
    (:func:`record_dwells`); restarted from the ring alone when the ring's mean cycle departs
    from the record's (:func:`check_stationary`: the load changed). Unchanged when the ring
    shows no two levels."""
    levels = bin_levels(durations, currents, tolerance_a)
    if levels is None:
        return record
    share = levels[2]
    updated = record_dwells(record, durations, share, t_end_s, memory_s)
    ring = record_dwells(DwellRecord(), durations, share, t_end_s, memory_s)
    if check_stationary(updated, ring):
        return updated
    return replace(ring, restarts=record.restarts + 1.0)


def dwell_load(
    durations: FloatArray,
    currents: FloatArray,
    pairs: int,
    tolerance_a: float,
    record: DwellRecord | None = None,
) -> DwellLoad | None:
    """Two-level switching load from binned current (oldest bin first), and the stream's
    dwell record if given.

    The levels and each bin's share at the high level are :func:`bin_levels`. Walking the
    bins, the time at the level in force comes first, then the rest starts the next dwell.
    The first and last dwells are censored by the ring and dropped. None when the two levels
    are within ``tolerance_a`` or fewer than ``MIN_DWELLS`` dwells completed at either level.
    The future period alternates, from the level in force now, ``pairs`` dwells per level at
    the empirical quantiles ``(i + 0.5) / pairs``, the low dwells in a fixed low-discrepancy
    order (so that long and short dwells are not paired by rank).

    With a ``record`` holding at least ``MIN_DWELLS`` switches and two whole dwells at each
    level, the record gives the mean dwells, the cycle's variance and the count behind the
    sampling error; the shape of each level's distribution is the record's histogram where it
    holds more whole dwells than the ring, else the ring's, and its quantiles are scaled to the
    record's mean dwell (which also undoes the ring's bias toward short dwells: a long dwell is
    less often seen whole). The shape matters: at equal mean, regular dwells wear the contact
    about 1.5 times as fast as exponential ones, and the quantiles of the ring's 5-50 dwells
    miss the long tail."""
    levels = bin_levels(durations, currents, tolerance_a)
    if levels is None:
        return None
    low, high, share = levels
    runs, _, level, _ = _walk_runs(durations, share, int(share[0] >= 0.5), math.nan)
    runs = runs[1:]  # the first dwell began before the ring; the one under way is not done
    state = bool(level)
    hi_d = np.array([r for s, r in runs if s])
    lo_d = np.array([r for s, r in runs if not s])
    if hi_d.shape[0] < MIN_DWELLS or lo_d.shape[0] < MIN_DWELLS:
        return None
    mean = float(hi_d.mean() + lo_d.mean())
    var = float(hi_d.var(ddof=1) + lo_d.var(ddof=1))
    n = float(min(hi_d.shape[0], lo_d.shape[0]))
    counts = (int(lo_d.shape[0]), int(hi_d.shape[0]))
    source = "ring"
    q = (np.arange(pairs) + 0.5) / pairs
    hq = np.quantile(hi_d, q)
    lq = np.quantile(lo_d, q)
    stats = _cycle_stats(record) if record is not None else None
    if record is not None and stats is not None:
        shaped = []
        for lvl, ring_q, ring_n in ((0, lq, lo_d.shape[0]), (1, hq, hi_d.shape[0])):
            if sum(record.hist[lvl]) > ring_n:
                ring_q = record.dwell_quantiles(lvl, q)
            shaped.append(ring_q * (record.mean_dwell(lvl) / ring_q.mean()))
        lq, hq = shaped
        mean, var, n = stats
        counts = (round(record.switches[0]), round(record.switches[1]))
        source = "record"
    lq = lq[np.argsort(np.mod(np.arange(pairs) * 0.6180339887498949, 1.0))]
    first, second = (hq, lq) if state else (lq, hq)
    d_out = np.empty(2 * pairs)
    c_out = np.empty(2 * pairs)
    d_out[0::2] = first
    d_out[1::2] = second
    c_out[0::2] = high if state else low
    c_out[1::2] = low if state else high
    return DwellLoad(
        durations_s=d_out,
        currents_a=c_out,
        low_a=low,
        high_a=high,
        dwells=counts,
        cycle_mean_s=mean,
        cycle_var_s2=var,
        estimate_rel_var=var / (n * mean * mean),
        renewal_var_s=var / mean,
        source=source,
    )


def load_segments(
    load: SquareWaveLoad | ConstantLoad | ProfileLoad | ObservedLoad,
    t_s: float,
    observed: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """One period of the assumed future load as segments starting at stream time ``t_s``.

    Args:
        load: the assumption.
        t_s: time the prognosis is made at.
        observed: (durations, currents) of the filled observed-load bins, oldest first (only
            for :class:`ObservedLoad`).

    Returns:
        ``(durations_s, currents_a)``, or None when an observed load is not available yet.
    """
    if isinstance(load, ConstantLoad):
        return np.array([CONSTANT_SEGMENT_S]), np.array([load.current_a])
    if isinstance(load, ObservedLoad):
        if observed is None or observed[0].shape[0] < load.bins:
            return None
        if load.model == "dwells":
            dl = dwell_load(observed[0], observed[1], load.dwell_pairs, load.merge_tolerance_a)
            if dl is not None:
                return dl.durations_s, dl.currents_a
        return merge_bins(observed[0], observed[1], load.merge_tolerance_a)
    if isinstance(load, SquareWaveLoad):
        durations = np.array([load.duty * load.period_s, (1.0 - load.duty) * load.period_s])
        currents = np.array([load.high_a, load.low_a])
        t0 = load.t0_s
    else:
        durations, currents = merge_bins(
            np.array(load.durations_s), np.array(load.current_a), load.merge_tolerance_a
        )
        t0 = load.t0_s
    period = float(durations.sum())
    return _rotate(durations, currents, float(np.mod(t_s - t0, period)))


def span_wear(
    plant: FloatArray,
    segments: tuple[FloatArray, FloatArray],
    state: tuple[float, float, float, float],
    span_s: float,
    eps_seg: float,
) -> float:
    """The change of ``-ln alpha`` over ``span_s`` from ``state = (w1, w2, ln alpha, m)``
    under the load whose period from the state's time is ``segments``, propagated as the
    prognosis propagates (:func:`kern.one_period`, whole periods then the span's part of the
    next): the speeds' lag, the drift of the rate and the load's phase over the span are in it.
    """
    seg_d = np.ascontiguousarray(segments[0], dtype=np.float64)
    seg_c = np.ascontiguousarray(segments[1], dtype=np.float64)
    w1, w2, ell, m = state
    period = float(seg_d.sum())
    if not (period > 0.0 and span_s >= 0.0 and m > 0.0):
        return math.nan
    whole = int(span_s // period)
    rest = span_s - whole * period
    memo = np.zeros((seg_d.shape[0], kern.MAX_SUB + 2))
    end = ell
    for _ in range(whole):
        w1, w2, end, _ = kern.one_period(plant, seg_d, seg_c, w1, w2, end, m, -math.inf, eps_seg, memo)
    if rest > 0.0:
        ends = np.cumsum(seg_d)
        j = min(int(np.searchsorted(ends, rest, side="right")), seg_d.shape[0] - 1)
        part_d = np.append(seg_d[:j], rest - (ends[j - 1] if j > 0 else 0.0))
        part_c = np.ascontiguousarray(seg_c[: j + 1])
        part_memo = np.zeros((j + 1, kern.MAX_SUB + 2))
        _, _, end, _ = kern.one_period(
            plant, part_d, part_c, w1, w2, end, m, -math.inf, eps_seg, part_memo
        )
    return float(ell - end)


# ----------------------------------------------------------------------------- prognosis
@dataclass(frozen=True)
class PrognosisSettings:
    """Monte Carlo and propagation settings.

    Attributes:
        failure_dn: Dn at which the drive is declared failed (Dn only tends to 1).
        n_trajectories: Monte Carlo trajectories.
        horizon_s: longest RUL looked for; later failures are "not reached".
        seed: base seed; the generator of a prognosis is seeded by (seed, bits of t_s).
        bound_c: c of the deterministic bounds (seed eq. 24, c = 3).
        eps_seg: largest change of ln(alpha) per propagation segment (midpoint rule).
        eps_jump: change of ln(alpha) covered by one cycle jump.
        table_min_segments: a load of at least this many segments per period propagates the
            Monte Carlo samples from a shared table of the per-period wear
            (``rul_times_tabulated``); fewer, from a response surface fitted to propagated
            design points (:func:`fitted_times`) or each sample period by period.
        fit_min_trajectories: fewest trajectories for which the response surface is tried
            (below, its design and check propagations cost about as much as all samples).
    """

    failure_dn: float = 0.9
    n_trajectories: int = 1000
    horizon_s: float = 1.0e7
    seed: int = 0
    bound_c: float = 3.0
    eps_seg: float = 0.01
    eps_jump: float = 0.25
    table_min_segments: int = 64
    fit_min_trajectories: int = 200


@dataclass(frozen=True)
class PrognosisResult:
    """The outcome of one prognosis (times in seconds from the prognosis time).

    Attributes:
        times_s: RUL of each trajectory, NaN where not reached within the horizon.
        mean_s, std_s: None unless every trajectory reached the threshold.
        q05_s, q50_s, q95_s: None when fewer than that fraction reached it.
        optimistic_s, pessimistic_s: deterministic bounds (None: not reached).
        reached_fraction: fraction of trajectories that reached the threshold.
        alpha_failure: alpha at the threshold, ``alpha0 (1 - failure_dn)``.
        entropy: the seed sequence entropy used, ``[seed, bits of t_s]``.
        propagation: how the Monte Carlo samples were propagated: ``"table"`` (the per-period
            wear table), ``"fitted"`` (the response surface, :func:`fitted_times`) or
            ``"exact"`` (each sample period by period).
    """

    times_s: FloatArray
    mean_s: float | None
    std_s: float | None
    q05_s: float | None
    q50_s: float | None
    q95_s: float | None
    optimistic_s: float | None
    pessimistic_s: float | None
    reached_fraction: float
    alpha_failure: float
    entropy: tuple[int, int]
    propagation: Literal["table", "fitted", "exact"]


def prognosis_rng(seed: int, t_s: float) -> tuple[np.random.Generator, tuple[int, int]]:
    """Generator seeded by the configured seed and the exact bits of the prognosis time, so a
    replay of the same stream gives the same draws."""
    bits = struct.unpack("<Q", struct.pack("<d", float(t_s)))[0]
    entropy = (int(seed), int(bits))
    return np.random.default_rng(np.random.SeedSequence(list(entropy))), entropy


def covariance_factor(cov: FloatArray) -> FloatArray:
    """``L`` with ``L L^T = cov`` from the eigen-decomposition (negative round-off eigenvalues
    clipped to 0), usable when ``cov`` is only positive semi-definite."""
    sym = 0.5 * (cov + cov.T)
    eigval, eigvec = np.linalg.eigh(sym)
    return np.asarray(eigvec * np.sqrt(np.clip(eigval, 0.0, None)), dtype=np.float64)


def quantile_or_none(sorted_times: FloatArray, q: float) -> float | None:
    """Linear-interpolation quantile (numpy's default) of a sample whose not-reached entries
    count as +inf; None when the quantile falls on an infinite entry."""
    n = sorted_times.shape[0]
    h = (n - 1) * q
    lo = math.floor(h)
    hi = math.ceil(h)
    if not math.isfinite(sorted_times[hi]):
        return None
    return float(sorted_times[lo] + (h - lo) * (sorted_times[hi] - sorted_times[lo]))




#: largest relative difference between a fitted time and the propagated one, at every design
#: point and check sample, for the response surface to be used ...
FIT_TOL = 2e-3
#: ... and at most this share of the standard deviation of ln(time) over the samples (the
#: spread the surface has to resolve), or FIT_TOL_FLOOR if that is larger
FIT_SPREAD_SHARE = 0.1
FIT_TOL_FLOOR = 1e-5
#: Monte Carlo samples propagated to check the response surface at evenly spaced ranks of
#: their fitted times from the shortest to the longest, and at most as many again just after
#: the load's switches; their propagated times are kept
FIT_CHECKS = 16


def quadratic_features(z: FloatArray) -> FloatArray:
    """Columns ``1, z_k, z_k z_l (k <= l)`` of a full quadratic in the rows of ``z``."""
    n, d = z.shape
    cols = [np.ones(n), *(z[:, k] for k in range(d))]
    cols += [z[:, k] * z[:, j] for k in range(d) for j in range(k, d)]
    return np.column_stack(cols)


def composite_design(dim: int, radius: float) -> FloatArray:
    """Rotatable central composite design within the ball of ``radius``: the centre, the
    ``2^dim`` corners ``(+-f, ..., +-f)`` and the ``2 dim`` axial points ``+-2^(dim/4) f`` (the
    rotatable ratio: the fitted quadratic's variance depends only on the distance from the
    centre), ``f`` scaling the farthest of them to ``radius``."""
    axial = 2.0 ** (dim / 4.0)
    f = radius / max(axial, math.sqrt(dim))
    corners = np.array(list(itertools.product((-f, f), repeat=dim)))
    axes = np.concatenate([np.eye(dim) * axial * f, -np.eye(dim) * axial * f])
    return np.concatenate([np.zeros((1, dim)), corners, axes])


def fitted_times(
    plant: FloatArray,
    seg_d: FloatArray,
    seg_c: FloatArray,
    x: FloatArray,
    factor: FloatArray,
    z: FloatArray,
    samples: FloatArray,
    ell_fail: float,
    settings: PrognosisSettings,
) -> FloatArray | None:
    """Times to failure of ``samples = x + z factor^T`` from a response surface in ``z``, or
    None where it does not hold (then every sample is propagated).

    The samples are a cloud around the estimate and differ mainly in how fast they wear, so
    their failure times differ by where in the load the last wear falls: across a zero-current
    plateau the time jumps while the wear barely moves. The surface is therefore fitted to the
    failure time read on the load's wear clock, ``C(T) = int_0^T dv^2`` in the periodic steady
    state at alpha_f (:func:`estimators.kernels.dekf_kernels.wear_clock`), which is smooth in
    the initial state, and a fitted value is turned back into a time by the clock's inverse
    (``wear_clock_times``). ``ln C(T)`` is fitted by least squares, a full quadratic in z (15
    coefficients for 4 states), to the period-by-period propagation
    (:func:`estimators.kernels.dekf_kernels.rul_times`) of a rotatable central composite
    design (25 points) of the cloud's radius in z. ``FIT_CHECKS`` samples at evenly spaced
    ranks of their fitted times are then propagated, and the surface is used only if every
    design point and check is within ``min(FIT_TOL, max(FIT_SPREAD_SHARE std(ln T),
    FIT_TOL_FLOOR))`` of its propagated time (relative); the checks keep their propagated
    times, and a fitted time beyond the horizon is propagated.

    None when there are fewer than ``settings.fit_min_trajectories`` samples, a sample never
    wears or has failed (m <= 0, alpha <= alpha_f, not finite: the cloud spans a singular
    time), the load does not wear at alpha_f, a design point or check does not reach the
    threshold within the horizon, or a check fails.
    """
    n, dim = z.shape
    if n < settings.fit_min_trajectories:
        return None
    regular = (
        np.all(np.isfinite(samples), axis=1)
        & (samples[:, 2] > math.exp(ell_fail))
        & (samples[:, 3] > 0.0)
    )
    radius = float(np.sqrt(np.einsum("ij,ij->i", z, z)).max())
    if not (regular.all() and radius > 0.0):
        return None
    al_f = math.exp(ell_fail)
    if not float(kern.wear_clock(plant, seg_d, seg_c, al_f, np.array([seg_d.sum()]))[0]) > 0.0:
        return None  # no sliding at alpha_f: no clock

    def propagate(points: FloatArray) -> FloatArray:
        return np.asarray(
            kern.rul_times(
                plant, seg_d, seg_c, np.ascontiguousarray(points), ell_fail, settings.horizon_s,
                settings.eps_seg, settings.eps_jump,
            ),  # fmt: skip
            dtype=np.float64,
        )

    def reached(t: FloatArray) -> bool:
        return bool(np.all(np.isfinite(t)) and np.all(t > 0.0))

    dz = composite_design(dim, radius)
    design_t = propagate(x[None, :] + dz @ factor.T)
    if not reached(design_t):
        return None
    clock = kern.wear_clock(plant, seg_d, seg_c, al_f, design_t)
    coef = np.linalg.lstsq(quadratic_features(dz), np.log(clock), rcond=None)[0]

    def surface(zs: FloatArray) -> FloatArray:
        return np.asarray(
            kern.wear_clock_times(plant, seg_d, seg_c, al_f, np.exp(quadratic_features(zs) @ coef)),
            dtype=np.float64,
        )

    times = surface(z)
    order = np.argsort(times)
    ranks = np.round(np.linspace(0.0, n - 1.0, FIT_CHECKS)).astype(np.int64)
    # and the first samples after each switch of the load inside the fitted times (where the
    # wear rate changes and the clock's shape matters most), up to FIT_CHECKS of them
    period = float(seg_d.sum())
    starts = np.concatenate([[0.0], np.cumsum(seg_d)[:-1]])
    k0 = math.floor(float(times[order[0]]) / period)
    k1 = math.floor(float(times[order[-1]]) / period)
    switches = (np.arange(k0, k1 + 1)[:, None] * period + starts[None, :]).ravel()
    after = np.searchsorted(times[order], switches[(switches > times[order[0]])])
    after = np.unique(after[after < n])
    if after.shape[0] > FIT_CHECKS:
        after = after[np.round(np.linspace(0.0, after.shape[0] - 1.0, FIT_CHECKS)).astype(np.int64)]
    checks = order[np.unique(np.concatenate([ranks, after]))]
    check_t = propagate(samples[checks])
    if not reached(check_t):
        return None
    tol = min(FIT_TOL, max(FIT_SPREAD_SHARE * float(np.std(np.log(times))), FIT_TOL_FLOOR))
    err = np.concatenate([surface(dz) / design_t, times[checks] / check_t]) - 1.0
    if not float(np.max(np.abs(err))) <= tol:
        return None
    times[checks] = check_t
    beyond = np.flatnonzero(~(times <= settings.horizon_s))
    if beyond.shape[0] > 0:
        times[beyond] = propagate(samples[beyond])
    return times


def prognose(
    plant: FloatArray,
    alpha0: float,
    x: FloatArray,
    cov: FloatArray,
    t_s: float,
    segments: tuple[FloatArray, FloatArray],
    settings: PrognosisSettings,
    *,
    log_time_var: float = 0.0,
    walk_rel_var_per_s: float = 0.0,
    renewal_var_s: float = 0.0,
    time_scale: float = 1.0,
) -> PrognosisResult:
    """Monte Carlo RUL and deterministic bounds from the estimate ``x`` and covariance ``cov``.

    Args:
        plant: ``[r1, r2, B1, B2, J1, J2, Km]``.
        alpha0: alpha at Dn = 0.
        x: ``[w1, w2, alpha, m]``.
        cov: its 4x4 covariance.
        t_s: prognosis time (seeds the generator).
        segments: one period of the future load from now (:func:`load_segments`).
        settings: Monte Carlo and propagation settings.
        log_time_var: variance of a relative wear-rate error beyond the covariance (model and
            load error measured on the stream's own history); each trajectory's time is
            multiplied by ``exp(s z)``.
        walk_rel_var_per_s: relative random-walk variance of m per second (the filter's own
            model of a slowly varying m, seed assumption iii): over a remaining life T the mean
            of the walk has relative variance ``walk T / 3``, added to ``s^2`` per trajectory.
        renewal_var_s: a random future load whose wear comes in cycles (:class:`DwellLoad`):
            over a remaining life T the relative variance of the cycles, hence of the wear,
            is ``renewal_var_s / T``, added to ``s^2`` per trajectory (T at least
            ``renewal_var_s``).
        time_scale: factor on every time (Monte Carlo and bounds): the recalibration of the
            wear rate on the stream's record (``1 / (realized / predicted)``).

    Since the time to failure is inversely proportional to the mean wear rate, a relative rate
    error ``eps`` scales it by ``1 / (1 + eps)``, taken as ``exp(-eps)`` (lognormal, so the
    times stay positive); both widenings are drawn after the initial states, so they leave the
    draws of the states unchanged.
    """
    alpha_fail = alpha0 * (1.0 - settings.failure_dn)
    ell_fail = math.log(alpha_fail)
    # one layout for the compiled kernels (a read-only plant would compile a second version)
    plant = np.array(plant, dtype=np.float64)
    seg_d = np.ascontiguousarray(segments[0], dtype=np.float64)
    seg_c = np.ascontiguousarray(segments[1], dtype=np.float64)
    rng, entropy = prognosis_rng(settings.seed, t_s)
    z = rng.standard_normal((settings.n_trajectories, 4))
    factor = covariance_factor(cov)
    samples = np.ascontiguousarray(x[None, :] + z @ factor.T)
    args = (ell_fail, settings.horizon_s, settings.eps_seg, settings.eps_jump)
    propagation: Literal["table", "fitted", "exact"] = "exact"
    fitted = None
    if seg_d.shape[0] >= settings.table_min_segments:
        times = kern.rul_times_tabulated(plant, seg_d, seg_c, samples, *args)
        propagation = "table"
    else:
        fitted = fitted_times(plant, seg_d, seg_c, x, factor, z, samples, ell_fail, settings)
    if fitted is not None:
        times = fitted
        propagation = "fitted"
    elif propagation == "exact":
        times = kern.rul_times(plant, seg_d, seg_c, samples, *args)
    if log_time_var > 0.0 or walk_rel_var_per_s > 0.0 or renewal_var_s > 0.0:
        z_rate = rng.standard_normal(settings.n_trajectories)
        finite = np.isfinite(times)
        t_fin = np.where(finite, times, 0.0)
        var = log_time_var + walk_rel_var_per_s * t_fin / 3.0
        if renewal_var_s > 0.0:
            # a life shorter than about one cycle (renewal_var_s ~ the mean cycle for
            # exponential dwells) counts as one: at most one cycle's relative variance
            var = var + renewal_var_s / np.maximum(t_fin, renewal_var_s)
        times = np.where(finite, times * np.exp(np.sqrt(var) * z_rate), times)
    times = times * time_scale
    c = settings.bound_c
    s_alpha = math.sqrt(max(float(cov[2, 2]), 0.0))
    s_m = math.sqrt(max(float(cov[3, 3]), 0.0))
    bounds = np.array(
        [
            [x[0], x[1], x[2] + c * s_alpha, x[3] - c * s_m],
            [x[0], x[1], x[2] - c * s_alpha, x[3] + c * s_m],
        ]
    )
    opt, pes = kern.rul_times(plant, seg_d, seg_c, bounds, *args)
    opt = opt * time_scale
    pes = pes * time_scale
    reached = np.isfinite(times)
    sorted_times = np.sort(np.where(reached, times, np.inf))
    all_reached = bool(reached.all())
    return PrognosisResult(
        times_s=times,
        mean_s=float(times.mean()) if all_reached else None,
        std_s=float(times.std()) if all_reached else None,
        q05_s=quantile_or_none(sorted_times, 0.05),
        q50_s=quantile_or_none(sorted_times, 0.50),
        q95_s=quantile_or_none(sorted_times, 0.95),
        optimistic_s=_finite_or_none(opt),
        pessimistic_s=_finite_or_none(pes),
        reached_fraction=float(reached.mean()),
        alpha_failure=alpha_fail,
        entropy=entropy,
        propagation=propagation,
    )
