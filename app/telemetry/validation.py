"""Input validation at the edge: values, times and identifiers the service refuses.

One place for the checks every way into the telemetry log shares (REST batches and streamed
frames go through :func:`check_batch` from :mod:`app.telemetry.service`), and for the
identifier rule every route shares (:data:`Identifier` in schemas, :class:`ControlCharGuard`
for paths and query strings).

Why these bounds:

* Sample values and times are stored and processed as float64. An integer above 2**53 cannot be
  represented exactly (``2**53 + 1`` silently becomes ``2**53``), so such integers are refused
  rather than rounded; magnitudes beyond ``max_abs_value`` are not physical actuator readings
  and would overflow the estimators' squared residuals long before float64's own limit.
* Times: a batch far in the future is not harmless. The log only accepts batches after the
  stream's last sample, so one batch at ``t = 1e300`` would make every later batch stale. Times
  are bounded by ``max_time_s`` in absolute value, and times that look like epoch seconds
  (``t >= EPOCH_LIKE_S``) must not lie more than ``max_future_s`` after the server's clock. Epoch
  values in milliseconds, microseconds or nanoseconds are named as such in the refusal.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Annotated, Any
from urllib.parse import unquote_to_bytes

import numpy as np
import orjson
import pyarrow as pa
from pydantic import AfterValidator, Field
from starlette.types import ASGIApp, Receive, Scope, Send

from app.errors import InvalidBatch
from app.ingest import FLOAT64_EXACT_INT, SMALL_CHECK_MAX, ParsedBatch

#: Times at or above this (2001-09-09 as epoch seconds) are read as absolute epoch seconds.
EPOCH_LIKE_S = 1e9
#: Scales at which an epoch time looks like ms / us / ns instead of s (epoch s now ~1.8e9).
_SCALES = ((1e17, "nanoseconds", 1e9), (1e14, "microseconds", 1e6), (1e11, "milliseconds", 1e3))

_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


@dataclass(frozen=True)
class BatchLimits:
    """Bounds on a batch's size, values and times (settings ``FLEETHEALTH_MAX_BATCH_DECODED_BYTES``,
    ``FLEETHEALTH_MAX_ABS_VALUE``, ``FLEETHEALTH_MAX_TIME_S``, ``FLEETHEALTH_MAX_FUTURE_S``)."""

    max_abs_value: float = 1e12
    max_time_s: float = 1e10
    max_future_s: float = 86_400.0
    max_decoded_bytes: int = 1024 * 1024 * 1024

    @classmethod
    def from_settings(cls, settings: Any) -> BatchLimits:
        return cls(
            max_abs_value=float(settings.max_abs_value),
            max_time_s=float(settings.max_time_s),
            max_future_s=float(settings.max_future_s),
            max_decoded_bytes=int(settings.max_batch_decoded_bytes),
        )


DEFAULT_LIMITS = BatchLimits()


@contextmanager
def decoding_guard() -> Iterator[None]:
    """Turn a decoder's numeric conversion failure into :class:`InvalidBatch`.

    Casting an integer column to float64 refuses integers above 2**53 (``ArrowInvalid``: not
    exactly representable); an integer beyond 64 bits does not fit any column
    (``OverflowError``). Both are the client's input, not a server fault.
    """
    try:
        yield
    except (pa.ArrowInvalid, pa.ArrowTypeError, OverflowError) as exc:
        raise InvalidBatch(
            f"a value cannot be held exactly as float64 (integers must lie within +-2**53 = "
            f"{FLOAT64_EXACT_INT}): {exc}"
        ) from None


def _scale_hint(t_s: float) -> str:
    for bound, unit, factor in _SCALES:
        if abs(t_s) >= bound:
            return f"; this looks like epoch {unit}: times are seconds (divide by {factor:g})"
    return ""


def _bounds(values: list[float]) -> tuple[float, float]:
    """``(min, max)`` of non-empty ``values``; NaN for either when a NaN gets in the way (the
    comparisons against it are then False, so the caller goes on to the full check)."""
    return min(values), max(values)


def check_times(t_s: np.ndarray, limits: BatchLimits, now_s: float) -> None:
    """Refuse times outside ``[-max_time_s, max_time_s]`` and epoch times too far ahead of
    ``now_s`` (server clock, epoch seconds). ``t_s`` is finite (checked by the parser)."""
    if not t_s.size:
        return
    if t_s.size <= SMALL_CHECK_MAX:
        lo, hi = _bounds(t_s.tolist())
        if -limits.max_time_s <= lo and hi <= min(limits.max_time_s, now_s + limits.max_future_s):
            return  # within both bounds: nothing below can refuse it
    mags = np.abs(t_s)
    if mags.max() > limits.max_time_s:
        k = int(np.argmax(mags > limits.max_time_s))
        raise InvalidBatch(
            f"t[{k}]={float(t_s[k])!r} is outside the accepted range of +-{limits.max_time_s:g} s "
            f"(FLEETHEALTH_MAX_TIME_S){_scale_hint(float(t_s[k]))}"
        )
    latest = now_s + limits.max_future_s
    if t_s.max() > latest and (ahead := (t_s >= EPOCH_LIKE_S) & (t_s > latest)).any():
        k = int(np.argmax(ahead))
        raise InvalidBatch(
            f"t[{k}]={float(t_s[k])!r} reads as epoch seconds {float(t_s[k]) - now_s:.0f} s after the "
            f"server's clock; at most {limits.max_future_s:g} s ahead is accepted "
            "(FLEETHEALTH_MAX_FUTURE_S)"
        )


def check_values(channels: dict[str, np.ndarray], limits: BatchLimits) -> None:
    """Refuse channel values above ``max_abs_value`` in magnitude (NaN = missing, allowed; an
    infinite value is above any bound). A NaN compares False, without a floating-point warning
    (no ``np.errstate`` needed: entering one costs more than the check of a one-sample batch)."""
    bound = min(limits.max_abs_value, float(FLOAT64_EXACT_INT))
    for name, col in channels.items():
        if col.size <= SMALL_CHECK_MAX:
            lo, hi = _bounds(col.tolist())
            if -bound <= lo and hi <= bound:
                continue
        over = np.abs(col) > bound
        if over.any():
            k = int(np.argmax(over))
            raise InvalidBatch(
                f"channel {name!r} value {float(col[k])!r} at index {k} exceeds the accepted "
                f"magnitude {bound:g} (FLEETHEALTH_MAX_ABS_VALUE)"
            )


def check_batch(batch: ParsedBatch, limits: BatchLimits = DEFAULT_LIMITS, now_s: float | None = None) -> None:
    """All value checks on a parsed batch, before it is logged.

    Raises:
        InvalidBatch: naming the field, index and the setting that bounds it.
    """
    if _CONTROL.search(batch.batch_id):
        raise InvalidBatch("batch_id must not hold NUL or other control characters")
    check_times(batch.t_s, limits, time.time() if now_s is None else now_s)
    check_values(batch.channels, limits)


# ----------------------------------------------------------------------------- identifiers
def no_control_chars(value: str) -> str:
    """Identifiers and labels hold no NUL or other C0/DEL control characters: PostgreSQL text
    cannot store NUL, and the other backends must refuse what it refuses."""
    if _CONTROL.search(value):
        raise ValueError("must not contain NUL or other control characters")
    return value


#: A string that holds no control characters (names, ids, descriptions).
#: The same rule as a JSON Schema pattern, for the OpenAPI (bodies, paths and queries).
NO_CONTROL_PATTERN = r"^[^\x00-\x1f\x7f]*$"
Identifier = Annotated[
    str, AfterValidator(no_control_chars), Field(json_schema_extra={"pattern": NO_CONTROL_PATTERN})
]

_ENCODED_CONTROL = re.compile(rb"%(?:[01][0-9a-fA-F]|7[fF])")
_RAW_CONTROL = re.compile(rb"[\x00-\x1f\x7f]")


class ControlCharGuard:
    """ASGI middleware: a path or query string with a control character (raw or %-encoded) is
    refused before routing, with 422 ``ValidationError`` on HTTP and close code 1008 (policy) on
    a WebSocket. Every path and query parameter is an identifier or a plain value, none of which
    may hold one."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket") and self._bad(scope):
            if scope["type"] == "http":
                body = orjson.dumps({
                    "error": "ValidationError",
                    "detail": [{"loc": ["path"], "type": "control_characters",
                                "msg": "path and query must not contain NUL or other control characters"}],
                })
                await send({
                    "type": "http.response.start",
                    "status": 422,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode())],
                })
                await send({"type": "http.response.body", "body": body})
            else:
                await receive()  # websocket.connect
                await send({"type": "websocket.close", "code": 1008,
                            "reason": "path or query holds a control character"})
            return
        await self.app(scope, receive, send)

    @staticmethod
    def _bad(scope: Scope) -> bool:
        path = scope.get("path", "")
        raw = scope.get("raw_path") or path.encode("utf-8", "surrogateescape")
        query = scope.get("query_string", b"")
        if _RAW_CONTROL.search(path.encode("utf-8", "surrogateescape")):
            return True
        for part in (raw, query):
            if _RAW_CONTROL.search(part) or _ENCODED_CONTROL.search(part):
                return True
        # The query as the route's parameters will read it (%-decoded, '+' as space).
        return bool(_RAW_CONTROL.search(unquote_to_bytes(query.replace(b"+", b" "))))
