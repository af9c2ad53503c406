"""``GET /v1/jobs/summary`` and ``POST /v1/process``."""

from __future__ import annotations

from fastapi import APIRouter

from services.api import answers
from services.api.deps import Admin, Ctx, Reader, ReadSessionDep, SessionDep
from services.db import repo

router = APIRouter(prefix="/v1", tags=["jobs"])


@router.get(
    "/jobs/summary",
    responses={200: answers.answer(answers.JobsSummary, "Job counts and dirty tiles")},
)
def jobs_summary(_: Reader, session: ReadSessionDep) -> dict[str, int]:
    return repo.job_summary(session)


@router.post(
    "/process",
    status_code=202,
    responses={202: answers.answer(answers.Processed, "The jobs scheduled")},
)
def process_now(_: Admin, ctx: Ctx, session: SessionDep) -> dict:
    """Schedule a job for every dirty tile now, without waiting for the quiet period."""
    with session.begin():
        jobs = repo.schedule_dirty_tiles(session, last_marked_before=None)
        scheduled = [{"job_id": job.id, "tile": job.subject} for job in jobs]
    ctx.runner.wake()
    return {"scheduled": len(scheduled), "jobs": scheduled}
