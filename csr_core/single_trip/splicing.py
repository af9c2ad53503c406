"""Splicing a track's observations into one trip-level instance (paper III-C).

Lines: every observation point (world frame) is projected on a backbone (arclength s, signed
lateral offset d): the vehicle's own path while the element was seen when the element runs
along it (any curvature: curves, roundabouts), else the principal axis of the points (stop
lines, lines across the road), refined by a second pass on the first result. The lateral
profile d(s) is estimated per arclength bin by a median with outlier rejection (ghost points,
mis-assignments), smoothed by a Gaussian kernel along s, and turned back into a polyline. Gaps up to ``SPLICE_MAX_GAP_M`` (dashes, missed frames) are spanned, so a dashed
divider stays one instance; longer gaps split the instance. A Gaussian kernel along arclength
stands in for Qiao et al.'s Catmull-Rom fit: same role (a smooth curve through denoised
control points), closed form and vectorised.

Polygons (crosswalk, road marking): observations clipped by the BEV range are left out when
whole ones exist; the vertices of the others are brought into the order of the median-area
one and averaged by a per-vertex median.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.ndimage import gaussian_filter1d

from csr_core.single_trip.compiled import checks, growth, polyline, profile, search
from csr_core.single_trip.params import SingleTripParams


@dataclass(frozen=True, slots=True)
class SplicedLine:
    points_xy_world: np.ndarray  # (M, 2)
    lateral_residuals_m: np.ndarray  # (R,) of inlier observation points
    along_residuals_m: np.ndarray  # (A,) of observed element ends (not BEV cuts)
    observations: np.ndarray  # (m,) observations (indices) that support the instance


def _arclength(points: np.ndarray) -> np.ndarray:
    """Cumulative length (P,) along a polyline (P, 2), from 0 (compiled)."""
    return polyline.arclength(np.ascontiguousarray(points, dtype=float))


def _run_starts(ids: np.ndarray) -> np.ndarray:
    """Indices (R,) where the runs of equal consecutive ``ids`` start (the first is 0)."""
    change = np.empty(max(len(ids), 1), dtype=bool)
    change[0] = True
    np.not_equal(ids[1:], ids[:-1], out=change[1 : len(ids)])
    return np.flatnonzero(change)


class _Geometry(NamedTuple):
    """A backbone of B points with its arclength, unit tangents and points sorted for the nearest
    search (``_geometry``)."""

    columns: np.ndarray  # (4, B) x, y, unit tangent x, y: contiguous rows (the cheapest to gather)
    arclength: np.ndarray  # (B,)
    sorted_points: tuple[bool, np.ndarray, np.ndarray]  # search.sort_along_wider_axis of its points


def _geometry(backbone: np.ndarray) -> _Geometry:
    """A backbone (B >= 2, 2) with its arclength and unit tangents (central differences, one-sided
    at the ends, as ``np.gradient``), computed once per backbone (the path guide of a track is
    projected on twice, and kept for the tracks that share it). Compiled
    (``polyline.geometry_columns``, ``search.sort_along_wider_axis``)."""
    columns, arclength = polyline.geometry_columns(np.ascontiguousarray(backbone, dtype=float))
    return _Geometry(columns, arclength, search.sort_along_wider_axis(columns[0], columns[1]))


@functools.lru_cache(maxsize=16)
def _gaussian_kernel(sigma_bins: float, truncate: float = 4.0) -> np.ndarray:
    """The kernel of ``scipy.ndimage.gaussian_filter1d`` (same radius and normalisation)."""
    radius = int(truncate * sigma_bins + 0.5)
    x = np.arange(-radius, radius + 1, dtype=float)
    w = np.exp(-0.5 * (x / sigma_bins) ** 2)
    w /= w.sum()
    w.setflags(write=False)  # cached: shared by every caller
    return w


def resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """The polyline (P >= 1, 2) resampled at equal steps of at most ``spacing_m``, ends kept (its
    first point alone when it has no length). Compiled."""
    return polyline.resample_polyline(np.ascontiguousarray(points, dtype=float), float(spacing_m))


def _project(points: np.ndarray, geom: _Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Arclength s and signed lateral offset d (left positive) of points (P, 2) on a densely
    sampled backbone (``_geometry``): from its nearest point, along its tangent. Compiled
    (``search.nearest_in_sorted``, ``polyline.project_at``)."""
    points = np.ascontiguousarray(points, dtype=float)
    nearest, _ = search.nearest_in_sorted(points, geom.columns[0], geom.columns[1], *geom.sorted_points)
    return polyline.project_at(points, nearest, geom.columns, geom.arclength)


def _extend_ends(
    line: np.ndarray, length_m: float, spacing_m: float, curvature_m: float = 10.0
) -> np.ndarray:
    """The polyline prolonged at both ends by ``length_m`` along a circular arc with the
    curvature of its last ``curvature_m`` (a straight line where that is unknown)."""
    if len(line) < 3:
        return line
    s = _arclength(line)
    if s[-1] < 1e-6:
        return line
    q = np.arange(spacing_m, length_m + 1e-9, spacing_m)

    def arc(end: np.ndarray, before: np.ndarray, span: float, head_prev: float) -> np.ndarray:
        head = math.atan2(float(end[1] - before[1]), float(end[0] - before[0]))
        turn = head - head_prev
        kappa = math.atan2(math.sin(turn), math.cos(turn)) / max(span, 1e-6)
        kappa = min(max(kappa, -0.1), 0.1)  # radius at least 10 m
        th = head + kappa * q
        if abs(kappa) < 1e-6:
            return end + q[:, None] * np.array([math.cos(head), math.sin(head)])
        return end + np.column_stack(
            [(np.sin(th) - math.sin(head)) / kappa, -(np.cos(th) - math.cos(head)) / kappa]
        )

    def heading(i: int, j: int) -> float:
        return math.atan2(float(line[j, 1] - line[i, 1]), float(line[j, 0] - line[i, 0]))

    n = len(line)
    span = min(curvature_m, s[-1] / 2)
    # tail: heading over the last segment vs the heading span metres earlier
    i_span = max(int(np.searchsorted(s, s[-1] - span)) - 1, 0)
    tail = arc(
        line[-1], line[-2], s[-1] - s[i_span + 1] if i_span + 1 < n - 1 else span, heading(i_span, i_span + 1)
    )
    # head: the same on the reversed line
    j_span = min(int(np.searchsorted(s, span)) + 1, n - 1)
    head = arc(line[0], line[1], s[j_span - 1] if j_span - 1 > 0 else span, heading(j_span, j_span - 1))
    return np.concatenate([head[::-1], line, tail])


def grow_backbone(
    points_w: np.ndarray,
    obs_ends: np.ndarray,
    min_step_m: float = 0.5,
    tangent_m: float = 4.0,
    lateral_gate_m: float = 1.0,
    lateral_gate_slope: float = 0.15,
    max_gap_m: float = 15.0,
    follow_bends: bool = False,
) -> np.ndarray:
    """An ordered polyline covering an element of any shape from its observations (each an
    ordered polyline, in time order): the first one, extended at either end by the points of
    later ones that lie beyond it along its end tangent (over the last ``tangent_m``) and near
    that tangent line. Observations are oriented like the previous one first.

    ``follow_bends`` (dashed lines: a guide line through a junction bends between its dashes,
    and the straight tangent misses the next dash by metres): the tangent line becomes the arc
    with the curvature of the last two ``tangent_m``, and an observation that is not near it
    still continues the backbone when one circle fits it and the backbone's last
    ``2 tangent_m`` (``growth.kasa_circle``) within ``growth.BEND_SHAPE_TOL_M``, no
    tighter than ``BEND_MIN_RADIUS_M``, its nearest point within ``max_gap_m``. Compiled
    (``growth.grow_backbone``)."""
    return growth.grow_backbone(
        np.ascontiguousarray(points_w, dtype=float),
        obs_ends.astype(np.int64, copy=False),
        float(min_step_m),
        float(tangent_m),
        float(lateral_gate_m),
        float(lateral_gate_slope),
        float(max_gap_m),
        bool(follow_bends),
    )


def smooth_polyline(points: np.ndarray, spacing_m: float, sigma_m: float) -> np.ndarray:
    """Resampled at ``spacing_m`` and Gaussian-smoothed along arclength (ends kept in place)."""
    r = resample_polyline(points, spacing_m)
    if len(r) < 3 or sigma_m <= 0:
        return r
    out = gaussian_filter1d(r, sigma_m / spacing_m, axis=0, mode="nearest")
    out[0], out[-1] = r[0], r[-1]
    return out


def _principal_backbone(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """A straight backbone along the principal axis of the points, covering them."""
    mu = points.mean(0)
    _, _, vt = np.linalg.svd(points - mu, full_matrices=False)
    axis = vt[0]
    proj = (points - mu) @ axis
    q = np.arange(proj.min() - 1.0, proj.max() + 1.0 + spacing_m, spacing_m)
    return mu + q[:, None] * axis


def _cluster_sd(s: np.ndarray, d: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """Labels (P,) of the elements in a track's points in backbone coordinates (arclength s,
    lateral d): occupied cells (``SPLICE_BIN_M`` x ``SPLICE_CLUSTER_D_M``) joined across up to
    ``SPLICE_MAX_GAP_M`` along s (dash gaps, missed frames) and one cell across d. Two lines side
    by side (a track that took in a neighbour through a ramp or a ghost) come out apart.
    Compiled (``profile.cluster_sd``)."""
    reach = max(int(params.SPLICE_MAX_GAP_M / params.SPLICE_BIN_M / 2), 1)
    return profile.cluster_sd(s, d, float(params.SPLICE_BIN_M), float(params.SPLICE_CLUSTER_D_M), reach)


def _binned_profile(s: np.ndarray, d: np.ndarray, bin_m: float) -> tuple[np.ndarray, int, np.ndarray]:
    """Arclength bins (P,) of width ``bin_m`` from the smallest s, their number and the per-bin
    median of d (the upper middle value; NaN for an empty bin): the first step of
    ``_fit_profile``, shared with ``_mixture_sigma``. Compiled."""
    return profile.binned_profile(s, d, float(bin_m))


def _fit_profile(
    s: np.ndarray,
    d: np.ndarray,
    obs_id: np.ndarray,
    geom: _Geometry,
    params: SingleTripParams,
    binned: tuple[np.ndarray, int, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray] | None:
    """Robust lateral profile d(s) of one element: per-bin median with outlier rejection,
    Gaussian smoothing along s, ends from the observations. Returns (line (M, 2), inlier mask,
    s_lo, s_hi, fitted d at each point) or None. ``binned``: ``_binned_profile(s, d)`` when
    already computed. Compiled (``profile.fit_profile``)."""
    bin_m = params.SPLICE_BIN_M
    bins, n_bins, med = binned if binned is not None else _binned_profile(s, d, bin_m)
    ok, line, inl, s_lo, s_hi, d_fit = profile.fit_profile(
        s,
        d,
        obs_id,
        bins,
        n_bins,
        med,
        float(params.SPLICE_OUTLIER_SIGMAS),
        float(bin_m),
        _gaussian_kernel(params.SPLICE_SMOOTH_SIGMA_M / bin_m),
        float(params.SPLICE_OUTPUT_SPACING_M),
        geom.columns,
        geom.arclength,
    )
    return (line, inl, s_lo, s_hi, d_fit) if ok else None


@functools.lru_cache(maxsize=8)
def _guide_geometry(
    path_bytes: bytes, dtype: str, n: int, bin_m: float, extension_m: float
) -> _Geometry | None:
    """The geometry of the guide of a splice: the vehicle path ``(n, 2)`` (given by its bytes, to
    be cached) resampled and prolonged at both ends; None when too short. Tracks seen over the
    same frames share their path (a quarter of them): the last few guides are kept."""
    path = np.frombuffer(path_bytes, dtype=dtype).reshape(n, 2)
    guide = _extend_ends(resample_polyline(path, bin_m), extension_m, bin_m)
    if len(guide) < 3:
        return None
    return _geometry(guide)  # cached: shared by every caller, which only reads it


def splice_line(
    points_w: np.ndarray,
    obs_id: np.ndarray,
    obs_ends: np.ndarray,
    end_free: np.ndarray,
    guide_xy: np.ndarray | None,
    params: SingleTripParams,
    original: np.ndarray | None = None,
    follow_bends: bool = False,
) -> list[SplicedLine]:
    """Observations of one track -> one smoothed polyline per element found in it (usually one).

    ``points_w (P, 2)`` all observation points (world), ``obs_id (P,)`` their observation,
    ``obs_ends (n_obs, 2)`` indices of each observation's first and last point, ``end_free
    (n_obs, 2)`` whether those are element ends seen inside the BEV range (not cuts by the
    range): only those give along-track residuals; ``original (P,)`` marks the points as sent
    (not inserted by densification): only those give lateral residuals. ``guide_xy`` the vehicle path while the track
    was seen: the backbone when the element runs along it (curves, roundabouts), else the
    principal axis of the points, refined by a second pass on the first result.
    ``follow_bends``: a backbone grown from the observations follows the element round bends
    across gaps (``grow_backbone``): for dashed lines, whose gaps are the dash gaps; a continuous
    element that leaves the end tangent is a branch, not the same line.
    """
    bin_m = params.SPLICE_BIN_M
    if original is None:
        original = np.ones(len(points_w), dtype=bool)
    guide_geom = None
    if guide_xy is not None and len(guide_xy) >= 2:
        guide_xy = np.ascontiguousarray(guide_xy)
        guide_geom = _guide_geometry(
            guide_xy.tobytes(), guide_xy.dtype.str, len(guide_xy), bin_m, params.SPLICE_GUIDE_EXTENSION_M
        )
    if guide_geom is not None:
        # separate the elements of the track along the path; each element is then spliced on
        # the path if it runs along it, else on its own shape
        ends = unique_ids(obs_ends.ravel())  # the along/across test needs only the observation ends
        s_ends, _ = _project(points_w[ends], guide_geom)
        if _runs_along(s_ends, points_w[ends], obs_id[ends]) < params.SPLICE_ALONG_GUIDE_MIN:
            # the track runs across the path (a dashed line crossed in a junction): the gaps
            # between its pieces are along its own shape, not along the path
            return _splice_own_shape(
                points_w, np.arange(len(points_w)), obs_id, obs_ends, end_free, params, original, follow_bends
            )
        s, d = _project(points_w, guide_geom)
        labels = _cluster_sd(s, d, params)
        out = []
        groups: list[tuple[np.ndarray, tuple[np.ndarray, int, np.ndarray] | None]] = []  # points, their bins
        for lab in np.unique(labels):
            sel = np.flatnonzero(labels == lab)
            binned = _binned_profile(s[sel], d[sel], bin_m) if len(sel) > 10 else None
            if binned is not None and _mixture_sigma(d[sel], binned) > params.SPLICE_MIXTURE_SIGMA_M:
                sub = split_modes(s[sel], d[sel], params)
                groups.extend((sel[sub == k], None) for k in np.unique(sub[sub >= 0]))
            else:
                groups.append((sel, binned))
        for sel, binned in groups:
            if n_distinct(obs_id[sel]) < params.TRACK_MIN_FRAMES:
                continue
            if _runs_along(s[sel], points_w[sel], obs_id[sel]) >= params.SPLICE_ALONG_GUIDE_MIN:
                out.extend(
                    _splice_on(
                        points_w,
                        sel,
                        s[sel],
                        d[sel],
                        guide_geom,
                        False,
                        obs_id,
                        obs_ends,
                        end_free,
                        params,
                        original,
                        binned,
                    )
                )
            else:
                out.extend(
                    _splice_own_shape(
                        points_w, sel, obs_id, obs_ends, end_free, params, original, follow_bends
                    )
                )
        return out
    return _splice_own_shape(
        points_w, np.arange(len(points_w)), obs_id, obs_ends, end_free, params, original, follow_bends
    )


def _mixture_sigma(d: np.ndarray, binned: tuple[np.ndarray, int, np.ndarray]) -> float:
    """Robust spread (m) of lateral offsets ``d`` around their per-bin median (``binned``, from
    ``_binned_profile``): large for a cluster that mixes elements (a Y where a connector leaves
    a lane)."""
    bins, _, med = binned
    return profile.mixture_sigma(d, bins, med)


def split_modes(s: np.ndarray, d: np.ndarray, params: SingleTripParams) -> np.ndarray:
    """Labels (P,) separating elements that share cells (a Y): per arclength bin the lateral
    offsets are split into modes at gaps wider than ``SPLICE_MODE_GAP_M``; modes are chained
    along arclength to the nearest chain within ``SPLICE_MODE_GATE_M`` (a 1-D tracker along s);
    a mode that finds no chain starts one. -1: points of modes too small to count."""
    bin_m = params.SPLICE_BIN_M
    bins = np.floor((s - s.min()) / bin_m).astype(np.int64)
    order = np.lexsort((d, bins))
    b_sorted, d_sorted = bins[order], d[order]
    first = np.ones(1, dtype=bool)
    new_bin = np.concatenate([first, b_sorted[1:] != b_sorted[:-1]])
    gap = np.concatenate([first, np.diff(d_sorted) > params.SPLICE_MODE_GAP_M])
    mode_start = np.flatnonzero(new_bin | gap)
    mode_end = np.append(mode_start[1:], len(order))
    mode_bin = b_sorted[mode_start]
    # within a bin d is sorted, so each mode is a sorted run: its median is its middle element(s)
    mode_d = 0.5 * (d_sorted[(mode_start + mode_end - 1) // 2] + d_sorted[(mode_start + mode_end) // 2])
    mode_n = mode_end - mode_start
    max_gap_bins = params.SPLICE_MAX_GAP_M / bin_m
    chains_d: list[float] = []
    chains_bin: list[int] = []
    mode_chain = np.full(len(mode_start), -1)
    # the chaining walks the modes one by one: on plain Python numbers (numpy scalars cost ten times more)
    for m, (size, at_bin, offset) in enumerate(
        zip(mode_n.tolist(), mode_bin.tolist(), mode_d.tolist(), strict=True)
    ):
        if size < 2:
            continue
        best, best_dist = -1, params.SPLICE_MODE_GATE_M
        for c in range(len(chains_d)):
            if at_bin - chains_bin[c] > max_gap_bins or chains_bin[c] == at_bin:
                continue
            dist = abs(offset - chains_d[c])
            if dist < best_dist:
                best, best_dist = c, dist
        if best < 0:
            chains_d.append(offset)
            chains_bin.append(at_bin)
            best = len(chains_d) - 1
        else:
            chains_d[best] = offset
            chains_bin[best] = at_bin
        mode_chain[m] = best
    labels_sorted = np.repeat(mode_chain, mode_n)
    labels = np.empty(len(s), dtype=np.int64)
    labels[order] = labels_sorted
    return labels


def _runs_along(s: np.ndarray, points: np.ndarray, obs_id: np.ndarray) -> float:
    """Median over observations of |arclength span on the path| / chord: 1 along, 0 across
    (compiled, ``profile.runs_along``)."""
    return profile.runs_along(s, np.ascontiguousarray(points, dtype=float), obs_id)


def _splice_own_shape(
    points_w: np.ndarray,
    sel: np.ndarray,
    obs_id: np.ndarray,
    obs_ends: np.ndarray,
    end_free: np.ndarray,
    params: SingleTripParams,
    original: np.ndarray,
    follow_bends: bool = False,
) -> list[SplicedLine]:
    """Splice the points ``sel`` on a backbone grown from their own observations (any shape),
    or their principal axis, refined by a second pass; clustered on it first."""
    bin_m = params.SPLICE_BIN_M
    pts = points_w[sel]
    ids = obs_id[sel]
    starts = _run_starts(ids)
    ends = np.append(starts[1:], len(ids)) - 1
    short = float((pts.max(0) - pts.min(0)).max()) < params.SPLICE_STRAIGHT_BELOW_M  # np.ptp
    grown = (
        pts[:1]
        if short
        else grow_backbone(
            pts, np.column_stack([starts, ends]), max_gap_m=params.SPLICE_MAX_GAP_M, follow_bends=follow_bends
        )
    )
    if len(grown) >= 2 and _arclength(grown)[-1] > 2 * bin_m:
        backbone = smooth_polyline(grown, bin_m / 2, params.SPLICE_BACKBONE_SMOOTH_M)
    else:
        backbone = _principal_backbone(pts, bin_m / 2)
    if len(backbone) < 3:
        return []
    geom = _geometry(backbone)
    s, d = _project(pts, geom)
    labels = _cluster_sd(s, d, params)
    out = []
    for lab in np.unique(labels):
        sub = np.flatnonzero(labels == lab)
        if n_distinct(ids[sub]) < params.TRACK_MIN_FRAMES:
            continue
        out.extend(
            _splice_on(
                points_w, sel[sub], s[sub], d[sub], geom, True, obs_id, obs_ends, end_free, params, original
            )
        )
    return out


def _splice_on(
    points_w: np.ndarray,
    sel: np.ndarray,
    s_sel: np.ndarray,
    d_sel: np.ndarray,
    geom: _Geometry,
    refine: bool,
    obs_id: np.ndarray,
    obs_ends: np.ndarray,
    end_free: np.ndarray,
    params: SingleTripParams,
    original: np.ndarray,
    binned: tuple[np.ndarray, int, np.ndarray] | None = None,
) -> list[SplicedLine]:
    """One element (points ``sel`` with backbone coordinates) -> its SplicedLine (or none).
    ``binned``: ``_binned_profile(s_sel, d_sel)`` when already computed."""
    bin_m = params.SPLICE_BIN_M
    fit = _fit_profile(s_sel, d_sel, obs_id[sel], geom, params, binned)
    if fit is not None and refine and fit[3] - fit[2] >= 2 * bin_m:
        bb2 = resample_polyline(fit[0], bin_m / 2)
        if len(bb2) >= 3:
            geom2 = _geometry(bb2)
            s2, d2 = _project(points_w[sel], geom2)
            fit2 = _fit_profile(s2, d2, obs_id[sel], geom2, params)
            if fit2 is not None:
                fit, s_sel, d_sel = fit2, s2, d2
    if fit is None:
        return []
    line, inl, s_lo, s_hi, d_fit = fit
    # lateral residuals against the fitted profile; along-track: observation ends that are
    # element ends against the instance ends (both in backbone arclength)
    lat, along_res, obs = profile.splice_residuals(
        len(points_w),
        sel,
        inl,
        s_sel,
        d_sel,
        d_fit,
        original,
        obs_id,
        obs_ends,
        end_free,
        s_lo,
        s_hi,
        float(params.NOISE_END_WINDOW_M),
    )
    return [SplicedLine(line, lat, along_res, obs)]


def runs_along_observations(
    line_xy: np.ndarray,
    points_w: np.ndarray,
    obs_id: np.ndarray,
    obs: np.ndarray,
    max_angle_rad: float,
    near_m: float,
    window_m: float,
) -> list[np.ndarray]:
    """The parts of the spliced ``line_xy`` that run along its own observations ``obs`` (values of
    ``obs_id``, the observation of each of the points ``points_w``); the whole line when all of
    it does.

    A splice is tangent to what it was spliced from. Where it crosses its observations it joined
    pieces of different elements: in a junction a dashed divider's dashes, extended along their
    chords to bridge the gaps, reach the dashes of a divider that crosses it, and the splice runs
    on from one to the other, or across from the end of one dash to the end of another.
    Observation segments within ``near_m`` of the line count as along it or across it (more than
    ``max_angle_rad`` to the line's direction where they pass it; segment by segment, so a curved
    observation of a curved element runs along, and the leg of an observation that leaves the
    line, a boundary turning a corner, is not near it). A vertex is cut when, within
    ``window_m`` of arclength either side, more observed length runs across than along; a stretch
    with no observation near it (the gap between two dashes) is kept. A part left with less than
    ``window_m`` of observed length along it (summed over the observations) is dropped: it only
    joined two cut places."""
    if len(line_xy) < 2 or len(points_w) < 2:
        return [line_xy]
    whole, runs = checks.runs_along_observations(
        np.ascontiguousarray(line_xy, dtype=float),
        points_w,
        obs_id,
        obs,
        math.cos(max_angle_rad),
        float(near_m),
        float(window_m),
    )
    return [line_xy] if whole else [line_xy[a:b] for a, b in runs.tolist()]


def _robust_ends(
    s: np.ndarray, obs_id: np.ndarray, window_m: float = profile.ROBUST_END_WINDOW_M
) -> tuple[float, float]:
    """The ends (s_lo, s_hi) of an element from its observations' arclengths: the median of the
    observations' lowest s within ``window_m`` of the lowest, the same for the highest (compiled,
    ``profile.robust_ends``)."""
    return profile.robust_ends(
        np.ascontiguousarray(s, dtype=float), np.ascontiguousarray(obs_id, dtype=np.int64), float(window_m)
    )


def unique_ids(ids: np.ndarray) -> np.ndarray:
    """``np.unique(ids)``, without the sort when ``ids`` is already non-decreasing."""
    if len(ids) < 2:
        return np.unique(ids)
    if bool((ids[1:] < ids[:-1]).any()):
        return np.unique(ids)
    return ids[_run_starts(ids)]


def n_distinct(ids: np.ndarray) -> int:
    """``len(np.unique(ids))`` without the sort when ``ids`` is already non-decreasing."""
    if len(ids) < 2:
        return len(ids)
    step = ids[1:] != ids[:-1]
    if bool((ids[1:] < ids[:-1]).any()):
        return len(np.unique(ids))
    return 1 + int(np.count_nonzero(step))


def polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    nxt = np.arange(1, len(poly) + 1) % len(poly)  # np.roll(-1) as an index
    return 0.5 * float(np.dot(x, y[nxt]) - np.dot(y, x[nxt]))


def _edge_axes(polys: list[np.ndarray], inside: list[np.ndarray]) -> np.ndarray | None:
    """The axes (2, 2) of a rectangle from its observed edges: the length-weighted mean direction
    of the outline edges whose both ends lie inside the BEV range (the element's own sides, not
    the range's cut across it), modulo a right angle (a doubled-doubled angle average); None
    without such edges."""
    sum_sin = sum_cos = 0.0
    for poly, ins in zip(polys, inside, strict=True):
        nxt = np.roll(np.arange(len(poly)), -1)
        keep = ins & ins[nxt]
        if not keep.any():
            continue
        edge = poly[nxt[keep]] - poly[keep]
        length = np.hypot(edge[:, 0], edge[:, 1])
        angle4 = 4.0 * np.arctan2(edge[:, 1], edge[:, 0])
        sum_sin += float(np.dot(length, np.sin(angle4)))
        sum_cos += float(np.dot(length, np.cos(angle4)))
    if math.hypot(sum_sin, sum_cos) < 1e-9:
        return None
    theta = 0.25 * math.atan2(sum_sin, sum_cos)
    return np.array([[math.cos(theta), math.sin(theta)], [-math.sin(theta), math.cos(theta)]])


def _robust_rectangle(
    polys: list[np.ndarray], headings_rad: np.ndarray, q: float = 0.02, inside: list[np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An element never seen whole (a crosswalk wider than the BEV range): the rectangle spanning
    the q..1-q quantiles of all observed outline points along its axes. The axes are those of its
    observed sides (``_edge_axes``, ``inside`` (per outline, per vertex) marking the vertices
    inside the BEV range), else the principal axes of the points: the part of a crosswalk that the
    range lets through is a strip cut at the range's angle, whose principal axes can lie anywhere
    (Karlsruhe s3, docs/single-trip.md). Residuals: each observation's points beyond
    the rectangle, lateral/along the vehicle heading."""
    pts = np.concatenate(polys)
    mu = pts.mean(0)
    vt = _edge_axes(polys, inside) if inside is not None else None
    if vt is None:
        _, _, vt = np.linalg.svd(pts - mu, full_matrices=False)
    proj = (pts - mu) @ vt.T
    lo, hi = np.quantile(proj, q, axis=0), np.quantile(proj, 1 - q, axis=0)
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]) @ vt + mu
    if polygon_area(corners) < 0:
        corners = corners[::-1]
    over = np.maximum(proj - hi, 0.0) + np.minimum(proj - lo, 0.0)  # (P, 2) outside distance per axis
    h = np.repeat(headings_rad, [len(p) for p in polys])
    dev = over @ vt
    along = dev[:, 0] * np.cos(h) + dev[:, 1] * np.sin(h)
    lateral = -dev[:, 0] * np.sin(h) + dev[:, 1] * np.cos(h)
    return corners, lateral, along


def splice_polygon(
    polys: list[np.ndarray],
    whole: np.ndarray,
    headings_rad: np.ndarray,
    inside: list[np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observed outlines (world) -> one outline, lateral and along residuals (vehicle heading).

    ``whole`` (n_obs,) bool: the observation is not clipped by the BEV range; ``inside`` (per
    outline, per vertex): the vertex lies inside the range (for ``_robust_rectangle``)."""
    if not whole.any():
        return _robust_rectangle(polys, headings_rad, inside=inside)
    cand = [i for i in range(len(polys)) if whole[i]]
    # consistent winding (counter-clockwise)
    signed = [polygon_area(p) for p in polys]
    ccw = [p if area >= 0 else p[::-1] for p, area in zip(polys, signed, strict=True)]
    areas = np.array([abs(signed[i] if signed[i] >= 0 else polygon_area(ccw[i])) for i in cand])
    ref_i = cand[int(np.argsort(areas)[len(areas) // 2])]
    ref = ccw[ref_i]
    m = len(ref)
    roll = (np.arange(m)[:, None] + np.arange(m)[None, :]) % m  # row k: np.roll(p, -k) as an index
    stack, heads = [], []
    for i in cand:
        p = ccw[i]
        if len(p) != m:
            continue
        shifts = p[roll]
        diff = shifts - ref[None]
        err = np.sqrt(diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1]).sum(
            1
        )  # np.linalg.norm(diff, axis=-1)
        stack.append(shifts[int(np.argmin(err))])
        heads.append(headings_rad[i])
    arr = np.stack(stack)  # (n, m, 2)
    fused = np.median(arr, axis=0)
    dev = arr - fused[None]
    h = np.asarray(heads)[:, None]
    along = dev[..., 0] * np.cos(h) + dev[..., 1] * np.sin(h)
    lateral = -dev[..., 0] * np.sin(h) + dev[..., 1] * np.cos(h)
    return fused, lateral.ravel(), along.ravel()
