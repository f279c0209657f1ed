"""API keys over HTTP."""

from __future__ import annotations

from fastapi import APIRouter

from app.auth import schemas, service
from app.deps import AdminDep, WriteSessionDep
from app.errors import error_responses

router = APIRouter(prefix="/v1", tags=["fleet"])


@router.post("/keys", status_code=201, response_model=schemas.KeyCreated, responses=error_responses(401, 403, 422))
def create_api_key(body: schemas.KeyCreate, s: WriteSessionDep, p: AdminDep) -> schemas.KeyCreated:
    """Create another API key for the caller's operator (admin scope). The key is shown once."""
    row, plaintext = service.create_key(s, p.operator, list(body.scopes), name=body.name)
    return schemas.KeyCreated(
        id=row.id, name=row.name, prefix=row.prefix, scopes=row.scopes.split(","), key=plaintext
    )
