"""The statuses every estimator and actuator reports, as the API names them.

The members are ``estimators.base.STATUSES`` (a test checks they stay equal); their severity
order is ``estimators.base.STATUS_ORDER``. As an enum, the OpenAPI lists them in one schema.
"""

from __future__ import annotations

from enum import StrEnum


class HealthStatus(StrEnum):
    """``learning`` (no model yet, or not converged), ``ok``, ``watch``, ``alert``, ``unknown``
    (the estimator's own consistency checks reject its outputs; the reasons say why) and
    ``failed`` (past the failure threshold, or the stream cannot be applied; the reason says
    which)."""

    LEARNING = "learning"
    OK = "ok"
    WATCH = "watch"
    ALERT = "alert"
    UNKNOWN = "unknown"
    FAILED = "failed"
