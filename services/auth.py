"""Keys and roles (contract section 2): who is calling, and what each role may do."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from services.api.errors import ApiError
from services.db import repo


@dataclass(frozen=True, slots=True)
class Caller:
    key_id: str
    role: str  # vehicle | reader | admin
    vehicle_id: str | None  # vehicle keys only


def bearer_secret(authorization: str | None) -> str:
    scheme, _, secret = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not secret.strip():
        raise ApiError(
            401,
            "unauthorized",
            "missing API key: send Authorization: Bearer <key>",
            headers={"WWW-Authenticate": "Bearer"},
        )
    return secret.strip()


def authenticate(session_factory: sessionmaker[Session], authorization: str | None) -> Caller:
    secret = bearer_secret(authorization)
    with session_factory() as session:
        row = repo.active_key(session, secret=secret)
    if row is None:
        raise ApiError(
            401, "unauthorized", "unknown or revoked API key", headers={"WWW-Authenticate": "Bearer"}
        )
    return Caller(key_id=row.id, role=row.role, vehicle_id=row.vehicle_id)


def authorize(caller: Caller, roles: tuple[str, ...]) -> Caller:
    if caller.role not in roles:
        raise ApiError(
            403, "forbidden", f"a {caller.role} key may not make this call (needs: {', '.join(roles)})"
        )
    return caller


def may_read_trip(caller: Caller, trip_vehicle_id: str) -> None:
    """Vehicle keys read only their own trips."""
    if caller.role == "vehicle" and caller.vehicle_id != trip_vehicle_id:
        raise ApiError(403, "forbidden", f"this key reads trips of vehicle {caller.vehicle_id!r} only")
