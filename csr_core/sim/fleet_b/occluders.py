"""Other traffic as moving boxes around the ego vehicle, and the ground they hide from it.

Four slots follow the ego path (the road the ego drives): a lead vehicle ahead in the lane, a
vehicle on each side (an adjacent lane or a parked car) and an oncoming one passing on the left.
Each slot is present for exponential periods (``mean_present_s`` / ``mean_absent_s``), a car or
a truck drawn at each appearance; the lead and side gaps wander as Ornstein-Uhlenbeck processes
mapped onto their ranges; the oncoming vehicle closes at ``ego speed + oncoming_speed_mps``.

Occlusion is a 2-D shadow cast from the vehicle origin: a ground point is hidden when its bearing
lies in a box's angular extent and it is farther than the box's nearest corner (the ground
under the box included), the line-of-sight model of BEV occupancy and visibility maps.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from csr_core.sim import geometry as geo
from csr_core.sim.fleet_b.gnss import ou_unit
from csr_core.sim.fleet_b.params import OccluderParamsB

BOX_COLUMNS = 5  # cx, cy, yaw, length, width


def _presence(
    n: int, dt_s: float, p: OccluderParamsB, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(n,) presence of a slot and (n,) the index of its current appearance."""
    on = np.zeros(n, dtype=bool)
    appearance = np.zeros(n, dtype=np.int64)
    state = bool(rng.random() < p.mean_present_s / (p.mean_present_s + p.mean_absent_s))
    k, count = 0, 0
    while k < n:
        mean = p.mean_present_s if state else p.mean_absent_s
        dwell = max(1, int(rng.exponential(mean) / dt_s))
        on[k : k + dwell] = state
        appearance[k : k + dwell] = count
        count += int(state)
        k += dwell
        state = not state
    return on, appearance


def occluder_boxes(
    t_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    speed_mps: np.ndarray,
    p: OccluderParamsB,
    rng: np.random.Generator,
) -> np.ndarray:
    """(N, 4, 5) boxes per frame in the world frame (cx, cy, yaw, length, width); NaN rows for
    absent slots."""
    n = len(t_s)
    dt_s = float(np.median(np.diff(t_s))) if n > 1 else 0.1
    xy = poses_xyyaw_world[:, :2]
    s_ego = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    keep = np.concatenate([[True], np.diff(s_ego) > 1e-3])
    path, s_path = xy[keep], s_ego[keep]
    boxes = np.full((n, 4, BOX_COLUMNS), np.nan)
    if len(path) < 2:
        return boxes
    heading = np.unwrap(geo.headings_rad(path))
    sizes = np.array([p.car_size_m, p.truck_size_m])
    gaps = np.empty((n, 4))
    z = ou_unit(n, dt_s, p.gap_reversion_s, rng, size=3)
    for j, (lo, hi) in enumerate((p.lead_gap_m, p.side_gap_m, p.side_gap_m)):
        gaps[:, j] = lo + (hi - lo) * ndtr(z[:, j])
    closing = np.cumsum((speed_mps + p.oncoming_speed_mps) * dt_s)
    lateral = (0.0, p.side_offset_m, -p.side_offset_m, p.side_offset_m)
    for j in range(4):
        on, appearance = _presence(n, dt_s, p, rng)
        truck = rng.random(int(appearance.max()) + 1) < p.truck_share
        if j == 3:  # oncoming: each appearance starts far ahead and closes in
            start = np.zeros(n)
            first = np.flatnonzero(np.diff(np.concatenate([[-1], appearance])) != 0)
            start[first] = closing[first]
            start = np.maximum.accumulate(start)
            gaps[:, 3] = p.oncoming_start_gap_m - (closing - start)
        s = s_ego + gaps[:, j]
        on &= (s > 0.0) & (s < s_path[-1])
        cx = np.interp(s, s_path, path[:, 0])
        cy = np.interp(s, s_path, path[:, 1])
        yaw = np.interp(s, s_path, heading)
        cx, cy = cx - lateral[j] * np.sin(yaw), cy + lateral[j] * np.cos(yaw)
        size = sizes[truck[appearance].astype(int)]
        rows = np.column_stack([cx, cy, yaw, size])
        boxes[on, j] = rows[on]
    return boxes


def boxes_to_vehicle(boxes_world: np.ndarray, pose_xyyaw: np.ndarray) -> np.ndarray:
    """(K, 5) world boxes (NaN rows dropped) into the vehicle frame of ``pose_xyyaw``."""
    b = boxes_world[~np.isnan(boxes_world[:, 0])]
    c, s = np.cos(pose_xyyaw[2]), np.sin(pose_xyyaw[2])
    dx, dy = b[:, 0] - pose_xyyaw[0], b[:, 1] - pose_xyyaw[1]
    return np.column_stack([c * dx + s * dy, -s * dx + c * dy, b[:, 2] - pose_xyyaw[2], b[:, 3], b[:, 4]])


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(K, 4, 2) corners of (K, 5) boxes."""
    half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], dtype=float) / 2.0
    local = half[None, :, :] * boxes[:, None, 3:5]
    c, s = np.cos(boxes[:, 2])[:, None], np.sin(boxes[:, 2])[:, None]
    x = boxes[:, 0:1] + c * local[:, :, 0] - s * local[:, :, 1]
    y = boxes[:, 1:2] + s * local[:, :, 0] + c * local[:, :, 1]
    return np.stack([x, y], axis=2)


def occluded_mask(points_xy_vehicle: np.ndarray, boxes_vehicle: np.ndarray) -> np.ndarray:
    """(M,) True where a point lies in the shadow of (or under) one of the (K, 5) boxes, seen
    from the vehicle origin. Boxes that contain the origin are ignored."""
    hidden = np.zeros(len(points_xy_vehicle), dtype=bool)
    if len(boxes_vehicle) == 0 or len(points_xy_vehicle) == 0:
        return hidden
    corners = box_corners(boxes_vehicle)
    bearing = np.arctan2(points_xy_vehicle[:, 1], points_xy_vehicle[:, 0])
    rng_m = np.linalg.norm(points_xy_vehicle, axis=1)
    for box, cs in zip(boxes_vehicle, corners, strict=True):
        c, s = np.cos(box[2]), np.sin(box[2])
        ox, oy = -box[0] * c - box[1] * s, box[0] * s - box[1] * c  # origin in the box frame
        if abs(ox) < box[3] / 2 and abs(oy) < box[4] / 2:
            continue
        centre = np.arctan2(box[1], box[0])
        d = np.angle(np.exp(1j * (np.arctan2(cs[:, 1], cs[:, 0]) - centre)))
        near = float(np.linalg.norm(cs, axis=1).min())
        dp = np.angle(np.exp(1j * (bearing - centre)))
        hidden |= (dp >= d.min()) & (dp <= d.max()) & (rng_m > near)
    return hidden
