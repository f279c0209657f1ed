"""Dependencies shared by the routers, as ``Annotated`` aliases.

Endpoints are plain ``def`` functions: FastAPI runs them (and the session dependencies) in its
thread pool, so no endpoint wraps its work in a closure. A write session is one unit of work,
committed when the endpoint returns and before the response is sent (``scope="function"``); an
exception rolls it back.

The dependencies that block on nothing (the app's objects, a key remembered by the
:class:`~app.auth.service.KeyVerifier`, a scope check) are ``async``: FastAPI runs them in the
event loop, where a thread-pool hop would cost more than the work itself. Only a key that is not
remembered is read from the database, in a worker thread.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from app.auth.service import KeyVerifier, Principal
from app.config import Settings
from app.db import Database
from app.errors import Unauthorized
from app.fleet import service as fleet
from app.models import Actuator
from app.processing.processor import Processor

bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`")


async def get_db(request: Request) -> Database:
    return request.app.state.db  # type: ignore[no-any-return]


async def get_settings(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


async def get_processor(request: Request) -> Processor:
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


def _authorization(creds: HTTPAuthorizationCredentials | None) -> str:
    if creds is None:
        raise Unauthorized("missing Authorization header: send 'Authorization: Bearer <key>'")
    return f"{creds.scheme} {creds.credentials}"


async def get_principal(
    request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> Principal:
    authorization = _authorization(creds)
    verifier: KeyVerifier = request.app.state.key_verifier
    found = verifier.cached(authorization)
    if found is not None:
        return found
    return await run_in_threadpool(verifier.verify, authorization)


def verify_principal(request: Request, creds: HTTPAuthorizationCredentials | None) -> Principal:
    """:func:`get_principal` for code already in a worker thread (blocking)."""
    verifier: KeyVerifier = request.app.state.key_verifier
    return verifier.verify(_authorization(creds))


def scoped(scope: str) -> Callable[[Principal], Awaitable[Principal]]:
    async def _require(p: Annotated[Principal, Depends(get_principal)]) -> Principal:
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
