"""Read side: health, history, per-sample outputs, events and the fleet overview."""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.codec import decode_columns
from app.errors import NotFound
from app.ingest import TIME_COLUMN
from app.models import (
    Actuator,
    Aircraft,
    EstimatorEventRow,
    EstimatorState,
    HealthWindowRow,
    RulEstimateRow,
    SampleOutputRow,
    Stream,
    TelemetryBatch,
)
from estimators.base import STATUS_ORDER, worst_status


def _window(row: HealthWindowRow) -> dict[str, Any]:
    return {
        "estimator": row.estimator,
        "seq": row.seq,
        "t_start_s": row.t_start_s,
        "t_end_s": row.t_end_s,
        "n_samples": row.n_samples,
        "indicators": row.indicators,
        "status": row.status,
        "reasons": row.reasons,
    }


def latest_health(session: Session, tail: str, act: Actuator) -> dict[str, Any]:
    stream = session.get(Stream, act.id)
    assert stream is not None
    estimators: dict[str, Any] = {}
    for er in session.scalars(
        select(EstimatorState).where(EstimatorState.actuator_pk == act.id).order_by(EstimatorState.estimator)
    ):
        last = session.scalar(
            select(HealthWindowRow)
            .where(HealthWindowRow.actuator_pk == act.id, HealthWindowRow.estimator == er.estimator)
            .order_by(HealthWindowRow.t_end_s.desc())
            .limit(1)
        )
        estimators[er.estimator] = {
            "status": er.status,
            "reasons": er.reasons,
            "window": _window(last) if last is not None else None,
        }
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "kind": act.kind,
        "status": stream.status,
        "last_logged_seq": act.last_logged_seq,
        "last_applied_seq": stream.last_applied_seq,
        "t_last_s": stream.last_applied_t_s,
        "updated_at": stream.updated_at,
        "estimators": estimators,
    }


def _check_estimator(session: Session, act: Actuator, estimator: str | None) -> None:
    if estimator is not None and session.get(EstimatorState, (act.id, estimator)) is None:
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
    stmt = select(HealthWindowRow).where(HealthWindowRow.actuator_pk == act.id)
    if estimator is not None:
        stmt = stmt.where(HealthWindowRow.estimator == estimator)
    if from_s is not None:
        stmt = stmt.where(HealthWindowRow.t_end_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(HealthWindowRow.t_start_s <= to_s)
    stmt = stmt.order_by(HealthWindowRow.t_end_s, HealthWindowRow.estimator).limit(limit)
    return [_window(r) for r in session.scalars(stmt)]


def sample_outputs(
    session: Session,
    act: Actuator,
    estimator: str,
    from_s: float | None,
    to_s: float | None,
    max_samples: int,
) -> dict[str, Any]:
    _check_estimator(session, act, estimator)
    stmt = select(SampleOutputRow).where(
        SampleOutputRow.actuator_pk == act.id, SampleOutputRow.estimator == estimator
    )
    if from_s is not None:
        stmt = stmt.where(SampleOutputRow.t_last_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(SampleOutputRow.t_first_s <= to_s)
    parts: list[dict[str, np.ndarray]] = []
    n = 0
    truncated = False
    for row in session.scalars(stmt.order_by(SampleOutputRow.seq)):
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
        cols = {k: v[:take] for k, v in cols.items()}
        parts.append(cols)
        n += take
        if n >= max_samples:
            break
    names = [k for k in (parts[0] if parts else {}) if k != TIME_COLUMN]
    joined = {k: np.concatenate([p[k] for p in parts]) if parts else np.empty(0) for k in [TIME_COLUMN, *names]}

    def as_list(a: np.ndarray) -> list[float | None]:
        return [None if not np.isfinite(x) else x for x in a.tolist()]

    return {
        "estimator": estimator,
        "t_s": joined[TIME_COLUMN].tolist(),
        "series": {k: as_list(joined[k]) for k in names},
        "truncated": truncated,
    }


def events(
    session: Session, act: Actuator, from_s: float | None, to_s: float | None, limit: int
) -> list[dict[str, Any]]:
    stmt = select(EstimatorEventRow).where(EstimatorEventRow.actuator_pk == act.id)
    if from_s is not None:
        stmt = stmt.where(EstimatorEventRow.t_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(EstimatorEventRow.t_s <= to_s)
    rows = session.scalars(stmt.order_by(EstimatorEventRow.t_s, EstimatorEventRow.id).limit(limit))
    return [_event(r) for r in rows]


FAULT_EVENT_KINDS = ("fault_detected", "fault_cleared")


def _event(r: EstimatorEventRow) -> dict[str, Any]:
    return {"estimator": r.estimator, "seq": r.seq, "t_s": r.t_s, "kind": r.kind, "detail": r.detail}


def _open_faults(rows: list[EstimatorEventRow]) -> list[EstimatorEventRow]:
    """Detections with no later clearance of the same component by the same estimator.

    A detection marked ``"update": true`` revises the estimator's open detections (e.g. more
    residuals joined) and replaces them; a clearance naming no open component clears all of
    that estimator's.
    """
    open_: dict[tuple[str, str], EstimatorEventRow] = {}
    for r in rows:
        key = (r.estimator, str(r.detail.get("component")))
        if r.kind == "fault_detected":
            if r.detail.get("update"):
                for k in [k for k in open_ if k[0] == r.estimator]:
                    del open_[k]
            open_[key] = r
        elif key in open_:
            del open_[key]
        else:
            for k in [k for k in open_ if k[0] == r.estimator]:
                del open_[k]
    return sorted(open_.values(), key=lambda r: (r.t_s, r.id))


def _fault_rows(session: Session, actuator_pks: list[int]) -> dict[int, list[EstimatorEventRow]]:
    out: dict[int, list[EstimatorEventRow]] = {pk: [] for pk in actuator_pks}
    if not actuator_pks:
        return out
    for r in session.scalars(
        select(EstimatorEventRow)
        .where(EstimatorEventRow.actuator_pk.in_(actuator_pks), EstimatorEventRow.kind.in_(FAULT_EVENT_KINDS))
        .order_by(EstimatorEventRow.t_s, EstimatorEventRow.id)
    ):
        out[r.actuator_pk].append(r)
    return out


def faults(session: Session, tail: str, act: Actuator, limit: int) -> dict[str, Any]:
    stream = session.get(Stream, act.id)
    assert stream is not None
    rows = _fault_rows(session, [act.id])[act.id]
    estimators = {
        er.estimator: {
            "status": er.status,
            "reasons": er.reasons,
            "t_s": er.diagnosis_t_s,
            "diagnosis": er.diagnosis,
        }
        for er in session.scalars(
            select(EstimatorState).where(EstimatorState.actuator_pk == act.id).order_by(EstimatorState.estimator)
        )
    }
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "status": stream.status,
        "active_faults": [_event(r) for r in _open_faults(rows)],
        "estimators": estimators,
        "events": [_event(r) for r in rows[-limit:]],
    }


def _rul(r: RulEstimateRow) -> dict[str, Any]:
    return {
        c: getattr(r, c)
        for c in (
            "estimator", "seq", "t_s", "mean_s", "std_s", "q05_s", "q50_s", "q95_s",
            "optimistic_s", "pessimistic_s", "threshold", "health", "assumption", "status", "reasons",
        )
    }


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
    names = [estimator] if estimator is not None else list(
        session.scalars(select(EstimatorState.estimator).where(EstimatorState.actuator_pk == act.id))
    )
    latest: dict[str, Any] = {}
    for name in sorted(names):
        last = session.scalar(
            select(RulEstimateRow)
            .where(RulEstimateRow.actuator_pk == act.id, RulEstimateRow.estimator == name)
            .order_by(RulEstimateRow.t_s.desc())
            .limit(1)
        )
        if last is not None:
            latest[name] = _rul(last)
    stmt = select(RulEstimateRow).where(RulEstimateRow.actuator_pk == act.id)
    if estimator is not None:
        stmt = stmt.where(RulEstimateRow.estimator == estimator)
    if from_s is not None:
        stmt = stmt.where(RulEstimateRow.t_s >= from_s)
    if to_s is not None:
        stmt = stmt.where(RulEstimateRow.t_s <= to_s)
    rows = list(session.scalars(stmt.order_by(RulEstimateRow.t_s, RulEstimateRow.id).limit(limit + 1)))
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "latest": latest,
        "items": [_rul(r) for r in rows[:limit]],
        "truncated": len(rows) > limit,
    }


FLEET_SORTS = ("status", "tail", "updated", "rul")


def _rul_key(q05: float | None) -> tuple[bool, float]:
    return (q05 is None, q05 if q05 is not None else 0.0)


def fleet_health(session: Session, operator_id: int, sort: str) -> list[dict[str, Any]]:
    rows = session.execute(
        select(
            Aircraft.tail,
            Actuator.actuator_id,
            Actuator.kind,
            Actuator.last_logged_seq,
            Stream.status,
            Stream.last_applied_seq,
            Stream.last_applied_t_s,
            Stream.updated_at,
            Stream.rul_q05_s,
            Stream.rul_q50_s,
            Stream.rul_t_s,
            Actuator.id,
        )
        .join(Actuator, Actuator.aircraft_id == Aircraft.id, isouter=True)
        .join(Stream, Stream.actuator_pk == Actuator.id, isouter=True)
        .where(Aircraft.operator_id == operator_id)
        .order_by(Aircraft.tail, Actuator.actuator_id)
    ).all()
    fault_rows = _fault_rows(session, [r[-1] for r in rows if r[-1] is not None])
    by_tail: dict[str, dict[str, Any]] = {}
    for tail, act_id, kind, logged, status, applied, t_last, updated, q05, q50, rul_t, pk in rows:
        ac = by_tail.setdefault(tail, {"tail": tail, "status": "ok", "updated_at": None, "actuators": []})
        if act_id is None:
            continue
        ac["actuators"].append(
            {
                "actuator_id": act_id,
                "kind": kind,
                "status": status,
                "t_last_s": t_last,
                "last_logged_seq": logged,
                "last_applied_seq": applied,
                "updated_at": updated,
                "rul_q05_s": q05,
                "rul_q50_s": q50,
                "rul_t_s": rul_t,
                "active_faults": sorted(
                    {str(r.detail.get("component")) for r in _open_faults(fault_rows[pk])}
                ),
            }
        )
    for ac in by_tail.values():
        ac["status"] = worst_status([a["status"] for a in ac["actuators"]])
        ups = [a["updated_at"] for a in ac["actuators"] if a["updated_at"] is not None]
        ac["updated_at"] = max(ups) if ups else None
        if sort == "rul":
            ac["actuators"].sort(key=lambda a: (*_rul_key(a["rul_q05_s"]), a["actuator_id"]))
        else:
            ac["actuators"].sort(key=lambda a: (-STATUS_ORDER[a["status"]], a["actuator_id"]))
    out = list(by_tail.values())
    if sort == "rul":
        out.sort(
            key=lambda a: (
                *_rul_key(min((x["rul_q05_s"] for x in a["actuators"] if x["rul_q05_s"] is not None), default=None)),
                a["tail"],
            )
        )
    if sort == "status":
        out.sort(key=lambda a: (-STATUS_ORDER[a["status"]], a["tail"]))
    elif sort == "updated":
        out.sort(key=lambda a: (a["updated_at"] is None, -(a["updated_at"].timestamp() if a["updated_at"] else 0), a["tail"]))
    return out


def count_streams(session: Session) -> int:
    return int(session.scalar(select(func.count()).select_from(Stream)) or 0)


def applied_results(session: Session, actuator_pk: int, seqs: list[int]) -> list[dict[str, Any]]:
    """What applying each of ``seqs`` produced, read back from the store (when the live push
    was missed: another process applied the batch, or a subscriber queue overflowed).

    Same shape as a live result; ``status`` is the estimator's status now, and ``last`` holds the
    last per-sample outputs when they are stored.
    """
    if not seqs:
        return []
    lo, hi = min(seqs), max(seqs)
    wanted = set(seqs)
    batches = {
        b.seq: b
        for b in session.scalars(
            select(TelemetryBatch).where(
                TelemetryBatch.actuator_pk == actuator_pk, TelemetryBatch.seq.between(lo, hi)
            )
        )
        if b.seq in wanted
    }
    ests = list(session.scalars(select(EstimatorState).where(EstimatorState.actuator_pk == actuator_pk)))

    def by_seq(model: Any) -> dict[tuple[int, str], list[Any]]:
        out: dict[tuple[int, str], list[Any]] = {}
        for r in session.scalars(
            select(model).where(model.actuator_pk == actuator_pk, model.seq.between(lo, hi)).order_by(model.id)
        ):
            out.setdefault((r.seq, r.estimator), []).append(r)
        return out

    windows, evs, ruls, outs = (
        by_seq(HealthWindowRow),
        by_seq(EstimatorEventRow),
        by_seq(RulEstimateRow),
        by_seq(SampleOutputRow),
    )
    results = []
    for seq in sorted(wanted & set(batches)):
        b = batches[seq]
        per: dict[str, Any] = {}
        for er in ests:
            key = (seq, er.estimator)
            last: dict[str, float | None] = {}
            for o in outs.get(key, [])[-1:]:
                cols = decode_columns(o.payload)
                last = {k: (float(v[-1]) if np.isfinite(v[-1]) else None) for k, v in cols.items() if k != TIME_COLUMN}
            per[er.estimator] = {
                "status": er.status,
                "reasons": er.reasons,
                "last": last,
                "health": [dict(_window(w)) for w in windows.get(key, [])],
                "events": [_event(e) for e in evs.get(key, [])],
                "rul": [_rul(r) for r in ruls.get(key, [])],
                "diagnosis": None,
            }
        results.append(
            {
                "seq": seq,
                "batch_id": b.batch_id,
                "t_first_s": b.t_first_s,
                "t_last_s": b.t_last_s,
                "n_samples": b.n_samples,
                "status": worst_status([er.status for er in ests]),
                "estimators": per,
            }
        )
    return results
