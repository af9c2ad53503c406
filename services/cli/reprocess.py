"""`csr reprocess (--trip ID ... | --all | --stale) [--wait S]`: recompute trips from their kept
raw uploads. Each trip gets a new ingest job (through the job table, the transactional outbox),
which the deployment's runners (`csr serve` embedded, or `csr worker`) execute like any ingest:
the single-trip reconstruction of the current algorithm version is upserted, the track, length
and tiles rewritten and the tiles marked dirty again. A trip that failed becomes ``processing``
when it now succeeds. A trip whose raw upload retention deleted (``raw_purged_at``) has nothing to
recompute from: ``--trip`` names it and exits 2, ``--all`` / ``--stale`` leave it out and say how
many. Configured like `csr serve` (CSR_DATABASE_URL / CSR_DATA_DIR)."""

from __future__ import annotations

import argparse
import sys
import time

_POLL_S = 0.5


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reprocess", help="recompute trips from their raw uploads (new ingest jobs)")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--trip", action="append", metavar="ID", help="a trip id (repeatable)")
    which.add_argument("--all", action="store_true", help="every trip")
    which.add_argument(
        "--stale", action="store_true", help="trips without a reconstruction of the current algorithm version"
    )
    p.add_argument(
        "--wait",
        type=float,
        default=0.0,
        metavar="S",
        help="wait up to S seconds for the jobs to finish (needs a running deployment); exit 1 if any failed",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from services.db import repo
    from services.db.engine import make_engine, make_session_factory, migrate
    from services.reconstructions import ALGORITHM_VERSION
    from services.settings import get_settings

    settings = get_settings()
    engine = make_engine(settings.sqlalchemy_url)
    try:
        migrate(engine)
        session_factory = make_session_factory(engine)
        with session_factory.begin() as session:
            if args.trip:
                missing = [pk for pk in args.trip if repo.raw_upload(session, trip_pk=pk) is None]
                for pk in missing:
                    trip = repo.get_trip(session, trip_pk=pk)
                    if trip is None:
                        print(f"csr reprocess: no trip {pk}", file=sys.stderr)
                    elif trip.raw_purged_at is not None:
                        print(
                            f"csr reprocess: trip {pk} has no raw upload to recompute from: it was deleted "
                            f"at {trip.raw_purged_at.isoformat()} (CSR_RAW_RETENTION_DAYS); its reconstruction "
                            "and the map keep what it contributed",
                            file=sys.stderr,
                        )
                    else:
                        print(f"csr reprocess: trip {pk} has no stored upload", file=sys.stderr)
                if missing:
                    return 2
                trip_pks = list(args.trip)
            else:
                trip_pks = repo.trips_to_reprocess(
                    session, missing_version=ALGORITHM_VERSION if args.stale else None
                )
                purged = repo.count_purged_trips(session)
                if purged:
                    print(
                        f"csr reprocess: {purged} trip(s) left out: their raw uploads were deleted "
                        "(CSR_RAW_RETENTION_DAYS)"
                    )
            jobs = repo.schedule_reprocess(session, trip_pks=trip_pks)
            job_ids = [job.id for job in jobs]
        print(
            f"csr reprocess: {len(job_ids)} ingest job(s) scheduled for {len(trip_pks)} trip(s) "
            f"(algorithm {ALGORITHM_VERSION}); the rest already had one queued or running"
        )
        if args.wait <= 0 or not job_ids:
            return 0
        return _wait(session_factory, job_ids, args.wait)
    finally:
        engine.dispose()


def _wait(session_factory, job_ids: list[str], timeout_s: float) -> int:
    from sqlalchemy import select

    from services.db.models import Job

    deadline = time.monotonic() + timeout_s
    while True:
        with session_factory() as session:
            states = dict(session.execute(select(Job.id, Job.state).where(Job.id.in_(job_ids))).all())
        open_jobs = [j for j in job_ids if states.get(j) in ("queued", "running")]
        if not open_jobs:
            failed = [j for j in job_ids if states.get(j) == "failed"]
            print(f"csr reprocess: {len(job_ids) - len(failed)} done, {len(failed)} failed")
            return 1 if failed else 0
        if time.monotonic() > deadline:
            print(f"csr reprocess: {len(open_jobs)} job(s) still open after {timeout_s:g} s", file=sys.stderr)
            return 1
        time.sleep(_POLL_S)
