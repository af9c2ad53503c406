"""What the runners take from the outbox and in what order (``workers.dispatch``), on both
databases, and the priority the Celery relay gives each message on real Redis."""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from datetime import timedelta

import pytest
import redis
from celery import Celery
from sqlalchemy.orm import Session, sessionmaker

from services.db import repo
from services.db.engine import make_engine, make_session_factory, migrate
from services.db.models import Job, TileVersion, Trip, utcnow
from services.settings import Settings
from workers import dispatch
from workers.celery_app import celery_config
from workers.outbox import relay_once

pytestmark = pytest.mark.integration

Z, Y = 16, 22600
EVEN_X = 34400  # x + y even: aligns first; EVEN_X + 1 is odd and waits for it


@pytest.fixture(params=["sqlite", "postgresql"])
def session_factory(request, tmp_path, pg) -> Iterator[sessionmaker[Session]]:
    url = f"sqlite:///{tmp_path / 'd.sqlite3'}" if request.param == "sqlite" else pg.create()
    engine = make_engine(url)
    migrate(engine)
    yield make_session_factory(engine)
    engine.dispose()


def _trip(session: Session, tiles: dict[tuple[int, int, int], int]) -> str:
    pk = secrets.token_hex(8)
    session.add(
        Trip(
            id=pk,
            vehicle_id="veh",
            trip_id=pk,
            content_sha256=pk,
            schema_version="1.0",
            started_at="2026-01-01T00:00:00Z",
            n_frames=sum(tiles.values()),
            body_bytes=1,
            json_bytes=1,
        )
    )
    session.flush()
    repo.set_trip_tiles(session, trip_pk=pk, frames_of_tile=tiles)
    return pk


def _job(session: Session, kind: str, subject: str, age_s: float) -> Job:
    job = repo.add_job(session, kind=kind, subject=subject)
    job.created_at = utcnow() - timedelta(seconds=age_s)
    return job


def _version(session: Session, x: int) -> None:
    session.add(
        TileVersion(
            z=Z,
            x=x,
            y=Y,
            version=1,
            status="published",
            reason="merge",
            trips=[],
            corrections=[],
            quality={},
            changes={},
            n_features=0,
            origin_lat=0.0,
            origin_lon=0.0,
        )
    )


def test_merges_first_then_the_longest_chain_and_an_odd_tile_waits(session_factory):
    """Merges first; an odd tile waits for its even neighbour; that small even tile goes before a
    bigger one (4000 frames), since a bigger tile (5000) waits for it; the smallest last."""
    with session_factory.begin() as s:
        _trip(s, {(Z, EVEN_X, Y): 300, (Z, EVEN_X + 1, Y): 5000})
        _trip(s, {(Z, EVEN_X - 4, Y): 4000})
        _trip(s, {(Z, EVEN_X - 2, Y): 20})
        small = _job(s, "align_tile", f"{Z}/{EVEN_X - 2}/{Y}", age_s=40)  # oldest, smallest
        big = _job(s, "align_tile", f"{Z}/{EVEN_X - 4}/{Y}", age_s=30)
        even = _job(s, "align_tile", f"{Z}/{EVEN_X}/{Y}", age_s=20)
        odd = _job(s, "align_tile", f"{Z}/{EVEN_X + 1}/{Y}", age_s=20)  # biggest, but waits for `even`
        merge = _job(s, "merge_tile", f"{Z}/{EVEN_X + 6}/{Y}", age_s=1)  # newest
        ids = {
            j.id: name
            for j, name in ((small, "small"), (even, "even"), (odd, "odd"), (big, "big"), (merge, "merge"))
        }
    with session_factory.begin() as s:
        plan = dispatch.take_dispatchable(s, limit=10, redispatch_before=None, checkerboard=True)
        assert [ids[d.job.id] for d in plan] == ["merge", "even", "big", "small"]
        assert [d.frames for d in plan] == [0, 5300, 4000, 20]
        assert plan[0].priority == 0 < plan[1].priority <= plan[2].priority < plan[3].priority
        assert dispatch.neighbours_to_wait_for(s, Z, EVEN_X + 1, Y) == [f"{Z}/{EVEN_X}/{Y}"]
        # checkerboard off: the odd tile goes too, first of the alignments (the most frames)
        plan = dispatch.take_dispatchable(s, limit=10, redispatch_before=None, checkerboard=False)
        assert [ids[d.job.id] for d in plan] == ["merge", "odd", "big", "even", "small"]
        assert [
            ids[d.job.id]
            for d in dispatch.take_dispatchable(s, limit=2, redispatch_before=None, checkerboard=True)
        ] == ["merge", "even"]
    with session_factory.begin() as s:  # the even neighbour has its version: the odd tile may go
        s.get(Job, even.id).state = "done"
        _version(s, EVEN_X)
    with session_factory.begin() as s:
        assert dispatch.neighbours_to_wait_for(s, Z, EVEN_X + 1, Y) == []
        plan = dispatch.take_dispatchable(s, limit=10, redispatch_before=None, checkerboard=True)
        assert [ids[d.job.id] for d in plan] == ["merge", "odd", "big", "small"]


def test_held_back_rows_do_not_hide_the_job_they_wait_for(session_factory):
    """More held-back rows than a page, all older than the alignment they wait for: it is still
    found."""
    with session_factory.begin() as s:
        held = [_job(s, "align_tile", f"{Z}/{EVEN_X + 1 + 2 * k}/{Y}", age_s=60 + k) for k in range(5)]
        awaited = _job(s, "align_tile", f"{Z}/{EVEN_X}/{Y}", age_s=0)  # the first odd tile's west neighbour
        for k in range(5):  # each odd tile's east neighbour is busy with a runner (not in the outbox)
            _job(s, "align_tile", f"{Z}/{EVEN_X + 2 + 2 * k}/{Y}", age_s=120).dispatched_at = utcnow()
        awaited_id, held_ids = awaited.id, {j.id for j in held}
    with session_factory.begin() as s:
        waiting = dispatch.tiles_waiting_for_neighbours(s, [(Z, EVEN_X + 1 + 2 * k, Y) for k in range(5)])
        assert len(waiting) == 5 and f"{Z}/{EVEN_X}/{Y}" in waiting[(Z, EVEN_X + 1, Y)]
        plan = dispatch.take_dispatchable(s, limit=1, redispatch_before=None, checkerboard=True, page=2)
        assert [d.job.id for d in plan] == [awaited_id]
        assert not {d.job.id for d in plan} & held_ids


def test_the_relay_sends_each_job_with_its_priority(session_factory, private_redis):
    """On real Redis: the merge lands in the queue's highest-priority list, the alignment in a
    lower one, so that a worker's BRPOP takes the merge first."""
    settings = Settings(redis_url=private_redis.url)
    app = Celery("csr-test")
    app.conf.update(celery_config(settings))
    client = redis.Redis.from_url(private_redis.url)
    with session_factory.begin() as s:
        _trip(s, {(Z, EVEN_X, Y): 800})
        align = _job(s, "align_tile", f"{Z}/{EVEN_X}/{Y}", age_s=10)
        merge = _job(s, "merge_tile", f"{Z}/{EVEN_X + 2}/{Y}", age_s=0)
        align_id, merge_id = align.id, merge.id
    sep = "\x06\x16"
    keys = ["merge"] + [f"{q}{sep}{p}" for q in ("merge", "align") for p in range(1, 10)] + ["align"]
    assert relay_once(session_factory, app, redispatch_after_s=3600) == 2
    found = {}
    for key in keys:
        for body in client.lrange(key, 0, -1):
            for job_id in (align_id, merge_id):
                if job_id.encode() in body:
                    found[job_id] = key
    assert found[merge_id] == "merge"
    assert found[align_id] == f"align{sep}{dispatch.align_priority(800)}" and dispatch.align_priority(800) > 0
