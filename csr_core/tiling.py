"""Per-tile processing: which frames of a trip a tile aligns, the trip pieces it aligns, and how a
trip's final poses are put together from the tiles it crossed.

A trip's frames are owned by the web-mercator XYZ tile of their smoothed position (single-trip
poses). A tile job aligns every run of a trip's frames that lies in the tile or within
``halo_m`` of it (so roads crossing an edge are aligned with their neighbours) as one *piece*:
a ``TripReconstruction`` cut to those frames. A frame aligned by two tiles (the halo) gets the
weighted mean of both poses, the weight rising from 0 at ``halo_m`` outside a tile to 1 at
``halo_m`` inside it, so a trajectory crosses a tile edge without a step.

Everything here is in one tile's world frame (``LocalFrame``); :func:`reframe_reconstruction`
moves a trip between two local frames (positions through lon/lat, headings by the difference of
the two frames' grid north).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import shapely

from csr_core.geo import LocalFrame, tile_bounds_lonlat, tiles_touched
from csr_core.types import Trip, TripInstance, TripReconstruction

DEFAULT_HALO_M = 75.0  # > perception range (30 m lateral, 30 m ahead) + a sub-map radius
MIN_PIECE_FRAMES = 10  # a shorter run has nothing to align: its frames follow their neighbours'
INSTANCE_MARGIN_M = 40.0  # instances are cut to the piece's frames' box grown by this


def tile_polygon_xy(z: int, x: int, y: int, frame: LocalFrame) -> shapely.Polygon:
    """The tile's outline in ``frame`` (metres): its edges are lines of constant lon / lat,
    sampled so that the projection's curvature is kept."""
    west, south, east, north = tile_bounds_lonlat(z, x, y)
    t = np.linspace(0.0, 1.0, 9)
    ring = np.concatenate(
        [
            np.column_stack([west + (east - west) * t, np.full_like(t, south)]),
            np.column_stack([np.full_like(t, east), south + (north - south) * t]),
            np.column_stack([east - (east - west) * t, np.full_like(t, north)]),
            np.column_stack([np.full_like(t, west), north - (north - south) * t]),
        ]
    )
    return shapely.Polygon(frame.to_local(ring))


def frame_tiles(poses_xyyaw: np.ndarray, frame: LocalFrame, zoom: int) -> np.ndarray:
    """``(N, 2)`` int: the ``(x, y)`` tile at ``zoom`` owning each frame (its position)."""
    lonlat = frame.to_lonlat(np.asarray(poses_xyyaw, float)[:, :2])
    n = 2.0**zoom
    lat = np.radians(np.clip(lonlat[:, 1], -85.05112878, 85.05112878))
    xt = np.floor((lonlat[:, 0] + 180.0) / 360.0 * n)
    yt = np.floor((1.0 - np.log(np.tan(lat) + 1.0 / np.cos(lat)) / np.pi) / 2.0 * n)
    return np.clip(np.column_stack([xt, yt]), 0, n - 1).astype(np.int64)


def owned_tiles(poses_xyyaw: np.ndarray, frame: LocalFrame, zoom: int) -> list[tuple[int, int, int]]:
    """Sorted unique tiles owning at least one frame."""
    return tiles_touched(frame.to_lonlat(np.asarray(poses_xyyaw, float)[:, :2]), zoom=zoom)


def owned_frame_counts(
    poses_xyyaw: np.ndarray, frame: LocalFrame, zoom: int
) -> dict[tuple[int, int, int], int]:
    """``{(z, x, y): frames}``: how many frames each tile owns (sorted by tile); a tile job's cost
    grows with the frames it aligns, so the scheduler reads it from this."""
    tiles, counts = np.unique(frame_tiles(poses_xyyaw, frame, zoom), axis=0, return_counts=True)
    return {(zoom, int(x), int(y)): int(n) for (x, y), n in zip(tiles, counts, strict=True)}


def signed_distance_m(points_xy: np.ndarray, polygon: shapely.Polygon) -> np.ndarray:
    """Distance of each point to the polygon's outline, positive inside, negative outside."""
    pts = shapely.points(np.asarray(points_xy, float))
    d = shapely.distance(pts, polygon.exterior)
    return np.where(shapely.contains(polygon, pts), d, -d)


def piece_runs(
    signed_m: np.ndarray, halo_m: float, min_frames: int = MIN_PIECE_FRAMES
) -> list[tuple[int, int]]:
    """``[(start, stop), ...]``: the runs of frames within ``halo_m`` of the tile that contain at
    least one frame inside it and have ``min_frames`` frames or more."""
    near = signed_m > -halo_m
    edges = np.flatnonzero(np.diff(np.concatenate([[0], near.astype(np.int8), [0]])))
    runs = []
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        if stop - start >= min_frames and np.any(signed_m[start:stop] >= 0):
            runs.append((int(start), int(stop)))
    return runs


def crop_trip(trip: Trip, start: int, stop: int, *, suffix: str) -> Trip:
    """Frames ``[start, stop)`` of a trip as a trip of their own, ``trip_id`` + ``suffix``."""
    return replace(
        trip,
        trip_id=f"{trip.trip_id}{suffix}",
        timestamps_s=trip.timestamps_s[start:stop],
        gnss_lonlat_deg=trip.gnss_lonlat_deg[start:stop],
        gnss_status=trip.gnss_status[start:stop],
        gnss_std_m=trip.gnss_std_m[start:stop],
        gnss_heading_deg=trip.gnss_heading_deg[start:stop],
        odom_xyyaw=trip.odom_xyyaw[start:stop],
        elements=trip.elements[start:stop],
    )


def crop_reconstruction(
    recon: TripReconstruction, start: int, stop: int, *, suffix: str
) -> TripReconstruction:
    """A piece of a trip: its frames ``[start, stop)``, keyframes and instances re-indexed, the
    instances seen in those frames cut to the frames' box (grown by ``INSTANCE_MARGIN_M``)."""
    poses = recon.poses_xyyaw_world[start:stop]
    lo, hi = poses[:, :2].min(axis=0) - INSTANCE_MARGIN_M, poses[:, :2].max(axis=0) + INSTANCE_MARGIN_M
    instances: list[TripInstance] = []
    for inst in recon.instances:
        if inst.last_frame < start or inst.first_frame >= stop:
            continue
        first, last = max(inst.first_frame, start) - start, min(inst.last_frame, stop - 1) - start
        for points in _clip_to_box(inst, lo, hi):
            instances.append(replace(inst, points_xy_world=points, first_frame=first, last_frame=last))
    keyframes = (
        recon.keyframe_indices[(recon.keyframe_indices >= start) & (recon.keyframe_indices < stop)] - start
    )
    if len(keyframes) == 0 or keyframes[0] != 0:
        keyframes = np.concatenate([[0], keyframes]).astype(recon.keyframe_indices.dtype)
    return replace(
        recon,
        trip=crop_trip(recon.trip, start, stop, suffix=suffix),
        poses_xyyaw_world=poses,
        pose_sigma_xy_m=recon.pose_sigma_xy_m[start:stop],
        keyframe_indices=keyframes,
        instances=tuple(instances),
        gnss_inlier=recon.gnss_inlier[start:stop] if recon.gnss_inlier is not None else None,
        white_poses_xyyaw_world=(
            recon.white_poses_xyyaw_world[start:stop] if recon.white_poses_xyyaw_world is not None else None
        ),
    )


def _clip_to_box(inst: TripInstance, lo: np.ndarray, hi: np.ndarray) -> list[np.ndarray]:
    pts = np.asarray(inst.points_xy_world, float)
    if inst.type.is_polygon:  # kept whole when its centre is in the box
        c = pts.mean(axis=0)
        return [pts] if np.all(c >= lo) and np.all(c <= hi) else []
    if len(pts) < 2:
        return [pts] if len(pts) and np.all(pts[0] >= lo) and np.all(pts[0] <= hi) else []
    clipped = shapely.clip_by_rect(shapely.LineString(pts), lo[0], lo[1], hi[0], hi[1])
    parts = [np.asarray(g.coords) for g in getattr(clipped, "geoms", [clipped]) if not g.is_empty]
    return [p for p in parts if len(p) >= 2 and p.ndim == 2]


def grid_rotation_rad(src: LocalFrame, dst: LocalFrame, at_xy_src: np.ndarray) -> float:
    """Angle to add to a heading in ``src`` to get it in ``dst`` (their grid norths differ by the
    meridian convergence between their origins), measured at ``at_xy_src``."""
    lonlat = src.to_lonlat(np.asarray(at_xy_src, float).reshape(1, 2))
    return float(dst.convergence_rad(lonlat)[0] - src.convergence_rad(lonlat)[0])


def reframe_poses(poses_xyyaw: np.ndarray, src: LocalFrame, dst: LocalFrame) -> np.ndarray:
    poses_xyyaw = np.asarray(poses_xyyaw, float)
    if src == dst or len(poses_xyyaw) == 0:
        return poses_xyyaw.copy()
    rot = grid_rotation_rad(src, dst, poses_xyyaw[:, :2].mean(axis=0))
    xy = dst.to_local(src.to_lonlat(poses_xyyaw[:, :2]))
    return np.column_stack([xy, np.angle(np.exp(1j * (poses_xyyaw[:, 2] + rot)))])


def reframe_points(points_xy: np.ndarray, src: LocalFrame, dst: LocalFrame) -> np.ndarray:
    points_xy = np.asarray(points_xy, float).reshape(-1, 2)
    return points_xy.copy() if src == dst else dst.to_local(src.to_lonlat(points_xy))


def reframe_reconstruction(recon: TripReconstruction, src: LocalFrame, dst: LocalFrame) -> TripReconstruction:
    """A trip's single-trip reconstruction moved from frame ``src`` to frame ``dst``."""
    if src == dst:
        return recon
    return replace(
        recon,
        poses_xyyaw_world=reframe_poses(recon.poses_xyyaw_world, src, dst),
        white_poses_xyyaw_world=(
            None
            if recon.white_poses_xyyaw_world is None
            else reframe_poses(recon.white_poses_xyyaw_world, src, dst)
        ),
        instances=tuple(
            replace(i, points_xy_world=reframe_points(i.points_xy_world, src, dst)) for i in recon.instances
        ),
    )


def blend_weight(signed_m: np.ndarray, halo_m: float) -> np.ndarray:
    """Weight of a tile's pose of a frame: 0.5 on the tile's edge, 1 at ``halo_m`` inside, 0 at
    ``halo_m`` outside (linear in between)."""
    return np.clip(0.5 + np.asarray(signed_m, float) / (2.0 * halo_m), 0.0, 1.0)


def assemble_poses(
    fallback_xyyaw: np.ndarray, contributions: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray]:
    """A trip's final poses from the tiles that aligned its frames.

    ``contributions``: ``(frame_indices (F,), poses_xyyaw (F, 3), weights (F,))`` per tile, all in
    one frame; frames of weight 0 (a piece that could not be aligned) do not count. A frame aligned
    by several tiles takes their weighted mean (headings on the
    circle). A frame no tile aligned (a run too short to align) moves with the correction
    (aligned minus ``fallback``, the single-trip pose) interpolated from the aligned frames
    around it. Returns the poses ``(N, 3)`` and which frames were aligned ``(N,)``."""
    fallback = np.asarray(fallback_xyyaw, float)
    n = len(fallback)
    acc = np.zeros((n, 4))  # sum w*x, w*y, w*e^{i yaw} (re, im)
    wsum = np.zeros(n)
    for idx, poses, w in contributions:
        w = np.asarray(w, float)
        idx, poses, w = np.asarray(idx)[w > 0], np.asarray(poses)[w > 0], w[w > 0]
        np.add.at(
            acc,
            idx,
            np.column_stack(
                [w * poses[:, 0], w * poses[:, 1], w * np.cos(poses[:, 2]), w * np.sin(poses[:, 2])]
            ),
        )
        np.add.at(wsum, idx, w)
    aligned = wsum > 0
    out = fallback.copy()
    if not aligned.any():
        return out, aligned
    out[aligned, 0] = acc[aligned, 0] / wsum[aligned]
    out[aligned, 1] = acc[aligned, 1] / wsum[aligned]
    out[aligned, 2] = np.arctan2(acc[aligned, 3], acc[aligned, 2])
    if not aligned.all():  # carry the correction of the nearest aligned frames across the gaps
        frames = np.arange(n)
        have = frames[aligned]
        delta = out[aligned] - fallback[aligned]
        delta[:, 2] = np.angle(np.exp(1j * delta[:, 2]))
        gap = ~aligned
        for k in range(3):
            out[gap, k] = fallback[gap, k] + np.interp(frames[gap], have, delta[:, k])
        out[:, 2] = np.angle(np.exp(1j * out[:, 2]))
    return out, aligned
