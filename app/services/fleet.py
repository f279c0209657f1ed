"""Aircraft and actuators of an operator."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.errors import AlreadyExists, InvalidConfig, NotFound
from app.models import Actuator, Aircraft, EstimatorState, Stream
from estimators.base import ConfigError
from estimators.registry import ACTUATOR_KINDS, ESTIMATORS


def get_aircraft(session: Session, operator_id: int, tail: str) -> Aircraft:
    ac = session.scalar(
        select(Aircraft).where(Aircraft.operator_id == operator_id, Aircraft.tail == tail)
    )
    if ac is None:
        raise NotFound(f"aircraft {tail!r} not found")
    return ac


def create_aircraft(session: Session, operator_id: int, tail: str, description: str | None) -> Aircraft:
    ac = Aircraft(operator_id=operator_id, tail=tail, description=description)
    try:
        with session.begin_nested():
            session.add(ac)
            session.flush()
    except IntegrityError:
        raise AlreadyExists(f"aircraft {tail!r} already exists") from None
    return ac


def list_aircraft(session: Session, operator_id: int) -> list[Aircraft]:
    return list(
        session.scalars(
            select(Aircraft).where(Aircraft.operator_id == operator_id).order_by(Aircraft.tail)
        )
    )


def get_actuator(
    session: Session, operator_id: int, tail: str, actuator_id: str, *, lock: bool = False
) -> Actuator:
    stmt = (
        select(Actuator)
        .join(Aircraft, Aircraft.id == Actuator.aircraft_id)
        .where(
            Aircraft.operator_id == operator_id,
            Aircraft.tail == tail,
            Actuator.actuator_id == actuator_id,
        )
    )
    if lock:
        stmt = stmt.with_for_update(of=Actuator)
    act = session.scalar(stmt)
    if act is None:
        # Same answer whether the aircraft is missing or the actuator is.
        get_aircraft(session, operator_id, tail)
        raise NotFound(f"actuator {actuator_id!r} not found on aircraft {tail!r}")
    return act


def list_actuators(session: Session, aircraft: Aircraft) -> list[Actuator]:
    return list(
        session.scalars(
            select(Actuator).where(Actuator.aircraft_id == aircraft.id).order_by(Actuator.actuator_id)
        )
    )


def estimator_configs(session: Session, actuator_pk: int) -> dict[str, dict[str, Any]]:
    rows = session.scalars(
        select(EstimatorState)
        .where(EstimatorState.actuator_pk == actuator_pk)
        .order_by(EstimatorState.estimator)
    )
    return {r.estimator: r.config for r in rows}


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
    if "t" in chans:
        raise InvalidConfig("'t' is reserved for timestamps and cannot be a channel name")
    raw = estimators if estimators is not None else spec.default_estimators
    configs: dict[str, dict[str, Any]] = {}
    for name, raw_cfg in raw.items():
        module = ESTIMATORS.get(name)
        if module is None:
            raise InvalidConfig(f"unknown estimator {name!r}; known: {', '.join(ESTIMATORS)}")
        try:
            cfg = module.parse_config(raw_cfg or {})
        except ConfigError as exc:
            raise InvalidConfig(f"estimator {name!r}: {exc}") from None
        need = [c for c in module.required_channels(cfg) if c not in chans]
        if need:
            raise InvalidConfig(
                f"estimator {name!r} reads channels {', '.join(need)} that the actuator does not send"
            )
        configs[name] = module.config_to_dict(cfg)
    act = Actuator(aircraft_id=aircraft.id, actuator_id=actuator_id, kind=kind, channels=chans)
    try:
        with session.begin_nested():
            session.add(act)
            session.flush()
    except IntegrityError:
        raise AlreadyExists(
            f"actuator {actuator_id!r} already exists on aircraft {aircraft.tail!r}"
        ) from None
    session.add(Stream(actuator_pk=act.id))
    for name, cfg_dict in configs.items():
        session.add(EstimatorState(actuator_pk=act.id, estimator=name, config=cfg_dict, reasons=[]))
    session.flush()
    return act, configs
