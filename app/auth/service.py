"""API keys: random bearer tokens, stored as SHA-256 digests, owned by an operator, with scopes."""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass

from sqlalchemy.orm import Session

from app.auth import repository
from app.cache import TtlCache
from app.db import Database
from app.errors import Forbidden, InvalidConfig, Unauthorized
from app.models import ApiKey, Operator

SCOPES = ("ingest", "read", "admin")
KEY_PREFIX = "fh_"
# Characters of the plaintext key kept in clear, so an operator can tell keys apart.
KEY_PREFIX_SHOWN = 10


@dataclass(frozen=True)
class Principal:
    operator_id: int
    operator: str
    scopes: frozenset[str]
    key_id: int

    def has(self, scope: str) -> bool:
        return scope in self.scopes or "admin" in self.scopes

    def require(self, scope: str) -> None:
        if not self.has(scope):
            raise Forbidden(f"this API key lacks the {scope!r} scope")


def generate_key() -> str:
    return KEY_PREFIX + secrets.token_urlsafe(32)


def hash_key(key: str) -> str:
    # Keys carry 256 random bits, so a plain digest is enough (no password stretching needed).
    return hashlib.sha256(key.encode()).hexdigest()


def parse_scopes(scopes: str | list[str] | tuple[str, ...]) -> list[str]:
    items = [s.strip() for s in (scopes.split(",") if isinstance(scopes, str) else scopes)]
    items = [s for s in items if s]
    bad = [s for s in items if s not in SCOPES]
    if bad or not items:
        raise InvalidConfig(f"scopes must be a non-empty subset of {', '.join(SCOPES)}; got {items}")
    return sorted(set(items))


def get_or_create_operator(session: Session, name: str) -> Operator:
    return repository.operator_by_name(session, name) or repository.add_operator(session, name)


def create_key(
    session: Session, operator: str, scopes: list[str], name: str = "", key: str | None = None
) -> tuple[ApiKey, str]:
    """Create a key (random unless ``key`` is given); returns the row and the plaintext."""
    op = get_or_create_operator(session, operator)
    plaintext = key or generate_key()
    row = ApiKey(
        operator_id=op.id,
        name=name,
        prefix=plaintext[:KEY_PREFIX_SHOWN],
        key_hash=hash_key(plaintext),
        scopes=",".join(parse_scopes(scopes)),
    )
    return repository.add_key(session, row), plaintext


def ensure_key(session: Session, operator: str, key: str, scopes: list[str], name: str) -> None:
    """Make ``key`` valid for ``operator`` (idempotent; used for the bootstrap admin key)."""
    if repository.key_by_hash(session, hash_key(key)) is None:
        create_key(session, operator, scopes, name=name, key=key)


def key_digest(authorization: str | None) -> str:
    """The digest of the bearer key in an ``Authorization`` header (401 when malformed)."""
    if not authorization:
        raise Unauthorized("missing Authorization header: send 'Authorization: Bearer <key>'")
    scheme, _, token = authorization.partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise Unauthorized("Authorization must be 'Bearer <key>'")
    return hash_key(token.strip())


def principal_of(session: Session, digest: str) -> Principal:
    found = repository.active_key_with_operator(session, digest)
    if found is None:
        raise Unauthorized("unknown or revoked API key")
    key, op_name = found
    return Principal(
        operator_id=key.operator_id,
        operator=op_name,
        scopes=frozenset(key.scopes.split(",")),
        key_id=key.id,
    )


def authenticate(session: Session, authorization: str | None) -> Principal:
    return principal_of(session, key_digest(authorization))


class KeyVerifier:
    """Verifies the API key of each request, remembering a valid key's principal for
    ``ttl_s`` seconds (``FLEETHEALTH_AUTH_CACHE_TTL_S``): a key revoked or re-scoped by any
    process stops working, or loses the scope, within that time. Unknown and revoked keys are
    never remembered (each such request reads the database)."""

    def __init__(self, db: Database, ttl_s: float, max_entries: int) -> None:
        self.db = db
        self.cache: TtlCache[str, Principal] = TtlCache(ttl_s, max_entries)

    def cached(self, authorization: str | None) -> Principal | None:
        """The remembered principal of this header, without touching the database."""
        return self.cache.get(key_digest(authorization))

    def verify(self, authorization: str | None) -> Principal:
        """The header's principal, from the database unless remembered (blocking)."""
        digest = key_digest(authorization)
        found = self.cache.get(digest)
        if found is not None:
            return found
        generation = self.cache.generation()
        with self.db.read() as s:
            principal = principal_of(s, digest)
        self.cache.put(digest, principal, generation)
        return principal


def recheck(session: Session, principal: Principal, scope: str) -> None:
    """Raise unless the principal's key is still active and still carries ``scope`` (an open
    WebSocket asks this periodically: a revocation or a scope change in any process ends it)."""
    scopes = repository.active_key_scopes(session, principal.key_id)
    if scopes is None:
        raise Unauthorized("the API key was revoked")
    Principal(principal.operator_id, principal.operator, frozenset(scopes.split(",")), principal.key_id).require(scope)


def set_scopes(session: Session, key_id: int, scopes: list[str]) -> bool:
    """Replace a key's scopes; open connections that lose the scope they need are closed."""
    return repository.set_scopes(session, key_id, ",".join(parse_scopes(scopes)))


def list_keys(session: Session) -> list[tuple[ApiKey, str]]:
    return repository.keys_with_operators(session)


def revoke_key(session: Session, key_id: int) -> bool:
    return repository.revoke_key(session, key_id)
