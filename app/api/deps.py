"""Dependencies shared by the routers."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from app.config import Settings
from app.db import Database
from app.errors import Unauthorized
from app.processing import Processor
from app.security import Principal, authenticate

bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`")


def get_db(request: Request) -> Database:
    return request.app.state.db  # type: ignore[no-any-return]


def get_settings(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


def get_processor(request: Request) -> Processor:
    return request.app.state.processor  # type: ignore[no-any-return]


async def get_principal(
    db: Annotated[Database, Depends(get_db)],
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> Principal:
    if creds is None:
        raise Unauthorized("missing Authorization header: send 'Authorization: Bearer <key>'")
    header = f"{creds.scheme} {creds.credentials}"

    def _auth() -> Principal:
        with db.read() as s:
            return authenticate(s, header)

    return await run_in_threadpool(_auth)


def scoped(scope: str):  # type: ignore[no-untyped-def]
    async def _dep(p: Annotated[Principal, Depends(get_principal)]) -> Principal:
        p.require(scope)
        return p

    return _dep


DbDep = Annotated[Database, Depends(get_db)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
ProcessorDep = Annotated[Processor, Depends(get_processor)]
ReadDep = Annotated[Principal, Depends(scoped("read"))]
IngestDep = Annotated[Principal, Depends(scoped("ingest"))]
AdminDep = Annotated[Principal, Depends(scoped("admin"))]
