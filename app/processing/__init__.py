"""The per-stream processor: log -> estimators -> results, one transaction.

``repository`` (claim, load, store), ``orchestration`` (the pure step over the batches),
``messages`` (the one result message), ``service`` (the rules, inside a transaction) and
``processor`` (the background thread, its retries and failures).
"""

from app.processing.service import (
    ApplyResult,
    Replay,
    applied_results,
    apply_pending,
    replay_estimator,
)

__all__ = ["ApplyResult", "Replay", "applied_results", "apply_pending", "replay_estimator"]
