"""SQL of operators and API keys."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.models import ApiKey, Operator, utcnow


def operator_by_name(session: Session, name: str) -> Operator | None:
    return session.scalar(select(Operator).where(Operator.name == name))


def add_operator(session: Session, name: str) -> Operator:
    op = Operator(name=name)
    session.add(op)
    session.flush()
    return op


def add_key(session: Session, row: ApiKey) -> ApiKey:
    session.add(row)
    session.flush()
    return row


def key_by_hash(session: Session, key_hash: str) -> ApiKey | None:
    return session.scalar(select(ApiKey).where(ApiKey.key_hash == key_hash))


def active_key_with_operator(session: Session, key_hash: str) -> tuple[ApiKey, str] | None:
    """The unrevoked key with this digest and its operator's name."""
    row = session.execute(
        select(ApiKey, Operator.name)
        .join(Operator, Operator.id == ApiKey.operator_id)
        .where(ApiKey.key_hash == key_hash, ApiKey.revoked_at.is_(None))
    ).first()
    return None if row is None else (row[0], row[1])


def active_key_scopes(session: Session, key_id: int) -> str | None:
    """The scopes of the key with this id, None when it is revoked or gone."""
    return session.scalar(
        select(ApiKey.scopes).where(ApiKey.id == key_id, ApiKey.revoked_at.is_(None))
    )


def set_scopes(session: Session, key_id: int, scopes: str) -> bool:
    key = session.get(ApiKey, key_id)
    if key is None:
        return False
    key.scopes = scopes
    session.flush()
    return True


def keys_with_operators(session: Session) -> list[tuple[ApiKey, str]]:
    rows = session.execute(select(ApiKey, Operator.name).join(Operator).order_by(ApiKey.id))
    return [(k, name) for k, name in rows]


def revoke_key(session: Session, key_id: int) -> bool:
    key = session.get(ApiKey, key_id)
    if key is None:
        return False
    key.revoked_at = utcnow()
    session.flush()
    return True
