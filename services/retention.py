"""Retention of raw uploads: an upload is kept ``CSR_RAW_RETENTION_DAYS`` after it was received,
then deleted by the background loop of every deployment (``workers.loop``). The trip record, its
single-trip reconstruction, its poses and the map stay; the trip's ``raw_purged_at`` says when the
upload went, and ``csr reprocess`` says that such a trip has nothing to recompute from.

An upload whose ingest has not finished (the trip is ``received``, or an ingest job is queued or
running) is kept until it has: deleting it would lose the trip."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import cast

from sqlalchemy import CursorResult, delete, select, update
from sqlalchemy.orm import Session

from services.db.models import Job, Trip, TripUpload, utcnow

BATCH = 500  # uploads deleted per transaction


@dataclass(frozen=True, slots=True)
class RetentionResult:
    purged: int  # raw uploads deleted
    cutoff: datetime  # uploads received before this were due


def retention_cutoff(*, retention_days: float, now: datetime) -> datetime:
    return now - timedelta(days=retention_days)


def expired_uploads(session: Session, *, cutoff: datetime, limit: int = BATCH) -> list[str]:
    """Trips whose raw upload is still stored, received before ``cutoff``, and ingested (no ingest
    job queued or running): their uploads may go."""
    pending_ingest = (
        select(Job.id)
        .where(Job.kind == "ingest_trip", Job.subject == Trip.id, Job.state.in_(("queued", "running")))
        .exists()
    )
    stmt = (
        select(Trip.id)
        .join(TripUpload, TripUpload.trip_pk == Trip.id)
        .where(Trip.received_at < cutoff, Trip.status != "received", ~pending_ingest)
        .order_by(Trip.received_at, Trip.id)
        .limit(limit)
    )
    return list(session.scalars(stmt))


def purge_raw_uploads(session: Session, *, trip_pks: Sequence[str], now: datetime) -> int:
    """Delete the trips' raw uploads and stamp ``raw_purged_at``; returns how many were deleted."""
    if not trip_pks:
        return 0
    deleted = cast(
        CursorResult, session.execute(delete(TripUpload).where(TripUpload.trip_pk.in_(list(trip_pks))))
    ).rowcount
    session.execute(
        update(Trip)
        .where(Trip.id.in_(list(trip_pks)), Trip.raw_purged_at.is_(None))
        .values(raw_purged_at=now)
        .execution_options(synchronize_session=False)
    )
    return deleted


def purge_expired(session_factory, *, retention_days: float, now: datetime | None = None) -> RetentionResult:
    """Delete every raw upload past its retention, ``BATCH`` per transaction."""
    now = now or utcnow()
    cutoff = retention_cutoff(retention_days=retention_days, now=now)
    total = 0
    while True:
        with session_factory.begin() as session:
            due = expired_uploads(session, cutoff=cutoff)
            total += purge_raw_uploads(session, trip_pks=due, now=now)
        if len(due) < BATCH:
            return RetentionResult(purged=total, cutoff=cutoff)
