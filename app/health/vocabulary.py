"""Prognostics' usual words alongside the RUL in stream seconds (progpy's vocabulary).

* ``event_state``: normalized health in [0, 1], 1 for a new part and 0 when the failure
  threshold is met (progpy's ``event_state``; ``threshold_met`` says whether it is). For an estimator whose health quantity is a
  normalized deterioration rising from 0 (new) to the failure threshold, it is
  ``1 - health / threshold``, clipped to [0, 1]; its bounds come from the quantity's bounds.
* ``time_of_event``: when the threshold is met (progpy's ``time_of_event``), the prognosis
  time plus the RUL. Absolute UTC when the stream's clock is epoch seconds (times at or above
  :data:`app.telemetry.validation.EPOCH_LIKE_S`); otherwise only the stream time
  ``time_of_event_t_s`` is known and ``time_basis`` says ``stream``.
* RUL in operating hours or cycles: when the actuator sends a counter channel
  (:data:`USAGE_COUNTERS`), the RUL in seconds times the counter's average rate over the
  current baseline (from its first logged sample to the prognosis), i.e. assuming the future
  usage rate equals the rate so far.

Pure functions; the read side (``app.health.service``) feeds them stored rows.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any

from app.telemetry.validation import EPOCH_LIKE_S

#: Estimator -> the key of its RUL ``health`` that rises from 0 (new) to ``threshold``, with
#: the keys of its lower and upper bounds.
HEALTH_QUANTITY: dict[str, tuple[str, str, str]] = {
    "deterioration_ekf": ("dn", "dn_lower", "dn_upper"),
}

#: Counter channels an actuator may send, and the unit its RUL is also given in:
#: ``operating_hours`` (cumulative operating hours) -> ``rul_operating_hours``,
#: ``cycles`` (cumulative cycle count) -> ``rul_cycles``.
USAGE_COUNTERS: dict[str, str] = {"operating_hours": "rul_operating_hours", "cycles": "rul_cycles"}

RUL_STATS = ("mean_s", "q05_s", "q50_s", "q95_s")


def _event_state(health: float | None, threshold: float) -> float | None:
    if health is None or not math.isfinite(health) or threshold <= 0:
        return None
    return min(1.0, max(0.0, 1.0 - health / threshold))


def event_state(estimator: str, health: Mapping[str, Any], threshold: float) -> dict[str, Any]:
    """``event_state`` with its bounds (``event_state_lower`` from the deterioration's upper
    bound) and ``threshold_met`` (progpy's: the health quantity has reached the threshold); all
    None for an estimator without a normalized health quantity."""
    keys = HEALTH_QUANTITY.get(estimator)
    if keys is None:
        return {"event_state": None, "event_state_lower": None, "event_state_upper": None, "threshold_met": None}
    mid, lo, hi = (health.get(k) for k in keys)
    return {
        "threshold_met": None if mid is None or not math.isfinite(mid) else bool(mid >= threshold),
        "event_state": _event_state(mid, threshold),
        "event_state_lower": _event_state(hi, threshold),
        "event_state_upper": _event_state(lo, threshold),
    }


def _utc(t_s: float) -> datetime:
    return datetime.fromtimestamp(t_s, UTC)


def time_of_event(t_s: float, rul: Mapping[str, float | None]) -> dict[str, Any]:
    """When the threshold is met (median, 5 % and 95 % quantiles): stream seconds always,
    absolute UTC when the stream's clock is epoch seconds."""
    epoch = t_s >= EPOCH_LIKE_S
    out: dict[str, Any] = {"time_basis": "epoch" if epoch else "stream"}
    for name, key in (("", "q50_s"), ("_q05", "q05_s"), ("_q95", "q95_s")):
        v = rul.get(key)
        toe = t_s + v if v is not None else None
        out[f"time_of_event{name}_t_s"] = toe
        out[f"time_of_event{name}"] = _utc(toe) if epoch and toe is not None else None
    return out


def usage_rate(first: tuple[float, float] | None, now: tuple[float, float] | None) -> float | None:
    """A counter's average rate (units per stream second) between two ``(t_s, value)`` points;
    None when it cannot be measured (a point missing, no time between them, or the counter did
    not advance)."""
    if first is None or now is None:
        return None
    dt, dc = now[0] - first[0], now[1] - first[1]
    if dt <= 0 or dc <= 0 or not math.isfinite(dc):
        return None
    return dc / dt


def rul_in_usage(rul: Mapping[str, float | None], rate: float | None) -> dict[str, float | None] | None:
    """The RUL statistics in counter units (``mean``, ``q05``, ``q50``, ``q95``)."""
    if rate is None:
        return None
    return {k[:-2]: (rul[k] * rate if rul.get(k) is not None else None) for k in RUL_STATS}  # type: ignore[operator]
