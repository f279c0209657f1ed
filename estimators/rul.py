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

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from estimators.base import ConfigError, FloatArray
from estimators.checks import finite_or_none as _finite_or_none
from estimators.kernels import dekf_kernels as kern

#: Segment length used for a constant current (any length is exact; this one keeps the
#: per-segment wear small enough for the midpoint rule without extra subdivision).
CONSTANT_SEGMENT_S = 1.0


# ----------------------------------------------------------------------------- load laws
@dataclass(frozen=True)
class SquareWaveLoad:
    """Pulse current between ``low_a`` and ``high_a``; rising edges at ``t0_s + k period_s``
    (stream time), ``high_a`` during ``duty * period_s``."""

    high_a: float = 20.0
    low_a: float = 0.0
    period_s: float = 2.0
    duty: float = 0.5
    t0_s: float = 0.0
    kind: Literal["square_wave"] = "square_wave"


@dataclass(frozen=True)
class ConstantLoad:
    """Constant current (the seed's own prognosis assumption, 20 A)."""

    current_a: float = 20.0
    kind: Literal["constant"] = "constant"


@dataclass(frozen=True)
class ProfileLoad:
    """A recorded current profile repeated periodically: ``current_a[i]`` is held for
    ``durations_s[i]``; the profile starts at ``t0_s + k * sum(durations_s)`` (stream time)."""

    durations_s: tuple[float, ...]
    current_a: tuple[float, ...]
    t0_s: float = 0.0
    kind: Literal["profile"] = "profile"


@dataclass(frozen=True)
class ObservedLoad:
    """The recently applied current, repeated: the filter bins the held current over
    ``bin_samples`` stream samples into a ring of ``bins`` bins; at a prognosis the ring (oldest
    bin first) is one period of the future load, starting now. Consecutive bins whose currents
    differ by at most ``merge_tolerance_a`` from the first of their run are merged."""

    bin_samples: int = 20
    bins: int = 200
    merge_tolerance_a: float = 0.05
    kind: Literal["observed"] = "observed"


LoadAssumption = SquareWaveLoad | ConstantLoad | ProfileLoad | ObservedLoad


def _number(name: str, value: Any, *, positive: bool = False, unit: bool = False) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool):
        raise ConfigError(f"{name}: expected a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{name}: expected a finite number, got {value!r}")
    if positive and v <= 0.0:
        raise ConfigError(f"{name}: expected a positive number, got {value!r}")
    if unit and not 0.0 < v < 1.0:
        raise ConfigError(f"{name}: expected a number in (0, 1), got {value!r}")
    return v


def _integer(name: str, value: Any, lo: int, hi: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
        raise ConfigError(f"{name}: expected an integer in [{lo}, {hi}], got {value!r}")
    return value


def _check_keys(name: str, raw: Mapping[str, Any], known: set[str]) -> None:
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(f"{name}.{unknown[0]}: unknown field (known: {', '.join(sorted(known))})")


def parse_load(raw: Any, name: str = "rul_load") -> LoadAssumption:
    """Validate a JSON-like load assumption ``{"kind": ..., ...}``.

    Raises:
        ConfigError: unknown kind or field, non-finite numbers, non-positive period or
            durations, duty outside (0, 1), profile arrays of different lengths or empty.
    """
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{name}: expected an object with a 'kind'")
    kind = raw.get("kind")
    if kind == "square_wave":
        d = SquareWaveLoad()
        _check_keys(name, raw, {"kind", "high_a", "low_a", "period_s", "duty", "t0_s"})
        return SquareWaveLoad(
            high_a=_number(f"{name}.high_a", raw.get("high_a", d.high_a)),
            low_a=_number(f"{name}.low_a", raw.get("low_a", d.low_a)),
            period_s=_number(f"{name}.period_s", raw.get("period_s", d.period_s), positive=True),
            duty=_number(f"{name}.duty", raw.get("duty", d.duty), unit=True),
            t0_s=_number(f"{name}.t0_s", raw.get("t0_s", d.t0_s)),
        )
    if kind == "constant":
        _check_keys(name, raw, {"kind", "current_a"})
        return ConstantLoad(
            current_a=_number(f"{name}.current_a", raw.get("current_a", ConstantLoad.current_a))
        )
    if kind == "profile":
        _check_keys(name, raw, {"kind", "durations_s", "current_a", "t0_s"})
        durations = raw.get("durations_s")
        currents = raw.get("current_a")
        if not isinstance(durations, list | tuple) or not isinstance(currents, list | tuple):
            raise ConfigError(f"{name}: a profile needs the lists durations_s and current_a")
        if len(durations) != len(currents) or not durations:
            raise ConfigError(
                f"{name}: durations_s and current_a must be non-empty and of equal length "
                f"(got {len(durations)} and {len(currents)})"
            )
        if len(durations) > 100_000:
            raise ConfigError(f"{name}: at most 100000 profile segments")
        return ProfileLoad(
            durations_s=tuple(
                _number(f"{name}.durations_s[{i}]", v, positive=True)
                for i, v in enumerate(durations)
            ),
            current_a=tuple(_number(f"{name}.current_a[{i}]", v) for i, v in enumerate(currents)),
            t0_s=_number(f"{name}.t0_s", raw.get("t0_s", 0.0)),
        )
    if kind == "observed":
        d2 = ObservedLoad()
        _check_keys(name, raw, {"kind", "bin_samples", "bins", "merge_tolerance_a"})
        tol = _number(
            f"{name}.merge_tolerance_a", raw.get("merge_tolerance_a", d2.merge_tolerance_a)
        )
        if tol < 0.0:
            raise ConfigError(f"{name}.merge_tolerance_a: expected a number >= 0, got {tol!r}")
        return ObservedLoad(
            bin_samples=_integer(
                f"{name}.bin_samples", raw.get("bin_samples", d2.bin_samples), 1, 10_000_000
            ),
            bins=_integer(f"{name}.bins", raw.get("bins", d2.bins), 1, 10_000),
            merge_tolerance_a=tol,
        )
    raise ConfigError(
        f"{name}.kind: expected 'square_wave', 'constant', 'profile' or 'observed', got {kind!r}"
    )


def load_to_dict(load: LoadAssumption) -> dict[str, Any]:
    """The load assumption as a JSON-serializable mapping (the form :func:`parse_load` takes)."""
    if isinstance(load, SquareWaveLoad):
        return {
            "kind": load.kind,
            "high_a": load.high_a,
            "low_a": load.low_a,
            "period_s": load.period_s,
            "duty": load.duty,
            "t0_s": load.t0_s,
        }
    if isinstance(load, ConstantLoad):
        return {"kind": load.kind, "current_a": load.current_a}
    if isinstance(load, ProfileLoad):
        return {
            "kind": load.kind,
            "durations_s": list(load.durations_s),
            "current_a": list(load.current_a),
            "t0_s": load.t0_s,
        }
    return {
        "kind": load.kind,
        "bin_samples": load.bin_samples,
        "bins": load.bins,
        "merge_tolerance_a": load.merge_tolerance_a,
    }


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


def load_segments(
    load: LoadAssumption,
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
        return merge_bins(observed[0], observed[1], load.merge_tolerance_a)
    if isinstance(load, SquareWaveLoad):
        durations = np.array([load.duty * load.period_s, (1.0 - load.duty) * load.period_s])
        currents = np.array([load.high_a, load.low_a])
        t0 = load.t0_s
    else:
        durations = np.array(load.durations_s)
        currents = np.array(load.current_a)
        t0 = load.t0_s
    period = float(durations.sum())
    return _rotate(durations, currents, float(np.mod(t_s - t0, period)))


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
    """

    failure_dn: float = 0.9
    n_trajectories: int = 1000
    horizon_s: float = 1.0e7
    seed: int = 0
    bound_c: float = 3.0
    eps_seg: float = 0.01
    eps_jump: float = 0.25


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




def prognose(
    plant: FloatArray,
    alpha0: float,
    x: FloatArray,
    cov: FloatArray,
    t_s: float,
    segments: tuple[FloatArray, FloatArray],
    settings: PrognosisSettings,
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
    """
    alpha_fail = alpha0 * (1.0 - settings.failure_dn)
    ell_fail = math.log(alpha_fail)
    seg_d = np.ascontiguousarray(segments[0], dtype=np.float64)
    seg_c = np.ascontiguousarray(segments[1], dtype=np.float64)
    rng, entropy = prognosis_rng(settings.seed, t_s)
    z = rng.standard_normal((settings.n_trajectories, 4))
    samples = np.ascontiguousarray(x[None, :] + z @ covariance_factor(cov).T)
    times = kern.rul_times(
        plant,
        seg_d,
        seg_c,
        samples,
        ell_fail,
        settings.horizon_s,
        settings.eps_seg,
        settings.eps_jump,
    )
    c = settings.bound_c
    s_alpha = math.sqrt(max(float(cov[2, 2]), 0.0))
    s_m = math.sqrt(max(float(cov[3, 3]), 0.0))
    bounds = np.array(
        [
            [x[0], x[1], x[2] + c * s_alpha, x[3] - c * s_m],
            [x[0], x[1], x[2] - c * s_alpha, x[3] + c * s_m],
        ]
    )
    opt, pes = kern.rul_times(
        plant,
        seg_d,
        seg_c,
        bounds,
        ell_fail,
        settings.horizon_s,
        settings.eps_seg,
        settings.eps_jump,
    )
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
    )
