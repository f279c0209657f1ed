"""Webhook rules: which URLs an operator may deliver to, subscriptions, the outbox rows an
event queues, the signature, and what an attempt's outcome does to its delivery (retry with
exponential back-off, give up after the last attempt).

Signature (docs/api.md, "Webhooks"): ``X-Fleethealth-Signature: v1=<hex>`` where ``<hex>`` is
HMAC-SHA256 keyed by the subscription's secret over ``<timestamp>.<body>``, and
``X-Fleethealth-Timestamp: <unix seconds>`` is the time of the attempt; a receiver refuses a
timestamp too far from its clock (a replayed request) and a signature that does not match.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import timedelta
from typing import Any
from urllib.parse import urlsplit

import orjson
from sqlalchemy.orm import Session

from app.auth.service import get_or_create_operator
from app.errors import DomainError, InvalidConfig, NotFound
from app.models import WebhookAttempt, WebhookDelivery, WebhookSubscription, utcnow
from app.webhooks import repository

SIGNATURE_HEADER = "X-Fleethealth-Signature"
TIMESTAMP_HEADER = "X-Fleethealth-Timestamp"
SIGNATURE_VERSION = "v1"
SECRET_PREFIX = "whsec_"
TEST_EVENT_TYPE = "webhook_test"
DELIVERY_STATUSES = ("pending", "delivered", "failed")
DEFAULT_PORTS = {"http": 80, "https": 443}


class WebhookTargetRefused(DomainError):
    """The URL is outside what the service's administrator allowed for the operator."""

    status_code = 422


# ----------------------------------------------------------------------------- targets
@dataclass(frozen=True)
class Target:
    scheme: str
    host: str
    port: int
    path: str

    def __str__(self) -> str:
        default = DEFAULT_PORTS[self.scheme] == self.port
        return f"{self.scheme}://{self.host}{'' if default else f':{self.port}'}{self.path}"


def parse_target(url: str, *, prefix: bool) -> Target:
    """An http(s) URL split into what matching compares. Refuses credentials in the URL, and
    (for a prefix) a query or fragment."""
    try:
        parts = urlsplit(url.strip())
        port = parts.port
    except ValueError as exc:
        raise InvalidConfig(f"invalid URL {url!r}: {exc}") from None
    scheme = parts.scheme.lower()
    if scheme not in DEFAULT_PORTS:
        raise InvalidConfig(f"URL {url!r}: the scheme must be http or https")
    if not parts.hostname:
        raise InvalidConfig(f"URL {url!r} has no host")
    if parts.username is not None or parts.password is not None:
        raise InvalidConfig(f"URL {url!r}: credentials in the URL are not accepted")
    if prefix and (parts.query or parts.fragment):
        raise InvalidConfig(f"prefix {url!r}: no query or fragment")
    return Target(
        scheme, parts.hostname.lower().rstrip("."), port or DEFAULT_PORTS[scheme], parts.path or "/"
    )


def covers(prefix: Target, url: Target) -> bool:
    """Whether ``url`` is within ``prefix``: same scheme, host and port, and a path equal to
    the prefix's or below it at a ``/`` boundary (``/hooks`` covers ``/hooks/a``, not
    ``/hooksmith``)."""
    if (prefix.scheme, prefix.host, prefix.port) != (url.scheme, url.host, url.port):
        return False
    base = prefix.path
    return url.path == base or url.path.startswith(base if base.endswith("/") else base + "/")


def url_allowed(url: str, prefixes: Sequence[str]) -> bool:
    try:
        target = parse_target(url, prefix=False)
    except InvalidConfig:
        return False
    return any(covers(parse_target(p, prefix=True), target) for p in prefixes)


def _operator(session: Session, operator: str) -> int:
    op = repository.operator_id(session, operator)
    if op is None:
        raise NotFound(f"operator {operator!r} not found")
    return op


def allow_target(session: Session, operator: str, prefix: str) -> str:
    """Register a URL prefix the operator's webhooks may deliver to; returns it normalized."""
    norm = str(parse_target(prefix, prefix=True))
    repository.add_target(session, get_or_create_operator(session, operator).id, norm)
    return norm


def disallow_target(session: Session, operator: str, prefix: str) -> bool:
    """Forget a prefix; deliveries to URLs it covered fail from now on."""
    norm = str(parse_target(prefix, prefix=True))
    return repository.remove_target(session, _operator(session, operator), norm)


def targets(session: Session, operator_id: int) -> list[str]:
    return repository.target_prefixes(session, operator_id)


def targets_by_name(session: Session, operator: str) -> list[str]:
    return repository.target_prefixes(session, _operator(session, operator))


# ----------------------------------------------------------------------------- subscriptions
def subscription_public(row: WebhookSubscription) -> dict[str, Any]:
    return {
        "id": row.id,
        "url": row.url,
        "event_types": list(row.event_types),
        "tails": None if row.tails is None else list(row.tails),
        "description": row.description,
        "active": row.active,
        "created_at": row.created_at,
    }


def create_subscription(
    session: Session,
    operator_id: int,
    url: str,
    event_types: list[str],
    tails: list[str] | None,
    secret: str | None,
    description: str | None,
    known_types: frozenset[str],
) -> tuple[WebhookSubscription, str]:
    """A subscription to the operator's events (every logged type when ``event_types`` is
    empty); returns it and its signing secret (generated unless given)."""
    bad = sorted(set(event_types) - known_types)
    if bad:
        raise InvalidConfig(f"unknown event types {bad}; known: {sorted(known_types)}")
    parse_target(url, prefix=False)
    allowed = repository.target_prefixes(session, operator_id)
    if not url_allowed(url, allowed):
        raise WebhookTargetRefused(
            f"URL {url!r} is not within the targets allowed for this operator "
            f"({', '.join(allowed) if allowed else 'none registered'}); the service's "
            "administrator adds them with `fleethealth webhooks allow`"
        )
    key = secret or SECRET_PREFIX + secrets.token_urlsafe(32)
    row = repository.add_subscription(
        session,
        WebhookSubscription(
            operator_id=operator_id,
            url=url.strip(),
            event_types=sorted(set(event_types)),
            tails=sorted(set(tails)) if tails else None,
            secret=key,
            description=description,
            active=True,
        ),
    )
    return row, key


def get_subscription(session: Session, operator_id: int, sub_id: int) -> WebhookSubscription:
    row = repository.subscription_of(session, operator_id, sub_id)
    if row is None:
        raise NotFound(f"webhook {sub_id} not found")
    return row


def list_subscriptions(session: Session, operator_id: int) -> list[WebhookSubscription]:
    return repository.subscriptions(session, operator_id)


def delete_subscription(session: Session, operator_id: int, sub_id: int) -> None:
    """Remove a subscription with its outbox and log (pending deliveries are dropped)."""
    repository.delete_subscription(session, get_subscription(session, operator_id, sub_id))


# ----------------------------------------------------------------------------- outbox
def _body(sub_id: int, event: dict[str, Any]) -> str:
    return orjson.dumps(
        {"subscription_id": sub_id, "event": event}, option=orjson.OPT_UTC_Z
    ).decode()


def _matches(sub: WebhookSubscription, event: dict[str, Any]) -> bool:
    return (not sub.event_types or event["type"] in sub.event_types) and (
        sub.tails is None or event["tail"] in sub.tails
    )


def enqueue_events(session: Session, operator_id: int, events: Sequence[dict[str, Any]]) -> int:
    """Queue a delivery of each event to each matching subscription, in the caller's
    transaction (the one that logs the events). The idempotency key names the event and the
    subscription, so a receiver can drop a redelivery."""
    if not events:
        return 0
    subs = repository.subscriptions(session, operator_id, active_only=True)
    now = utcnow()
    rows = [
        {
            "subscription_id": sub.id,
            "operator_id": operator_id,
            "event_id": ev["id"],
            "event_type": ev["type"],
            "idempotency_key": f"fh-{operator_id}-{ev['id']}-{sub.id}",
            "body": _body(sub.id, ev),
            "status": "pending",
            "attempts": 0,
            "next_attempt_at": now,
            "created_at": now,
        }
        for ev in events
        for sub in subs
        if _matches(sub, ev)
    ]
    repository.insert_deliveries(session, rows)
    return len(rows)


def test_fire(session: Session, operator_id: int, sub_id: int) -> WebhookDelivery:
    """Queue a ``webhook_test`` delivery to one subscription, through the same outbox."""
    sub = get_subscription(session, operator_id, sub_id)
    now = utcnow()
    event = {"id": None, "type": TEST_EVENT_TYPE, "time": now, "detail": "test delivery"}
    return repository.add_delivery(
        session,
        WebhookDelivery(
            subscription_id=sub.id,
            operator_id=operator_id,
            event_id=None,
            event_type=TEST_EVENT_TYPE,
            idempotency_key=f"fh-test-{uuid.uuid4().hex}",
            body=_body(sub.id, event),
            status="pending",
            attempts=0,
            next_attempt_at=now,
            created_at=now,
        ),
    )


def sign(secret: str, timestamp: int, body: bytes) -> str:
    """The signature header's value: ``v1=`` + hex HMAC-SHA256 over ``<timestamp>.<body>``."""
    mac = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256)
    return f"{SIGNATURE_VERSION}={mac.hexdigest()}"


def backoff_s(attempts: int, base_s: float, max_s: float) -> float:
    """Wait before the next attempt after ``attempts`` failed ones: base, 2 base, 4 base, ...
    capped at ``max_s``."""
    return float(min(base_s * 2 ** (attempts - 1), max_s))


@dataclass(frozen=True)
class Outcome:
    """What one attempt got: an HTTP status, or an error before any."""

    status_code: int | None
    error: str | None
    duration_ms: float

    @property
    def ok(self) -> bool:
        return self.status_code is not None and 200 <= self.status_code < 300


def record_attempt(
    session: Session,
    delivery_id: int,
    outcome: Outcome,
    *,
    max_attempts: int,
    base_s: float,
    max_s: float,
    final: bool = False,
) -> str:
    """Log an attempt and move the delivery on: delivered, retried after the back-off, or
    failed after ``max_attempts`` (or at once when ``final``). Returns its new status."""
    row = repository.delivery(session, delivery_id)
    if row is None:  # the subscription was deleted meanwhile
        return "gone"
    now = utcnow()
    row.attempts += 1
    row.last_attempt_at = now
    row.last_status_code = outcome.status_code
    row.last_error = None if outcome.error is None else outcome.error[:500]
    repository.add_attempt(
        session,
        WebhookAttempt(
            delivery_id=row.id,
            attempt=row.attempts,
            at=now,
            status_code=outcome.status_code,
            error=row.last_error,
            duration_ms=outcome.duration_ms,
        ),
    )
    if outcome.ok:
        row.status = "delivered"
        row.delivered_at = now
    elif final or row.attempts >= max_attempts:
        row.status = "failed"
    else:
        row.next_attempt_at = now + timedelta(seconds=backoff_s(row.attempts, base_s, max_s))
    session.flush()
    return row.status


def delivery_public(row: WebhookDelivery, attempts: list[WebhookAttempt]) -> dict[str, Any]:
    return {
        "id": row.id,
        "event_id": row.event_id,
        "event_type": row.event_type,
        "idempotency_key": row.idempotency_key,
        "status": row.status,
        "attempts": row.attempts,
        "next_attempt_at": row.next_attempt_at if row.status == "pending" else None,
        "last_attempt_at": row.last_attempt_at,
        "last_status_code": row.last_status_code,
        "last_error": row.last_error,
        "delivered_at": row.delivered_at,
        "created_at": row.created_at,
        "log": [
            {
                "attempt": a.attempt,
                "at": a.at,
                "status_code": a.status_code,
                "error": a.error,
                "duration_ms": a.duration_ms,
            }
            for a in attempts
        ],
    }


def deliveries(
    session: Session,
    operator_id: int,
    sub_id: int,
    status: str | None,
    before: int | None,
    limit: int,
) -> dict[str, Any]:
    """The delivery log of a subscription, newest first, with each attempt."""
    sub = get_subscription(session, operator_id, sub_id)
    rows = repository.deliveries_of(session, sub.id, status, before, limit + 1)
    more = len(rows) > limit
    rows = rows[:limit]
    log = repository.attempts_of(session, [r.id for r in rows])
    return {
        "items": [delivery_public(r, log[r.id]) for r in rows],
        "next_before": rows[-1].id if more else None,
    }
