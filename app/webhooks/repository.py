"""SQL of webhooks: allowed targets, subscriptions, the outbox (claimed with ``FOR UPDATE
SKIP LOCKED`` on PostgreSQL) and the attempts log."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import delete, insert, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.models import (
    Operator,
    WebhookAttempt,
    WebhookDelivery,
    WebhookSubscription,
    WebhookTarget,
)


# ----------------------------------------------------------------------------- targets
def operator_id(session: Session, name: str) -> int | None:
    return session.scalar(select(Operator.id).where(Operator.name == name))


def target_prefixes(session: Session, operator_id: int) -> list[str]:
    return list(
        session.scalars(
            select(WebhookTarget.prefix)
            .where(WebhookTarget.operator_id == operator_id)
            .order_by(WebhookTarget.prefix)
        )
    )


def add_target(session: Session, operator_id: int, prefix: str) -> bool:
    """False when the prefix was registered already."""
    try:
        with session.begin_nested():
            session.add(WebhookTarget(operator_id=operator_id, prefix=prefix))
            session.flush()
    except IntegrityError:
        return False
    return True


def remove_target(session: Session, operator_id: int, prefix: str) -> bool:
    res = session.execute(
        delete(WebhookTarget).where(
            WebhookTarget.operator_id == operator_id, WebhookTarget.prefix == prefix
        )
    )
    return bool(getattr(res, "rowcount", 0))


# ----------------------------------------------------------------------------- subscriptions
def add_subscription(session: Session, row: WebhookSubscription) -> WebhookSubscription:
    session.add(row)
    session.flush()
    return row


def subscription_of(session: Session, operator_id: int, sub_id: int) -> WebhookSubscription | None:
    return session.scalar(
        select(WebhookSubscription).where(
            WebhookSubscription.id == sub_id, WebhookSubscription.operator_id == operator_id
        )
    )


def subscriptions(
    session: Session, operator_id: int, *, active_only: bool = False
) -> list[WebhookSubscription]:
    stmt = select(WebhookSubscription).where(WebhookSubscription.operator_id == operator_id)
    if active_only:
        stmt = stmt.where(WebhookSubscription.active.is_(True))
    return list(session.scalars(stmt.order_by(WebhookSubscription.id)))


def delete_subscription(session: Session, row: WebhookSubscription) -> None:
    session.delete(row)
    session.flush()


# ----------------------------------------------------------------------------- outbox
def insert_deliveries(session: Session, rows: Sequence[dict[str, Any]]) -> None:
    if rows:
        session.execute(insert(WebhookDelivery), list(rows))


def add_delivery(session: Session, row: WebhookDelivery) -> WebhookDelivery:
    session.add(row)
    session.flush()
    return row


@dataclass(frozen=True)
class DueDelivery:
    """What one attempt needs, detached from the session."""

    id: int
    operator_id: int
    subscription_id: int
    url: str
    secret: str
    active: bool
    event_type: str
    idempotency_key: str
    body: str
    attempts: int


def due(session: Session, now: datetime, limit: int, *, lock: bool) -> list[DueDelivery]:
    """Pending deliveries whose next attempt is due, oldest first. With ``lock`` (PostgreSQL)
    they stay locked for this transaction and rows another process holds are skipped."""
    stmt = (
        select(WebhookDelivery, WebhookSubscription)
        .join(WebhookSubscription, WebhookSubscription.id == WebhookDelivery.subscription_id)
        .where(WebhookDelivery.status == "pending", WebhookDelivery.next_attempt_at <= now)
        .order_by(WebhookDelivery.next_attempt_at, WebhookDelivery.id)
        .limit(limit)
    )
    if lock:
        stmt = stmt.with_for_update(skip_locked=True, of=WebhookDelivery)
    return [
        DueDelivery(
            id=d.id,
            operator_id=d.operator_id,
            subscription_id=d.subscription_id,
            url=sub.url,
            secret=sub.secret,
            active=sub.active,
            event_type=d.event_type,
            idempotency_key=d.idempotency_key,
            body=d.body,
            attempts=d.attempts,
        )
        for d, sub in session.execute(stmt)
    ]


def delivery(session: Session, delivery_id: int) -> WebhookDelivery | None:
    return session.get(WebhookDelivery, delivery_id)


def add_attempt(session: Session, row: WebhookAttempt) -> None:
    session.add(row)
    session.flush()


def deliveries_of(
    session: Session, sub_id: int, status: str | None, before: int | None, limit: int
) -> list[WebhookDelivery]:
    """Newest first, ids below ``before`` when given."""
    stmt = select(WebhookDelivery).where(WebhookDelivery.subscription_id == sub_id)
    if status is not None:
        stmt = stmt.where(WebhookDelivery.status == status)
    if before is not None:
        stmt = stmt.where(WebhookDelivery.id < before)
    return list(session.scalars(stmt.order_by(WebhookDelivery.id.desc()).limit(limit)))


def attempts_of(session: Session, delivery_ids: Sequence[int]) -> dict[int, list[WebhookAttempt]]:
    out: dict[int, list[WebhookAttempt]] = {i: [] for i in delivery_ids}
    if delivery_ids:
        for a in session.scalars(
            select(WebhookAttempt)
            .where(WebhookAttempt.delivery_id.in_(list(delivery_ids)))
            .order_by(WebhookAttempt.delivery_id, WebhookAttempt.attempt)
        ):
            out[a.delivery_id].append(a)
    return out
