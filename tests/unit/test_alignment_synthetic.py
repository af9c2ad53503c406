"""Synthetic multi-trip fixtures for the alignment tests, built directly as TripReconstruction
objects (no simulator): a curved two-way road with two lanes each way, dividers, boundaries,
centrelines, stop lines and crosswalks; each trip drives one lane (some the other way) with a
per-trip GNSS-like error (offset + slow drift + small yaw) on its smoothed poses and instances,
element noise, missed elements and an occasional ghost divider one lane width off.

Also the end-to-end known-answer tests of ``align_trips``.
"""

from __future__ import annotations

import numpy as np
import pytest

from csr_core import se2
from csr_core.alignment.geometry import resample_polyline
from csr_core.geo import LocalFrame
from csr_core.types import (
    ElementNoise,
    ElementType,
    GnssStatus,
    PerceivedElement,
    Trip,
    TripInstance,
    TripReconstruction,
)

pytestmark = pytest.mark.unit

LANE_W = 3.5
FRAME = LocalFrame(origin_lat=31.2, origin_lon=121.4)


def road_reference(length_m: float = 500.0) -> np.ndarray:
    s = np.arange(0.0, length_m + 0.5, 1.0)
    return np.column_stack([s, 25.0 * np.sin(s / 120.0)])


def offset_line(ref: np.ndarray, offset_m: float) -> np.ndarray:
    t = np.gradient(ref, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    return ref + offset_m * np.column_stack([-t[:, 1], t[:, 0]])


def truth_elements(length_m: float = 500.0):
    """``[(type, points)]`` of the true road."""
    ref = road_reference(length_m)
    out = [
        (ElementType.ROAD_BOUNDARY, offset_line(ref, -2 * LANE_W - 0.5)),
        (ElementType.ROAD_BOUNDARY, offset_line(ref, 2 * LANE_W + 0.5)),
    ]
    out += [(ElementType.LANE_DIVIDER, offset_line(ref, o)) for o in (-LANE_W, 0.0, LANE_W)]
    out += [
        (ElementType.CENTERLINE, offset_line(ref, o))
        for o in (-1.5 * LANE_W, -0.5 * LANE_W, 0.5 * LANE_W, 1.5 * LANE_W)
    ]
    for s_stop in (int(0.3 * length_m), int(0.76 * length_m)):
        i = s_stop
        left, right = offset_line(ref, 2 * LANE_W)[i], offset_line(ref, -2 * LANE_W)[i]
        out.append((ElementType.STOP_LINE, np.vstack([right, 0.5 * (left + right)])))
        i2 = s_stop + 6
        a, b = (
            offset_line(ref, -2 * LANE_W)[i2 - 2 : i2 + 3 : 4],
            offset_line(ref, 2 * LANE_W)[i2 + 2 : i2 - 3 : -4],
        )
        out.append((ElementType.CROSSWALK, np.vstack([a, b])))
    return out


def truth_trajectory(
    lane: int, reverse: bool, rng, length_m: float = 500.0, start: float = 10.0, end: float | None = None
) -> np.ndarray:
    """(N, 3) true poses, one per metre, along lane ``lane`` (0, 1 forward lanes -> right side)."""
    ref = road_reference(length_m)
    offset = -(lane + 0.5) * LANE_W if not reverse else (lane + 0.5) * LANE_W
    wander = 0.1 * np.sin(np.arange(len(ref)) / 40.0 + rng.uniform(0, 6))
    centre = offset_line(ref, 0.0)
    path = np.vstack([offset_line(ref, offset + w)[i] for i, w in enumerate(wander)])
    del centre
    end = length_m - 10.0 if end is None else end
    s = np.arange(start, end, 1.0)
    path = np.column_stack(
        [np.interp(s, np.arange(len(path)), path[:, 0]), np.interp(s, np.arange(len(path)), path[:, 1])]
    )
    if reverse:
        path = path[::-1]
    d = np.gradient(path, axis=0)
    return np.column_stack([path, np.arctan2(d[:, 1], d[:, 0])])


def make_trip(
    key: str,
    truth_xyyaw: np.ndarray,
    elements,
    rng,
    *,
    offset_xy=(0.0, 0.0),
    drift_xy_per_m=(0.0, 0.0),
    yaw_err=0.0,
    noise_m=0.05,
    miss_prob=0.1,
    ghost=False,
    perception=True,
) -> TripReconstruction:
    n = len(truth_xyyaw)
    s = np.arange(n, dtype=float)
    err = np.column_stack(
        [offset_xy[0] + drift_xy_per_m[0] * s, offset_xy[1] + drift_xy_per_m[1] * s, np.full(n, yaw_err)]
    )
    # world-left error about each true position: g_t = E_t o x_t, rotation about the vehicle
    smoothed = truth_xyyaw.copy()
    smoothed[:, :2] += err[:, :2]
    smoothed[:, 2] = se2.wrap_angle(smoothed[:, 2] + yaw_err)
    smoothed_of = lambda t: se2.compose(smoothed[t], se2.inverse(truth_xyyaw[t]))  # noqa: E731  world correction
    # per-frame perception in the vehicle frame (truth, clipped to range, noisy)
    dense = [(t, resample_polyline(p, 2.0, t.is_polygon)) for t, p in elements]
    per_frame = []
    inst_pts: dict[int, list] = {}
    seen_frames: dict[int, list] = {}
    for f in range(n):
        inv = se2.inverse(truth_xyyaw[f])
        frame_elems = []
        for e, (etype, pts) in enumerate(dense):
            pv = se2.transform_points(inv, pts)
            m = (pv[:, 0] > -15) & (pv[:, 0] < 30) & (np.abs(pv[:, 1]) < 15)
            if m.sum() < 2 or (perception and rng.random() < 0.05):
                continue
            pv = pv[m] + rng.normal(0, noise_m, 2) + rng.normal(0, 0.02, (m.sum(), 2))
            frame_elems.append(PerceivedElement(etype, pv))
            inst_pts.setdefault(e, []).append(pts[m])
            seen_frames.setdefault(e, []).append(f)
        per_frame.append(tuple(frame_elems) if perception else ())
    instances = []
    tree_pos = truth_xyyaw[:, :2]
    for e, chunks in inst_pts.items():
        if rng.random() < miss_prob:
            continue
        etype = dense[e][0]
        if etype.is_polygon:
            pts = dense[e][1]
        else:
            all_pts = np.vstack(chunks)
            s_along = np.linalg.norm(dense[e][1] - dense[e][1][0], axis=1)
            keep = np.isin(
                np.round(dense[e][1], 6).view([("x", float), ("y", float)]),
                np.round(all_pts, 6).view([("x", float), ("y", float)]),
            ).ravel()
            pts = dense[e][1][keep]
            del s_along
            if len(pts) < 2:
                continue
        near = np.argmin(np.linalg.norm(pts[:, None, :] - tree_pos[None, :, :], axis=2), axis=1)
        moved = np.vstack(
            [se2.transform_points(smoothed_of(t), p[None, :]) for t, p in zip(near, pts, strict=False)]
        )
        moved = moved + rng.normal(0, 0.5 * noise_m, 2) + rng.normal(0, 0.01, moved.shape)
        instances.append(
            TripInstance(etype, moved, None, len(seen_frames[e]), min(seen_frames[e]), max(seen_frames[e]))
        )
    if ghost:  # a divider copy one lane width to the side for 40 m
        f0 = n // 2
        seg = truth_xyyaw[f0 : f0 + 40, :2]
        g = offset_line(seg, LANE_W * 1.0)
        instances.append(TripInstance(ElementType.LANE_DIVIDER, g + err[f0, :2], None, 5, f0, f0 + 40))
    # GNSS (truth + the same error), odometry (truth increments)
    gnss_xy = truth_xyyaw[:, :2] + err[:, :2] + rng.normal(0, 0.03, (n, 2))
    lonlat = FRAME.to_lonlat(gnss_xy)
    odom = se2.compose(se2.inverse(truth_xyyaw[0])[None, :], truth_xyyaw)
    vehicle, trip_id = key.split("__")
    trip = Trip(
        vehicle,
        trip_id,
        "2026-01-01T00:00:00Z",
        np.arange(n) * 0.1,
        lonlat,
        np.full(n, int(GnssStatus.DGPS), np.uint8),
        np.full(n, 0.5),
        np.full(n, np.nan),
        odom,
        tuple(per_frame),
    )
    noise = {
        t: ElementNoise(noise_m if t != ElementType.ROAD_BOUNDARY else 2 * noise_m, 0.2, 100)
        for t in ElementType
    }
    return TripReconstruction(trip, smoothed, np.full(n, 0.8), np.arange(0, n, 5), tuple(instances), noise)


def make_scenario(
    n_trips: int = 6,
    seed: int = 0,
    *,
    error_m: float = 1.5,
    ghost_every: int = 0,
    perception: bool = True,
    length_m: float = 500.0,
):
    """``(trips, truth_poses)``: trips drive random lanes/directions with random GNSS errors."""
    rng = np.random.default_rng(seed)
    elements = truth_elements(length_m)
    trips, truths = [], []
    for k in range(n_trips):
        reverse = bool(k % 3 == 2)
        truth = truth_trajectory(int(rng.integers(0, 2)), reverse, rng, length_m)
        ang = rng.uniform(0, 2 * np.pi)
        off = rng.uniform(0.5, error_m) * np.array([np.cos(ang), np.sin(ang)])
        drift = rng.normal(0, 0.001, 2)
        trips.append(
            make_trip(
                f"veh{k}__t{k}",
                truth,
                elements,
                rng,
                offset_xy=off,
                drift_xy_per_m=drift,
                yaw_err=rng.normal(0, 0.002),
                ghost=bool(ghost_every and k % ghost_every == 1),
                perception=perception,
            )
        )
        truths.append(truth)
    return trips, truths


def submaps_every_20_frames(trips) -> tuple[list, dict[int, list]]:
    """Bare sub-maps (no elements) every 20 frames of each trip, anchored at their smoothed poses:
    ``(sub-maps, sub-maps by trip index)``, sub-map ids = their index (for pose-graph tests)."""
    from csr_core.alignment.submaps import Submap

    subs: list[Submap] = []
    by_trip: dict[int, list[Submap]] = {}
    for k, t in enumerate(trips):
        for a in range(10, t.trip.n_frames - 10, 20):
            s = Submap(len(subs), a, k, t.trip.key, a, a - 10, a + 10, t.poses_xyyaw_world[a].copy(), ())
            subs.append(s)
            by_trip.setdefault(k, []).append(s)
    return subs, by_trip


#: a well-conditioned registration: 5 cm per axis, 0.002 rad
FULL_REGISTRATION_INFO = np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.002**2])


def true_registration(si, sj, truths, n: int, information: np.ndarray = FULL_REGISTRATION_INFO):
    """A ``PairMatch`` between bare sub-maps ``si`` (trip 0) and ``sj`` (trip 1) carrying their
    true relative pose: ``delta`` such that between(gi, delta o gj) = between(ti, tj), about the
    centre of ``si``, with the given information and confidence 0.9."""
    from csr_core.alignment.association import PairMatch

    c = np.array([*si.world_T_submap[:2], 0.0])
    gi, gj = si.world_T_submap - c, sj.world_T_submap - c
    ti, tj = truths[0][si.anchor_frame] - c, truths[1][sj.anchor_frame] - c
    delta = se2.compose(se2.compose(gi, se2.between(ti, tj)), se2.inverse(gj))
    return PairMatch(
        si.submap_id,
        sj.submap_id,
        0,
        1,
        n,
        si.world_T_submap[:2].copy(),
        delta,
        information,
        ((0, 0),),
        ((0, 0),),
        np.full(1, 0.9),
        0.9,
        0.03,
        1.0,
    )


def aligned_errors(est: dict, trips, truths) -> tuple[float, float, list[float]]:
    """Aligned ATE RMSE, RPE(10 m) RMSE and per-trip aligned ATE (one rigid SE(2) over all)."""
    keys = [t.trip.key for t in trips]
    E = np.vstack([est[k][:, :2] for k in keys if k in est])
    T = np.vstack([tr[:, :2] for k, tr in zip(keys, truths, strict=False) if k in est])
    me, mt = E.mean(0), T.mean(0)
    U, _, Vt = np.linalg.svd((E - me).T @ (T - mt))
    R = (U @ Vt).T
    if np.linalg.det(R) < 0:
        R = (U @ np.diag([1, -1]) @ Vt).T
    fix = lambda P: (P - me) @ R.T + mt  # noqa: E731
    err = np.linalg.norm(fix(E) - T, axis=1)
    per_trip, rpe = [], []
    for k, tr in zip(keys, truths, strict=False):
        if k not in est:
            continue
        P = fix(est[k][:, :2])
        per_trip.append(float(np.sqrt(np.mean(np.sum((P - tr[:, :2]) ** 2, axis=1)))))
        rpe.append((P[10:] - P[:-10]) - (tr[10:, :2] - tr[:-10, :2]))
    rpe_all = np.vstack(rpe)
    return float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(np.sum(rpe_all**2, axis=1)))), per_trip


# --- end-to-end known answers ----------------------------------------------------------------


def _relative_errors(
    est: np.ndarray, truth: np.ndarray, est_ref: np.ndarray, truth_ref: np.ndarray
) -> np.ndarray:
    """Distance between where trip B sits relative to trip A, estimated vs true (nearest frames)."""
    d = np.linalg.norm(truth[:, None, :2] - truth_ref[None, :, :2], axis=2)
    j = np.argmin(d, axis=1)
    return np.linalg.norm((est[:, :2] - est_ref[j, :2]) - (truth[:, :2] - truth_ref[j, :2]), axis=1)


def test_two_trips_with_a_known_relative_offset_are_brought_together():
    from csr_core.alignment import AlignmentParams, align_trips

    rng = np.random.default_rng(3)
    elements = truth_elements(300.0)
    truth_a = truth_trajectory(0, False, rng, 300.0)
    truth_b = truth_trajectory(1, False, rng, 300.0)
    a = make_trip("va__a", truth_a, elements, rng, offset_xy=(0.3, -0.2))
    b = make_trip("vb__b", truth_b, elements, rng, offset_xy=(1.4, -0.9), yaw_err=0.003)
    before = _relative_errors(b.poses_xyyaw_world, truth_b, a.poses_xyyaw_world, truth_a)
    assert np.median(before) > 1.0
    res = align_trips([a, b], params=AlignmentParams(fine=False))
    assert res.failed == {}
    after = _relative_errors(res.poses_xyyaw_world["vb__b"], truth_b, res.poses_xyyaw_world["va__a"], truth_a)
    assert np.sqrt(np.mean(after**2)) < 0.15
    assert len(res.match_pairs) > 0 and all(0.0 < m.confidence <= 1.0 for m in res.match_pairs)
    assert set(res.frame_residuals_m) == {"va__a", "vb__b"}
    assert res.frame_residuals_m["vb__b"].shape == (b.trip.n_frames,)


def test_many_trips_coarse_then_fine_beats_gnss_and_keeps_shape():
    from csr_core.alignment import AlignmentParams, align_trips

    trips, truths = make_scenario(5, seed=7, length_m=300.0, ghost_every=3)
    before, rpe_before, _ = aligned_errors({t.trip.key: t.poses_xyyaw_world for t in trips}, trips, truths)
    coarse = align_trips(trips, params=AlignmentParams(fine=False))
    both = align_trips(trips)
    ate_c, rpe_c, per_c = aligned_errors(coarse.poses_xyyaw_world, trips, truths)
    ate_b, rpe_b, per_b = aligned_errors(both.poses_xyyaw_world, trips, truths)
    assert both.failed == {} and coarse.failed == {}
    assert ate_c < 0.5 * before
    assert ate_b < 0.2 and max(per_b) < 0.3
    assert rpe_b < 0.05


def test_new_trip_against_a_prior_map_converges_and_the_map_moves_within_its_weight():
    from csr_core.alignment import AlignmentParams, PriorMap, align_trips
    from csr_core.types import MapFeature

    rng = np.random.default_rng(11)
    elements = truth_elements(300.0)
    prior = PriorMap(tuple(MapFeature(t, p) for t, p in elements), sigma_xy_m=0.05, sigma_yaw_rad=0.002)
    truth = truth_trajectory(1, False, rng, 300.0)
    trip = make_trip("vn__new", truth, elements, rng, offset_xy=(1.3, 0.9), yaw_err=0.002)
    res = align_trips([trip], prior_map=prior, params=AlignmentParams(fine=False))
    assert res.failed == {}
    err = np.linalg.norm(res.poses_xyyaw_world["vn__new"][:, :2] - truth[:, :2], axis=1)  # raw, not aligned
    assert np.sqrt(np.mean(err**2)) < 0.2
    shifts = np.asarray(res.diagnostics["prior_patch_shifts_m"])
    assert len(shifts) > 0 and shifts.max() < 3 * 0.05
    assert any(m.trip_key_i == "<prior>" for m in res.match_pairs)


def test_empty_input_raises():
    from csr_core.alignment import align_trips
    from csr_core.errors import AlignmentFailed

    with pytest.raises(AlignmentFailed):
        align_trips([])


def test_an_unfused_prior_map_is_reduced_to_one_copy_of_each_element():
    from csr_core.alignment import AlignmentParams
    from csr_core.alignment.submaps import reduce_prior_map
    from csr_core.types import MapFeature

    rng = np.random.default_rng(2)
    elements = truth_elements(200.0)
    copies = []
    for k in range(6):  # six earlier trips' aligned instances, a few cm apart
        t = make_trip(
            f"v{k}__m",
            truth_trajectory(0, False, rng, 200.0),
            elements,
            rng,
            offset_xy=tuple(rng.normal(0, 0.05, 2)),
            perception=False,
        )
        copies += [MapFeature(i.type, i.points_xy_world) for i in t.instances]
    new = make_trip("vn__n", truth_trajectory(1, False, rng, 200.0), elements, rng, perception=False)
    reduced = reduce_prior_map(copies, [new], AlignmentParams())
    lines = [f for f in reduced if not f.type.is_polygon]
    assert len(copies) > 4 * len(elements)
    assert len(lines) <= len([e for e in elements if not e[0].is_polygon]) + 4


def test_the_two_directions_of_a_wide_road_are_paired_and_registered():
    """Trips in the outer lanes of the two directions drive 10.5 m apart, each with its own GNSS
    error. Their fields of view overlap (+-15 m), so the frame graph joins them and their
    relative position is recovered; with the old fixed 6 m edges nothing paired them."""
    from dataclasses import replace

    from csr_core.alignment import AlignmentParams, align_trips
    from csr_core.alignment.submaps import frame_graph_distance_m

    rng = np.random.default_rng(5)
    elements = truth_elements(300.0)
    truth_a = truth_trajectory(1, False, rng, 300.0)
    truth_b = truth_trajectory(1, True, rng, 300.0)
    a = make_trip("va__a", truth_a, elements, rng, offset_xy=(0.2, 0.9))
    b = make_trip("vb__b", truth_b, elements, rng, offset_xy=(-0.3, -0.8), yaw_err=0.002)
    assert np.median(np.linalg.norm(truth_a[:, None, :2] - truth_b[None, :, :2], axis=2).min(axis=1)) > 10.0
    before = _relative_errors(b.poses_xyyaw_world, truth_b, a.poses_xyyaw_world, truth_a)
    assert np.median(before) > 1.0
    params = AlignmentParams(fine=False)
    assert (
        10.5 < frame_graph_distance_m([a, b], params) <= 15.0
    )  # the reach of the detections (no sensor_setup)
    res = align_trips([a, b], params=params)
    assert res.failed == {}
    after = _relative_errors(res.poses_xyyaw_world["vb__b"], truth_b, res.poses_xyyaw_world["va__a"], truth_a)
    assert np.sqrt(np.mean(after**2)) < 0.15
    apart = align_trips([a, b], params=replace(params, frame_graph_distance_m=6.0))
    assert set(apart.failed) == {"va__a", "vb__b"}
    assert all(reason.startswith("no_overlap") for reason in apart.failed.values())


def test_the_frame_graph_distance_is_the_shortest_stated_lateral_reach():
    from dataclasses import replace

    from csr_core.alignment import AlignmentParams
    from csr_core.alignment.submaps import frame_graph_distance_m

    rng = np.random.default_rng(1)
    trip = make_trip("va__a", truth_trajectory(0, False, rng, 100.0), truth_elements(100.0), rng)

    def stated(y):
        return replace(trip, trip=replace(trip.trip, sensor_setup={"bev_range_m": {"x": [-10, 30], "y": y}}))

    wide, narrow = stated([-15, 15]), stated([-12, 8])
    assert frame_graph_distance_m([wide], AlignmentParams()) == pytest.approx(15.0)
    assert frame_graph_distance_m([wide, narrow], AlignmentParams()) == pytest.approx(
        12.0
    )  # the shortest reach
    assert frame_graph_distance_m([trip], AlignmentParams()) < 15.0  # no stated range: where detections lie
    assert frame_graph_distance_m([narrow], AlignmentParams(frame_graph_distance_m=6.0)) == 6.0
