"""``POST /v1/keys`` and ``DELETE /v1/keys/{id}`` (admin)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Body, Response
from pydantic import BaseModel, ConfigDict, Field, StringConstraints

from services.api import answers
from services.api.deps import Admin, SessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.db import repo

router = APIRouter(prefix="/v1/keys", tags=["keys"])


VehicleId = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9._:-]{1,64}$")]


class VehicleKeyRequest(BaseModel):
    """A vehicle's key: it uploads for this ``vehicle_id`` only."""

    model_config = ConfigDict(extra="forbid")

    role: Literal["vehicle"]
    vehicle_id: VehicleId


class ReaderKeyRequest(BaseModel):
    """A reader's key (no ``vehicle_id``)."""

    model_config = ConfigDict(extra="forbid")

    role: Literal["reader"]
    vehicle_id: None = None


class AdminKeyRequest(BaseModel):
    """An admin's key (no ``vehicle_id``)."""

    model_config = ConfigDict(extra="forbid")

    role: Literal["admin"]
    vehicle_id: None = None


# ``role`` picks the body's shape, so that the document says which fields go with which role
KeyRequest = Annotated[VehicleKeyRequest | ReaderKeyRequest | AdminKeyRequest, Field(discriminator="role")]


@router.post(
    "",
    status_code=201,
    responses={201: answers.answer(answers.KeyCreated, "The new key; its secret is shown only here")},
)
def create_key(request: Annotated[KeyRequest, Body()], _: Admin, session: SessionDep) -> dict:
    with session.begin():
        row, secret = repo.create_key(session, role=request.role, vehicle_id=request.vehicle_id)
    return {"id": row.id, "key": secret, "role": row.role, "vehicle_id": row.vehicle_id}


@router.delete(
    "/{key_id}",
    status_code=204,
    response_class=Response,
    responses=errors({404: {"not_found": "no active key with this id (unknown or already revoked)."}}),
)
def revoke_key(key_id: str, _: Admin, session: SessionDep) -> Response:
    with session.begin():
        revoked = repo.revoke_key(session, key_id=key_id)
    if not revoked:
        raise ApiError(404, "not_found", f"no active key {key_id!r}", location="id")
    return Response(status_code=204)
