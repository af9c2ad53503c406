"""Naive fusion for the baselines: perceived elements placed with given poses, stitched per trip.

The "fused naively" baseline, chosen to be honest and simple:

1. Keyframes every ``spacing_m`` of odometry travel (5 m by default).
2. Each keyframe contributes only the strip of its perception just ahead of the vehicle,
   ``0 <= x_vehicle < travel to the next keyframe`` (the last keyframe keeps up to 30 m), so a
   trip tiles its road once, with the nearest (least noisy) part of each detection.
   Line elements are clipped to the strip (exactly, with shapely ``clip_by_rect``); a polygon
   is kept whole from the keyframe whose strip holds its centroid.
3. Pieces of one trip with the same type and on-vehicle ``track_id`` are chained in keyframe
   order while consecutive pieces are within 2 m (gaps come from GNSS jumps); pieces without a
   track id stay alone; a track's polygon is kept once.
4. No merging across trips: every trip that saw an element contributes its own copy. (Merging
   trips is the pipeline's fuse stage; the metric consequence, documented in BENCHMARKS.md, is
   that truth-side distances take the nearest copy while predicted-side distances count every
   copy.)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import shapely

from csr_core.types import DividerStyle, ElementType, MapFeature, PerceivedElement, Trip

KEYFRAME_SPACING_M = 5.0
LAST_STRIP_M = 30.0
CHAIN_GAP_M = 2.0


@dataclass(frozen=True, slots=True)
class PlacedPiece:
    """A piece of one detection in world coordinates, from keyframe ``frame`` of trip ``trip_key``."""

    trip_key: str
    frame: int
    type: ElementType
    points_xy_world: np.ndarray  # (M, 2), along the direction of travel for lines
    style: DividerStyle | None
    track_id: int | None


def keyframe_indices(trip: Trip, spacing_m: float = KEYFRAME_SPACING_M) -> np.ndarray:
    """Ascending frame indices, one per ``spacing_m`` of odometry travel (first frame included)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(trip.odom_xyyaw[:, :2], axis=0), axis=1))])
    idx = np.searchsorted(s, np.arange(0.0, s[-1] + 1e-9, spacing_m), side="left")
    return np.unique(np.clip(idx, 0, trip.n_frames - 1))


def _to_world(poses: np.ndarray, points_xy_vehicle: np.ndarray) -> np.ndarray:
    """Per-point poses ``(P, 3)`` applied to ``(P, 2)`` points."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x, y = points_xy_vehicle[:, 0], points_xy_vehicle[:, 1]
    return np.column_stack([poses[:, 0] + c * x - s * y, poses[:, 1] + s * x + c * y])


def place_pieces(
    trip: Trip, poses_xyyaw_world: np.ndarray, spacing_m: float = KEYFRAME_SPACING_M
) -> list[PlacedPiece]:
    """Steps 1-2: the strip pieces of one trip, in keyframe order."""
    kf = keyframe_indices(trip, spacing_m)
    odom_xy = trip.odom_xyyaw[:, :2]
    strip_len = np.append(np.linalg.norm(np.diff(odom_xy[kf], axis=0), axis=1), LAST_STRIP_M)
    strip_len = np.maximum(strip_len, 1e-3)
    line_coords: list[np.ndarray] = []
    line_owner: list[np.ndarray] = []
    line_meta: list[tuple[int, int, float, PerceivedElement]] = []
    pieces: list[PlacedPiece] = []
    for k, (f, length) in enumerate(zip(kf, strip_len, strict=False)):
        for e in trip.elements[f]:
            pts = e.points_xy_vehicle
            if e.type.is_polygon:
                cx = pts[:, 0].mean()
                if 0.0 <= cx < length and len(pts) >= 3:
                    world = _to_world(np.repeat(poses_xyyaw_world[f][None], len(pts), 0), pts)
                    pieces.append(PlacedPiece(trip.key, int(f), e.type, world, e.style, e.track_id))
                continue
            if pts[:, 0].max() < 0.0 or pts[:, 0].min() >= length:
                continue
            line_coords.append(pts / [length, 1.0])  # strip becomes x in [0, 1]
            line_owner.append(np.full(len(pts), len(line_meta)))
            line_meta.append((k, int(f), length, e))
    if line_meta:
        lines = shapely.linestrings(np.concatenate(line_coords), indices=np.concatenate(line_owner))
        clipped = shapely.clip_by_rect(lines, 0.0, -1e4, 1.0, 1e4)
        parts, src = shapely.get_parts(clipped, return_index=True)
        coords, part_of = shapely.get_coordinates(parts, return_index=True)
        splits = np.flatnonzero(np.diff(part_of)) + 1
        part_ids = part_of[np.r_[0, splits]] if len(coords) else np.zeros(0, int)
        for p, xy in zip(part_ids, np.split(coords, splits) if len(coords) else [], strict=False):
            k, f, length, e = line_meta[int(src[p])]
            if len(xy) < 2:
                continue
            xy = xy * [length, 1.0]
            if e.type != ElementType.STOP_LINE and xy[-1, 0] < xy[0, 0]:
                xy = xy[::-1]
            world = _to_world(np.repeat(poses_xyyaw_world[f][None], len(xy), 0), xy)
            pieces.append(PlacedPiece(trip.key, f, e.type, world, e.style, e.track_id))
    pieces.sort(key=lambda p: p.frame)
    return pieces


def _ahead_of_chain(chain: list[np.ndarray], points_xy: np.ndarray, margin_m: float = 0.05) -> np.ndarray:
    """The points of a new piece from its first one lying ahead of the chain's end (along the
    chain's last direction): GNSS noise between keyframes must not fold the line back."""
    tail = np.concatenate(chain[-2:])[-2:] if sum(len(c) for c in chain[-2:]) >= 2 else None
    if tail is None or np.allclose(tail[0], tail[1]):
        return points_xy
    direction = (tail[1] - tail[0]) / np.linalg.norm(tail[1] - tail[0])
    ahead = (points_xy - tail[1]) @ direction > margin_m
    return points_xy[int(np.argmax(ahead)) :] if ahead.any() else points_xy[:0]


def stitch_pieces(pieces: Sequence[PlacedPiece]) -> list[MapFeature]:
    """Step 3: chain one trip's pieces per (type, track id); see the module docstring."""
    features: list[MapFeature] = []
    open_chains: dict[tuple[ElementType, int], list[np.ndarray]] = {}
    chain_style: dict[tuple[ElementType, int], DividerStyle | None] = {}
    seen_polygons: set[tuple[ElementType, int | None]] = set()
    trip_key = pieces[0].trip_key if pieces else ""

    def emit(points: list[np.ndarray], etype: ElementType, style: DividerStyle | None) -> None:
        xy = np.concatenate(points)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6])
        xy = xy[keep]
        if len(xy) >= 2:
            features.append(
                MapFeature(
                    type=etype,
                    points_xy_world=xy,
                    style=style,
                    feature_id=f"{trip_key}/{len(features)}",
                    properties={"trip": trip_key},
                )
            )

    for piece in pieces:
        if piece.type.is_polygon:
            key = (piece.type, piece.track_id)
            if piece.track_id is not None and key in seen_polygons:
                continue
            seen_polygons.add(key)
            features.append(
                MapFeature(
                    type=piece.type,
                    points_xy_world=piece.points_xy_world,
                    style=piece.style,
                    feature_id=f"{trip_key}/{len(features)}",
                    properties={"trip": trip_key},
                )
            )
            continue
        if piece.track_id is None:
            emit([piece.points_xy_world], piece.type, piece.style)
            continue
        key = (piece.type, piece.track_id)
        chain = open_chains.get(key)
        if chain is not None and np.linalg.norm(chain[-1][-1] - piece.points_xy_world[0]) <= CHAIN_GAP_M:
            ahead = _ahead_of_chain(chain, piece.points_xy_world)
            if len(ahead):
                chain.append(ahead)
            continue
        if chain is not None:
            emit(chain, key[0], chain_style[key])
        open_chains[key] = [piece.points_xy_world]
        chain_style[key] = piece.style
    for key, chain in open_chains.items():
        emit(chain, key[0], chain_style[key])
    return features


def fuse_naively(
    trips: Sequence[Trip], poses_by_key: Mapping[str, np.ndarray], spacing_m: float = KEYFRAME_SPACING_M
) -> tuple[MapFeature, ...]:
    """Steps 1-4 over all trips that have poses: the baselines' map."""
    out: list[MapFeature] = []
    for trip in trips:
        if trip.key in poses_by_key:
            out.extend(stitch_pieces(place_pieces(trip, poses_by_key[trip.key], spacing_m)))
    return tuple(out)
