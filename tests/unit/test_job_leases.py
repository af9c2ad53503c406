"""Job leases and lost broker messages (services.db.repo, workers.lease, workers.outbox) on an
embedded SQLite database: which running jobs count as abandoned, what is queued again, and that
a heartbeat keeps a working job's lease alive."""

from __future__ import annotations

import time
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from services.db import repo
from services.db.engine import make_engine, make_session_factory, migrate
from services.db.models import Job, utcnow
from workers.lease import LeaseHeartbeat
from workers.outbox import BROKER_MARKER_KEY, resend_if_broker_lost_messages

pytestmark = pytest.mark.unit


@pytest.fixture
def sessions(tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    engine = make_engine(f"sqlite:///{tmp_path / 'csr.sqlite3'}", busy_timeout_s=5.0)
    migrate(engine)
    yield make_session_factory(engine)
    engine.dispose()


def _job(
    session: Session, name: str, state: str, *, lease_in_s: float | None, dispatched: bool = True
) -> str:
    job = repo.add_job(session, kind="ingest_trip", subject=name)
    now = utcnow()
    job.state, job.attempts = state, 1 if state != "queued" else 0
    job.dispatched_at = now if dispatched else None
    job.lease_expires_at = None if lease_in_s is None else now + timedelta(seconds=lease_in_s)
    return job.id


def _states(sessions: sessionmaker[Session]) -> dict[str, tuple]:
    with sessions() as session:
        return {j.subject: (j.state, j.dispatched_at is not None, j.attempts) for j in session.query(Job)}


def test_only_running_jobs_whose_lease_ran_out_or_is_missing_are_queued_again(sessions) -> None:
    with sessions.begin() as session:
        _job(session, "live", "running", lease_in_s=60)
        _job(session, "expired", "running", lease_in_s=-1)
        _job(session, "no-lease", "running", lease_in_s=None)
        _job(session, "queued", "queued", lease_in_s=None)
        _job(session, "done", "done", lease_in_s=-1)
    with sessions.begin() as session:
        requeued = repo.requeue_expired_leases(session, now=utcnow())
    assert len(requeued) == 2
    assert _states(sessions) == {
        "live": ("running", True, 1),
        "expired": ("queued", False, 1),  # an outbox row again; its attempt stays counted
        "no-lease": ("queued", False, 1),
        "queued": ("queued", True, 0),
        "done": ("done", True, 1),
    }
    with sessions.begin() as session:
        assert repo.requeue_expired_leases(session, now=utcnow()) == []


def test_a_lease_is_judged_at_the_given_time(sessions) -> None:
    with sessions.begin() as session:
        _job(session, "live", "running", lease_in_s=60)
    with sessions.begin() as session:
        job = session.query(Job).one()  # read back: SQLite returns naive UTC times
        assert not repo.lease_has_expired(job, now=utcnow())
        assert repo.lease_has_expired(job, now=utcnow() + timedelta(seconds=61))
        assert repo.requeue_expired_leases(session, now=utcnow() + timedelta(seconds=61)) == [job.id]


def test_a_reprocess_supersedes_a_stuck_ingest_but_not_a_live_one(sessions) -> None:
    with sessions.begin() as session:
        stuck = _job(session, "trip-a", "running", lease_in_s=-1)
        _job(session, "trip-b", "running", lease_in_s=60)
    with sessions.begin() as session:
        new = repo.schedule_reprocess(session, trip_pks=["trip-a", "trip-b"])
        assert [j.subject for j in new] == ["trip-a"]
    with sessions() as session:
        old = session.get(Job, stuck)
        assert old is not None and old.state == "failed" and "lease expired" in (old.error or "")
        assert repo.job_summary(session)["failed"] == 0  # superseded by the new job


class _Broker:
    """The two Redis calls the relay makes about its marker key."""

    def __init__(self) -> None:
        self.keys: dict[str, str] = {}

    def exists(self, key: str) -> int:
        return int(key in self.keys)

    def set(self, key: str, value: str) -> None:
        self.keys[key] = value


def test_queued_jobs_are_sent_again_when_the_broker_lost_its_marker(sessions) -> None:
    with sessions.begin() as session:
        _job(session, "sent", "queued", lease_in_s=None)
        _job(session, "unsent", "queued", lease_in_s=None, dispatched=False)
        _job(session, "running", "running", lease_in_s=60)
    broker = _Broker()
    assert resend_if_broker_lost_messages(sessions, broker) == 1  # type: ignore[arg-type]
    assert BROKER_MARKER_KEY in broker.keys
    assert _states(sessions)["sent"] == ("queued", False, 0)
    assert _states(sessions)["running"] == ("running", True, 1)
    with sessions.begin() as session:
        session.query(Job).filter(Job.subject == "sent").one().dispatched_at = utcnow()
    assert resend_if_broker_lost_messages(sessions, broker) == 0  # type: ignore[arg-type]  # marker kept
    assert _states(sessions)["sent"] == ("queued", True, 0)


def test_the_heartbeat_renews_the_lease_while_the_job_runs_and_stops_after(sessions) -> None:
    with sessions.begin() as session:
        job_id = _job(session, "trip", "running", lease_in_s=0.3)
    with LeaseHeartbeat(sessions, job_id, lease_s=0.3):
        time.sleep(1.0)
        with sessions() as session:
            assert not repo.lease_has_expired(session.get(Job, job_id), now=utcnow())  # type: ignore[arg-type]
    time.sleep(0.5)
    with sessions() as session:
        assert repo.lease_has_expired(session.get(Job, job_id), now=utcnow())  # type: ignore[arg-type]
