"""Bounded retries with exponential backoff for the REST clients."""

from __future__ import annotations

import random
from dataclasses import dataclass, field

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
    """

    max_retries: int = 4
    backoff_s: float = 0.2
    max_backoff_s: float = 5.0
    retry_statuses: frozenset[int] = field(default_factory=lambda: frozenset({429, 502, 503, 504}))

    def delay_s(self, attempt: int) -> float:
        """Delay before retry number ``attempt`` (0-based), with +-50 % jitter."""
        base = min(self.max_backoff_s, self.backoff_s * (2.0**attempt))
        return base * (0.5 + random.random())

    def should_retry_status(self, status: int) -> bool:
        """True for the statuses in :attr:`retry_statuses` and every 5xx."""
        return status in self.retry_statuses or status >= 500
