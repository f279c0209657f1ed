"""The read side: latest health, history, per-sample outputs, events and RUL (with
prognostics' vocabulary: event state, time of event, RUL in usage units)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pyarrow as pa
from sqlalchemy.orm import Session

from app import series
from app.codec import column_names, decode_columns
from app.errors import InvalidQuery, NotFound
from app.fleet import service as fleet
from app.health import repository, vocabulary
from app.health.downsample import min_max_downsample
from app.ingest import TIME_COLUMN
from app.models import Actuator
from app.pagination import Order
from app.processing.messages import event_public, rul_public, window_public
from app.telemetry import readback

LABELS = ("config_version", "baseline")


def _labelled(public: dict[str, Any], row: Any) -> dict[str, Any]:
    return {**public, **{k: getattr(row, k) for k in LABELS}}


def latest_health(session: Session, tail: str, act: Actuator) -> dict[str, Any]:
    stream = repository.stream(session, act.id)
    estimators: dict[str, Any] = {}
    for er in repository.estimators(session, act.id):
        last = repository.latest_window(session, act.id, er.estimator, er.baseline)
        estimators[er.estimator] = {
            "status": er.status,
            "reasons": er.reasons,
            "config_version": er.config_version,
            "baseline": er.baseline,
            "window": _labelled(window_public(last), last) if last is not None else None,
        }
    return {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "kind": act.kind,
        "status": stream.status,
        "failure": stream.failure,
        "last_logged_seq": act.last_logged_seq,
        "last_applied_seq": stream.last_applied_seq,
        "t_last_s": stream.last_applied_t_s,
        "updated_at": stream.updated_at,
        "estimators": estimators,
    }


def check_estimator(session: Session, act: Actuator, estimator: str | None) -> None:
    if estimator is not None and not repository.has_estimator(session, act.id, estimator):
        raise NotFound(f"estimator {estimator!r} is not attached to actuator {act.actuator_id!r}")


def health_history(
    session: Session,
    act: Actuator,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    after: Sequence[Any] | None,
    order: Order,
    limit: int,
) -> tuple[list[dict[str, Any]], list[Any] | None]:
    """A page of windows and the key to continue after (None on the last page)."""
    check_estimator(session, act, estimator)
    rows = repository.windows(session, act.id, estimator, from_s, to_s, after=after, order=order, limit=limit + 1)
    items = [_labelled(window_public(r), r) for r in rows[:limit]]
    return items, ([rows[limit - 1].t_end_s, rows[limit - 1].id] if len(rows) > limit else None)


def _as_list(a: np.ndarray) -> list[float | None]:
    return [None if not np.isfinite(x) else x for x in a.tolist()]


def _output_blocks(
    session: Session, act: Actuator, estimator: str, from_s: float | None, to_s: float | None, order: Order
) -> Iterator[dict[str, np.ndarray]]:
    for row in repository.sample_outputs(session, act.id, estimator, from_s, to_s, order):
        yield decode_columns(row.payload)


def sample_outputs(
    session: Session,
    act: Actuator,
    estimator: str,
    from_s: float | None,
    to_s: float | None,
    after_t: float | None,
    order: Order,
    max_samples: int,
) -> tuple[dict[str, Any], float | None]:
    """A page of per-sample outputs and the time to continue after (None on the last page)."""
    check_estimator(session, act, estimator)
    cols, last = series.page(
        _output_blocks(session, act, estimator, from_s, to_s, order), from_s, to_s, after_t, order, max_samples
    )
    t = cols.pop(TIME_COLUMN)
    return {"estimator": estimator, "t_s": t.tolist(), "series": {k: _as_list(v) for k, v in cols.items()}}, last


def output_export(
    session: Session, act: Actuator, estimator: str, from_s: float | None, to_s: float | None
) -> tuple[pa.Schema, Iterator[dict[str, np.ndarray]]]:
    """The export schema of an estimator's per-sample outputs (time, the outputs of every
    block, and the ``seq``, ``config_version`` and ``baseline`` of each sample) and an
    iterator of its blocks in stream order. The schema is read first from the blocks' headers,
    so a change of outputs between config versions loses no column."""
    check_estimator(session, act, estimator)
    names: dict[str, None] = {}
    for row in repository.sample_outputs(session, act.id, estimator, from_s, to_s):
        for n in pa.ipc.open_stream(pa.py_buffer(row.payload)).schema.names:
            names.setdefault(n, None)
    outs = [n for n in names if n != TIME_COLUMN]
    schema = series.schema_of([TIME_COLUMN, *outs, "seq", *LABELS], int_columns=("seq", *LABELS))

    def blocks() -> Iterator[dict[str, np.ndarray]]:
        for row in repository.sample_outputs(session, act.id, estimator, from_s, to_s):
            cols = series.clip(decode_columns(row.payload), from_s, to_s, None, "asc")
            n = len(cols[TIME_COLUMN])
            cols["seq"] = np.full(n, row.seq, dtype=np.int64)
            for k in LABELS:
                cols[k] = np.full(n, getattr(row, k), dtype=np.int64)
            yield cols

    return schema, blocks()


def events(
    session: Session,
    act: Actuator,
    from_s: float | None,
    to_s: float | None,
    after: Sequence[Any] | None,
    order: Order,
    limit: int,
) -> tuple[list[dict[str, Any]], list[Any] | None]:
    rows = repository.events(session, act.id, from_s, to_s, after=after, order=order, limit=limit + 1)
    items = [_labelled(event_public(r), r) for r in rows[:limit]]
    return items, ([rows[limit - 1].t_s, rows[limit - 1].id] if len(rows) > limit else None)


class _Usage:
    """Counter values of an actuator's usage channels (operating hours, cycles) read from the
    telemetry log for one request (each batch decoded once)."""

    def __init__(self, session: Session, act: Actuator) -> None:
        self.session = session
        self.act = act
        self.counters = [c for c in vocabulary.USAGE_COUNTERS if c in act.channels]
        self._start: dict[tuple[int, str], tuple[float, float] | None] = {}

    def _baseline_start(self, baseline: int, counter: str) -> tuple[float, float] | None:
        key = (baseline, counter)
        if key not in self._start:
            first = fleet.baseline_start(self.session, self.act.id, baseline)
            self._start[key] = readback.first_counter_point(self.session, self.act, first, counter)
        return self._start[key]

    def convert(self, r: Any, rul: dict[str, Any]) -> dict[str, Any]:
        """``rul_operating_hours`` and ``rul_cycles`` of one prognosis (None without the
        counter, or when its rate cannot be measured: raw batches dropped by retention, or a
        counter that did not advance)."""
        out: dict[str, Any] = dict.fromkeys(vocabulary.USAGE_COUNTERS.values())
        for counter in self.counters:
            now = readback.counter_point_at(self.session, self.act, r.seq, r.t_s, counter)
            rate = vocabulary.usage_rate(self._baseline_start(r.baseline, counter), now)
            out[vocabulary.USAGE_COUNTERS[counter]] = vocabulary.rul_in_usage(rul, rate)
        return out


def _rul_item(row: Any, usage: _Usage) -> dict[str, Any]:
    pub = _labelled(rul_public(row), row)
    return {
        **pub,
        **vocabulary.event_state(row.estimator, row.health, row.threshold),
        **vocabulary.time_of_event(row.t_s, pub),
        **usage.convert(row, pub),
    }


def rul(
    session: Session,
    tail: str,
    act: Actuator,
    estimator: str | None,
    from_s: float | None,
    to_s: float | None,
    after: Sequence[Any] | None,
    order: Order,
    limit: int,
) -> tuple[dict[str, Any], list[Any] | None]:
    check_estimator(session, act, estimator)
    ests = repository.estimators(session, act.id)
    usage = _Usage(session, act)
    latest: dict[str, Any] = {}
    for er in ests:
        if estimator is not None and er.estimator != estimator:
            continue
        last = repository.latest_rul(session, act.id, er.estimator, er.baseline)
        if last is not None:
            latest[er.estimator] = _rul_item(last, usage)
    rows = repository.ruls(session, act.id, estimator, from_s, to_s, after=after, order=order, limit=limit + 1)
    body = {
        "tail": tail,
        "actuator_id": act.actuator_id,
        "latest": latest,
        "items": [_rul_item(r, usage) for r in rows[:limit]],
    }
    return body, ([rows[limit - 1].t_s, rows[limit - 1].id] if len(rows) > limit else None)


def _column_blocks(
    payloads: Iterator[bytes], what: str, from_s: float | None, to_s: float | None, names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The columns of stored blocks (outputs or telemetry) cut to [from_s, to_s], joined."""
    times: list[np.ndarray] = []
    columns: dict[str, list[np.ndarray]] = {}
    for payload in payloads:
        cols = decode_columns(payload, None if names is None else {TIME_COLUMN, *names})
        t = cols.pop(TIME_COLUMN)
        keep: slice | np.ndarray = slice(None)
        if (from_s is not None and t[0] < from_s) or (to_s is not None and t[-1] > to_s):
            keep = (t >= (-np.inf if from_s is None else from_s)) & (t <= (np.inf if to_s is None else to_s))
        times.append(t[keep])
        for name in names if names is not None else cols:
            if name not in cols:
                have = [c for c in column_names(payload) if c != TIME_COLUMN]
                raise NotFound(f"{what} has no series {name!r} (it has {', '.join(have)})")
            columns.setdefault(name, []).append(cols[name][keep])
    t_all = np.concatenate(times) if times else np.empty(0)
    return t_all, {k: np.concatenate(v) for k, v in columns.items()}


def _outputs_columns(
    session: Session, act: Actuator, estimator: str, from_s: float | None, to_s: float | None,
    names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Every per-sample output of ``estimator`` in [from_s, to_s] (only ``names`` if given)."""
    rows = repository.sample_outputs(session, act.id, estimator, from_s, to_s)
    return _column_blocks((r.payload for r in rows), f"estimator {estimator!r}", from_s, to_s, names)


def _telemetry_columns(
    session: Session, act: Actuator, from_s: float | None, to_s: float | None, names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The channels of the logged batches in [from_s, to_s] that still hold their samples."""
    rows = repository.telemetry_batches(session, act.id, from_s, to_s)
    payloads = (r.payload for r in rows if r.payload is not None)
    return _column_blocks(payloads, f"actuator {act.actuator_id!r}", from_s, to_s, names)


def _health_columns(
    session: Session, act: Actuator, estimator: str, from_s: float | None, to_s: float | None,
    names: list[str] | None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The health indicators of ``estimator``'s windows ending in [from_s, to_s], at each
    window's end."""
    rows = [
        r for r in repository.windows(session, act.id, estimator, from_s, to_s, limit=None)
        if (from_s is None or r.t_end_s >= from_s) and (to_s is None or r.t_end_s <= to_s)
    ]
    found = sorted({k for r in rows for k in r.indicators})
    for name in names or []:
        if rows and name not in found:
            raise NotFound(f"estimator {estimator!r} has no health indicator {name!r} (it has {', '.join(found)})")
    wanted = names if names is not None else found
    t = np.array([r.t_end_s for r in rows], dtype=np.float64)
    cols = {
        name: np.array([np.nan if r.indicators.get(name) is None else r.indicators[name] for r in rows],
                       dtype=np.float64)
        for name in wanted
    }
    return t, cols


def plot_series(
    session: Session,
    act: Actuator,
    estimator: str | None,
    source: str,
    names: list[str] | None,
    from_s: float | None,
    to_s: float | None,
    points: int,
) -> dict[str, Any]:
    """Outputs or health indicators of one estimator, or the logged telemetry, over
    [from_s, to_s], min/max downsampled to ``points`` (docs/api.md, "Plotting series")."""
    if source == "telemetry":
        t, cols = _telemetry_columns(session, act, from_s, to_s, names)
    elif estimator is None:
        raise InvalidQuery(f"source {source!r} needs estimator=<name>")
    else:
        check_estimator(session, act, estimator)
        read = _outputs_columns if source == "outputs" else _health_columns
        t, cols = read(session, act, estimator, from_s, to_s, names)
    n = len(t)
    span_from = from_s if from_s is not None else (float(t[0]) if n else None)
    span_to = to_s if to_s is not None else (float(t[-1]) if n else None)
    if n:
        d = min_max_downsample(t, cols, points, span_from, span_to)
        t, cols, reduced = d.t_s, d.series, d.reduced
    else:
        reduced = False
    return {
        "estimator": estimator,
        "source": source,
        "from_s": span_from,
        "to_s": span_to,
        "n_samples": n,
        "reduced": reduced,
        "t_s": t.tolist(),
        "series": {k: _as_list(v) for k, v in cols.items()},
    }
