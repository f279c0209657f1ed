"""The telemetry log read back: raw samples by time range, a page at a time or exported, and
usage counters (operating hours, cycles) at a point of the stream.

Read-only; the log's append path is :mod:`app.telemetry.service`.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pyarrow as pa
from sqlalchemy.orm import Session

from app import series
from app.codec import decode_columns
from app.ingest import TIME_COLUMN
from app.models import Actuator
from app.pagination import Order
from app.telemetry import repository

#: At most this many dropped batches are named per page.
MAX_DROPPED_LISTED = 1000


def _blocks(
    session: Session, act: Actuator, from_s: float | None, to_s: float | None, order: Order,
    dropped: list[dict[str, Any]] | None = None,
) -> Iterator[dict[str, np.ndarray]]:
    for row in repository.logged_blocks(session, act.id, from_s, to_s, order=order):
        if row.payload is None:
            if dropped is not None and len(dropped) < MAX_DROPPED_LISTED:
                dropped.append({"seq": row.seq, "t_first_s": row.t_first_s, "t_last_s": row.t_last_s})
            continue
        cols = decode_columns(row.payload)
        yield {TIME_COLUMN: cols[TIME_COLUMN], **{c: cols[c] for c in act.channels if c in cols}}


def read(
    session: Session,
    act: Actuator,
    from_s: float | None,
    to_s: float | None,
    after_t: float | None,
    order: Order,
    max_samples: int,
) -> tuple[dict[str, Any], float | None]:
    """A page of raw samples (the channels as logged; a missing sample is None) and the time to
    continue after (None on the last page). Batches whose samples retention has dropped
    (``FLEETHEALTH_LOG_RETENTION_S``) are listed in ``dropped`` instead (the first
    :data:`MAX_DROPPED_LISTED` met)."""
    dropped: list[dict[str, Any]] = []
    cols, last = series.page(_blocks(session, act, from_s, to_s, order, dropped), from_s, to_s, after_t, order, max_samples)
    t = cols.pop(TIME_COLUMN)
    return {
        "t_s": t.tolist(),
        "channels": {c: [None if not np.isfinite(x) else x for x in cols[c].tolist()] if c in cols else [] for c in act.channels},
        "dropped": dropped,
    }, last


def export_blocks(
    session: Session, act: Actuator, from_s: float | None, to_s: float | None
) -> tuple[pa.Schema, Iterator[dict[str, np.ndarray]]]:
    """The export schema (``t`` and the actuator's channels) and the log's blocks in [from_s,
    to_s] in stream order (batches dropped by retention are skipped)."""
    schema = series.schema_of([TIME_COLUMN, *act.channels])

    def blocks() -> Iterator[dict[str, np.ndarray]]:
        for cols in _blocks(session, act, from_s, to_s, "asc"):
            yield series.clip(cols, from_s, to_s, None, "asc")

    return schema, blocks()


def first_counter_point(
    session: Session, act: Actuator, from_seq: int, counter: str
) -> tuple[float, float] | None:
    """``(t_s, value)`` of the first finite sample of a counter channel from batch ``from_seq``
    on (in the first batch the log still holds)."""
    row = repository.first_kept_batch(session, act.id, from_seq, act.last_logged_seq)
    if row is None or row.payload is None:
        return None
    cols = decode_columns(row.payload)
    t, c = cols[TIME_COLUMN], cols.get(counter)
    if c is None:
        return None
    ok = np.flatnonzero(np.isfinite(c))
    return (float(t[ok[0]]), float(c[ok[0]])) if len(ok) else None


def counter_point_at(
    session: Session, act: Actuator, seq: int, t_s: float, counter: str
) -> tuple[float, float] | None:
    """``(t_s, value)`` of a counter channel's last finite sample at or before ``t_s`` in batch
    ``seq``; None when the log no longer holds that batch's samples."""
    row = repository.batch_at(session, act.id, seq)
    if row is None or row.payload is None:
        return None
    cols = decode_columns(row.payload)
    t, c = cols[TIME_COLUMN], cols.get(counter)
    if c is None:
        return None
    ok = np.flatnonzero(np.isfinite(c) & (t <= t_s))
    return (float(t[ok[-1]]), float(c[ok[-1]])) if len(ok) else None
