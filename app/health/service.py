"""The read side: latest health, history, per-sample outputs, events and RUL."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from app.codec import column_names, decode_columns
from app.errors import InvalidQuery, NotFound
from app.health import repository
from app.health.downsample import min_max_downsample
from app.ingest import TIME_COLUMN
from app.models import Actuator
from app.processing.messages import event_public, rul_public, window_public


def latest_health(session: Session, tail: str, act: Actuator) -> dict[str, Any]:
    stream = repository.stream(session, act.id)
    estimators: dict[str, Any] = {}
    for er in repository.estimators(session, act.id):
        last = repository.latest_window(session, act.id, er.estimator)
        estimators[er.estimator] = {
            "status": er.status,
            "reasons": er.reasons,
            "window": window_public(last) if last is not None else None,
        }
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "kind": act.kind,
        "status": stream.status,
        "failure": stream.failure,
        "last_logged_seq": act.last_logged_seq,
        "last_applied_seq": stream.last_applied_seq,
        "t_last_s": stream.last_applied_t_s,
        "updated_at": stream.updated_at,
        "estimators": estimators,
    }


def _check_estimator(session: Session, act: Actuator, estimator: str | None) -> None:
    if estimator is not None and not repository.has_estimator(session, act.id, estimator):
        raise NotFound(f"estimator {estimator!r} is not attached to actuator {act.actuator_id!r}")


def health_history(
    session: Session,
    act: Actuator,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    limit: int,
) -> list[dict[str, Any]]:
    _check_estimator(session, act, estimator)
    return [window_public(r) for r in repository.windows(session, act.id, estimator, from_s, to_s, limit)]


def _as_list(a: np.ndarray) -> list[float | None]:
    return [None if not np.isfinite(x) else x for x in a.tolist()]


def sample_outputs(
    session: Session,
    act: Actuator,
    estimator: str,
    from_s: float | None,
    to_s: float | None,
    max_samples: int,
) -> dict[str, Any]:
    _check_estimator(session, act, estimator)
    parts: list[dict[str, np.ndarray]] = []
    n = 0
    truncated = False
    for row in repository.sample_outputs(session, act.id, estimator, from_s, to_s):
        cols = decode_columns(row.payload)
        t = cols[TIME_COLUMN]
        keep = np.ones(t.shape, dtype=bool)
        if from_s is not None:
            keep &= t >= from_s
        if to_s is not None:
            keep &= t <= to_s
        cols = {k: v[keep] for k, v in cols.items()}
        take = min(len(cols[TIME_COLUMN]), max_samples - n)
        if take < len(cols[TIME_COLUMN]):
            truncated = True
        parts.append({k: v[:take] for k, v in cols.items()})
        n += take
        if n >= max_samples:
            break
    names = [k for k in (parts[0] if parts else {}) if k != TIME_COLUMN]
    joined = {
        k: np.concatenate([p[k] for p in parts]) if parts else np.empty(0) for k in [TIME_COLUMN, *names]
    }
    return {
        "estimator": estimator,
        "t_s": joined[TIME_COLUMN].tolist(),
        "series": {k: _as_list(joined[k]) for k in names},
        "truncated": truncated,
    }


def events(
    session: Session, act: Actuator, from_s: float | None, to_s: float | None, limit: int
) -> list[dict[str, Any]]:
    return [event_public(r) for r in repository.events(session, act.id, from_s, to_s, limit)]


def rul(
    session: Session,
    tail: str,
    act: Actuator,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    limit: int,
) -> dict[str, Any]:
    _check_estimator(session, act, estimator)
    names = [estimator] if estimator is not None else [er.estimator for er in repository.estimators(session, act.id)]
    latest: dict[str, Any] = {}
    for name in sorted(names):
        last = repository.latest_rul(session, act.id, name)
        if last is not None:
            latest[name] = rul_public(last)
    rows = repository.ruls(session, act.id, estimator, from_s, to_s, limit + 1)
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "latest": latest,
        "items": [rul_public(r) for r in rows[:limit]],
        "truncated": len(rows) > limit,
    }


def _column_blocks(
    payloads: Iterator[bytes], what: str, from_s: float | None, to_s: float | None, names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The columns of stored blocks (outputs or telemetry) cut to [from_s, to_s], joined."""
    times: list[np.ndarray] = []
    columns: dict[str, list[np.ndarray]] = {}
    for payload in payloads:
        cols = decode_columns(payload, None if names is None else {TIME_COLUMN, *names})
        t = cols.pop(TIME_COLUMN)
        keep: slice | np.ndarray = slice(None)
        if (from_s is not None and t[0] < from_s) or (to_s is not None and t[-1] > to_s):
            keep = (t >= (-np.inf if from_s is None else from_s)) & (t <= (np.inf if to_s is None else to_s))
        times.append(t[keep])
        for name in names if names is not None else cols:
            if name not in cols:
                have = [c for c in column_names(payload) if c != TIME_COLUMN]
                raise NotFound(f"{what} has no series {name!r} (it has {', '.join(have)})")
            columns.setdefault(name, []).append(cols[name][keep])
    t_all = np.concatenate(times) if times else np.empty(0)
    return t_all, {k: np.concatenate(v) for k, v in columns.items()}


def _outputs_columns(
    session: Session, act: Actuator, estimator: str, from_s: float | None, to_s: float | None,
    names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Every per-sample output of ``estimator`` in [from_s, to_s] (only ``names`` if given)."""
    rows = repository.sample_outputs(session, act.id, estimator, from_s, to_s)
    return _column_blocks((r.payload for r in rows), f"estimator {estimator!r}", from_s, to_s, names)


def _telemetry_columns(
    session: Session, act: Actuator, from_s: float | None, to_s: float | None, names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The channels of the logged batches in [from_s, to_s] that still hold their samples."""
    rows = repository.telemetry_batches(session, act.id, from_s, to_s)
    payloads = (r.payload for r in rows if r.payload is not None)
    return _column_blocks(payloads, f"actuator {act.actuator_id!r}", from_s, to_s, names)


def _health_columns(
    session: Session, act: Actuator, estimator: str, from_s: float | None, to_s: float | None,
    names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The health indicators of ``estimator``'s windows ending in [from_s, to_s], at each
    window's end."""
    rows = [
        r for r in repository.windows(session, act.id, estimator, from_s, to_s, limit=None)
        if (from_s is None or r.t_end_s >= from_s) and (to_s is None or r.t_end_s <= to_s)
    ]
    found = sorted({k for r in rows for k in r.indicators})
    for name in names or []:
        if rows and name not in found:
            raise NotFound(f"estimator {estimator!r} has no health indicator {name!r} (it has {', '.join(found)})")
    wanted = names if names is not None else found
    t = np.array([r.t_end_s for r in rows], dtype=np.float64)
    cols = {
        name: np.array([np.nan if r.indicators.get(name) is None else r.indicators[name] for r in rows],
                       dtype=np.float64)
        for name in wanted
    }
    return t, cols


def series(
    session: Session,
    act: Actuator,
    estimator: str | None,
    source: str,
    names: list[str] | None,
    from_s: float | None,
    to_s: float | None,
    points: int,
) -> dict[str, Any]:
    """Outputs or health indicators of one estimator, or the logged telemetry, over
    [from_s, to_s], min/max downsampled to ``points`` (docs/api.md, "Plotting series")."""
    if source == "telemetry":
        t, cols = _telemetry_columns(session, act, from_s, to_s, names)
    elif estimator is None:
        raise InvalidQuery(f"source {source!r} needs estimator=<name>")
    else:
        _check_estimator(session, act, estimator)
        read = _outputs_columns if source == "outputs" else _health_columns
        t, cols = read(session, act, estimator, from_s, to_s, names)
    n = len(t)
    span_from = from_s if from_s is not None else (float(t[0]) if n else None)
    span_to = to_s if to_s is not None else (float(t[-1]) if n else None)
    if n:
        d = min_max_downsample(t, cols, points, span_from, span_to)
        t, cols, reduced = d.t_s, d.series, d.reduced
    else:
        reduced = False
    return {
        "estimator": estimator,
        "source": source,
        "from_s": span_from,
        "to_s": span_to,
        "n_samples": n,
        "reduced": reduced,
        "t_s": t.tolist(),
        "series": {k: _as_list(v) for k, v in cols.items()},
    }
