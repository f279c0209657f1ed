"""The read side: latest health, history, per-sample outputs, events and RUL."""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlalchemy.orm import Session

from app.codec import decode_columns
from app.errors import NotFound
from app.health import repository
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
