"""Tiles as the per-tile jobs and the correction endpoints both see them: a tile's world frame, a
job subject ``z/x/y``, and a stored match pair's two sides as trip frames. (Light: no algorithm
imports, so the API does not load the job code to answer a correction.)"""

from __future__ import annotations

from csr_core.geo import LocalFrame, region_frame_for, tile_bounds_lonlat
from services.db.models import MatchPair

# A constraint as stored: (trip pk or None for the pre-built map, (first, last) frame of the trip)
Side = tuple[str | None, tuple[int, int]]


def tile_frame(z: int, x: int, y: int) -> LocalFrame:
    """The world frame a tile is processed in: its region's (shared with the trips around it)."""
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

    def side(pk: str | None, key: str, frames) -> Side:
        if pk is None:
            return None, (0, 0)
        start = int(key.rsplit("@", 1)[1]) if "@" in key else 0
        return pk, (int(frames[0]) + start, int(frames[1]) + start)

    r = pair.record
    return side(pair.trip_pk_i, r["trip_key_i"], r["frames_i"]), side(pair.trip_pk_j, r["trip_key_j"], r["frames_j"])
