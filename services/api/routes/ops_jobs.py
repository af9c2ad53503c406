"""Ops: ``GET /v1/jobs`` (with errors), ``GET /v1/jobs/{id}``, ``GET /v1/tiles/dirty`` and
``POST /v1/jobs/{id}/retry``.

A retry does not touch the failed job: it adds a NEW job of the same kind and subject, an outbox
row like any other (``dispatched_at`` NULL), committed in one transaction with what points at it
(the tile's dirty row, the trip's status), and wakes the runner. Why a new row: the failed row stays
as the record of what went wrong (its error, attempts and duration); ``run_job`` deliberately
refuses a job already ``failed`` so that a stale or duplicated message never runs it twice; and the
Celery task id is the job id, so a fresh id is a fresh message on both runners. The failed job is
linked forward by ``retried_by`` in the listings (the newer job of the same kind and subject).
A running job whose lease ran out (``workers.lease``: no worker renews it) is first recorded as
failed, then retried the same way; a late finish of its old run writes nothing.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import JSONResponse
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from services.api import answers
from services.api.deps import Admin, Ctx, Reader, ReadSessionDep, SessionDep
from services.api.errors import ApiError
from services.api.openapi import errors
from services.db import repo
from services.db.models import DirtyTile, Job, Trip, TripTile, utcnow

router = APIRouter(prefix="/v1", tags=["ops"])

MAX_LIMIT = 500


def _iso(moment: datetime | None) -> str | None:
    if moment is None:
        return None
    return (moment if moment.tzinfo else moment.replace(tzinfo=UTC)).isoformat()


def job_json(job: Job, *, retried_by: str | None = None) -> dict[str, Any]:
    return {
        "id": job.id,
        "kind": job.kind,
        "queue": job.queue,
        "subject": job.subject,
        "state": job.state,
        "attempts": job.attempts,
        "error": job.error,
        "created_at": _iso(job.created_at),
        "dispatched_at": _iso(job.dispatched_at),
        "started_at": _iso(job.started_at),
        "finished_at": _iso(job.finished_at),
        "duration_s": job.duration_s,
        "lease_expires_at": _iso(job.lease_expires_at),
        "retried_by": retried_by,
    }


def _retried_by(session: Session, jobs: list[Job]) -> dict[str, str]:
    """For each failed job: the id of the newest later job of the same kind and subject."""
    failed = [j for j in jobs if j.state == "failed"]
    if not failed:
        return {}
    later = session.scalars(
        select(Job)
        .where(Job.subject.in_({j.subject for j in failed}), Job.kind.in_({j.kind for j in failed}))
        .order_by(Job.created_at)
    ).all()
    out: dict[str, str] = {}
    for job in failed:
        newer = [
            j
            for j in later
            if j.kind == job.kind and j.subject == job.subject and j.created_at > job.created_at
        ]
        if newer:
            out[job.id] = newer[-1].id
    return out


@router.get(
    "/jobs",
    responses={
        200: answers.answer(answers.Jobs, "Jobs, newest first, and the counts per queue and state"),
        **errors({422: {"query": "`state` or `kind` is not one of the known ones."}}),
    },
)
def list_jobs(
    _: Reader,
    session: ReadSessionDep,
    state: Annotated[
        str | None, Query(description="a job state", json_schema_extra={"enum": list(repo.JOB_STATES)})
    ] = None,
    kind: Annotated[
        str | None, Query(description="a job kind", json_schema_extra={"enum": list(repo.QUEUE_OF_KIND)})
    ] = None,
    subject: Annotated[str | None, Query(description="a trip id or z/x/y")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT)] = 100,
) -> dict[str, Any]:
    """Jobs, newest first, with their errors; ``queues``: job counts per queue and state (all jobs)."""
    if state is not None and state not in repo.JOB_STATES:
        raise ApiError(422, "query", f"state must be one of {', '.join(repo.JOB_STATES)}", location="state")
    if kind is not None and kind not in repo.QUEUE_OF_KIND:
        raise ApiError(422, "query", f"kind must be one of {', '.join(repo.QUEUE_OF_KIND)}", location="kind")
    stmt = select(Job).order_by(Job.created_at.desc(), Job.id).limit(limit)
    if state is not None:
        stmt = stmt.where(Job.state == state)
    if kind is not None:
        stmt = stmt.where(Job.kind == kind)
    if subject is not None:
        stmt = stmt.where(Job.subject == subject)
    jobs = list(session.scalars(stmt))
    retried = _retried_by(session, jobs)
    queues: dict[str, dict[str, int]] = {q: dict.fromkeys(repo.JOB_STATES, 0) for q in repo.QUEUES}
    for queue, job_state, count in repo.job_counts(session):
        queues.setdefault(queue, dict.fromkeys(repo.JOB_STATES, 0))[job_state] = int(count)
    return {"jobs": [job_json(j, retried_by=retried.get(j.id)) for j in jobs], "queues": queues}


def _load_job(session: Session, job_id: str) -> Job:
    job = repo.get_job(session, job_id=job_id)
    if job is None:
        raise ApiError(404, "not_found", f"no job {job_id!r}", location="id")
    return job


@router.get(
    "/jobs/{job_id}",
    responses={
        200: answers.answer(answers.Job, "The job"),
        **errors({404: {"not_found": "no job with this id."}}),
    },
)
def get_job(job_id: str, _: Reader, session: ReadSessionDep) -> dict[str, Any]:
    job = _load_job(session, job_id)
    return job_json(job, retried_by=_retried_by(session, [job]).get(job.id))


@router.get(
    "/tiles/dirty",
    responses={200: answers.answer(answers.DirtyTiles, "Tiles with trips not yet processed")},
)
def dirty_tiles(
    _: Reader, session: ReadSessionDep, limit: Annotated[int, Query(ge=1, le=10 * MAX_LIMIT)] = 1000
) -> dict[str, Any]:
    """Tiles with trips not yet processed, oldest mark first: the job scheduled for each (if any)
    and how many of its trips wait."""
    pending = (
        select(TripTile.z, TripTile.x, TripTile.y, func.count().label("n"))
        .where(TripTile.processed_job_id.is_(None))
        .group_by(TripTile.z, TripTile.x, TripTile.y)
        .subquery()
    )
    rows = session.execute(
        select(DirtyTile, Job.state, pending.c.n)
        .outerjoin(Job, Job.id == DirtyTile.job_id)
        .outerjoin(
            pending,
            (pending.c.z == DirtyTile.z) & (pending.c.x == DirtyTile.x) & (pending.c.y == DirtyTile.y),
        )
        .order_by(DirtyTile.first_marked_at, DirtyTile.z, DirtyTile.x, DirtyTile.y)
        .limit(limit)
    ).all()
    return {
        "tiles": [
            {
                "tile": f"{t.z}/{t.x}/{t.y}",
                "z": t.z,
                "x": t.x,
                "y": t.y,
                "first_marked_at": _iso(t.first_marked_at),
                "last_marked_at": _iso(t.last_marked_at),
                "job_id": t.job_id,
                "job_state": job_state,
                "pending_trips": int(n or 0),
            }
            for t, job_state, n in rows
        ]
    }


@router.post(
    "/jobs/{job_id}/retry",
    status_code=202,
    response_class=JSONResponse,
    responses={
        202: answers.answer(
            answers.Job, "The new job (`retry_of`: the failed one)", headers=answers.LOCATION_HEADER
        ),
        **errors(
            {
                404: {"not_found": "no job with this id."},
                409: {
                    "not_failed": "the job did not fail (nor did its lease run out).",
                    "superseded": "a newer job for the same subject exists.",
                },
            }
        ),
    },
)
def retry_job(job_id: str, _: Admin, ctx: Ctx, session: SessionDep) -> JSONResponse:
    """Queue a failed job again, as a new job of the same kind and subject (see the module doc). A
    running job whose lease ran out (no worker renews it) is recorded as failed and retried alike.
    409 when the job did not fail, or when a newer job for the same subject exists already."""
    with session.begin():
        failed = repo.get_job(session, job_id=job_id, for_update=True)
        if failed is None:
            raise ApiError(404, "not_found", f"no job {job_id!r}", location="id")
        if repo.lease_has_expired(failed, now=utcnow()):
            repo.supersede_stuck_job(failed, now=utcnow())
        if failed.state != "failed":
            raise ApiError(
                409,
                "not_failed",
                f"job {job_id} is {failed.state}: only a failed job, or a running "
                "one whose lease ran out, is retried",
            )
        newer = session.scalars(
            select(Job.id)
            .where(Job.kind == failed.kind, Job.subject == failed.subject, Job.created_at > failed.created_at)
            .order_by(Job.created_at.desc())
            .limit(1)
        ).first()
        if newer is not None:
            raise ApiError(
                409,
                "superseded",
                f"job {job_id} already has a newer {failed.kind} job for {failed.subject}: {newer}",
            )
        job = repo.add_job(session, kind=failed.kind, subject=failed.subject)
        session.flush()
        # what pointed at the failed job points at the new one
        session.execute(update(DirtyTile).where(DirtyTile.job_id == failed.id).values(job_id=job.id))
        if failed.kind == "ingest_trip":
            session.execute(
                update(Trip)
                .where(Trip.id == failed.subject, Trip.status == "failed")
                .values(status="received", error=None, updated_at=utcnow())
            )
        body = {**job_json(job), "retry_of": failed.id}
    ctx.runner.wake()
    return JSONResponse(body, status_code=202, headers={"Location": f"/v1/jobs/{body['id']}"})
