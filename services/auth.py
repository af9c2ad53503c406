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


def may_read_trace(caller: Caller, trip_vehicle_id: str, *, reader_sees_traces: bool) -> None:
    """A trip's traces (poses, track, raw upload): admin keys all, a vehicle key its own trips'; reader
    keys only while ``CSR_READER_SEES_TRACES`` is true (the default: the contract lets readers read
    poses)."""
    may_read_trip(caller, trip_vehicle_id)
    if caller.role == "reader" and not reader_sees_traces:
        raise ApiError(
            403,
            "forbidden",
            "reader keys may not read trip traces on this deployment (CSR_READER_SEES_TRACES=false)",
        )
