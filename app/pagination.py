"""Cursor pagination shared by every list endpoint.

A page is read by keyset: the rows after the last row of the previous page in the list's sort
key (never an offset, so rows added meanwhile neither repeat nor skip an item of a stable
list). The cursor is opaque to clients: a URL-safe base64 of the list's name, the order and the
last key. Lists are newest first unless ``order=asc``.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Sequence
from typing import Annotated, Any, Literal

import orjson
from fastapi import Query
from sqlalchemy import ColumnElement, and_, or_

from app.errors import InvalidCursor

Order = Literal["asc", "desc"]

OrderQuery = Annotated[
    Order, Query(description="`desc` (default): newest first; `asc`: oldest first")
]
CursorQuery = Annotated[
    str | None,
    Query(max_length=1024, description="`next_cursor` of the previous page (same order and filters)"),
]
CURSOR_DOC = "Opaque cursor of the next page (pass it as `cursor`); null on the last page"


def encode_cursor(scope: str, order: Order, key: Sequence[Any]) -> str:
    raw = orjson.dumps({"s": scope, "o": order, "k": list(key)})
    return base64.urlsafe_b64encode(raw).rstrip(b"=").decode("ascii")


def decode_cursor(cursor: str | None, scope: str, order: Order, arity: int) -> list[Any] | None:
    """The last key of the previous page; None for the first page.

    Raises:
        InvalidCursor: not a cursor of this list (``scope``), or issued for the other order.
    """
    if not cursor:  # absent, or empty (``?cursor=``): the first page
        return None
    try:
        doc = orjson.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
    except (binascii.Error, ValueError):
        raise InvalidCursor("cursor is not one this service issued") from None
    if not isinstance(doc, dict) or doc.get("s") != scope:
        raise InvalidCursor("cursor belongs to another list")
    if doc.get("o") != order:
        raise InvalidCursor(f"cursor was issued for order={doc.get('o')}, not order={order}")
    key = doc.get("k")
    if not isinstance(key, list) or len(key) != arity or not all(
        isinstance(v, int | float | str) and not isinstance(v, bool) for v in key
    ):
        raise InvalidCursor("cursor is damaged")
    return key


def after_key(columns: Sequence[Any], key: Sequence[Any], order: Order) -> ColumnElement[bool]:
    """The clause selecting rows strictly after ``key`` in the order of ``columns``
    (lexicographic, ascending or descending)."""
    clauses = []
    for i, col in enumerate(columns):
        head = [columns[j] == key[j] for j in range(i)]
        clauses.append(and_(*head, col > key[i] if order == "asc" else col < key[i]))
    return or_(*clauses)


def order_by(columns: Sequence[Any], order: Order) -> list[Any]:
    return [c.asc() if order == "asc" else c.desc() for c in columns]


def page(rows: Sequence[Any], limit: int) -> tuple[list[Any], bool]:
    """The first ``limit`` of ``rows`` (read with ``limit + 1``) and whether more follow."""
    return list(rows[:limit]), len(rows) > limit
