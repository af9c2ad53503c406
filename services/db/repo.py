"""Repository functions: keyword-only, typed, one short unit of work each. The caller owns the
transaction (``with session.begin(): ...``) unless a function says otherwise."""

from __future__ import annotations

import hashlib
import hmac
import secrets
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime, timedelta
from typing import Any, cast

from sqlalchemy import ColumnElement, CursorResult, case, delete, func, or_, select, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert
from sqlalchemy.orm import Session, aliased

from services.db.models import (
    ApiKey,
    DirtyTile,
    Job,
    Trip,
    TripReconstructionRecord,
    TripTile,
    TripUpload,
    utcnow,
)
from services.tile_frames import tile_subject

ROLES = ("vehicle", "reader", "admin")
BOOTSTRAP_ADMIN_ID = "admin-bootstrap"
QUEUE_OF_KIND = {
    "ingest_trip": "ingest",
    "align_tile": "align",
    "correct_tile": "align",
    "merge_tile": "merge",
}
QUEUES = ("ingest", "align", "merge")
JOB_STATES = ("queued", "running", "done", "failed")


def new_id() -> str:
    return str(uuid.uuid4())


def _insert(session: Session):
    return pg_insert if session.get_bind().dialect.name == "postgresql" else sqlite_insert


# --- keys ---------------------------------------------------------------------------------------


def hash_key(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def ensure_bootstrap_admin(session: Session, *, secret: str) -> None:
    """Make ``secret`` the (only) bootstrap admin key, replacing a previous one."""
    row = session.get(ApiKey, BOOTSTRAP_ADMIN_ID)
    digest = hash_key(secret)
    if row is None:
        session.add(ApiKey(id=BOOTSTRAP_ADMIN_ID, key_sha256=digest, role="admin", vehicle_id=None))
    else:
        row.key_sha256, row.role, row.revoked_at = digest, "admin", None


def create_key(session: Session, *, role: str, vehicle_id: str | None) -> tuple[ApiKey, str]:
    """A new key; returns the row and the secret (the only time it exists in clear)."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}")
    secret = "csr_" + secrets.token_urlsafe(32)
    row = ApiKey(
        id="key_" + secrets.token_hex(8), key_sha256=hash_key(secret), role=role, vehicle_id=vehicle_id
    )
    session.add(row)
    return row, secret


def revoke_key(session: Session, *, key_id: str) -> bool:
    result = session.execute(
        update(ApiKey).where(ApiKey.id == key_id, ApiKey.revoked_at.is_(None)).values(revoked_at=utcnow())
    )
    return cast(CursorResult, result).rowcount == 1


def active_key(session: Session, *, secret: str) -> ApiKey | None:
    digest = hash_key(secret)
    row = session.scalars(select(ApiKey).where(ApiKey.key_sha256 == digest)).one_or_none()
    if row is None or row.revoked_at is not None or not hmac.compare_digest(row.key_sha256, digest):
        return None
    return row


# --- trips --------------------------------------------------------------------------------------


def find_trip(session: Session, *, vehicle_id: str, trip_id: str) -> Trip | None:
    return session.scalars(
        select(Trip).where(Trip.vehicle_id == vehicle_id, Trip.trip_id == trip_id)
    ).one_or_none()


def get_trip(session: Session, *, trip_pk: str) -> Trip | None:
    return session.get(Trip, trip_pk)


def add_trip(
    session: Session,
    *,
    vehicle_id: str,
    trip_id: str,
    content_sha256: str,
    schema_version: str,
    started_at: str,
    n_frames: int,
    body_bytes: int,
    json_bytes: int,
    raw_gzip: bytes,
    encoding: str = "gzip",
) -> tuple[Trip, Job]:
    """A received trip, its raw upload and its ingest job (the outbox row), to be committed together."""
    trip = Trip(
        id=new_id(),
        vehicle_id=vehicle_id,
        trip_id=trip_id,
        content_sha256=content_sha256,
        status="received",
        schema_version=schema_version,
        started_at=started_at,
        n_frames=n_frames,
        body_bytes=body_bytes,
        json_bytes=json_bytes,
    )
    session.add(trip)
    session.flush()  # the trip row first: the upload references it
    session.add(TripUpload(trip_pk=trip.id, encoding=encoding, body=raw_gzip))
    job = add_job(session, kind="ingest_trip", subject=trip.id)
    return trip, job


def raw_upload(session: Session, *, trip_pk: str) -> TripUpload | None:
    return session.get(TripUpload, trip_pk)


def tiles_of_trip(session: Session, *, trip_pk: str) -> list[TripTile]:
    return list(
        session.scalars(
            select(TripTile).where(TripTile.trip_pk == trip_pk).order_by(TripTile.z, TripTile.x, TripTile.y)
        )
    )


def set_trip_tiles(
    session: Session, *, trip_pk: str, frames_of_tile: Mapping[tuple[int, int, int], int]
) -> None:
    """Replace the trip's tiles, each with the frames it owns (idempotent: a re-run writes the
    same rows)."""
    session.execute(delete(TripTile).where(TripTile.trip_pk == trip_pk))
    rows = [
        {"trip_pk": trip_pk, "z": z, "x": x, "y": y, "frames": n} for (z, x, y), n in frames_of_tile.items()
    ]
    if rows:
        session.execute(_insert(session)(TripTile), rows)


def mark_tiles_dirty(session: Session, *, tiles: Sequence[tuple[int, int, int]]) -> None:
    if not tiles:
        return
    now = utcnow()
    stmt = _insert(session)(DirtyTile).values(
        [{"z": z, "x": x, "y": y, "first_marked_at": now, "last_marked_at": now} for z, x, y in tiles]
    )
    session.execute(stmt.on_conflict_do_update(index_elements=["z", "x", "y"], set_={"last_marked_at": now}))


# --- single-trip reconstructions -------------------------------------------------------------


def upsert_reconstruction(session: Session, *, trip_pk: str, values: dict[str, Any]) -> None:
    """Write the trip's reconstruction for ``values["algorithm_version"]``, replacing an earlier
    one of that version (a re-run or re-delivered job leaves exactly one row)."""
    row = {**values, "trip_pk": trip_pk, "created_at": utcnow()}
    stmt = _insert(session)(TripReconstructionRecord).values(row)
    session.execute(
        stmt.on_conflict_do_update(
            index_elements=["trip_pk", "algorithm_version"],
            set_={k: v for k, v in row.items() if k not in ("trip_pk", "algorithm_version")},
        )
    )


def get_reconstruction(
    session: Session, *, trip_pk: str, algorithm_version: str
) -> TripReconstructionRecord | None:
    return session.get(TripReconstructionRecord, (trip_pk, algorithm_version))


def reconstruction_summary(
    session: Session, *, trip_pk: str, algorithm_version: str
) -> dict[str, Any] | None:
    """The small columns of the trip's reconstruction (not the pose blob nor the instance points)."""
    r = TripReconstructionRecord
    row = session.execute(
        select(
            r.algorithm_version,
            r.origin_lat,
            r.origin_lon,
            r.n_frames,
            r.n_keyframes,
            r.n_instances,
            r.noise,
            r.diagnostics,
            r.created_at,
        ).where(r.trip_pk == trip_pk, r.algorithm_version == algorithm_version)
    ).one_or_none()
    return None if row is None else row._asdict()


def trips_to_reprocess(session: Session, *, missing_version: str | None = None) -> list[str]:
    """Ids of the trips with a stored upload (all, or those without a reconstruction of
    ``missing_version``), oldest first."""
    stmt = select(Trip.id).join(TripUpload, TripUpload.trip_pk == Trip.id).order_by(Trip.received_at, Trip.id)
    if missing_version is not None:
        stmt = stmt.where(
            ~select(TripReconstructionRecord.trip_pk)
            .where(
                TripReconstructionRecord.trip_pk == Trip.id,
                TripReconstructionRecord.algorithm_version == missing_version,
            )
            .exists()
        )
    return list(session.scalars(stmt))


def count_purged_trips(session: Session) -> int:
    """Trips whose raw upload retention deleted (nothing to reprocess them from)."""
    return int(
        session.scalar(select(func.count()).select_from(Trip).where(Trip.raw_purged_at.is_not(None))) or 0
    )


def schedule_reprocess(session: Session, *, trip_pks: Sequence[str]) -> list[Job]:
    """An ingest job (the outbox row) for each trip that has no ingest job queued or running
    yet: it recomputes the trip from its kept upload. A running ingest job whose lease ran out
    does not count: it is recorded as failed and superseded by the new job."""
    now = utcnow()
    pending = session.scalars(
        select(Job)
        .where(Job.kind == "ingest_trip", Job.subject.in_(trip_pks), Job.state.in_(("queued", "running")))
        .with_for_update()
    ).all()
    stuck = [job for job in pending if lease_has_expired(job, now=now)]
    busy = {job.subject for job in pending} - {job.subject for job in stuck}
    for job in stuck:
        if job.subject not in busy:
            supersede_stuck_job(job, now=now)
    return [
        add_job(session, kind="ingest_trip", subject=pk) for pk in dict.fromkeys(trip_pks) if pk not in busy
    ]


# --- jobs ---------------------------------------------------------------------------------------


def add_job(session: Session, *, kind: str, subject: str) -> Job:
    job = Job(id=new_id(), kind=kind, queue=QUEUE_OF_KIND[kind], subject=subject, state="queued", attempts=0)
    session.add(job)
    return job


def get_job(session: Session, *, job_id: str, for_update: bool = False) -> Job | None:
    stmt = select(Job).where(Job.id == job_id)
    if for_update:
        stmt = stmt.with_for_update()
    return session.scalars(stmt).one_or_none()


def jobs_for_subject(session: Session, *, subject: str) -> list[Job]:
    return list(session.scalars(select(Job).where(Job.subject == subject).order_by(Job.created_at)))


def jobs_to_dispatch(
    session: Session, *, limit: int, redispatch_before: datetime | None, offset: int = 0
) -> list[Job]:
    """Outbox rows to hand to a runner: never dispatched, or (with ``redispatch_before``) queued so
    long that the broker may have lost the message; tile alignments after the other kinds, then
    oldest first. Rows are locked (``SKIP LOCKED`` on PostgreSQL) so that concurrent relays split
    them. ``workers.dispatch`` decides which of them go and in what order."""
    pending: ColumnElement[bool] = Job.dispatched_at.is_(None)
    if redispatch_before is not None:
        pending = or_(pending, (Job.state == "queued") & (Job.dispatched_at < redispatch_before))
    stmt = (
        select(Job)
        .where(pending)
        .where(Job.state.in_(("queued", "running")))
        .order_by(case((Job.kind == "align_tile", 1), else_=0), Job.created_at, Job.id)
        .offset(offset)
        .limit(limit)
        .with_for_update(skip_locked=True)
    )
    return list(session.scalars(stmt))


def reset_running_jobs(session: Session) -> int:
    """Embedded start-up: jobs left running by a previous process of this deployment run again."""
    return cast(
        CursorResult,
        session.execute(
            update(Job)
            .where(Job.state == "running")
            .values(state="queued", dispatched_at=None, lease_expires_at=None)
        ),
    ).rowcount


def _aware(moment: datetime) -> datetime:
    """SQLite gives back naive datetimes; every stored time is UTC."""
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)


def lease_expired_clause(now: datetime) -> ColumnElement[bool]:
    """SQL: a running job whose lease ran out before ``now``, or that has none."""
    return (Job.state == "running") & (Job.lease_expires_at.is_(None) | (Job.lease_expires_at < now))


def lease_has_expired(job: Job, *, now: datetime) -> bool:
    """:func:`lease_expired_clause` on a loaded row."""
    return job.state == "running" and (job.lease_expires_at is None or _aware(job.lease_expires_at) < now)


def requeue_expired_leases(session: Session, *, now: datetime) -> list[str]:
    """Queue again, as outbox rows, the running jobs whose lease ran out before ``now``: their
    runner stopped renewing it (a worker killed, a task cancelled when the broker went away), so
    nothing works on them, and their broker message may be lost too. Their attempts stay
    counted; a re-run is idempotent like any re-delivery. Rows locked elsewhere (a job finishing
    now) are skipped. Returns the ids."""
    ids = list(
        session.scalars(select(Job.id).where(lease_expired_clause(now)).with_for_update(skip_locked=True))
    )
    if ids:
        session.execute(
            update(Job)
            .where(Job.id.in_(ids), lease_expired_clause(now))
            .values(
                state="queued", dispatched_at=None, lease_expires_at=None, error="lease expired: queued again"
            )
            .execution_options(synchronize_session=False)  # rows loaded here may hold naive SQLite times
        )
    return ids


def forget_dispatches(session: Session) -> int:
    """Mark every queued job as not yet dispatched (the broker lost its messages): the outbox
    sends them again. Returns how many."""
    return cast(
        CursorResult,
        session.execute(
            update(Job)
            .where(Job.state == "queued", Job.dispatched_at.is_not(None))
            .values(dispatched_at=None)
        ),
    ).rowcount


def supersede_stuck_job(job: Job, *, now: datetime) -> None:
    """Record a running job whose lease ran out as failed, to be replaced by a new job (an admin
    retry, a reprocess); a late finish of its old run then writes nothing."""
    job.state, job.finished_at, job.lease_expires_at = "failed", now, None
    job.error = "lease expired: superseded by a new job"


def job_summary(session: Session) -> dict[str, int]:
    counts = dict(session.execute(select(Job.state, func.count()).group_by(Job.state)).all())
    # a failed job retried since (a newer job of the same kind and subject) is no longer outstanding
    newer = aliased(Job)
    retried = (
        session.scalar(
            select(func.count())
            .select_from(Job)
            .where(
                Job.state == "failed",
                select(newer.id)
                .where(
                    newer.kind == Job.kind, newer.subject == Job.subject, newer.created_at > Job.created_at
                )
                .exists(),
            )
        )
        or 0
    )
    counts["failed"] = counts.get("failed", 0) - retried
    dirty = session.scalar(select(func.count()).select_from(DirtyTile)) or 0
    return {
        "queued": int(counts.get("queued", 0)),
        "running": int(counts.get("running", 0)),
        "failed": int(counts.get("failed", 0)),
        "dirty_tiles": int(dirty),
    }


def job_counts(session: Session) -> list[tuple[str, str, int]]:
    """``(queue, state, count)`` for the metrics."""
    return [
        (queue, state, count)
        for queue, state, count in session.execute(
            select(Job.queue, Job.state, func.count()).group_by(Job.queue, Job.state)
        )
    ]


def job_duration_stats(
    session: Session, *, buckets: Sequence[float]
) -> dict[str, tuple[list[int], int, float]]:
    """Per job kind: cumulative counts at each bucket bound, total count and sum of finished durations."""
    columns = [func.sum(case((Job.duration_s <= b, 1), else_=0)) for b in buckets]
    rows = session.execute(
        select(Job.kind, func.count(), func.sum(Job.duration_s), *columns)
        .where(Job.duration_s.is_not(None))
        .group_by(Job.kind)
    ).all()
    return {r[0]: ([int(v or 0) for v in r[3:]], int(r[1]), float(r[2] or 0.0)) for r in rows}


def schedule_dirty_tiles(session: Session, *, last_marked_before: datetime | None) -> list[Job]:
    """Create a tile job for each dirty tile without one whose last new trip is older than
    ``last_marked_before`` (``None``: every dirty tile, now). Safe against concurrent schedulers.

    The biggest tiles (most frames of trips waiting) are queued first: with several workers the
    batch ends when its longest job does, so that one must not start last (longest processing
    time first), after the checkerboard colour (even x + y first). The runners take them in
    ``workers.dispatch``'s order, which also weighs the neighbours waiting for a tile."""
    waiting = (
        select(func.coalesce(func.sum(func.coalesce(TripTile.frames, 1)), 0))
        .select_from(TripTile)
        .where(
            TripTile.z == DirtyTile.z,
            TripTile.x == DirtyTile.x,
            TripTile.y == DirtyTile.y,
            TripTile.processed_job_id.is_(None),
        )
        .scalar_subquery()
    )
    stmt = select(DirtyTile).where(DirtyTile.job_id.is_(None))
    if last_marked_before is not None:
        stmt = stmt.where(DirtyTile.last_marked_at <= last_marked_before)
    # checkerboard: the tiles with x + y even first (the odd ones wait for their first versions,
    # ``workers.dispatch.neighbours_to_wait_for``), each colour biggest first
    stmt = stmt.order_by(
        (DirtyTile.x + DirtyTile.y) % 2, waiting.desc(), DirtyTile.z, DirtyTile.x, DirtyTile.y
    )
    jobs = []
    for tile in session.scalars(stmt.with_for_update(skip_locked=True)).all():
        job = add_job(session, kind="align_tile", subject=tile_subject(tile.z, tile.x, tile.y))
        taken = cast(
            CursorResult,
            session.execute(
                update(DirtyTile)
                .where(
                    DirtyTile.z == tile.z,
                    DirtyTile.x == tile.x,
                    DirtyTile.y == tile.y,
                    DirtyTile.job_id.is_(None),
                )
                .values(job_id=job.id)
            ),
        ).rowcount
        if taken:
            jobs.append(job)
        else:
            session.expunge(job)
    return jobs


def quiet_before(quiet_period_s: float) -> datetime:
    return utcnow() - timedelta(seconds=quiet_period_s)
