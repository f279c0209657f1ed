"""Rules of aircraft and actuators: ownership, kinds, channels, estimator configurations, and
the fleet board's order."""

from __future__ import annotations

from typing import Any, Literal

from sqlalchemy.orm import Session

from app.alarms import service as alarms
from app.errors import AlreadyExists, InvalidConfig, NotFound
from app.faults import service as faults
from app.fleet import repository
from app.fleet.repository import BoardRow
from app.ingest import TIME_COLUMN
from app.models import Actuator, Aircraft
from estimators.base import STATUS_ORDER, ConfigError, worst_status
from estimators.registry import ACTUATOR_KINDS, ESTIMATORS

FleetSort = Literal["status", "tail", "updated", "rul"]


def get_aircraft(session: Session, operator_id: int, tail: str) -> Aircraft:
    ac = repository.aircraft_by_tail(session, operator_id, tail)
    if ac is None:
        raise NotFound(f"aircraft {tail!r} not found")
    return ac


def create_aircraft(session: Session, operator_id: int, tail: str, description: str | None) -> Aircraft:
    ac = Aircraft(operator_id=operator_id, tail=tail, description=description)
    if not repository.add_aircraft(session, ac):
        raise AlreadyExists(f"aircraft {tail!r} already exists")
    return ac


def list_aircraft(session: Session, operator_id: int) -> list[Aircraft]:
    return repository.list_aircraft(session, operator_id)


def get_actuator(
    session: Session, operator_id: int, tail: str, actuator_id: str, *, lock: bool = False
) -> Actuator:
    """The operator's actuator; 404 alike whether the aircraft or the actuator is missing (or
    owned by another operator)."""
    act = repository.actuator_of(session, operator_id, tail, actuator_id, lock=lock)
    if act is None:
        get_aircraft(session, operator_id, tail)
        raise NotFound(f"actuator {actuator_id!r} not found on aircraft {tail!r}")
    return act


def list_actuators(session: Session, aircraft: Aircraft) -> list[Actuator]:
    return repository.list_actuators(session, aircraft.id)


def estimator_configs(session: Session, actuator_pk: int) -> dict[str, dict[str, Any]]:
    return repository.estimator_configs(session, actuator_pk)


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
        raise AlreadyExists(f"actuator {actuator_id!r} already exists on aircraft {aircraft.tail!r}")
    return act, configs


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


def fleet_board(session: Session, operator_id: int, sort: FleetSort) -> list[dict[str, Any]]:
    """Every aircraft of the operator with its actuators, worst first by ``STATUS_ORDER``
    (``sort=status``), by tail, by last update, or by the shortest RUL (5 % quantile)."""
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
    out = list(by_tail.values())
    if sort == "rul":
        out.sort(
            key=lambda a: (
                *_rul_key(min((x["rul_q05_s"] for x in a["actuators"] if x["rul_q05_s"] is not None), default=None)),
                a["tail"],
            )
        )
    elif sort == "status":
        out.sort(key=lambda a: (-STATUS_ORDER[a["status"]], a["tail"]))
    elif sort == "updated":
        out.sort(key=lambda a: (a["updated_at"] is None, -(a["updated_at"].timestamp() if a["updated_at"] else 0), a["tail"]))
    return out
