"""Aggregate figures of the map for ``/metrics``, read at scrape time: bounded in size whatever the
size of the map (no row per tile or per trip leaves this module)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.db.models import Job, TileHead, TileVersion, Trip, TripTile
from services.db.versions import LIVE_STATUSES


@dataclass(frozen=True, slots=True)
class TileStats:
    tiles: int  # tiles with at least one version (published or candidate)
    published_tiles: int  # tiles with a live version
    map_version: int  # the newest tile version id (the map version, GET /v1/map?version=N)
    last_update_unix_s: float | None  # when the newest tile version was made


@dataclass(frozen=True, slots=True)
class LatencyHistogram:
    cumulative_counts: list[int]  # per bucket bound: how many observations are <= it
    count: int
    sum_s: float


def tile_stats(session: Session) -> TileStats:
    tiles, published, last = session.execute(
        select(
            func.count(),
            func.count(TileHead.live_version_id),
            func.max(TileHead.updated_at),
        )
    ).one()
    map_version = session.scalar(select(func.max(TileVersion.id))) or 0
    return TileStats(int(tiles), int(published), int(map_version), _unix_s(last) if last else None)


def upload_to_published(session: Session, *, buckets_s: Sequence[float]) -> LatencyHistogram:
    """For every ``aligned`` trip, the seconds from its upload until each of its tiles had a live
    version made after the tile job that took the trip finished (the trip is then in the published
    map), as a cumulative histogram over ``buckets_s``."""
    first_live = (
        select(func.min(TileVersion.created_at))
        .where(
            TileVersion.z == TripTile.z,
            TileVersion.x == TripTile.x,
            TileVersion.y == TripTile.y,
            TileVersion.status.in_(LIVE_STATUSES),
            TileVersion.created_at >= Job.finished_at,
        )
        .correlate(TripTile, Job)
        .scalar_subquery()
    )
    per_tile = (
        select(Trip.id.label("trip"), Trip.received_at.label("received_at"), first_live.label("live_at"))
        .join(TripTile, TripTile.trip_pk == Trip.id)
        .outerjoin(Job, Job.id == TripTile.processed_job_id)
        .where(Trip.status == "aligned")
        .subquery()
    )
    rows = session.execute(
        select(per_tile.c.received_at, func.max(per_tile.c.live_at))
        .group_by(per_tile.c.trip, per_tile.c.received_at)
        .having(func.count(per_tile.c.live_at) == func.count())
    ).all()
    latencies_s = [max(0.0, _unix_s(live_at) - _unix_s(received_at)) for received_at, live_at in rows]
    return LatencyHistogram(
        cumulative_counts=[sum(1 for s in latencies_s if s <= bound) for bound in buckets_s],
        count=len(latencies_s),
        sum_s=float(sum(latencies_s)),
    )


def _unix_s(at: datetime | str) -> float:
    if isinstance(at, str):  # SQLite returns aggregates of datetimes as text
        at = datetime.fromisoformat(at)
    return (at if at.tzinfo else at.replace(tzinfo=UTC)).timestamp()
