"""What each job does, for both runners (Celery tasks and the in-process pool).

A job takes its id, re-reads its state from the database, holds a lease while it runs
(``workers.lease``) and writes its result in one transaction that also marks it done; a job
already done is not run again, so a re-delivered or duplicated message never counts twice. A
bad input fails the job (recorded on it); a database outage (``OperationalError``) propagates so
that the runner retries the job.

- ``ingest_trip``: decode the stored upload (csr_core), compute the GNSS track, its length and
  the tiles owning its frames (by smoothed position), run single-trip reconstruction (``csr_core.single_trip``) in the trip's
  region frame, store its result (``trip_reconstructions``, upserted per algorithm version) and
  mark the tiles dirty. A trip that cannot be reconstructed fails with the reason. The same job
  recomputes a trip from its kept upload (``csr reprocess``).
- ``align_tile`` / ``merge_tile``: the per-tile alignment and merge (``workers.tile_jobs``). A merge
  that finds the tile written by another job meanwhile (``RetryJob``) is queued again.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import UTC
from typing import Any

import numpy as np
from sqlalchemy import select, update
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

from csr_core.errors import ReconstructionError
from csr_core.geo import LocalFrame, polyline_length_m, region_frame_for
from csr_core.single_trip import reconstruct_trip
from csr_core.tiling import owned_frame_counts
from services.db import repo
from services.db.engine import read_only
from services.db.models import Trip, TripTileAlignment, ewkt_linestring, utcnow
from services.reconstructions import row_values
from services.settings import Settings
from services.tile_frames import parse_tile
from services.upload_formats import stored_trip
from workers import tile_jobs
from workers.lease import LeaseHeartbeat, lease_until

log = logging.getLogger(__name__)


class JobFailed(Exception):
    """The job's input cannot be processed; recorded on the job (and the trip) as its failure."""


@dataclass(frozen=True, slots=True)
class IngestResult:
    length_km: float
    track_ewkt: str
    frames_of_tile: dict[tuple[int, int, int], int]  # the tiles owning the trip's frames, and how many
    reconstruction: dict[str, Any]  # trip_reconstructions columns (services.reconstructions)


def run_job(session_factory: sessionmaker[Session], settings: Settings, job_id: str) -> str:
    """Run one job to its end; returns the job's final state (or ``missing``)."""
    with session_factory.begin() as session:
        job = repo.get_job(session, job_id=job_id, for_update=True)
        if job is None:
            log.warning("job %s does not exist", job_id)
            return "missing"
        if job.state in ("done", "failed"):
            log.info("job %s is already %s: nothing to do", job_id, job.state)
            return job.state
        job.state, job.attempts, job.started_at = "running", job.attempts + 1, utcnow()
        job.dispatched_at = job.dispatched_at or job.started_at
        job.lease_expires_at = lease_until(settings.job_lease_s, now=job.started_at)
        kind, subject, attempt = job.kind, job.subject, job.attempts
    with LeaseHeartbeat(session_factory, job_id, settings.job_lease_s):
        return _run_started(session_factory, settings, job_id, kind, subject, attempt)


def _run_started(
    session_factory: sessionmaker[Session],
    settings: Settings,
    job_id: str,
    kind: str,
    subject: str,
    attempt: int,
) -> str:
    """The work of a job marked running, to its final state."""
    started = time.perf_counter()
    try:
        if kind == "ingest_trip":
            result = _compute_ingest(session_factory, trip_pk=subject, zoom=settings.tile_zoom)
            if settings.test_ingest_delay_s and attempt == 1:
                time.sleep(settings.test_ingest_delay_s)
            return _finish(session_factory, job_id, started, lambda s: _persist_ingest(s, subject, result))
        if kind == "align_tile":
            z, x, y = parse_tile(subject)
            aligned = tile_jobs.compute_align_tile(session_factory, settings, z, x, y)
            return _finish(
                session_factory,
                job_id,
                started,
                lambda s: tile_jobs.persist_align_tile(s, settings, job_id, z, x, y, aligned),
            )
        if kind == "correct_tile":  # the map team's corrections: re-align the whole tile with them
            z, x, y = parse_tile(subject)
            aligned = tile_jobs.compute_align_tile(session_factory, settings, z, x, y, full=True)
            return _finish(
                session_factory,
                job_id,
                started,
                lambda s: tile_jobs.persist_align_tile(s, settings, job_id, z, x, y, aligned),
            )
        if kind == "merge_tile":
            z, x, y = parse_tile(subject)
            merged = tile_jobs.compute_merge_tile(session_factory, settings, z, x, y)
            if settings.test_merge_delay_s and attempt == 1:
                time.sleep(settings.test_merge_delay_s)
            return _finish(
                session_factory,
                job_id,
                started,
                lambda s: tile_jobs.persist_merge_tile(s, job_id, z, x, y, merged),
            )
        raise JobFailed(f"unknown job kind {kind!r}")
    except OperationalError:  # the database is unreachable: transient, the runner retries the job
        raise
    except tile_jobs.RetryJob as exc:  # another job wrote the tile first (or a neighbour's comes first)
        log.info("job %s (%s %s) is queued again: %s", job_id, kind, subject, exc)
        return requeue_job(session_factory, job_id, exc, attempt_counts=exc.counts_as_attempt)
    except Exception as exc:  # recorded on the job: a failed job is visible in /v1/jobs/summary
        log.exception("job %s (%s %s) failed", job_id, kind, subject)
        return mark_job_failed(session_factory, job_id, exc, started=started)


def requeue_job(
    session_factory: sessionmaker[Session], job_id: str, exc: BaseException, attempt_counts: bool = True
) -> str:
    """Queue a running job again (the outbox hands it to a runner anew); ``attempt_counts``
    False: it did no work (it waits for another job), its attempt is given back."""
    with session_factory.begin() as session:
        job = repo.get_job(session, job_id=job_id, for_update=True)
        if job is None or job.state != "running":
            return job.state if job else "missing"
        job.state, job.dispatched_at, job.error = "queued", None, f"retrying: {exc}"
        job.lease_expires_at = None
        if not attempt_counts:
            job.attempts = max(job.attempts - 1, 0)
    return "queued"


def mark_job_failed(
    session_factory: sessionmaker[Session], job_id: str, exc: BaseException, *, started: float | None = None
) -> str:
    """Record a job's failure (and its trip's, for an ingest job), unless it already finished.
    Also called by the Celery task's ``on_failure`` (hard time limit, retries exhausted)."""
    with session_factory.begin() as session:
        job = repo.get_job(session, job_id=job_id, for_update=True)
        if job is None or job.state in ("done", "failed"):
            return job.state if job else "missing"
        job.state, job.error, job.finished_at = "failed", f"{type(exc).__name__}: {exc}", utcnow()
        job.lease_expires_at = None
        if started is not None:
            job.duration_s = time.perf_counter() - started
        elif job.started_at is not None:
            started_at = job.started_at if job.started_at.tzinfo else job.started_at.replace(tzinfo=UTC)
            job.duration_s = (job.finished_at - started_at).total_seconds()
        if job.kind == "ingest_trip":
            session.execute(
                update(Trip)
                .where(Trip.id == job.subject)
                .values(status="failed", error=str(exc), updated_at=utcnow())
            )
    return "failed"


def _finish(session_factory: sessionmaker[Session], job_id: str, started: float, persist) -> str:
    with session_factory.begin() as session:
        job = repo.get_job(session, job_id=job_id, for_update=True)
        if job is None or job.state in ("done", "failed"):
            # another delivery of the same message finished first: write nothing
            return job.state if job else "missing"
        persist(session)
        job.state, job.error, job.finished_at, job.lease_expires_at = "done", None, utcnow(), None
        job.duration_s = time.perf_counter() - started
    return "done"


def _compute_ingest(session_factory: sessionmaker[Session], *, trip_pk: str, zoom: int) -> IngestResult:
    with read_only(session_factory)() as session:
        upload = repo.raw_upload(session, trip_pk=trip_pk)
        if upload is None:
            raise JobFailed(f"trip {trip_pk} has no stored upload")
        encoding, body = upload.encoding, upload.body
    trip = stored_trip(encoding, body)  # a JSON upload frame batch by frame batch: no whole parsed tree
    lonlat_deg = trip.gnss_lonlat_deg[trip.has_fix]
    if len(lonlat_deg) < 2:
        raise JobFailed("the trip has fewer than two frames with a GNSS fix")
    # consecutive duplicate fixes add nothing to the track
    keep = np.concatenate([[True], np.any(np.diff(lonlat_deg, axis=0) != 0, axis=1)])
    lonlat_deg = lonlat_deg[keep]
    if len(lonlat_deg) < 2:
        lonlat_deg = np.repeat(lonlat_deg, 2, axis=0)
    frame = LocalFrame.around(lonlat_deg)
    length_m = polyline_length_m(frame.to_local(lonlat_deg))
    region = region_frame_for(lonlat_deg[0])  # the first fix's region: shared by the trips around it
    try:  # single-trip reconstruction (paper III-C)
        reconstruction = reconstruct_trip(trip, region)
    except ReconstructionError as exc:  # the input, not a transient fault: fail, do not retry
        raise JobFailed(f"single-trip reconstruction failed: {exc}") from exc
    return IngestResult(
        length_km=length_m / 1000.0,
        track_ewkt=ewkt_linestring(lonlat_deg),
        frames_of_tile=owned_frame_counts(reconstruction.poses_xyyaw_world, region, zoom),
        reconstruction=row_values(reconstruction, region),
    )


def _persist_ingest(session: Session, trip_pk: str, result: IngestResult) -> None:
    trip = session.get(Trip, trip_pk)
    if trip is None:
        raise JobFailed(f"trip {trip_pk} does not exist")
    trip.length_km, trip.track, trip.updated_at = result.length_km, result.track_ewkt, utcnow()
    if trip.status in ("received", "failed", "aligned"):  # failed / aligned: reprocessed
        trip.status, trip.error = "processing", None
    kept = list(result.frames_of_tile)
    for old in session.scalars(select(TripTileAlignment).where(TripTileAlignment.trip_pk == trip_pk)):
        if (old.z, old.x, old.y) not in kept:  # a tile the trip no longer crosses
            session.delete(old)
    repo.upsert_reconstruction(session, trip_pk=trip_pk, values=result.reconstruction)
    repo.set_trip_tiles(session, trip_pk=trip_pk, frames_of_tile=result.frames_of_tile)
    repo.mark_tiles_dirty(session, tiles=kept)
