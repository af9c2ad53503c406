"""BEV vector perception of fleet b: per-frame instances as a MapTR-style online mapper outputs
them (Liao et al., *MapTR*, ICLR 2023: a 60 m x 30 m BEV range, every instance a fixed number
of points, a confidence score), with the visibility and error structure of a camera BEV stack.

Per frame, from the true pose:

- Visibility: truth lines sampled every ``sample_step_m``; samples outside the BEV box, under or
  in the shadow of other traffic (``occluders``), or in the gap between painted dashes are not
  seen. Each visible run is one instance, so lines are cut at the BEV border and where a box
  hides them. Dashed dividers are reported dash by dash (dash phase fixed by the element id,
  the same in every trip); beyond ``dash_merge_range_m`` a dashed run is one instance.
- Missed detections: ``p = miss_prob_base + miss_prob_range (r / 30 m)^2 + miss_prob_occlusion x
  (occluded share of the element)``, plus ``small_element_miss_prob`` for stop lines and
  crosswalks, ``r`` the instance's mean distance.
- Noise grows quadratically with distance, as depth error of a monocular camera does (the
  error of the lifted ground point goes with r^2 / (f b)): a per-point white sigma
  ``point_sigma_base_m + point_sigma_quad_per_m2 r^2``, a per-instance offset normal to the line
  with ``offset_sigma_*``, and a per-track bias kept until the track id changes; centrelines
  ``centerline_noise_factor`` noisier. A per-vehicle rig misalignment (yaw and x/y) turns and
  shifts every instance of every frame of that vehicle.
- Tracker (the contract's per-element ``track_id``): an id per visible instance, kept while it is
  seen again within ``track_lost_frames``, replaced at an id switch (``track_switch_prob`` per
  track and frame) or after a longer gap.
- False positives: Poisson(``false_positive_rate_per_frame``) straight instances roughly along the
  driving direction, each with a new track id and a low Beta-distributed score.
- Score: ``sigmoid(score_logit_base - score_logit_range r / 30 m - 2 x occluded share + N(0,
  score_logit_sigma))``; divider style from the truth, solid and dashed confused with probability
  ``style_confusion_prob x r / 30 m``. Crosswalks: the polygon clipped to the BEV box.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from shapely.geometry import Polygon, box

from csr_core.sim import geometry as geo
from csr_core.sim.fleet_b.occluders import boxes_to_vehicle, occluded_mask, occluder_boxes
from csr_core.sim.fleet_b.params import PerceptionParamsB
from csr_core.sim.world import TruthElement
from csr_core.types import DividerStyle, ElementType

_LINE_TYPES = (
    ElementType.LANE_DIVIDER,
    ElementType.ROAD_BOUNDARY,
    ElementType.CENTERLINE,
    ElementType.STOP_LINE,
)
_NOT_DASHED, _GAP, _MERGED = -1, -2, -3
_GOLDEN = 0.6180339887498949
_FP_TYPES = (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE)
_FP_TYPE_PROBS = (0.6, 0.25, 0.15)


@dataclass(frozen=True)
class TruthIndexB:
    """Truth lines as samples (with a KD-tree) and polygons with outline samples, world frame."""

    lines: tuple[TruthElement, ...]
    samples_xy: np.ndarray  # (M, 2)
    sample_line: np.ndarray  # (M,) index into ``lines``
    sample_seq: np.ndarray  # (M,) ordinal along its line
    sample_s: np.ndarray  # (M,) arclength along its line, m
    sample_dash: np.ndarray  # (M,) dash number, or _NOT_DASHED / _GAP
    tree: cKDTree | None
    polygons: tuple[TruthElement, ...]
    polygon_samples: tuple[np.ndarray, ...]  # outline samples per polygon
    polygon_centroids_xy: np.ndarray  # (P, 2)


def dash_numbers(element_id: int, s_m: np.ndarray, params: PerceptionParamsB) -> np.ndarray:
    """Painted dash number at arclengths ``s_m`` of a dashed divider, ``_GAP`` between dashes."""
    period = params.dash_length_m + params.dash_gap_m
    u = s_m + ((element_id * _GOLDEN) % 1.0) * period
    return np.where(np.mod(u, period) < params.dash_length_m, np.floor(u / period).astype(np.int64), _GAP)


def build_truth_index_b(elements: tuple[TruthElement, ...], params: PerceptionParamsB) -> TruthIndexB:
    lines = tuple(e for e in elements if e.type in _LINE_TYPES and len(e.points_xy_world) >= 2)
    polys = tuple(e for e in elements if e.type.is_polygon and len(e.points_xy_world) >= 3)
    xy, which, seq, dash, arc = [], [], [], [], []
    for i, e in enumerate(lines):
        pts = geo.dedupe(np.asarray(e.points_xy_world, float))
        if len(pts) < 2:
            continue
        total = geo.arclength_m(pts)[-1]
        s = np.append(np.arange(0.0, total, params.sample_step_m), total)
        xy.append(geo.interpolate_at(pts, s))
        which.append(np.full(len(s), i))
        seq.append(np.arange(len(s)))
        arc.append(s)
        dashed = e.type == ElementType.LANE_DIVIDER and e.style == DividerStyle.DASHED
        dash.append(dash_numbers(e.element_id, s, params) if dashed else np.full(len(s), _NOT_DASHED))
    samples = np.vstack(xy) if xy else np.zeros((0, 2))
    outlines = tuple(
        geo.resample(np.vstack([p.points_xy_world, p.points_xy_world[:1]]), params.sample_step_m)
        for p in polys
    )
    return TruthIndexB(
        lines,
        samples,
        np.concatenate(which) if which else np.zeros(0, np.int64),
        np.concatenate(seq) if seq else np.zeros(0, np.int64),
        np.concatenate(arc) if arc else np.zeros(0),
        np.concatenate(dash) if dash else np.zeros(0, np.int64),
        cKDTree(samples) if len(samples) else None,
        polys,
        outlines,
        np.array([np.mean(p.points_xy_world, axis=0) for p in polys]).reshape(-1, 2),
    )


@dataclass
class Tracker:
    """On-vehicle tracker state of one trip: instance key -> (track id, last frame, track bias)."""

    params: PerceptionParamsB
    next_id: int
    tracks: dict = field(default_factory=dict)
    continued: int = 0
    switched: int = 0

    def fresh_id(self) -> int:
        self.next_id += 1
        return self.next_id

    def assign(self, key: tuple, frame_k: int, rng: np.random.Generator) -> tuple[int, float]:
        track = self.tracks.get(key)
        if track is not None and frame_k - track[1] - 1 <= self.params.track_lost_frames:
            self.continued += 1
            if rng.random() < self.params.track_switch_prob:
                self.switched += 1
                track = None
        else:
            track = None
        if track is None:
            track = (self.fresh_id(), frame_k, float(rng.normal(0.0, self.params.track_bias_sigma_m)))
        self.tracks[key] = (track[0], frame_k, track[2])
        return track[0], track[2]


def sigma_at_range_m(base_m: float, quad_per_m2: float, r_m: np.ndarray | float) -> np.ndarray:
    """Noise sigma growing quadratically with the distance ``r_m`` from the vehicle."""
    return base_m + quad_per_m2 * np.square(np.asarray(r_m, dtype=float))


def miss_probability(r_m: float, occluded_share: float, small: bool, params: PerceptionParamsB) -> float:
    r_max = max(abs(v) for v in params.range_x_m)
    p = params.miss_prob_base + params.miss_prob_range * (r_m / r_max) ** 2
    p += params.miss_prob_occlusion * occluded_share + (params.small_element_miss_prob if small else 0.0)
    return float(min(p, 1.0))


def _score(r_m: float, occluded_share: float, params: PerceptionParamsB, rng: np.random.Generator) -> float:
    r_max = max(abs(v) for v in params.range_x_m)
    logit = params.score_logit_base - params.score_logit_range * r_m / r_max - 2.0 * occluded_share
    logit += rng.normal(0.0, params.score_logit_sigma)
    return round(float(1.0 / (1.0 + np.exp(-logit))), 3)


def _apply_rig(points_xy: np.ndarray, rig: np.ndarray) -> np.ndarray:
    c, s = np.cos(rig[2]), np.sin(rig[2])
    return np.column_stack(
        [
            c * points_xy[:, 0] - s * points_xy[:, 1] + rig[0],
            s * points_xy[:, 0] + c * points_xy[:, 1] + rig[1],
        ]
    )


def _in_box(local: np.ndarray, params: PerceptionParamsB) -> np.ndarray:
    (x0, x1), (y0, y1) = params.range_x_m, params.range_y_m
    return (local[:, 0] >= x0) & (local[:, 0] <= x1) & (local[:, 1] >= y0) & (local[:, 1] <= y1)


def _to_vehicle(xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = xy - pose[:2]
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


def _style(line: TruthElement, r_m: float, params: PerceptionParamsB, rng: np.random.Generator) -> str:
    style = line.style or DividerStyle.UNKNOWN
    r_max = max(abs(v) for v in params.range_x_m)
    if (
        style in (DividerStyle.SOLID, DividerStyle.DASHED)
        and rng.random() < params.style_confusion_prob * r_m / r_max
    ):
        style = DividerStyle.DASHED if style == DividerStyle.SOLID else DividerStyle.SOLID
    return style.value


def perceive_lines(
    index: TruthIndexB,
    pose_xyyaw: np.ndarray,
    boxes_vehicle: np.ndarray,
    params: PerceptionParamsB,
    rig: np.ndarray,
    tracker: Tracker,
    frame_k: int,
    rng: np.random.Generator,
) -> list[dict]:
    """Line instances of one frame (vehicle frame), as upload element dicts."""
    if index.tree is None:
        return []
    r_query = float(np.hypot(max(map(abs, params.range_x_m)), max(map(abs, params.range_y_m)))) + 1.0
    cand = np.sort(np.asarray(index.tree.query_ball_point(pose_xyyaw[:2], r_query), dtype=np.int64))
    if len(cand) == 0:
        return []
    local = _to_vehicle(index.samples_xy[cand], pose_xyyaw)
    r = np.linalg.norm(local, axis=1)
    dash = index.sample_dash[cand]
    far = r > params.dash_merge_range_m
    key = np.where(dash == _NOT_DASHED, _NOT_DASHED, np.where(far, _MERGED, dash))
    in_range = _in_box(local, params) & ((dash != _GAP) | far)
    visible = in_range.copy()
    visible[in_range] &= ~occluded_mask(local[in_range], boxes_vehicle)
    line = index.sample_line[cand]
    n_lines = len(index.lines)
    occluded_share = 1.0 - np.bincount(line[visible], minlength=n_lines) / np.maximum(
        np.bincount(line[in_range], minlength=n_lines), 1
    )
    vis = np.flatnonzero(visible)
    if len(vis) == 0:
        return []
    seq, li, ky = index.sample_seq[cand][vis], line[vis], key[vis]
    s_m, pts_v, r_v = index.sample_s[cand][vis], local[vis], r[vis]
    first = np.flatnonzero(np.r_[True, (np.diff(li) != 0) | (np.diff(seq) != 1) | (np.diff(ky) != 0)])
    last = np.r_[first[1:], len(vis)] - 1
    count = last - first + 1
    length_m = s_m[last] - s_m[first]
    r_mean = np.add.reduceat(r_v, first) / count
    small = np.array([index.lines[i].type == ElementType.STOP_LINE for i in li[first]])
    r_max = max(abs(v) for v in params.range_x_m)
    occ = occluded_share[li[first]]
    p_miss = params.miss_prob_base + params.miss_prob_range * (r_mean / r_max) ** 2
    p_miss = np.minimum(
        p_miss + params.miss_prob_occlusion * occ + params.small_element_miss_prob * small, 1.0
    )
    # the ordinal of each run among the runs of its (line, dash) in this frame
    run_key = li[first] * 1_000_003 + ky[first]
    ordinal = np.zeros(len(first), dtype=np.int64)
    _, inverse = np.unique(run_key, return_inverse=True)
    seen: dict[int, int] = {}
    for j, g in enumerate(inverse.tolist()):
        ordinal[j] = seen.get(g, 0)
        seen[g] = ordinal[j] + 1
    detected = (count >= 2) & (length_m >= params.min_piece_m) & (rng.random(len(first)) >= p_miss)
    runs = np.flatnonzero(detected)
    if len(runs) == 0:
        return []
    # resample every detected run to n points by arclength (runs kept apart by a large offset)
    n_pts = np.clip(np.ceil(length_m[runs] / params.min_point_spacing_m) + 1, 2, params.points_per_instance)
    n_pts = n_pts.astype(np.int64)
    run_of_sample = np.repeat(np.arange(len(first)), count)
    s_global = s_m + run_of_sample * 1.0e6
    run_of_pt = np.repeat(runs, n_pts)
    starts = np.r_[0, np.cumsum(n_pts)[:-1]]
    frac = (np.arange(n_pts.sum()) - np.repeat(starts, n_pts)) / np.repeat(n_pts - 1, n_pts)
    s_new = s_m[first][run_of_pt] + frac * length_m[run_of_pt] + run_of_pt * 1.0e6
    pts = np.column_stack([np.interp(s_new, s_global, pts_v[:, 0]), np.interp(s_new, s_global, pts_v[:, 1])])
    # noise: per-track bias and per-instance offset normal to the chord, per-point white noise
    tracks = [
        tracker.assign(
            (index.lines[li[first[j]]].element_id, int(ky[first[j]]), int(ordinal[j])), frame_k, rng
        )
        for j in runs.tolist()
    ]
    ends = starts + n_pts - 1
    chord = pts[ends] - pts[starts]
    normal = (
        np.column_stack([-chord[:, 1], chord[:, 0]])
        / np.maximum(np.linalg.norm(chord, axis=1), 1e-9)[:, None]
    )
    offset = np.array([b for _, b in tracks]) + rng.standard_normal(len(runs)) * sigma_at_range_m(
        params.offset_sigma_base_m, params.offset_sigma_quad_per_m2, r_mean[runs]
    )
    factor = np.array(
        [
            params.centerline_noise_factor
            if index.lines[li[first[j]]].type == ElementType.CENTERLINE
            else 1.0
            for j in runs.tolist()
        ]
    )
    sig = sigma_at_range_m(
        params.point_sigma_base_m, params.point_sigma_quad_per_m2, np.linalg.norm(pts, axis=1)
    )
    k_of_pt = np.repeat(np.arange(len(runs)), n_pts)
    pts = pts + factor[k_of_pt, None] * (
        (offset * normal.T).T[k_of_pt] + sig[:, None] * rng.standard_normal(pts.shape)
    )
    coords = np.round(_apply_rig(pts, rig), 3).tolist()
    logit = params.score_logit_base - params.score_logit_range * r_mean[runs] / r_max - 2.0 * occ[runs]
    score = np.round(
        1.0 / (1.0 + np.exp(-(logit + params.score_logit_sigma * rng.standard_normal(len(runs))))), 3
    )
    out: list[dict] = []
    for k, j in enumerate(runs.tolist()):
        truth = index.lines[li[first[j]]]
        el: dict = {"type": truth.type.value, "points": coords[starts[k] : starts[k] + n_pts[k]]}
        if truth.type == ElementType.LANE_DIVIDER:
            el["style"] = _style(truth, float(r_mean[j]), params, rng)
        el["score"] = float(score[k])
        el["track_id"] = tracks[k][0]
        out.append(el)
    return out


def perceive_polygons(
    index: TruthIndexB,
    pose_xyyaw: np.ndarray,
    boxes_vehicle: np.ndarray,
    params: PerceptionParamsB,
    rig: np.ndarray,
    tracker: Tracker,
    frame_k: int,
    rng: np.random.Generator,
) -> list[dict]:
    """Crosswalk / road-marking instances of one frame: the polygon clipped to the BEV box."""
    if not index.polygons:
        return []
    reach = float(np.hypot(max(map(abs, params.range_x_m)), max(map(abs, params.range_y_m)))) + 20.0
    near = np.flatnonzero(np.linalg.norm(index.polygon_centroids_xy - pose_xyyaw[:2], axis=1) < reach)
    (x0, x1), (y0, y1) = params.range_x_m, params.range_y_m
    bev = box(x0, y0, x1, y1)
    out: list[dict] = []
    for j in near.tolist():
        poly_el = index.polygons[j]
        outline = _to_vehicle(index.polygon_samples[j], pose_xyyaw)
        inside = _in_box(outline, params)
        if not inside.any():
            continue
        hidden = occluded_mask(outline[inside], boxes_vehicle)
        clipped = Polygon(_to_vehicle(poly_el.points_xy_world, pose_xyyaw)).buffer(0).intersection(bev)
        if clipped.is_empty or clipped.area < 2.0 or clipped.geom_type != "Polygon":
            continue
        share = float(hidden.mean())
        corners = np.asarray(clipped.exterior.coords)[:-1]
        r_c = float(np.linalg.norm(np.mean(corners, axis=0)))
        if len(corners) < 3 or rng.random() < miss_probability(r_c, share, True, params):
            continue
        track_id, _ = tracker.assign((poly_el.element_id, 0, 0), frame_k, rng)
        sig = sigma_at_range_m(
            params.point_sigma_base_m, params.point_sigma_quad_per_m2, np.linalg.norm(corners, axis=1)
        )
        corners = corners + sig[:, None] * rng.standard_normal(corners.shape)
        out.append(
            {
                "type": poly_el.type.value,
                "points": np.round(_apply_rig(corners, rig), 3).tolist()[:200],
                "score": _score(r_c, share, params, rng),
                "track_id": track_id,
            }
        )
    return out


def false_positives(
    params: PerceptionParamsB, rig: np.ndarray, tracker: Tracker, rng: np.random.Generator
) -> list[dict]:
    """Spurious instances of one frame: straight, roughly along the driving direction."""
    out = []
    (x0, x1), (y0, y1) = params.range_x_m, params.range_y_m
    for _ in range(int(rng.poisson(params.false_positive_rate_per_frame))):
        kind = _FP_TYPES[int(rng.choice(len(_FP_TYPES), p=_FP_TYPE_PROBS))]
        length = rng.uniform(*params.false_positive_length_m)
        start = np.array([rng.uniform(x0, max(x0, x1 - length)), rng.uniform(y0, y1)])
        ang = rng.normal(0.0, 0.3)
        u = np.linspace(0.0, length, params.points_per_instance)[:, None]
        pts = start + u * np.array([np.cos(ang), np.sin(ang)])
        pts = np.column_stack([np.clip(pts[:, 0], x0, x1), np.clip(pts[:, 1], y0, y1)])
        if geo.arclength_m(pts)[-1] < params.min_piece_m:
            continue
        el: dict = {"type": kind.value, "points": np.round(_apply_rig(pts, rig), 3).tolist()}
        if kind == ElementType.LANE_DIVIDER:
            el["style"] = "dashed" if rng.random() < 0.5 else "solid"
        el["score"] = round(float(rng.beta(*params.spurious_score_beta)), 3)
        el["track_id"] = tracker.fresh_id()
        out.append(el)
    return out


def perceive_trip_b(
    index: TruthIndexB,
    t_s: np.ndarray,
    poses_xyyaw_world: np.ndarray,
    speed_mps: np.ndarray,
    params: PerceptionParamsB,
    rig: np.ndarray,
    rng: np.random.Generator,
) -> tuple[list[list[dict]], dict[str, float]]:
    """Element lists of every frame and the trip's perception statistics. ``rig`` (3,) is the
    vehicle's rig misalignment (x, y, yaw)."""
    boxes = occluder_boxes(t_s, poses_xyyaw_world, speed_mps, params.occluders, rng)
    tracker = Tracker(params, next_id=int(rng.integers(1, 2**30)))
    frames = []
    for k, pose in enumerate(poses_xyyaw_world):
        bv = boxes_to_vehicle(boxes[k], pose)
        els = perceive_lines(index, pose, bv, params, rig, tracker, k, rng)
        els += perceive_polygons(index, pose, bv, params, rig, tracker, k, rng)
        els += false_positives(params, rig, tracker, rng)
        frames.append(els)
    info = {
        "track_continuations": tracker.continued,
        "track_switches": tracker.switched,
        "occluders_present_share": round(float(np.mean(~np.isnan(boxes[:, :, 0]))), 3),
    }
    return frames, info
