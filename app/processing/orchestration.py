"""The pure step of processing: run a stream's estimators over its next logged batches.

No database here: the repository loads the batches and the estimators' rows, this module turns
them into the rows to store and one :class:`~app.processing.messages.BatchResult` per batch,
and the repository stores them. Each estimator is a :class:`Runner`; a step returns new runners
and never mutates its inputs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from app.codec import encode_columns
from app.ingest import TIME_COLUMN
from app.processing.messages import (
    BatchResult,
    EstimatorResult,
    event_public,
    finite_or_none,
    rul_public,
    window_public,
)
from estimators.base import (
    Batch,
    EstimatorKind,
    HealthWindow,
    RulEstimate,
    StateVersionError,
    StepOutputs,
    worst_status,
)
from estimators.registry import ESTIMATORS


class StateUnreadable(Exception):
    """An estimator's stored state has a version this build cannot read."""

    def __init__(self, estimator: str, detail: str) -> None:
        super().__init__(f"estimator {estimator!r}: {detail}")
        self.estimator = estimator
        self.detail = detail


@dataclass(frozen=True)
class Runner:
    """One estimator of a stream between two steps: its kind, config, state and latest report."""

    name: str
    kind: EstimatorKind
    config: Any
    state: Any
    status: str
    reasons: tuple[str, ...] = ()
    diagnosis_t_s: float | None = None
    diagnosis: dict[str, Any] | None = None


def make_runner(
    name: str,
    raw_config: Mapping[str, Any],
    state_blob: bytes | None,
    status: str,
    reasons: Sequence[str],
    diagnosis_t_s: float | None = None,
    diagnosis: dict[str, Any] | None = None,
) -> Runner:
    """A runner from a stored config and state (the initial state when there is none yet).

    Raises:
        StateUnreadable: the state's version is unknown to this build.
    """
    kind = ESTIMATORS[name]
    config = kind.parse_config(raw_config)
    if state_blob is None:
        state = kind.initial_state(config)
    else:
        try:
            state = kind.load_state(state_blob)
        except StateVersionError as exc:
            raise StateUnreadable(name, str(exc)) from exc
    return Runner(name, kind, config, state, status, tuple(reasons), diagnosis_t_s, diagnosis)


def fresh_runner(name: str, raw_config: Mapping[str, Any]) -> Runner:
    """A runner from its initial state, as before the stream's first batch."""
    return make_runner(name, raw_config, None, "learning", ())


@dataclass(frozen=True)
class LoggedBatch:
    """A batch of the telemetry log, decoded."""

    seq: int
    batch_id: str
    t_first_s: float
    t_last_s: float
    n_samples: int
    batch: Batch


@dataclass
class Rows:
    """Rows to insert, as dicts keyed by column name."""

    health: list[dict[str, Any]] = field(default_factory=list)
    outputs: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    rul: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class Step:
    """What running the estimators over some batches produced."""

    runners: list[Runner]
    rows: Rows
    results: list[BatchResult]
    status: str


def _clean(value: Any) -> Any:
    """JSON-safe values: non-finite floats become None, numpy scalars and arrays plain Python."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_clean(v) for v in value.tolist()]
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return finite_or_none(float(value))
    return value


def _window_row(base: dict[str, Any], w: HealthWindow) -> dict[str, Any]:
    return dict(
        base,
        t_start_s=float(w.t_start_s),
        t_end_s=float(w.t_end_s),
        n_samples=int(w.n_samples),
        indicators={k: _clean(v) for k, v in w.indicators.items()},
        status=w.status,
        reasons=list(w.reasons),
    )


def _opt(x: float | None) -> float | None:
    return None if x is None else finite_or_none(float(x))


def _rul_row(base: dict[str, Any], r: RulEstimate) -> dict[str, Any]:
    return dict(
        base,
        t_s=float(r.t_s),
        mean_s=_opt(r.mean_s),
        std_s=_opt(r.std_s),
        q05_s=_opt(r.q05_s),
        q50_s=_opt(r.q50_s),
        q95_s=_opt(r.q95_s),
        optimistic_s=_opt(r.optimistic_s),
        pessimistic_s=_opt(r.pessimistic_s),
        threshold=float(r.threshold),
        health=_clean(r.health),
        assumption=_clean(r.assumption),
        status=r.status,
        reasons=list(r.reasons),
    )


def _reported(runner: Runner, out: StepOutputs) -> Runner:
    """The runner's status after a step: the last window's, then the last prognosis's, then a
    status the estimator reports directly (each later one overrides)."""
    status, reasons = runner.status, runner.reasons
    if out.health:
        status, reasons = out.health[-1].status, tuple(out.health[-1].reasons)
    if out.rul:
        status, reasons = out.rul[-1].status, tuple(out.rul[-1].reasons)
    if out.status is not None:
        status, reasons = out.status.status, tuple(out.status.reasons)
    diag_t, diag = runner.diagnosis_t_s, runner.diagnosis
    if out.diagnosis is not None:
        diag_t, diag = float(out.diagnosis.t_s), _clean(out.diagnosis.detail)
    return replace(runner, status=status, reasons=reasons, diagnosis_t_s=diag_t, diagnosis=diag)


def run_estimators(
    actuator_pk: int,
    runners: Sequence[Runner],
    batches: Sequence[LoggedBatch],
    *,
    store_outputs: bool,
) -> Step:
    """Step every runner over ``batches`` in stream order.

    Returns the new runners, the rows to store, one result per batch and the stream's status
    after the last batch (the worst of its estimators', ``STATUS_ORDER``).
    """
    current = list(runners)
    rows = Rows()
    results: list[BatchResult] = []
    for lb in batches:
        per_est: dict[str, EstimatorResult] = {}
        per_samples: dict[str, dict[str, Any]] = {}
        for i, runner in enumerate(current):
            state, out = runner.kind.step(runner.config, runner.state, lb.batch)
            runner = _reported(replace(runner, state=state), out)
            current[i] = runner
            base = {"actuator_pk": actuator_pk, "estimator": runner.name, "seq": lb.seq}
            windows = [_window_row(base, w) for w in out.health]
            events = [
                dict(base, t_s=float(ev.t_s), kind=ev.kind, detail=_clean(ev.detail)) for ev in out.events
            ]
            ruls = [_rul_row(base, r) for r in out.rul]
            rows.health.extend(windows)
            rows.events.extend(events)
            rows.rul.extend(ruls)
            if store_outputs and out.samples:
                rows.outputs.append(
                    dict(
                        base,
                        t_first_s=lb.t_first_s,
                        t_last_s=lb.t_last_s,
                        n_samples=lb.n_samples,
                        payload=encode_columns({TIME_COLUMN: lb.batch.t_s, **out.samples}),
                    )
                )
            per_samples[runner.name] = out.samples
            per_est[runner.name] = EstimatorResult(
                status=runner.status,
                reasons=list(runner.reasons),
                last={k: finite_or_none(v[-1]) for k, v in out.samples.items() if len(v)},
                health=[window_public(w) for w in windows],
                events=[event_public(e) for e in events],
                rul=[rul_public(r) for r in ruls],
                diagnosis=_clean(out.diagnosis.detail) if out.diagnosis is not None else None,
            )
        results.append(
            BatchResult(
                seq=lb.seq,
                batch_id=lb.batch_id,
                t_first_s=lb.t_first_s,
                t_last_s=lb.t_last_s,
                n_samples=lb.n_samples,
                status=worst_status([r.status for r in current]),
                estimators=per_est,
                t_s=lb.batch.t_s,
                samples=per_samples,
            )
        )
    return Step(current, rows, results, worst_status([r.status for r in current]))


def most_urgent_rul(rul_rows: Sequence[Mapping[str, Any]]) -> Mapping[str, Any] | None:
    """The fleet board's RUL: per estimator the latest prognosis, across estimators the most
    urgent (smallest 5 % quantile; one without a quantile last)."""
    latest: dict[str, Mapping[str, Any]] = {}
    for r in rul_rows:
        latest[r["estimator"]] = r
    if not latest:
        return None
    return min(
        latest.values(),
        key=lambda r: (r["q05_s"] is None, r["q05_s"] if r["q05_s"] is not None else 0.0),
    )
