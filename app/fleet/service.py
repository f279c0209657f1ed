"""Rules of aircraft and actuators: ownership, kinds, channels, estimator configurations, and
the fleet board's order."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from datetime import datetime, timedelta
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from sqlalchemy.orm import Session

from app.alarms import service as alarms
from app.errors import AlreadyExists, Gone, InvalidConfig, MaintenancePending, NotFound
from app.events import repository as event_repository
from app.events.log import NewEvent
from app.faults import service as faults
from app.fleet import repository
from app.fleet.repository import BoardRow
from app.ingest import TIME_COLUMN
from app.models import (
    Actuator,
    Aircraft,
    EstimatorConfigVersion,
    EstimatorState,
    MaintenanceAction,
    Stream,
    utcnow,
)
from app.pagination import Order
from estimators.base import STATUS_ORDER, ConfigError, worst_status
from estimators.registry import ACTUATOR_KINDS, ESTIMATORS

if TYPE_CHECKING:
    from app.processing.repository import EstimatorRow

FleetSort = Literal["status", "tail", "updated", "rul"]


def _deleted(what: str, at: datetime) -> str:
    return f"{what} was deleted at {at.isoformat()}; its data is kept until it is purged"


def get_aircraft(session: Session, operator_id: int, tail: str) -> Aircraft:
    """The operator's live aircraft; 404 when missing, 410 when deleted."""
    ac = repository.aircraft_by_tail(session, operator_id, tail)
    if ac is None:
        raise NotFound(f"aircraft {tail!r} not found")
    if ac.deleted_at is not None:
        raise Gone(_deleted(f"aircraft {tail!r}", ac.deleted_at))
    return ac


def create_aircraft(session: Session, operator_id: int, tail: str, description: str | None) -> Aircraft:
    ac = Aircraft(operator_id=operator_id, tail=tail, description=description)
    if not repository.add_aircraft(session, ac):
        prior = repository.aircraft_by_tail(session, operator_id, tail)
        if prior is not None and prior.deleted_at is not None:
            raise AlreadyExists(
                f"aircraft {tail!r} was deleted at {prior.deleted_at.isoformat()} and its tail is "
                "taken until its data is purged"
            )
        raise AlreadyExists(f"aircraft {tail!r} already exists")
    return ac


def list_aircraft(
    session: Session, operator_id: int, after: int | None, order: Order, limit: int
) -> list[Aircraft]:
    return repository.list_aircraft(session, operator_id, after=after, order=order, limit=limit)


def get_actuator(
    session: Session, operator_id: int, tail: str, actuator_id: str, *, lock: bool = False
) -> Actuator:
    """The operator's actuator; 404 alike whether the aircraft or the actuator is missing (or
    owned by another operator)."""
    act = repository.actuator_of(session, operator_id, tail, actuator_id, lock=lock)
    if act is None:
        get_aircraft(session, operator_id, tail)
        raise NotFound(f"actuator {actuator_id!r} not found on aircraft {tail!r}")
    if act.deleted_at is not None:
        raise Gone(_deleted(f"actuator {actuator_id!r} of aircraft {tail!r}", act.deleted_at))
    return act


def list_actuators(
    session: Session, aircraft: Aircraft, after: int | None, order: Order, limit: int
) -> list[Actuator]:
    return repository.list_actuators(session, aircraft.id, after=after, order=order, limit=limit)


def estimator_configs(session: Session, actuator_pk: int) -> dict[str, dict[str, Any]]:
    return repository.estimator_configs(session, actuator_pk)


def estimator_rows(session: Session, actuator_pk: int) -> list[EstimatorState]:
    return repository.estimator_rows(session, actuator_pk)


def validate_estimators(
    raw: dict[str, dict[str, Any]], channels: list[str]
) -> dict[str, dict[str, Any]]:
    """Each estimator's configuration with every default filled in; InvalidConfig names the
    estimator and the problem (unknown estimator, invalid setting, a channel not sent)."""
    configs: dict[str, dict[str, Any]] = {}
    for name, raw_cfg in raw.items():
        kind = ESTIMATORS.get(name)
        if kind is None:
            raise InvalidConfig(f"unknown estimator {name!r}; known: {', '.join(ESTIMATORS)}")
        try:
            cfg = kind.parse_config(raw_cfg or {})
        except ConfigError as exc:
            raise InvalidConfig(f"estimator {name!r}: {exc}") from None
        need = [c for c in kind.required_channels(cfg) if c not in channels]
        if need:
            raise InvalidConfig(
                f"estimator {name!r} reads channels {', '.join(need)} that the actuator does not send"
            )
        configs[name] = kind.config_to_dict(cfg)
    return configs


def create_actuator(
    session: Session,
    aircraft: Aircraft,
    actuator_id: str,
    kind: str,
    channels: list[str] | None,
    estimators: dict[str, dict[str, Any]] | None,
) -> tuple[Actuator, dict[str, dict[str, Any]]]:
    spec = ACTUATOR_KINDS.get(kind)
    if spec is None:
        raise InvalidConfig(f"unknown actuator kind {kind!r}; known: {', '.join(ACTUATOR_KINDS)}")
    chans = list(channels) if channels is not None else list(spec.channels)
    if not chans or len(set(chans)) != len(chans):
        raise InvalidConfig("channels must be a non-empty list of distinct names")
    if TIME_COLUMN in chans:
        raise InvalidConfig(f"{TIME_COLUMN!r} is reserved for timestamps and cannot be a channel name")
    configs = validate_estimators(
        estimators if estimators is not None else spec.default_estimators, chans
    )
    act = Actuator(aircraft_id=aircraft.id, actuator_id=actuator_id, kind=kind, channels=chans)
    if not repository.add_actuator(session, act, dict(configs)):
        raise AlreadyExists(
            f"actuator {actuator_id!r} already exists on aircraft {aircraft.tail!r} (a deleted "
            "actuator keeps its id until its data is purged)"
        )
    return act, configs


# ----------------------------------------------------------------------------- lifecycle
def update_aircraft(session: Session, aircraft: Aircraft, fields: Mapping[str, Any]) -> Aircraft:
    """Change an aircraft's editable fields (its description; the tail is its identity)."""
    if "description" in fields:
        aircraft.description = fields["description"]
    session.flush()
    return aircraft


def delete_aircraft(session: Session, aircraft: Aircraft) -> datetime:
    """Soft-delete an aircraft and its actuators: hidden from reads and ingest at once, their
    data purged after the retention period."""
    now = utcnow()
    aircraft.deleted_at = now
    for act in repository.live_actuators_of(session, aircraft.id):
        act.deleted_at = now
    session.flush()
    return now


def delete_actuator(session: Session, act: Actuator) -> datetime:
    act.deleted_at = utcnow()
    session.flush()
    return act.deleted_at


def purge_deleted(session: Session, retention_s: float) -> tuple[int, int]:
    """Remove for good the aircraft and actuators deleted more than ``retention_s`` ago, with
    all their data: (aircraft, actuators) purged."""
    return repository.purge_deleted(session, utcnow() - timedelta(seconds=retention_s))


def _merge(base: Mapping[str, Any], change: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with the settings of ``change``; nested settings are merged member by member,
    except a nested setting of another ``kind`` (a different member of a union), which replaces
    the current one."""
    out = dict(base)
    for k, v in change.items():
        cur = out.get(k)
        same = isinstance(v, Mapping) and isinstance(cur, Mapping) and v.get("kind", cur.get("kind")) == cur.get("kind")
        out[k] = _merge(cur, v) if same else v  # type: ignore[arg-type]
    return out


def state_layout(value: Any) -> Any:
    """The shape of an estimator state (array shapes and dtypes, fields, lengths), not its
    values: two configurations whose initial states have the same layout read each other's
    states."""
    if isinstance(value, np.ndarray):
        return ("array", value.shape, value.dtype.str)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return (type(value).__name__, tuple((f.name, state_layout(getattr(value, f.name))) for f in dataclasses.fields(value)))
    if isinstance(value, tuple | list):
        return (type(value).__name__, tuple(state_layout(v) for v in value))
    if isinstance(value, dict):
        return ("dict", tuple(sorted((str(k), state_layout(v)) for k, v in value.items())))
    return type(value).__name__


def _restart(er: EstimatorState | EstimatorRow, reason: str) -> None:
    er.state = None
    er.status, er.reasons = "learning", [reason]
    er.diagnosis_t_s, er.diagnosis = None, None


def _stream_status(stream: Stream, ests: list[EstimatorState]) -> None:
    if stream.failure is None:
        stream.status = worst_status([er.status for er in ests])
    stream.updated_at = utcnow()


def _log_asset_events(
    session: Session,
    act: Actuator,
    stream: Stream,
    events: list[tuple[str, dict[str, Any]]],
    status_before: str,
    ests: list[EstimatorState],
) -> None:
    """Log a person's change to the actuator as fleet events, in the change's transaction: each
    ``(type, body)`` given, then ``status_changed`` when the change restarted the estimators at
    once and so changed the status (the alarm rules see it, as after an apply). A restart that
    waits for pending batches changes the status when the processor applies it."""
    operator_id, tail, actuator_id = event_repository.stream_owner(session, act.id)

    def new(type_: str, body: dict[str, Any]) -> NewEvent:
        return NewEvent(type=type_, tail=tail, actuator_id=actuator_id, actuator_pk=act.id, body=body)

    logged = [new(t, b) for t, b in events]
    if stream.status != status_before:
        reasons = [r for er in ests for r in er.reasons]
        logged.append(new("status_changed", {"from": status_before, "to": stream.status, "reasons": reasons}))
    alarms.log_with_alarms(session, operator_id, act.id, tail, actuator_id, logged)


def update_estimators(
    session: Session,
    act: Actuator,
    changes: Mapping[str, Mapping[str, Any]],
    *,
    reset_state: bool,
    comment: str | None,
    key_id: int | None,
) -> list[EstimatorConfigVersion]:
    """A new config version of each estimator named in ``changes`` (its settings merged onto
    the current ones and validated by the kind's config model), in force from the next batch
    the processor applies.

    The estimator keeps its state unless ``reset_state``; a change that alters the layout of the
    state (e.g. a different number of models) needs ``reset_state`` (InvalidConfig otherwise).
    """
    if not changes:
        raise InvalidConfig("estimators: name at least one estimator and the settings to change")
    stream = repository.lock_stream(session, act.id)
    status_before = stream.status
    ests = {er.estimator: er for er in repository.estimator_rows(session, act.id)}
    unknown = [n for n in changes if n not in ests]
    if unknown:
        raise InvalidConfig(
            f"estimator {unknown[0]!r} is not attached to actuator {act.actuator_id!r} "
            f"(attached: {', '.join(ests)}); estimators cannot be added to a running stream"
        )
    merged = {n: _merge(ests[n].config, dict(c)) for n, c in changes.items()}
    configs = validate_estimators(merged, list(act.channels))
    versions = []
    for name, cfg in configs.items():
        er, kind = ests[name], ESTIMATORS[name]
        if not reset_state and er.state is not None:
            old = state_layout(kind.initial_state(kind.parse_config(er.config)))
            if old != state_layout(kind.initial_state(kind.parse_config(cfg))):
                raise InvalidConfig(
                    f"estimator {name!r}: this change alters the layout of the estimator's state, "
                    "which cannot carry over; send \"reset_state\": true to restart it from its "
                    "initial state"
                )
        er.config = cfg
        er.config_version += 1
        if reset_state:
            _restart(er, f"restarted with config version {er.config_version}")
        row = EstimatorConfigVersion(
            actuator_pk=act.id,
            estimator=name,
            version=er.config_version,
            config=cfg,
            from_seq=stream.last_applied_seq + 1,
            state="reset" if reset_state else "kept",
            comment=comment,
            created_by_key_id=key_id,
        )
        repository.add(session, row)
        versions.append(row)
    if reset_state:
        stream.rul_t_s = stream.rul_q05_s = stream.rul_q50_s = None
        _stream_status(stream, list(ests.values()))
    session.flush()
    _log_asset_events(
        session,
        act,
        stream,
        [
            (
                "config_changed",
                {
                    "estimator": v.estimator,
                    "version": v.version,
                    "from_seq": v.from_seq,
                    "state": v.state,
                    "comment": v.comment,
                },
            )
            for v in versions
        ],
        status_before,
        list(ests.values()),
    )
    return versions


def config_versions(
    session: Session, act: Actuator, estimator: str | None, after: int | None, order: Order, limit: int
) -> list[EstimatorConfigVersion]:
    return repository.config_versions(session, act.id, estimator, after=after, order=order, limit=limit)


RESETTING_ACTIONS = frozenset({"repair", "replacement"})


def start_baseline(er: EstimatorState | EstimatorRow, baseline: int) -> None:
    """Restart an estimator from its initial state as ``baseline`` (a repaired or replaced
    part): its earlier outputs stay, labelled with the earlier baseline."""
    _restart(er, f"new baseline {baseline} after maintenance")
    er.baseline = baseline
    er.reset_at_seq = er.reset_baseline = None


def record_maintenance(
    session: Session,
    tail: str,
    actuator_id: str,
    operator_id: int,
    *,
    action: str,
    performed_by: str,
    performed_at: datetime | None,
    comment: str | None,
    key_id: int | None,
) -> MaintenanceAction:
    """Record an inspection, repair or replacement.

    A repair or replacement starts a new baseline with the first batch logged after it: every
    estimator restarts from its initial state there (a ``failed`` status latched by the old
    part is cleared, RUL starts again); batches of the old part still pending are applied to
    the old baseline first. With nothing pending, the restart happens at once. An inspection
    changes nothing but the record.
    """
    act = get_actuator(session, operator_id, tail, actuator_id, lock=True)
    stream = repository.lock_stream(session, act.id)
    ests = repository.estimator_rows(session, act.id)
    status_before = stream.status
    current = max((er.reset_baseline or er.baseline for er in ests), default=1)
    baseline = max(current, repository.last_baseline(session, act.id))
    from_seq: int | None = None
    if action in RESETTING_ACTIONS:
        pending = [er.reset_at_seq for er in ests if er.reset_at_seq is not None]
        if pending:
            # One restart can wait at a time: a second one would drop the first's baseline.
            raise MaintenancePending(
                f"the repair or replacement starting baseline {current} at batch {pending[0]} is not "
                f"applied yet (the processor is at batch {stream.last_applied_seq}); record this one "
                "once it is"
            )
        baseline += 1
        from_seq = act.last_logged_seq + 1
        if stream.last_applied_seq >= act.last_logged_seq:
            for er in ests:
                start_baseline(er, baseline)
            stream.rul_t_s = stream.rul_q05_s = stream.rul_q50_s = None
            _stream_status(stream, ests)
        else:
            for er in ests:
                er.reset_at_seq, er.reset_baseline = from_seq, baseline
    row = MaintenanceAction(
        actuator_pk=act.id,
        action=action,
        performed_by=performed_by,
        performed_at=performed_at or utcnow(),
        comment=comment,
        baseline=baseline,
        from_seq=from_seq,
        status_before=status_before,
        recorded_by_key_id=key_id,
    )
    repository.add(session, row)
    _log_asset_events(
        session,
        act,
        stream,
        [
            (
                "maintenance_recorded",
                {
                    "maintenance_id": row.id,
                    "action": row.action,
                    "performed_by": row.performed_by,
                    "performed_at": row.performed_at,
                    "comment": row.comment,
                    "baseline": row.baseline,
                    "from_seq": row.from_seq,
                    "status_before": status_before,
                },
            )
        ],
        status_before,
        ests,
    )
    return row


def baseline_start(session: Session, actuator_pk: int, baseline: int) -> int:
    """The first batch (stream seq) of a baseline."""
    return repository.baseline_start(session, actuator_pk, baseline)


def maintenance_actions(
    session: Session, act: Actuator, after: int | None, order: Order, limit: int
) -> list[MaintenanceAction]:
    return repository.maintenance_actions(session, act.id, after=after, order=order, limit=limit)


# ----------------------------------------------------------------------------- fleet board
def _rul_key(q05: float | None) -> tuple[bool, float]:
    return (q05 is None, q05 if q05 is not None else 0.0)


def _actuator_entry(r: BoardRow, open_faults: list[str], open_alarms: int) -> dict[str, Any]:
    return {
        "actuator_id": r.actuator_id,
        "kind": r.kind,
        "status": r.status,
        "failure": r.failure,
        "t_last_s": r.t_last_s,
        "last_logged_seq": r.last_logged_seq,
        "last_applied_seq": r.last_applied_seq,
        "updated_at": r.updated_at,
        "rul_q05_s": r.rul_q05_s,
        "rul_q50_s": r.rul_q50_s,
        "rul_t_s": r.rul_t_s,
        "active_faults": open_faults,
        "open_alarms": open_alarms,
    }


def _board_key(ac: dict[str, Any], sort: FleetSort) -> list[Any]:
    """An aircraft's place on the board, as a JSON-safe key of numbers and strings (the
    board's cursor)."""
    return [int(v) if isinstance(v, bool) else v for v in _board_sort_key(ac, sort)]


def _board_sort_key(ac: dict[str, Any], sort: FleetSort) -> list[Any]:
    if sort == "rul":
        best = min((x["rul_q05_s"] for x in ac["actuators"] if x["rul_q05_s"] is not None), default=None)
        return [*_rul_key(best), ac["tail"]]
    if sort == "status":
        return [-STATUS_ORDER[ac["status"]], ac["tail"]]
    if sort == "updated":
        up = ac["updated_at"]
        return [up is None, -(up.timestamp() if up is not None else 0.0), ac["tail"]]
    return [ac["tail"]]


def fleet_board(
    session: Session, operator_id: int, sort: FleetSort, after: list[Any] | None = None, limit: int | None = None
) -> tuple[list[dict[str, Any]], list[Any] | None]:
    """The operator's aircraft with their actuators, worst first by ``STATUS_ORDER``
    (``sort=status``), by tail, by last update, or by the shortest RUL (5 % quantile): up to
    ``limit`` aircraft after the board key ``after``, and the key of the last one when more
    follow."""
    rows = repository.board_rows(session, operator_id)
    pks = [r.actuator_pk for r in rows if r.actuator_pk is not None]
    components = faults.open_fault_components(session, pks)
    alarm_counts = alarms.open_counts(session, pks)
    by_tail: dict[str, dict[str, Any]] = {}
    for r in rows:
        ac = by_tail.setdefault(r.tail, {"tail": r.tail, "updated_at": None, "actuators": []})
        if r.actuator_pk is not None:
            ac["actuators"].append(
                _actuator_entry(r, components[r.actuator_pk], alarm_counts.get(r.actuator_pk, 0))
            )
    for ac in by_tail.values():
        acts = ac["actuators"]
        ac["status"] = worst_status([a["status"] for a in acts])
        ac["open_alarms"] = sum(a["open_alarms"] for a in acts)
        ups = [a["updated_at"] for a in acts if a["updated_at"] is not None]
        ac["updated_at"] = max(ups) if ups else None
        if sort == "rul":
            acts.sort(key=lambda a: (*_rul_key(a["rul_q05_s"]), a["actuator_id"]))
        else:
            acts.sort(key=lambda a: (-STATUS_ORDER[a["status"]], a["actuator_id"]))
    keyed = sorted(((_board_key(a, sort), a) for a in by_tail.values()), key=lambda ka: ka[0])
    if after is not None:
        keyed = [(k, a) for k, a in keyed if k > after]
    if limit is None or len(keyed) <= limit:
        return [a for _, a in keyed], None
    return [a for _, a in keyed[:limit]], keyed[limit - 1][0]
