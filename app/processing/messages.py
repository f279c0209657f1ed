"""The one result message: what applying a logged batch produced.

The processor builds it from the estimators' outputs and pushes it to WebSocket subscribers;
the read-back (a push missed: another process applied the batch, or a queue overflowed) builds
the same type from the stored rows. The row projections below serve both, and the REST read
side, so a health window, an event or a RUL prognosis has one public shape.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.ingest import client_seq_of
from estimators.base import FloatArray

HEALTH_KEYS = ("estimator", "seq", "t_start_s", "t_end_s", "n_samples", "indicators", "status", "reasons")
EVENT_KEYS = ("estimator", "seq", "t_s", "kind", "detail")
RUL_KEYS = (
    "estimator", "seq", "t_s", "mean_s", "std_s", "q05_s", "q50_s", "q95_s",
    "optimistic_s", "pessimistic_s", "threshold", "health", "assumption", "status", "reasons",
)


def _pick(row: Mapping[str, Any] | object, keys: tuple[str, ...]) -> dict[str, Any]:
    """The public keys of a row, given as a dict about to be stored or as an ORM row."""
    if isinstance(row, Mapping):
        return {k: row[k] for k in keys}
    return {k: getattr(row, k) for k in keys}


def window_public(row: Mapping[str, Any] | object) -> dict[str, Any]:
    return _pick(row, HEALTH_KEYS)


def event_public(row: Mapping[str, Any] | object) -> dict[str, Any]:
    return _pick(row, EVENT_KEYS)


def rul_public(row: Mapping[str, Any] | object) -> dict[str, Any]:
    return _pick(row, RUL_KEYS)


def finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


@dataclass(frozen=True)
class EstimatorResult:
    """One estimator's part of a result: its status after the batch, the last value of each
    per-sample output, and the windows, events and prognoses the batch completed."""

    status: str
    reasons: list[str]
    last: dict[str, float | None]
    health: list[dict[str, Any]]
    events: list[dict[str, Any]]
    rul: list[dict[str, Any]]
    diagnosis: dict[str, Any] | None

    def as_dict(self) -> dict[str, Any]:
        return {
            "status": self.status,
            "reasons": self.reasons,
            "last": self.last,
            "health": self.health,
            "events": self.events,
            "rul": self.rul,
            "diagnosis": self.diagnosis,
        }


@dataclass(frozen=True)
class BatchResult:
    """What applying one logged batch produced (JSON-safe except the sample arrays).

    ``t_s`` and ``samples`` (estimator -> output name -> array) ride along for subscribers that
    ask for per-sample outputs; the read-back leaves them empty.
    """

    seq: int
    batch_id: str
    t_first_s: float
    t_last_s: float
    n_samples: int
    status: str
    estimators: dict[str, EstimatorResult]
    t_s: FloatArray | None = None
    samples: dict[str, dict[str, FloatArray]] = field(default_factory=dict)

    def message(self, *, with_samples: bool = False) -> dict[str, Any]:
        """The WebSocket ``result`` message (docs/api.md, "Streaming")."""
        msg: dict[str, Any] = {
            "type": "result",
            "seq": self.seq,
            "client_seq": client_seq_of(self.batch_id),
            "t_first_s": self.t_first_s,
            "t_last_s": self.t_last_s,
            "n_samples": self.n_samples,
            "status": self.status,
            "estimators": {name: est.as_dict() for name, est in self.estimators.items()},
        }
        if with_samples and self.t_s is not None:
            msg["samples"] = {
                "t": self.t_s,
                **{
                    name: {k: np.where(np.isfinite(v), v, np.nan) for k, v in outs.items()}
                    for name, outs in self.samples.items()
                },
            }
        return msg
