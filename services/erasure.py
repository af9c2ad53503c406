"""Erasure of a vehicle's data (``csr purge --vehicle ID``, ``DELETE /v1/vehicles/{id}/data``).

One transaction erases everything keyed by the vehicle's trips: the trip rows and, through their
foreign keys, the raw uploads, single-trip reconstructions, tile rows, per-tile alignments and
final poses; the match pairs that name a trip; the trips' jobs. It also takes the trip ids out of
every tile version's provenance (``tile_versions.trips``), drops the topology state of the touched
tiles' earlier versions (it holds the trips' probe points; their held-back lines answer 409
afterwards), and queues a ``merge_tile`` for every touched tile. That merge finds trips in the
tile's state that no longer exist and rebuilds the tile from the trips that remain
(``workers.tile_jobs.compute_merge_tile``): a new map version without them (an empty one when no
trip remains). The fused geometry of earlier versions stays: it is the map, not a trace.

A killed process loses nothing: before the commit nothing is erased, after it the merges are in the
job table (the outbox) and run like any job. A second erasure finds no trip and changes nothing."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import cast

from sqlalchemy import CursorResult, delete, or_, select, tuple_
from sqlalchemy.orm import Session

from services.db import repo
from services.db.models import Job, MatchPair, TileVersion, Trip, TripTile, TripTileAlignment
from services.tile_frames import tile_subject

Tile = tuple[int, int, int]


@dataclass(frozen=True, slots=True)
class ErasurePlan:
    """What erasing a vehicle touches: its trips (server ids) and the tiles they reach."""

    vehicle_id: str
    trip_pks: list[str]
    tiles: list[Tile]


@dataclass(slots=True)
class ErasureResult:
    vehicle_id: str
    trips: int = 0  # trip rows deleted (with their uploads, reconstructions, alignments, poses)
    match_pairs: int = 0
    jobs: int = 0  # the trips' own jobs deleted
    versions_rewritten: int = 0  # tile versions whose provenance named a trip
    merge_jobs: list[str] = field(default_factory=list)  # merge_tile jobs queued
    tiles: list[Tile] = field(default_factory=list)


def plan_vehicle_erasure(session: Session, *, vehicle_id: str) -> ErasurePlan:
    trip_pks = list(
        session.scalars(
            select(Trip.id).where(Trip.vehicle_id == vehicle_id).order_by(Trip.received_at, Trip.id)
        )
    )
    tiles: set[Tile] = set()
    for start in range(0, len(trip_pks), 500):
        chunk = trip_pks[start : start + 500]
        tiles |= {
            (z, x, y)
            for z, x, y in session.execute(
                select(TripTile.z, TripTile.x, TripTile.y).where(TripTile.trip_pk.in_(chunk))
            )
        }
        tiles |= {
            (z, x, y)
            for z, x, y in session.execute(
                select(TripTileAlignment.z, TripTileAlignment.x, TripTileAlignment.y).where(
                    TripTileAlignment.trip_pk.in_(chunk)
                )
            )
        }
    return ErasurePlan(vehicle_id, trip_pks, sorted(tiles))


def _rowcount(result) -> int:
    return cast(CursorResult, result).rowcount


def erase_vehicle(
    session: Session, *, plan: ErasurePlan, progress: Callable[[int], None] | None = None
) -> ErasureResult:
    """Erase the planned trips in the caller's transaction (see the module docstring);
    ``progress(n)`` is called as trips are erased."""
    result = ErasureResult(plan.vehicle_id, tiles=list(plan.tiles))
    gone = set(plan.trip_pks)
    for start in range(0, len(plan.trip_pks), 200):
        chunk = plan.trip_pks[start : start + 200]
        result.match_pairs += _rowcount(
            session.execute(
                delete(MatchPair).where(or_(MatchPair.trip_pk_i.in_(chunk), MatchPair.trip_pk_j.in_(chunk)))
            )
        )
        result.jobs += _rowcount(session.execute(delete(Job).where(Job.subject.in_(chunk))))
        result.trips += _rowcount(session.execute(delete(Trip).where(Trip.id.in_(chunk))))
        if progress is not None:
            progress(len(chunk))
    if plan.tiles:
        result.versions_rewritten = _forget_in_versions(session, plan.tiles, gone)
        result.merge_jobs = _queue_merges(session, plan.tiles)
    return result


def _versions_of(session: Session, tiles: Iterable[Tile]) -> list[TileVersion]:
    tiles = list(tiles)
    out: list[TileVersion] = []
    for start in range(0, len(tiles), 200):
        chunk = tiles[start : start + 200]
        out += session.scalars(
            select(TileVersion)
            .where(tuple_(TileVersion.z, TileVersion.x, TileVersion.y).in_(chunk))
            .order_by(TileVersion.id)
        ).all()
    return out


def _forget_in_versions(session: Session, tiles: list[Tile], gone: set[str]) -> int:
    """Take the erased trips out of the touched tiles' version provenance; drop the topology state
    of every version but each tile's latest (which the rebuilding merge continues its ids from)."""
    rewritten = 0
    rows = _versions_of(session, tiles)
    latest: dict[Tile, int] = {}
    for v in rows:
        latest[(v.z, v.x, v.y)] = max(latest.get((v.z, v.x, v.y), 0), v.version)
    for v in rows:
        kept = [t for t in (v.trips or []) if t not in gone]
        if len(kept) != len(v.trips or []):
            v.trips = kept
            rewritten += 1
        if v.state is not None and v.version != latest[(v.z, v.x, v.y)]:
            v.state = None
    return rewritten


def _queue_merges(session: Session, tiles: list[Tile]) -> list[str]:
    """A ``merge_tile`` per tile, unless one is queued and has not started (it reads after this commits)."""
    subjects = [tile_subject(*t) for t in tiles]
    queued = set(
        session.scalars(
            select(Job.subject).where(
                Job.kind == "merge_tile", Job.state == "queued", Job.subject.in_(subjects)
            )
        )
    )
    return [repo.add_job(session, kind="merge_tile", subject=s).id for s in subjects if s not in queued]
