"""MapTR-like BEV vector perception (parameters: ``profiles.PerceptionParams``).

Per frame, every truth element inside the BEV range (vehicle frame x in ``range_x_m``, y in
``range_y_m``, from the TRUE pose) is reported as the pieces that fall inside the range:
- lines are resampled every ``point_spacing_m``; dashed dividers are reported dash by dash
  ("as seen": ``dash_length_m`` painted, ``dash_gap_m`` gap, phase fixed on the truth polyline,
  so the same dashes appear in every frame and every trip);
- noise: a per-frame BEV distortion (small yaw and longitudinal scale, common to all elements
  of the frame), a per-element offset (the same for all points of the element: correlated
  along it) made of a per-trip part (``track_bias_sigma_m``, the same in every frame) and a
  per-frame part (sigma ``base + per_m * distance``) that partly varies slowly with the distance
  travelled (frame-to-frame correlated, as a detector's errors on the same scene are), plus
  white noise per point (likewise);
  road boundaries ``boundary_noise_factor`` times noisier;
- missed detections (more likely far away), false positives (short spurious lines), ghosts (a
  divider/boundary copy shifted sideways by about one lane width for a few frames);
- crosswalks are polygons clipped to the range (first point not repeated), stop lines short lines;
- ``score``, ``style`` (dividers), and ``track_id``: stable per truth element (per dash) within a
  trip, scrambled per trip so that ids do not match across trips.

Output is JSON-ready (the upload's element dicts, vehicle frame, metres rounded to mm) because
the simulator writes millions of them.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from scipy.spatial import cKDTree

from csr_core.sim import geometry as geo
from csr_core.sim.profiles import PerceptionParams
from csr_core.sim.world import World
from csr_core.types import DividerStyle, ElementType

_TYPE_CODES = (
    ElementType.LANE_DIVIDER,
    ElementType.ROAD_BOUNDARY,
    ElementType.CENTERLINE,
    ElementType.STOP_LINE,
)
_DIVIDER, _BOUNDARY, _CENTERLINE, _STOP = range(4)
_TYPE_NAMES = tuple(t.value for t in _TYPE_CODES)
_GHOST_KEY, _FALSE_KEY = 1 << 28, 1 << 29
_DASH_KEYS = 4096


@dataclass(frozen=True)
class TruthIndex:
    """Dense samples of the world's line elements, and its polygons, for fast per-frame clipping."""

    points_xy: np.ndarray  # (P, 2) world
    element_of_point: np.ndarray  # (P,) index into ``element_type`` etc.
    dash_of_point: np.ndarray  # (P,) dash number along the element; -1 where not dashed
    element_type: np.ndarray  # (E,) type code
    element_style: tuple[str | None, ...]  # (E,)
    element_id: np.ndarray  # (E,) truth element id
    tree: cKDTree
    polygons_xy: tuple[np.ndarray, ...]  # world outlines
    polygon_centroids_xy: np.ndarray  # (Q, 2)
    polygon_radius_m: np.ndarray  # (Q,) largest vertex distance from the centroid
    polygon_ids: np.ndarray  # (Q,)
    polygon_vertices_xy: np.ndarray  # (V, 2) all outlines, concatenated
    polygon_first_vertex: np.ndarray  # (Q,) index of each polygon's first vertex there
    polygon_n_vertices: np.ndarray  # (Q,)


def build_truth_index(world: World, params: PerceptionParams) -> TruthIndex:
    pts: list[np.ndarray] = []
    elem: list[np.ndarray] = []
    dash: list[np.ndarray] = []
    types: list[int] = []
    styles: list[str | None] = []
    ids: list[int] = []
    polys, poly_ids = [], []
    period = params.dash_length_m + params.dash_gap_m
    for e in world.elements:
        if e.type.is_polygon:
            polys.append(e.points_xy_world)
            poly_ids.append(e.element_id)
            continue
        k = len(types)
        types.append(_TYPE_CODES.index(e.type))
        styles.append(e.style.value if e.style is not None else None)
        ids.append(e.element_id)
        if e.style == DividerStyle.DASHED:
            # only the painted dashes, each sampled exactly from its start to its end
            length = float(geo.arclength_m(e.points_xy_world)[-1])
            s_parts, dash_parts = [], []
            for j, a in enumerate(np.arange(0.0, length, period)):
                b = min(a + params.dash_length_m, length)
                if b - a < 0.05:
                    continue
                n = max(int(np.ceil((b - a) / params.dense_step_m)), 1) + 1
                s_parts.append(np.linspace(a, b, n))
                dash_parts.append(np.full(n, j))
            if not s_parts:
                continue
            dense = geo.interpolate_at(e.points_xy_world, np.concatenate(s_parts))
            dash.append(np.concatenate(dash_parts))
        else:
            dense = geo.resample(e.points_xy_world, params.dense_step_m)
            dash.append(np.full(len(dense), -1))
        pts.append(dense)
        elem.append(np.full(len(dense), k))
    points = np.vstack(pts) if pts else np.zeros((0, 2))
    centroids = np.array([p.mean(axis=0) for p in polys]).reshape(-1, 2)
    n_vertices = np.array([len(p) for p in polys], np.intp)
    return TruthIndex(
        points_xy=points,
        element_of_point=np.concatenate(elem) if elem else np.zeros(0, int),
        dash_of_point=np.concatenate(dash) if dash else np.zeros(0, int),
        element_type=np.array(types, int),
        element_style=tuple(styles),
        element_id=np.array(ids, int),
        tree=cKDTree(points if len(points) else np.zeros((1, 2))),
        polygons_xy=tuple(polys),
        polygon_centroids_xy=centroids,
        polygon_radius_m=np.array(
            [np.linalg.norm(p - c, axis=1).max() for p, c in zip(polys, centroids, strict=True)]
        ),
        polygon_ids=np.array(poly_ids, int),
        polygon_vertices_xy=np.vstack(polys) if polys else np.zeros((0, 2)),
        polygon_first_vertex=(np.cumsum(n_vertices) - n_vertices).astype(np.intp),
        polygon_n_vertices=n_vertices,
    )


def _line_sigma(
    params: PerceptionParams, type_code: np.ndarray, dist_m: np.ndarray, offset: bool
) -> np.ndarray:
    base, per_m = (
        (params.line_offset_base_m, params.line_offset_per_m)
        if offset
        else (params.line_white_base_m, params.line_white_per_m)
    )
    factor = np.where(type_code == _BOUNDARY, params.boundary_noise_factor, 1.0)
    return (base + per_m * dist_m) * factor


class _FramePerceiver:
    """Holds the per-trip state (RNG, ghosts, id scrambling) across frames."""

    def __init__(
        self,
        index: TruthIndex,
        params: PerceptionParams,
        rng: np.random.Generator,
        n_frames: int,
        travelled_m: np.ndarray | None = None,
    ):
        self.index, self.p, self.rng = index, params, rng
        self.salt = int(rng.integers(1, 1 << 30))
        self.box = np.array(
            [params.range_x_m[0], params.range_y_m[0], params.range_x_m[1], params.range_y_m[1]]
        )
        self.far_m = float(np.hypot(max(abs(params.range_x_m[0]), params.range_x_m[1]), params.range_y_m[1]))
        self.subsample = max(int(round(params.point_spacing_m / params.dense_step_m)), 1)
        self.min_run = int(np.ceil(params.min_visible_m / params.dense_step_m)) + 1
        starts = np.flatnonzero(rng.random(n_frames) < params.ghost_rate_per_frame)
        self.ghost_event = np.full(n_frames, -1)
        for k, i in enumerate(starts.tolist()):
            n = int(rng.integers(params.ghost_frames[0], params.ghost_frames[1] + 1))
            self.ghost_event[i : i + n] = k
        self.ghost_side = rng.choice([-1.0, 1.0], size=max(len(starts), 1))
        self.ghost_target: dict[int, int] = {}
        self.frame_yaw_rad = np.radians(params.frame_yaw_sigma_deg) * rng.standard_normal(n_frames)
        self.frame_scale = params.frame_scale_sigma * rng.standard_normal(n_frames)
        n_tracks = len(index.element_type) + len(index.polygons_xy)
        self.track_bias = params.track_bias_sigma_m * rng.standard_normal((n_tracks, 2))
        # slowly varying part of the per-frame offset: per track and axis a sinusoid of the
        # distance the vehicle has travelled (unit variance over the phase)
        self.offset_wavelength_m = rng.uniform(*params.offset_wavelength_m, size=(n_tracks, 2))
        self.offset_phase = rng.uniform(0.0, 2 * np.pi, size=(n_tracks, 2))
        self.travelled_m = travelled_m if travelled_m is not None else np.zeros(n_frames)
        self.false_count = 0

    def _extend_to_range_edge(self, xv, yv, sel, elem, dash, starts, lengths, frame_of, poses_xyyaw) -> None:
        """Move the first / last point of each visible piece onto the range edge where the truth
        line continues outside (in place), so pieces end exactly at the BEV border."""
        ix = self.index
        n_points = len(ix.points_xy)
        for end_idx, step in ((starts, -1), (starts + lengths - 1, 1)):
            nb = sel[end_idx] + step
            valid = (nb >= 0) & (nb < n_points)
            nb_c = np.clip(nb, 0, n_points - 1)
            valid &= (ix.element_of_point[nb_c] == elem[end_idx]) & (ix.dash_of_point[nb_c] == dash[end_idx])
            k = end_idx[valid]
            if k.size == 0:
                continue
            pose = poses_xyyaw[frame_of[k]]
            c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
            d = ix.points_xy[nb_c[valid]] - pose[:, :2]
            out = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
            inside = np.column_stack([xv[k], yv[k]])
            delta = out - inside
            # largest step from the inside point towards the outside one that stays in the box
            t = np.ones(k.size)
            for axis, lo, hi in ((0, self.box[0], self.box[2]), (1, self.box[1], self.box[3])):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t_hi = np.where(out[:, axis] > hi, (hi - inside[:, axis]) / delta[:, axis], 1.0)
                    t_lo = np.where(out[:, axis] < lo, (lo - inside[:, axis]) / delta[:, axis], 1.0)
                t = np.minimum(t, np.minimum(t_hi, t_lo))
            t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
            xv[k] = inside[:, 0] + t * delta[:, 0]
            yv[k] = inside[:, 1] + t * delta[:, 1]

    def _offset_unit(self, track: np.ndarray, frame: np.ndarray) -> np.ndarray:
        """Unit-variance per-frame offsets ``(R, 2)`` of tracks seen in frames: a part that varies
        slowly with the distance travelled (share ``offset_temporal_share`` of the variance;
        constant while the vehicle stands) and a white part, new in every frame."""
        share = self.p.offset_temporal_share
        white = self.rng.standard_normal((track.size, 2))
        if share <= 0:
            return white
        s = self.travelled_m[frame][:, None]
        smooth = np.sqrt(2.0) * np.sin(
            2 * np.pi * s / self.offset_wavelength_m[track] + self.offset_phase[track]
        )
        return np.sqrt(share) * smooth + np.sqrt(1.0 - share) * white

    def _distort(self, xy: np.ndarray, frame_of: np.ndarray | int) -> np.ndarray:
        """Per-frame BEV distortion: a small yaw (camera/IMU extrinsic jitter) and a longitudinal
        scale (ground-plane pitch), ``xy (M, 2)`` vehicle frame."""
        yaw, scale = self.frame_yaw_rad[frame_of], self.frame_scale[frame_of]
        return np.column_stack([(1.0 + scale) * xy[:, 0] - yaw * xy[:, 1], xy[:, 1] + yaw * xy[:, 0]])

    def _score(self, dist_m: np.ndarray) -> np.ndarray:
        p = self.p
        s = p.score_mean - p.score_drop_at_range_end * dist_m / self.far_m
        if p.score_sigma > 0:
            s = s + p.score_sigma * self.rng.standard_normal(len(dist_m))
        return np.round(np.clip(s, 0.05, 0.99), 3)

    def lines(
        self,
        frames: np.ndarray,
        poses_xyyaw: np.ndarray,
        candidates: np.ndarray,
        out: list[list[dict[str, Any]]],
    ) -> None:
        """Perceive line elements for a batch of frames at once, appending to ``out[frame]``.

        ``candidates (T,)`` are dense truth point indices near each frame, ``frames (T,)`` their
        frame numbers (ascending, candidates ascending within a frame), ``poses_xyyaw (n, 3)``.
        """
        ix, p, rng = self.index, self.p, self.rng
        if candidates.size == 0:
            return
        f0 = int(frames[0])
        cos_f, sin_f = np.cos(poses_xyyaw[f0:, 2]), np.sin(poses_xyyaw[f0:, 2])
        c, s = cos_f[frames - f0], sin_f[frames - f0]
        d = ix.points_xy[candidates] - poses_xyyaw[frames, :2]
        xv = c * d[:, 0] + s * d[:, 1]
        yv = -s * d[:, 0] + c * d[:, 1]
        ok = (xv >= self.box[0]) & (xv <= self.box[2]) & (yv >= self.box[1]) & (yv <= self.box[3])
        sel, frame_of = candidates[ok], frames[ok]
        if sel.size == 0:
            return
        xv, yv = xv[ok], yv[ok]
        elem, dash = ix.element_of_point[sel], ix.dash_of_point[sel]
        brk = (np.diff(sel) != 1) | (np.diff(elem) != 0) | (np.diff(dash) != 0) | (np.diff(frame_of) != 0)
        starts = np.flatnonzero(np.concatenate([[True], brk]))
        n_runs = starts.size
        lengths = np.diff(np.append(starts, sel.size))
        self._extend_to_range_edge(xv, yv, sel, elem, dash, starts, lengths, frame_of, poses_xyyaw)
        run_of = np.repeat(np.arange(n_runs), lengths)
        pos = np.arange(sel.size) - starts[run_of]
        keep = ((pos % self.subsample) == 0) | (pos == lengths[run_of] - 1)
        run_elem = elem[starts]
        run_frame = frame_of[starts]
        run_type = ix.element_type[run_elem]
        mid = starts + lengths // 2
        run_dist = np.hypot(xv[mid], yv[mid])
        # which runs are reported
        report = lengths >= self.min_run
        p_miss = np.where(
            run_type == _STOP,
            p.small_miss_prob,
            p.miss_prob_base + p.miss_prob_at_range_end * run_dist / self.far_m,
        )
        if p_miss.any():
            report &= rng.random(n_runs) >= p_miss
        # noise: per-frame BEV distortion (yaw, longitudinal scale), per-element offset (correlated
        # along the element; a per-trip part and a per-frame part), per-point white noise
        xy = self._distort(np.column_stack([xv, yv]), frame_of)
        if p.track_bias_sigma_m > 0:
            factor = np.where(run_type == _BOUNDARY, p.boundary_noise_factor, 1.0)
            xy += (self.track_bias[run_elem] * factor[:, None])[run_of]
        off_sigma = _line_sigma(p, run_type, run_dist, offset=True)
        if off_sigma.any():
            xy += (off_sigma[:, None] * self._offset_unit(run_elem, run_frame))[run_of]
        white = _line_sigma(p, run_type[run_of], np.hypot(xv, yv), offset=False)
        if white.any():
            xy += white[:, None] * rng.standard_normal((sel.size, 2))
        xy = np.round(xy, 3)
        scores = self._score(run_dist).tolist()
        kept_idx = np.flatnonzero(keep)
        bounds = np.searchsorted(run_of[kept_idx], np.arange(n_runs + 1)).tolist()
        kept_xy = xy[kept_idx]
        style_wrong = (
            (rng.random(n_runs) < p.style_error_prob) if p.style_error_prob > 0 else np.zeros(n_runs, bool)
        )
        keys = ((ix.element_id[run_elem] * _DASH_KEYS + np.maximum(dash[starts], 0)) ^ self.salt).tolist()
        run_elem_l, run_type_l, run_frame_l = run_elem.tolist(), run_type.tolist(), run_frame.tolist()
        style_wrong_l = style_wrong.tolist()
        styles = ix.element_style
        points = kept_xy.tolist()  # one conversion, sliced per run
        for r in np.flatnonzero(report).tolist():
            b0, b1 = bounds[r], bounds[r + 1]
            if b1 - b0 < 2:
                continue
            t = run_type_l[r]
            item: dict[str, Any] = {"type": _TYPE_NAMES[t], "points": points[b0:b1]}
            if t == _DIVIDER:
                item["style"] = "unknown" if style_wrong_l[r] else styles[run_elem_l[r]]
            item["score"] = scores[r]
            item["track_id"] = keys[r]
            out[run_frame_l[r]].append(item)
        # ghosts: frames inside a ghost event copy one visible divider/boundary sideways
        ghost_frames = np.flatnonzero(self.ghost_event[run_frame] >= 0)
        if ghost_frames.size:
            for f in np.unique(run_frame[ghost_frames]).tolist():
                in_f = np.flatnonzero(run_frame == f)
                out[f].extend(
                    self._ghost(
                        f,
                        run_elem[in_f],
                        run_type[in_f],
                        report[in_f],
                        kept_xy,
                        np.asarray(bounds)[in_f],
                        np.asarray(bounds)[in_f + 1],
                    )
                )

    def _ghost(self, frame, run_elem, run_type, report, kept_xy, b0, b1) -> list[dict[str, Any]]:
        event = int(self.ghost_event[frame])
        eligible = np.flatnonzero(
            report & ((run_type == _DIVIDER) | (run_type == _BOUNDARY)) & (b1 - b0 >= 2)
        )
        if event < 0 or eligible.size == 0:
            return []
        if event not in self.ghost_target:
            self.ghost_target[event] = int(run_elem[eligible[int(self.rng.integers(eligible.size))]])
        runs = eligible[run_elem[eligible] == self.ghost_target[event]]
        if runs.size == 0:
            return []
        r = int(runs[0])
        pts = kept_xy[b0[r] : b1[r]].copy()
        pts[:, 1] += self.ghost_side[event] * self.p.ghost_shift_m
        pts = pts[(pts[:, 1] >= self.box[1]) & (pts[:, 1] <= self.box[3])]
        if len(pts) < 2:
            return []
        item: dict[str, Any] = {"type": _TYPE_NAMES[int(run_type[r])], "points": np.round(pts, 3).tolist()}
        if run_type[r] == _DIVIDER:
            item["style"] = self.index.element_style[int(run_elem[r])]
        item["score"] = round(float(self.rng.uniform(*self.p.spurious_score)), 3)
        item["track_id"] = (_GHOST_KEY + event) ^ self.salt
        return [item]

    def false_positives(self, count: int) -> list[dict[str, Any]]:
        p, rng = self.p, self.rng
        out = []
        for _ in range(count):
            start = np.array(
                [rng.uniform(self.box[0] + 5, self.box[2] - 5), rng.uniform(self.box[1] + 3, self.box[3] - 3)]
            )
            a = rng.normal(0.0, 0.3)
            n = max(int(rng.uniform(*p.false_positive_length_m) / p.point_spacing_m), 1) + 1
            pts = start + np.arange(n)[:, None] * p.point_spacing_m * np.array([np.cos(a), np.sin(a)])
            pts += 0.1 * rng.standard_normal(pts.shape)
            pts = pts[(pts[:, 0] <= self.box[2]) & (np.abs(pts[:, 1]) <= self.box[3])]
            if len(pts) < 2:
                continue
            is_divider = rng.random() < 0.7
            item: dict[str, Any] = {
                "type": "lane_divider" if is_divider else "road_boundary",
                "points": np.round(pts, 3).tolist(),
            }
            if is_divider:
                item["style"] = "dashed" if rng.random() < 0.5 else "solid"
            item["score"] = round(float(rng.uniform(*p.spurious_score)), 3)
            item["track_id"] = (_FALSE_KEY + self.false_count) ^ self.salt
            self.false_count += 1
            out.append(item)
        return out

    def polygons(
        self,
        frames: np.ndarray,
        poly_ids: np.ndarray,
        poses_xyyaw: np.ndarray,
        out: list[list[dict[str, Any]]],
    ) -> None:
        """Crosswalks for (frame, polygon) pairs near each other, appending to ``out[frame]``."""
        p, rng, ix = self.p, self.rng, self.index
        n_verts = ix.polygon_n_vertices[poly_ids]
        first = np.cumsum(n_verts) - n_verts  # first vertex of each pair in the flat arrays
        pair_of_v = np.repeat(np.arange(poly_ids.size), n_verts)
        vidx = ix.polygon_first_vertex[poly_ids][pair_of_v] + np.arange(n_verts.sum()) - first[pair_of_v]
        pose = poses_xyyaw[frames[pair_of_v]]
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        d = ix.polygon_vertices_xy[vidx] - pose[:, :2]
        v_all = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
        below, above = v_all < self.box[:2], v_all > self.box[2:]
        outside = np.zeros(poly_ids.size, bool)
        for side in (below[:, 0], below[:, 1], above[:, 0], above[:, 1]):
            outside |= np.logical_and.reduceat(side, first)  # every vertex beyond one border
        partial = np.logical_or.reduceat(below.any(axis=1) | above.any(axis=1), first)
        visible = np.flatnonzero(~outside)
        if p.small_miss_prob > 0:
            visible = visible[rng.random(visible.size) >= p.small_miss_prob]
        pieces, kept = [], []
        for j in visible.tolist():
            v = v_all[first[j] : first[j] + n_verts[j]]
            if partial[j]:
                clipped = shapely.clip_by_rect(shapely.Polygon(v), *self.box)
                if clipped.is_empty or clipped.geom_type != "Polygon" or clipped.area < 2.0:
                    continue
                v = np.asarray(clipped.exterior.coords)[:-1, :2]
            pieces.append(v)
            kept.append(j)
        if not kept:
            return
        # noise for all kept polygons at once
        kept_a = np.asarray(kept)
        counts = np.array([len(v) for v in pieces])
        starts = np.cumsum(counts) - counts
        pair = np.repeat(np.arange(kept_a.size), counts)
        v = np.vstack(pieces)
        frame_k, track = frames[kept_a], len(ix.element_type) + poly_ids[kept_a]
        dist = np.hypot(*(np.add.reduceat(v, starts, axis=0) / counts[:, None]).T)
        v = self._distort(v, frame_k[pair]) + (self.track_bias[track] * p.polygon_noise_factor)[pair]
        off = (p.line_offset_base_m + p.line_offset_per_m * dist) * p.polygon_noise_factor
        sigma = (p.line_white_base_m + p.line_white_per_m * dist) * p.polygon_noise_factor
        if off.any() or sigma.any():
            v = v + (off[:, None] * self._offset_unit(track, frame_k))[pair]
            v = v + sigma[pair][:, None] * rng.standard_normal(v.shape)
        points = np.round(v, 3).tolist()
        scores = self._score(dist).tolist()
        ids = ((ix.polygon_ids[poly_ids[kept_a]] * _DASH_KEYS) ^ self.salt).tolist()
        bounds = np.append(starts, len(v)).tolist()
        for k, f in enumerate(frame_k.tolist()):
            out[f].append(
                {
                    "type": "crosswalk",
                    "points": points[bounds[k] : bounds[k + 1]],
                    "score": scores[k],
                    "track_id": ids[k],
                }
            )


def perceive_trip(
    index: TruthIndex,
    poses_xyyaw_world: np.ndarray,
    params: PerceptionParams,
    rng: np.random.Generator,
    batch_frames: int = 400,
) -> list[list[dict[str, Any]]]:
    """Per frame, the perceived elements as upload dicts (vehicle frame), from TRUE poses ``(N, 3)``."""
    n = len(poses_xyyaw_world)
    steps = np.linalg.norm(np.diff(poses_xyyaw_world[:, :2], axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    perceiver = _FramePerceiver(index, params, rng, n, travelled)
    cx = (params.range_x_m[0] + params.range_x_m[1]) / 2.0
    half_diag = float(
        np.hypot(
            (params.range_x_m[1] - params.range_x_m[0]) / 2.0,
            (params.range_y_m[1] - params.range_y_m[0]) / 2.0,
        )
    )
    yaw = poses_xyyaw_world[:, 2]
    centers = poses_xyyaw_world[:, :2] + cx * np.column_stack([np.cos(yaw), np.sin(yaw)])
    frames: list[list[dict[str, Any]]] = [[] for _ in range(n)]
    for f0 in range(0, n, batch_frames):
        f1 = min(f0 + batch_frames, n)
        if len(index.points_xy):
            balls = index.tree.query_ball_point(centers[f0:f1], r=half_diag + 0.01, return_sorted=True)
            lens = np.fromiter((len(b) for b in balls), np.intp, f1 - f0)
            cand = np.fromiter(itertools.chain.from_iterable(balls), np.intp, int(lens.sum()))
            perceiver.lines(np.repeat(np.arange(f0, f1), lens), poses_xyyaw_world, cand, frames)
    if len(index.polygons_xy):
        # (frame, polygon) pairs whose circles overlap: box centre within half diagonal + polygon radius
        near = (
            np.linalg.norm(centers[:, None, :] - index.polygon_centroids_xy[None, :, :], axis=2)
            < half_diag + index.polygon_radius_m[None, :]
        )
        pair_frames, pair_polys = np.nonzero(near)
        perceiver.polygons(pair_frames, pair_polys, poses_xyyaw_world, frames)
    if params.false_positive_rate_per_frame > 0:
        counts = rng.poisson(params.false_positive_rate_per_frame, n)
        for k in np.flatnonzero(counts).tolist():
            frames[k].extend(perceiver.false_positives(int(counts[k])))
    return frames
