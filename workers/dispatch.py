"""Which outbox jobs go to the runners now, and in what order (both deployments: the Celery outbox
relay and the embedded pool).

- **Hold back**: a tile's first alignment that waits for its edge neighbours' first versions
  (checkerboard order, :func:`neighbours_to_wait_for`) stays in the outbox until they have one,
  instead of being taken by a worker only to be put back.
- **Order** (a priority per job, 0 first; Celery's Redis transport pops the lowest step first
  across the queues): merges first (short, and a new version lets the neighbours waiting for it
  go), then ingests and the map team's corrections, then alignments, biggest first: with several
  workers a batch ends when its longest chain of jobs does, so that one must not start last
  (longest processing time first, on the chains of the checkerboard). A tile's size is the
  frames of its trips not yet aligned there (``trip_tiles.frames``), plus the largest neighbour
  waiting for its first version; one priority step per doubling, the exact size orders the jobs
  of one step within a batch.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.db import repo
from services.db.models import Job, TileVersion, TripTile
from services.tile_frames import parse_tile, tile_subject

TILE_JOBS = ("align_tile", "merge_tile")
PRIORITY_OF_KIND = {"merge_tile": 0, "ingest_trip": 1, "correct_tile": 1}
ALIGN_PRIORITIES = (2, 9)  # the biggest alignments get 2, the smallest 9
FRAMES_PER_STEP = 250  # an alignment of twice the frames goes one priority step earlier
PRIORITY_STEPS = tuple(range(10))  # Celery / kombu Redis priority steps (0 highest)

Tile = tuple[int, int, int]


@dataclass(frozen=True, slots=True)
class Dispatch:
    job: Job
    priority: int
    frames: int = 0  # an alignment's size (frames of its chain): orders jobs of one priority step


def edge_neighbours(z: int, x: int, y: int) -> list[Tile]:
    return [(z, x - 1, y), (z, x + 1, y), (z, x, y - 1), (z, x, y + 1)]


@dataclass(frozen=True, slots=True)
class TileStates:
    """Which of some tiles (and their edge neighbours) have a version, and which have a tile job
    queued or running: what the checkerboard order reads."""

    versioned: frozenset[Tile]
    pending: frozenset[str]  # subjects

    @classmethod
    def around(cls, session: Session, tiles: Iterable[Tile]) -> TileStates:
        tiles = set(tiles)
        involved = tiles | {n for t in tiles for n in edge_neighbours(*t)}
        if not involved:
            return cls(frozenset(), frozenset())
        pending = session.scalars(
            select(Job.subject).where(
                Job.kind.in_(TILE_JOBS),
                Job.state.in_(("queued", "running")),
                Job.subject.in_([tile_subject(*t) for t in involved]),
            )
        )
        return cls(frozenset(_tiles_with_versions(session, involved)), frozenset(pending))

    def first_version_pending(self, tile: Tile) -> bool:
        return tile not in self.versioned and tile_subject(*tile) in self.pending

    def waits_for(self, tile: Tile) -> list[str]:
        """Checkerboard order, so that every seam is aligned once against a map: tiles with x + y
        even align first, side by side (they touch only at corners); a tile with x + y odd and no
        version waits while an edge neighbour has no version yet and a job of its own queued or
        running, and then aligns with the neighbours' maps in its halo as the prior
        (``P_sub-pre``). Aligned at the same time, two neighbours would each settle on their own
        consensus and meet with a step in the halo. Even tiles never wait, so the odd ones always
        get their turn."""
        if (tile[1] + tile[2]) % 2 == 0 or tile in self.versioned:
            return []
        return [tile_subject(*n) for n in edge_neighbours(*tile) if self.first_version_pending(n)]

    def waiting_on(self, tile: Tile) -> list[Tile]:
        """The neighbours whose first alignment waits for this tile's first version."""
        if not self.first_version_pending(tile):
            return []
        return [n for n in edge_neighbours(*tile) if (n[1] + n[2]) % 2 == 1 and self.first_version_pending(n)]


def tiles_waiting_for_neighbours(session: Session, tiles: Iterable[Tile]) -> dict[Tile, list[str]]:
    """For each tile whose first alignment must wait: the edge neighbours it waits for
    (:meth:`TileStates.waits_for`)."""
    tiles = list(dict.fromkeys(tiles))
    states = TileStates.around(session, tiles)
    return {t: w for t in tiles if (w := states.waits_for(t))}


def neighbours_to_wait_for(session: Session, z: int, x: int, y: int) -> list[str]:
    """The edge neighbours one tile's first alignment waits for (see :meth:`TileStates.waits_for`)."""
    return tiles_waiting_for_neighbours(session, [(z, x, y)]).get((z, x, y), [])


def _tiles_with_versions(session: Session, tiles: set[Tile]) -> set[Tile]:
    if not tiles:
        return set()
    zs, xs, ys = zip(*tiles, strict=True)
    rows = session.execute(
        select(TileVersion.z, TileVersion.x, TileVersion.y)
        .distinct()
        .where(
            TileVersion.z.in_(set(zs)),
            TileVersion.x.between(min(xs), max(xs)),
            TileVersion.y.between(min(ys), max(ys)),
        )
    ).all()
    return {(z, x, y) for z, x, y in rows} & tiles


def frames_to_align(session: Session, tiles: Iterable[Tile]) -> dict[Tile, int]:
    """The frames of each tile's trips not yet aligned there (a row from before migration 0005
    counts as one frame)."""
    tiles = set(tiles)
    if not tiles:
        return {}
    zs, xs, ys = zip(*tiles, strict=True)
    rows = session.execute(
        select(TripTile.z, TripTile.x, TripTile.y, func.sum(func.coalesce(TripTile.frames, 1)))
        .where(
            TripTile.processed_job_id.is_(None),
            TripTile.z.in_(set(zs)),
            TripTile.x.between(min(xs), max(xs)),
            TripTile.y.between(min(ys), max(ys)),
        )
        .group_by(TripTile.z, TripTile.x, TripTile.y)
    ).all()
    return {(z, x, y): int(n) for z, x, y, n in rows if (z, x, y) in tiles}


def align_priority(frames: int) -> int:
    """One step earlier per doubling of the frames (``FRAMES_PER_STEP`` frames: one step from the last)."""
    first, last = ALIGN_PRIORITIES
    return max(first, last - int(math.log2(1.0 + frames / FRAMES_PER_STEP)))


def plan_dispatch(session: Session, jobs: Sequence[Job], *, checkerboard: bool) -> list[Dispatch]:
    """``jobs`` (outbox rows) less those held back, each with its priority, in dispatch order
    (priority, then age). An alignment's size is its own frames plus, in checkerboard order, the
    largest of the neighbours waiting for its first version: a small tile that holds a big one
    back goes as early as the big one would (the longest chain first)."""
    align_tiles = {job.id: parse_tile(job.subject) for job in jobs if job.kind == "align_tile"}
    states = TileStates.around(session, align_tiles.values()) if checkerboard else None
    followers = {t: states.waiting_on(t) for t in align_tiles.values()} if states else {}
    frames = frames_to_align(session, set(align_tiles.values()) | {n for f in followers.values() for n in f})
    out = []
    for job in jobs:
        tile = align_tiles.get(job.id)
        if tile is None:
            out.append(Dispatch(job, PRIORITY_OF_KIND.get(job.kind, ALIGN_PRIORITIES[0])))
        elif states is None or not states.waits_for(tile):
            chain = frames.get(tile, 0) + max((frames.get(n, 0) for n in followers.get(tile, [])), default=0)
            out.append(Dispatch(job, align_priority(chain), chain))
    return sorted(out, key=_dispatch_order)


def take_dispatchable(
    session: Session, *, limit: int, redispatch_before: datetime | None, checkerboard: bool, page: int = 200
) -> list[Dispatch]:
    """Up to ``limit`` outbox rows to dispatch now, in order (:func:`plan_dispatch`). Reads the
    outbox page by page until it has enough, so that held-back rows never hide the jobs they
    wait for (a merge queued behind them). The rows read stay locked until the session ends."""
    chosen: list[Dispatch] = []
    offset = 0
    while len(chosen) < limit:
        rows = repo.jobs_to_dispatch(session, limit=page, offset=offset, redispatch_before=redispatch_before)
        chosen += plan_dispatch(session, rows, checkerboard=checkerboard)
        if len(rows) < page:
            break
        offset += page
    return sorted(chosen, key=_dispatch_order)[:limit]


def _dispatch_order(d: Dispatch) -> tuple:
    return (d.priority, -d.frames, d.job.created_at, d.job.id)
