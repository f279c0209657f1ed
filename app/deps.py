"""Dependencies shared by the routers, as ``Annotated`` aliases.

Endpoints are plain ``def`` functions: FastAPI runs them (and these dependencies) in its thread
pool, so no endpoint wraps its work in a closure. A write session is one unit of work, committed
when the endpoint returns and before the response is sent (``scope="function"``); an exception
rolls it back.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from app.auth.service import Principal, authenticate
from app.config import Settings
from app.db import Database
from app.errors import Unauthorized
from app.fleet import service as fleet
from app.models import Actuator
from app.processing.processor import Processor

bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`")


def get_db(request: Request) -> Database:
    return request.app.state.db  # type: ignore[no-any-return]


def get_settings(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


def get_processor(request: Request) -> Processor:
    return request.app.state.processor  # type: ignore[no-any-return]


DbDep = Annotated[Database, Depends(get_db)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
ProcessorDep = Annotated[Processor, Depends(get_processor)]


def read_session(db: DbDep) -> Iterator[Session]:
    with db.read() as session:
        yield session


def write_session(db: DbDep) -> Iterator[Session]:
    with db.write() as session:
        yield session


ReadSessionDep = Annotated[Session, Depends(read_session, scope="function")]
WriteSessionDep = Annotated[Session, Depends(write_session, scope="function")]


def get_principal(
    db: DbDep, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> Principal:
    if creds is None:
        raise Unauthorized("missing Authorization header: send 'Authorization: Bearer <key>'")
    with db.read() as s:
        return authenticate(s, f"{creds.scheme} {creds.credentials}")


def scoped(scope: str) -> Callable[[Principal], Principal]:
    def _require(p: Annotated[Principal, Depends(get_principal)]) -> Principal:
        p.require(scope)
        return p

    return _require


ReadDep = Annotated[Principal, Depends(scoped("read"))]
IngestDep = Annotated[Principal, Depends(scoped("ingest"))]
AdminDep = Annotated[Principal, Depends(scoped("admin"))]


def read_actuator(tail: str, actuator_id: str, s: ReadSessionDep, p: ReadDep) -> Actuator:
    """The caller's actuator named by the path (404 for another operator's), in the request's
    read session."""
    return fleet.get_actuator(s, p.operator_id, tail, actuator_id)


ActuatorDep = Annotated[Actuator, Depends(read_actuator)]
