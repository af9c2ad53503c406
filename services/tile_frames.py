"""Tiles as the per-tile jobs and the correction endpoints both see them: a tile's world frame, a
job subject ``z/x/y``, and a stored match pair's two sides as trip frames. (Light: no algorithm
imports, so the API does not load the job code to answer a correction.)"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

from csr_core.geo import LocalFrame, region_frame_for, tile_bounds_lonlat
from services.db.models import MatchPair

# A constraint as stored: (trip pk or None for the pre-built map, (first, last) frame of the trip)
Side = tuple[str | None, tuple[int, int]]


@lru_cache(maxsize=4096)
def tile_frame(z: int, x: int, y: int) -> LocalFrame:
    """The world frame a tile is processed in: its region's (shared with the trips around it).
    Cached: a frame builds each of its projections once, on first use (~36 ms each)."""
    west, south, east, north = tile_bounds_lonlat(z, x, y)
    return region_frame_for(((west + east) / 2, (south + north) / 2))


def tile_subject(z: int, x: int, y: int) -> str:
    """A tile job's subject (``parse_tile`` reads it back)."""
    return f"{z}/{x}/{y}"


def parse_tile(subject: str) -> tuple[int, int, int]:
    z, x, y = (int(v) for v in subject.split("/"))
    return z, x, y


def record_sides(pair: MatchPair) -> tuple[Side, Side]:
    """A stored match pair's two sides as trip frames (its record names pieces: ``key@start``)."""
    return sides_of(pair.trip_pk_i, pair.trip_pk_j, pair.record)


def sides_of(trip_pk_i: str | None, trip_pk_j: str | None, record: dict[str, Any]) -> tuple[Side, Side]:
    """The two sides, as trip frames, of a pair between trips ``trip_pk_i`` and ``trip_pk_j`` (None:
    the pre-built map) whose ``record`` is ``MatchPair.record``."""

    def side(pk: str | None, key: str, frames) -> Side:
        if pk is None:
            return None, (0, 0)
        start = int(key.rsplit("@", 1)[1]) if "@" in key else 0
        return pk, (int(frames[0]) + start, int(frames[1]) + start)

    return (
        side(trip_pk_i, record["trip_key_i"], record["frames_i"]),
        side(trip_pk_j, record["trip_key_j"], record["frames_j"]),
    )
