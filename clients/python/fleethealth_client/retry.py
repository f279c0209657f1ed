"""Bounded retries with exponential backoff for the REST clients."""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime

__all__ = ["RetryPolicy"]


@dataclass(frozen=True)
class RetryPolicy:
    """Bounded retries with exponential backoff and jitter.

    The delay before retry ``k`` (0-based) is ``min(max_backoff_s, backoff_s * 2**k)`` times a
    factor drawn uniformly in [0.5, 1.5), so that many clients failing together do not come back
    together.

    Attributes:
        max_retries: retries after the first attempt (0 disables retries).
        backoff_s: delay before the first retry; doubled for each further one.
        max_backoff_s: cap on one delay.
        retry_statuses: HTTP statuses answered by retrying (every 5xx is retried as well).
        max_retry_after_s: cap on a server's ``Retry-After`` (a 503 while its database is
            unavailable, a 429), which replaces the computed delay when it is given.
    """

    max_retries: int = 4
    backoff_s: float = 0.2
    max_backoff_s: float = 5.0
    retry_statuses: frozenset[int] = field(default_factory=lambda: frozenset({429, 502, 503, 504}))
    max_retry_after_s: float = 60.0

    def delay_s(self, attempt: int, retry_after: str | None = None) -> float:
        """Delay before retry number ``attempt`` (0-based), with +-50 % jitter; the server's
        ``Retry-After`` (seconds or an HTTP date), when given, instead (plus up to 10 % so that
        clients told the same time spread out), capped at :attr:`max_retry_after_s`."""
        advised = parse_retry_after(retry_after)
        if advised is not None:
            return min(self.max_retry_after_s, advised) * (1.0 + 0.1 * random.random())
        base = min(self.max_backoff_s, self.backoff_s * (2.0**attempt))
        return base * (0.5 + random.random())

    def should_retry_status(self, status: int) -> bool:
        """True for the statuses in :attr:`retry_statuses` and every 5xx."""
        return status in self.retry_statuses or status >= 500


def parse_retry_after(value: str | None) -> float | None:
    """Seconds of a ``Retry-After`` header (delta-seconds or an HTTP date); None when absent or
    unreadable."""
    if value is None:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return max(0.0, (when - datetime.now(UTC)).total_seconds())
