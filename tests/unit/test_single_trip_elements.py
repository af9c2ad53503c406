"""Single-trip element tracking, splicing, ghost rejection and noise: known answers."""

from dataclasses import replace

import numpy as np
import pytest
import shapely
from scipy.spatial import cKDTree

from csr_core.metrics import map_scores
from csr_core.scenario import (
    geo_features_to_local,
    list_trip_files,
    load_trip,
    read_map_geojson,
    read_poses_dir,
    read_scenario_meta,
)
from csr_core.sim.scenario import simulate_scenario
from csr_core.single_trip import reconstruct_trip
from csr_core.single_trip.noise import robust_sigma
from csr_core.single_trip.params import DEFAULT
from csr_core.single_trip.synthetic import (
    SynthCrossing,
    SynthLine,
    SynthSpec,
    crossing_points_world,
    line_points_world,
    make_trip,
)
from csr_core.single_trip.tracking import pair_distance, resample_flat
from csr_core.types import DividerStyle, ElementType, MapFeature

pytestmark = pytest.mark.unit


def _dist_to_line(points, line):
    d = np.linalg.norm(points[:, None, :] - line[None, :, :], axis=-1)
    return d.min(axis=1)


def _instances(rec, etype):
    return [i for i in rec.instances if i.type == etype]


def test_resample_flat_matches_arclength_interpolation():
    a = np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])
    b = np.array([[1.0, 1.0], [1.0, 2.0]])
    out = resample_flat(np.vstack([a, b]), np.array([0, 3, 5]), 5)
    assert np.allclose(out[0], [[0, 0], [1.75, 0], [3, 0.5], [3, 2.25], [3, 4]])
    assert np.allclose(out[1, :, 1], np.linspace(1, 2, 5))


def test_pair_distance_extends_along_the_chord():
    poly = np.array([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]])
    pts = np.array([[[5.0, 0.2], [1.0, -0.3], [30.0, 0.0]]])
    d = pair_distance(pts, poly, max_extrapolation_m=12.0, cap_m=3.0)
    assert np.allclose(d, [[0.2, 0.3, 3.0]])


@pytest.mark.parametrize(("curvature_1pm", "tol_p95_m", "tol_max_m"), [(0.0, 0.01, 0.02), (0.01, 0.05, 0.15)])
def test_noiseless_trip_reproduces_the_lines(curvature_1pm, tol_p95_m, tol_max_m):
    # on a curve (R = 100 m) the parts seen beyond the trip's first and last pose are spliced on
    # the straight prolongation of the path, hence the looser bound at the very ends
    spec = SynthSpec(length_m=200.0, curvature_1pm=curvature_1pm)
    trip, _, frame = make_trip(spec)
    rec = reconstruct_trip(trip, frame)
    assert len(rec.instances) == len(spec.lines)
    for line in spec.lines:
        truth = line_points_world(spec, line, spacing_m=0.01)
        d = min((_dist_to_line(i.points_xy_world, truth) for i in _instances(rec, line.type)), key=np.max)
        assert np.percentile(d, 95) < tol_p95_m
        assert d.max() < tol_max_m


@pytest.mark.parametrize(
    "spec",
    [
        # the solid divider at 5.25 m seen shifted by a lane width for 6 frames, the right boundary for 5
        SynthSpec(
            length_m=300.0, element_sigma_m=0.05, ghosts=((120, 125, 2, 3.5), (200, 204, 0, -3.5)), seed=5
        ),
        # the right boundary seen a lane further out in the trip's first 13 frames: three tracked frames,
        # as few as an element the trip leaves behind (below), but the place stays in range unseen
        SynthSpec(length_m=200.0, element_sigma_m=0.03, seed=7, ghosts=((0, 12, 0, -3.5),)),
    ],
    ids=["mid-trip", "at-trip-start"],
)
def test_ghost_seen_for_a_few_frames_is_dropped(spec):
    trip, _, frame = make_trip(spec)
    rec = reconstruct_trip(trip, frame)
    assert len(rec.instances) == len(spec.lines)
    truth = np.vstack([line_points_world(spec, ln, 0.1) for ln in spec.lines])
    for inst in rec.instances:
        assert np.percentile(_dist_to_line(inst.points_xy_world, truth), 99) < 0.15


def test_an_element_seen_only_before_the_trip_left_it_behind_is_kept():
    # a boundary ending at the trip's start: in the BEV range (15 m behind) for the first 15 m only,
    # three tracked frames (5 m apart), fewer than TRACK_MIN_FRAMES; the trip, not its detector, cut it
    behind = SynthLine(ElementType.ROAD_BOUNDARY, -5.4, s_range_m=(-40.0, 0.0))
    spec = SynthSpec(length_m=200.0, element_sigma_m=0.03, seed=7, lines=(*SynthSpec().lines, behind))
    trip, _, frame = make_trip(spec)
    truth = line_points_world(spec, behind, 0.1)
    seen_in = [
        i
        for i, f in enumerate(trip.elements)
        if any(e.type == ElementType.ROAD_BOUNDARY and e.points_xy_vehicle[:, 1].mean() < -4.0 for e in f)
    ]
    assert seen_in and max(seen_in) < 15  # the first 1.5 s of a 20 s trip
    near = [
        i
        for i in _instances(reconstruct_trip(trip, frame), ElementType.ROAD_BOUNDARY)
        if np.median(_dist_to_line(i.points_xy_world, truth)) < 0.5
    ]
    assert len(near) == 1
    assert np.percentile(_dist_to_line(near[0].points_xy_world, truth), 95) < 0.15
    # the rule it passes: without it (as many frames as anywhere else) the boundary is dropped
    strict = replace(DEFAULT, TRACK_MIN_FRAMES_AT_TRIP_END=DEFAULT.TRACK_MIN_FRAMES)
    assert not [
        i
        for i in _instances(reconstruct_trip(trip, frame, strict), ElementType.ROAD_BOUNDARY)
        if np.median(_dist_to_line(i.points_xy_world, truth)) < 0.5
    ]


def test_dashed_divider_stays_one_instance():
    spec = SynthSpec(
        length_m=300.0,
        element_sigma_m=0.03,
        seed=6,
        lines=(
            SynthLine(ElementType.ROAD_BOUNDARY, -1.9),
            SynthLine(ElementType.LANE_DIVIDER, 1.75, style=DividerStyle.DASHED, dash_m=(3.0, 6.0)),
            SynthLine(ElementType.ROAD_BOUNDARY, 5.4),
        ),
    )
    trip, _, frame = make_trip(spec)
    # perception reports separate dashes
    assert max(sum(e.type == ElementType.LANE_DIVIDER for e in f) for f in trip.elements) >= 4
    rec = reconstruct_trip(trip, frame)
    dividers = _instances(rec, ElementType.LANE_DIVIDER)
    assert len(dividers) == 1
    d = dividers[0]
    assert d.style == DividerStyle.DASHED
    length = np.linalg.norm(np.diff(d.points_xy_world, axis=0), axis=1).sum()
    assert length > 300.0  # spans the gaps, from first to last dash seen
    truth = line_points_world(spec, spec.lines[1], 0.1)
    assert _dist_to_line(d.points_xy_world, truth).max() < 0.1


def _crossing_geometry(spec, crossing):
    pts = crossing_points_world(spec, crossing)
    return shapely.Polygon(pts) if crossing.type == ElementType.CROSSWALK else shapely.LineString(pts)


@pytest.mark.parametrize("crossing_type", [ElementType.CROSSWALK, ElementType.STOP_LINE])
def test_dashed_divider_is_cut_where_its_paint_breaks_at_a_crossing(crossing_type):
    # the paint stops 4 m before a crosswalk / stop line and starts again 4 m after it: an 8 m gap,
    # which the splice bridges like a dash gap (6 m here) unless the crossing in it breaks the line
    dashed = dict(type=ElementType.LANE_DIVIDER, offset_m=1.75, style=DividerStyle.DASHED, dash_m=(3.0, 6.0))
    crossing = SynthCrossing(crossing_type, s_m=142.0, from_m=-1.9, to_m=5.4)
    spec = SynthSpec(
        length_m=300.0,
        element_sigma_m=0.03,
        seed=6,
        crossings=(crossing,),
        lines=(
            SynthLine(ElementType.ROAD_BOUNDARY, -1.9),
            SynthLine(**dashed, s_range_m=(0.0, 138.0)),
            SynthLine(**dashed, s_range_m=(146.0, 400.0)),
            SynthLine(ElementType.ROAD_BOUNDARY, 5.4),
        ),
    )
    trip, _, frame = make_trip(spec)
    geometry = _crossing_geometry(spec, crossing)

    def across(rec):
        return [
            i
            for i in _instances(rec, ElementType.LANE_DIVIDER)
            if shapely.LineString(i.points_xy_world).distance(geometry) < 1.0
        ]

    assert across(
        reconstruct_trip(trip, frame, replace(DEFAULT, PAINT_BREAKS=False))
    )  # bridged without the rule
    rec = reconstruct_trip(trip, frame)
    assert _instances(rec, crossing_type)
    assert not across(rec)
    dividers = _instances(rec, ElementType.LANE_DIVIDER)
    assert len(dividers) == 2
    on_line = [
        [
            np.percentile(_dist_to_line(d.points_xy_world, line_points_world(spec, line, 0.1)), 95) < 0.2
            for line in spec.lines[1:3]
        ]
        for d in dividers
    ]
    assert sorted(on_line) == [[False, True], [True, False]]  # one instance on each painted line


def test_a_divider_seen_across_a_crosswalk_is_not_cut():
    crossing = SynthCrossing(ElementType.CROSSWALK, s_m=145.0, from_m=-1.9, to_m=5.4)
    spec = SynthSpec(length_m=300.0, element_sigma_m=0.03, seed=6, crossings=(crossing,))
    trip, _, frame = make_trip(spec)
    rec = reconstruct_trip(trip, frame)
    assert _instances(rec, ElementType.CROSSWALK)
    geometry = _crossing_geometry(spec, crossing)
    solid = [
        i
        for i in _instances(rec, ElementType.LANE_DIVIDER)
        if shapely.LineString(i.points_xy_world).intersects(geometry)
    ]
    assert len(solid) == 2  # both dividers of the default road, perceived unbroken through it, stay whole
    assert all(np.linalg.norm(np.diff(i.points_xy_world, axis=0), axis=1).sum() > 280.0 for i in solid)


def _u_turn(radius_m=1.8, lane_end_m=48.0, loop_from_m=50.0):
    """A trip up the lane x = 0 to a dead end, round a U-turn and back down the lane x = 2 r: its
    path (P, 2), and each lane's centreline seen piece by piece (flat points, observation ids)."""
    up = np.column_stack([np.zeros(51), np.linspace(0.0, loop_from_m, 51)])
    theta = np.linspace(np.pi, 0.0, 25)
    loop = np.column_stack([radius_m + radius_m * np.cos(theta), loop_from_m + radius_m * np.sin(theta)])
    path = np.vstack([up, loop[1:], up[::-1] + (2 * radius_m, 0.0)])
    rng = np.random.default_rng(2)
    points, ids = [], []
    for y0 in np.arange(0.0, lane_end_m - 10.0, 5.0):  # 20 m pieces ahead of the car
        for x, sense in ((0.0, 1.0), (2 * radius_m, -1.0)):
            y = np.arange(y0, min(y0 + 20.0, lane_end_m) + 1e-9, 0.5)
            piece = np.column_stack([np.full(len(y), x), y if sense > 0 else y[::-1]])
            points.append(piece + rng.normal(0.0, 0.03, piece.shape))
            ids.append(np.full(len(y), len(ids)))
    return path, np.vstack(points), np.concatenate(ids)


def test_centreline_spliced_round_a_u_turn_is_cut_back_to_what_was_seen():
    # the centrelines of both lanes of a dead-end road lie on the path the trip drove (up one,
    # back down the other), so one track holds both and the splice along the path bridges the
    # U-turn between them, where no centreline was seen. A centreline has no dash gaps: the
    # stretch none of its observations comes near is cut out, each lane keeps its own line
    from csr_core.single_trip.paint_breaks import ObservedPoints, cut_unseen
    from csr_core.single_trip.splicing import splice_line

    path, points, ids = _u_turn()
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    obs_ends = np.column_stack([starts, np.r_[starts[1:], len(ids)] - 1])
    spliced = splice_line(points, ids, obs_ends, np.ones(obs_ends.shape, bool), path, DEFAULT)
    assert len(spliced) == 1
    line = spliced[0].points_xy_world
    observed = ObservedPoints(points)
    assert cKDTree(points).query(line)[0].max() > 2.0  # it runs round the loop
    parts = cut_unseen(line, observed, DEFAULT.PAINT_BREAK_GATE_M)
    assert len(parts) == 2
    for part in parts:
        lane_x = 0.0 if abs(part[:, 0].mean()) < 1.0 else 3.6
        assert np.abs(part[:, 0] - lane_x).max() < 0.3
        assert np.ptp(part[:, 1]) > 40.0


def test_a_stretch_displaced_from_its_observations_beyond_the_trips_noise_is_cut():
    # a centreline observed with 0.1 m lateral noise, whose splice stands 0.7 m off its
    # observations over 10 m (a junction's fragment, Karlsruhe s3): within a fixed 1 m
    # gate, yet far outside what the trip's noise allows. The gate is 3 sigma of the
    # type's noise in the trip plus half the observations' spacing, so that stretch is cut
    from csr_core.single_trip import _unseen_gate_m
    from csr_core.single_trip.paint_breaks import ObservedPoints, cut_unseen
    from csr_core.types import ElementNoise

    rng = np.random.default_rng(7)
    x = np.arange(0.0, 40.0, DEFAULT.UNSEEN_CUT_STEP_M)
    frames = [
        np.column_stack([x, 0.7 * ((x > 15) & (x < 25)) + rng.normal(0, 0.1, len(x))]) for _ in range(20)
    ]
    observed = ObservedPoints(np.vstack(frames))
    line = np.column_stack([np.arange(0.0, 40.5, 1.0), np.zeros(41)])
    sigma_m = robust_sigma(np.concatenate([f[:, 1] for f in frames])[np.tile((x <= 15) | (x >= 25), 20)])
    gate_m = _unseen_gate_m(ElementNoise(lateral_sigma_m=sigma_m, along_sigma_m=0.5, n_samples=1000), DEFAULT)
    assert 0.35 < gate_m < 0.5
    parts = cut_unseen(line, observed, gate_m)
    assert [(p[0, 0], p[-1, 0]) for p in parts] == [(0.0, 15.0), (25.0, 40.0)]
    assert len(cut_unseen(line, observed, 1.0)) == 1  # a fixed 1 m gate keeps it
    # a near-noiseless perception: the gate keeps a floor, a line on its observations stays whole
    tiny = _unseen_gate_m(ElementNoise(lateral_sigma_m=0.002, along_sigma_m=0.5, n_samples=1000), DEFAULT)
    assert tiny >= 3 * DEFAULT.INSTANCE_MIXTURE_MIN_SIGMA_M
    assert len(cut_unseen(line, ObservedPoints(np.column_stack([x, np.zeros(len(x))])), tiny)) == 1


def test_crosswalk_never_seen_whole_keeps_the_axes_of_its_sides():
    # a 12 m x 4 m crosswalk on a side arm, 35 degrees off the vehicle's heading, only ever seen cut
    # by the BEV range's side (a line along the heading): the part seen is a strip cut at the
    # range's angle. Its rectangle takes the axes of the crosswalk's own sides, not the strip's
    from csr_core.single_trip.splicing import splice_polygon

    angle = np.radians(35.0)
    axis, across = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
    truth = shapely.Polygon([a * axis + b * across for a, b in ((0, 0), (12, 0), (12, 4), (0, 4))])
    rng = np.random.default_rng(3)
    polys, inside = [], []
    for edge_y in np.linspace(4.0, 7.0, 12):  # the range's side y = edge_y in the world (heading 0)
        seen = shapely.intersection(truth, shapely.box(-50.0, -50.0, 50.0, edge_y))
        outline = np.asarray(seen.exterior.coords)[:-1]
        polys.append(outline + rng.normal(0.0, 0.03, outline.shape))
        inside.append(np.abs(outline[:, 1] - edge_y) > 1e-6)
    headings = np.zeros(len(polys))

    def axis_error_deg(outline):
        side = outline[1] - outline[0]
        err = (np.degrees(np.arctan2(side[1], side[0])) - 35.0) % 90.0
        return min(err, 90.0 - err)

    fused, _, _ = splice_polygon(polys, np.zeros(len(polys), bool), headings, inside)
    assert axis_error_deg(fused) < 1.0
    assert shapely.Polygon(fused).intersection(truth).area > 0.9 * shapely.Polygon(fused).area
    principal, _, _ = splice_polygon(polys, np.zeros(len(polys), bool), headings)  # without the sides
    assert axis_error_deg(principal) > 5.0


def test_noise_estimate_recovers_the_injected_sigma():
    sigma = 0.12
    spec = SynthSpec(length_m=400.0, element_sigma_m=sigma, seed=8)
    trip, _, frame = make_trip(spec)
    rec = reconstruct_trip(trip, frame)
    for etype in (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY):
        assert rec.noise[etype].lateral_sigma_m == pytest.approx(sigma, rel=0.15)
        assert rec.noise[etype].n_samples > 1000
    # a type never seen keeps the prior and says so
    assert rec.noise[ElementType.CROSSWALK].n_samples == 0


def test_robust_sigma_ignores_outliers():
    rng = np.random.default_rng(0)
    r = np.r_[rng.normal(scale=0.2, size=5000), rng.uniform(3, 5, size=250)]
    assert robust_sigma(r) == pytest.approx(0.2, rel=0.1)


def test_results_are_recomputed_identically_from_the_raw_upload():
    from csr_core.upload import decode_trip, encode_trip

    trip, _, frame = make_trip(SynthSpec(length_m=150.0, element_sigma_m=0.05, gnss_sigma_m=0.2, seed=9))
    a = reconstruct_trip(trip, frame)
    b = reconstruct_trip(decode_trip(encode_trip(trip)), frame)
    assert np.allclose(a.poses_xyyaw_world, b.poses_xyyaw_world, atol=1e-6)
    assert len(a.instances) == len(b.instances)
    assert np.array_equal(a.keyframe_indices, b.keyframe_indices)


def _out_and_back(n_each: int = 20, step_m: float = 2.0):
    """Tracked-frame poses (2n, 3): along +x from x = 0, then back along -x on the same road."""
    x = np.arange(n_each) * step_m
    out = np.column_stack([x, np.zeros(n_each), np.zeros(n_each)])
    back = np.column_stack([x[::-1], np.full(n_each, -3.5), np.full(n_each, np.pi)])
    return np.vstack([out, back])


def test_road_driven_twice_is_not_taken_for_a_ghost():
    # an element seen by one track on the way out: on the way back the same frames see it again
    # through another track (corroborated: visibility 1), whereas detections 3.5 m away (a
    # ghost's shift) do not corroborate it (20 of 40 in-range frames: 0.5)
    from scipy.spatial import cKDTree

    from csr_core.single_trip import _visibility_ratio

    poses = _out_and_back()
    frames = np.arange(len(poses))
    element = np.column_stack([np.linspace(0.0, 40.0, 41), np.full(41, 3.0)])
    seen = np.arange(20)
    back_pts = np.repeat(element[::8][None], 20, axis=0)  # (20, 6, 2): the return pass's detections
    back_frames = np.repeat(np.arange(20, 40), back_pts.shape[1])
    box = (-15.0, 30.0, -15.0, 15.0)
    ratio = _visibility_ratio(
        element, seen, frames, poses, box, 2.0, cKDTree(back_pts.reshape(-1, 2)), back_frames, 0.9
    )
    assert ratio == pytest.approx(1.0)
    shifted = back_pts.reshape(-1, 2) + (0.0, 3.5)
    ratio = _visibility_ratio(element, seen, frames, poses, box, 2.0, cKDTree(shifted), back_frames, 0.9)
    assert ratio == pytest.approx(0.5)


def test_instances_are_cut_to_the_lateral_reach_of_the_path():
    # a line leaving the road at a right angle is kept up to the BEV range's lateral reach;
    # a polygon whose centre lies beyond it is left out
    from csr_core.single_trip import _within_reach
    from csr_core.single_trip.compiled.search import SortedPoints

    path = SortedPoints(np.column_stack([np.arange(-50.0, 50.5, 0.5), np.zeros(201)]))
    line = np.column_stack([np.zeros(41), np.linspace(5.0, 45.0, 41)])
    parts = _within_reach(line, path, 15.0, is_polygon=False)
    assert len(parts) == 1
    assert parts[0][:, 1].min() == pytest.approx(5.0)
    assert parts[0][:, 1].max() == pytest.approx(15.0)
    square = np.array([[0.0, 14.0], [4.0, 14.0], [4.0, 18.0], [0.0, 18.0]])
    assert _within_reach(square, path, 15.0, is_polygon=True) == []
    assert len(_within_reach(square - (0.0, 2.0), path, 15.0, is_polygon=True)) == 1


def test_dashed_line_crossed_in_a_junction_is_one_instance():
    # a dashed divider (3 m dashes, 6 m gaps) running across the vehicle path at a right angle,
    # each dash one observation in each of 6 frames: its gaps lie along its own shape, not along
    # the path, so it is spliced as one line across the junction (not as 3 m dashes)
    from csr_core.single_trip.params import DEFAULT
    from csr_core.single_trip.splicing import splice_line

    rng = np.random.default_rng(3)
    guide = np.column_stack([np.linspace(-40.0, 40.0, 161), np.zeros(161)])
    dashes = [(y0, y0 + 3.0) for y0 in np.arange(-14.0, 14.0, 9.0)]
    obs = [
        np.column_stack([5.0 + rng.normal(0.0, 0.03, 4), np.linspace(a, b, 4)])
        for _ in range(6)
        for a, b in dashes
    ]
    counts = np.array([len(o) for o in obs])
    offsets = np.r_[0, np.cumsum(counts)]
    points = np.concatenate(obs)
    obs_id = np.repeat(np.arange(len(obs)), counts)
    obs_ends = np.column_stack([offsets[:-1], offsets[1:] - 1])
    out = splice_line(points, obs_id, obs_ends, np.ones((len(obs), 2), bool), guide, DEFAULT)
    assert len(out) == 1
    line = out[0].points_xy_world
    assert np.ptp(line[:, 1]) == pytest.approx(dashes[-1][1] - dashes[0][0], abs=0.5)
    assert np.abs(line[:, 0] - 5.0).max() < 0.1


def test_dashed_line_bending_through_a_junction_is_one_instance():
    # a dashed guide line (3 m dashes, 6 m gaps) that runs straight, then turns by 110 degrees
    # on a 12 m radius, across the vehicle path; each dash one observation in each of 6 frames.
    # Past the bend's start the next dash lies 2-3 m off the straight tangent: the backbone
    # follows the bend (one circle fits its last points and the next dash)
    from csr_core.single_trip.params import DEFAULT
    from csr_core.single_trip.splicing import splice_line

    rng = np.random.default_rng(4)
    radius, turn = 12.0, np.radians(110.0)

    def at(s: np.ndarray) -> np.ndarray:  # the line by arclength: 12 m straight up x = 5, then left
        a = np.clip(s - 12.0, 0.0, None) / radius
        straight = np.column_stack([np.full_like(s, 5.0), np.minimum(s, 12.0) - 6.0])
        bent = np.column_stack([5.0 - radius * (1.0 - np.cos(a)), 6.0 + radius * np.sin(a)])
        return np.where((s <= 12.0)[:, None], straight, bent)

    length = 12.0 + radius * turn
    dashes = [(s0, s0 + 3.0) for s0 in np.arange(0.0, length - 3.0, 9.0)]
    obs = [at(np.linspace(a, b, 4)) + rng.normal(0.0, 0.03, (4, 2)) for _ in range(6) for a, b in dashes]
    guide = np.column_stack([np.linspace(-40.0, 40.0, 161), np.full(161, -20.0)])
    counts = np.array([len(o) for o in obs])
    offsets = np.r_[0, np.cumsum(counts)]
    obs_id = np.repeat(np.arange(len(obs)), counts)
    obs_ends = np.column_stack([offsets[:-1], offsets[1:] - 1])
    args = (np.concatenate(obs), obs_id, obs_ends, np.ones((len(obs), 2), bool), guide, DEFAULT)
    assert len(splice_line(*args)) == 2  # along the straight tangent only: the last dash is apart
    out = splice_line(*args, follow_bends=True)
    assert len(out) == 1
    line = out[0].points_xy_world
    truth = shapely.LineString(at(np.linspace(dashes[0][0], dashes[-1][1], 400)))
    assert max(truth.distance(shapely.Point(p)) for p in line) < 0.3  # on the line
    assert shapely.LineString(line).hausdorff_distance(truth) < 0.5  # all of it, ends included


def test_crossing_connectors_mixed_in_one_track_are_regrouped():
    # two connectors crossing in a junction at 30 degrees, observed in alternate frames (as a
    # tracker chaining them would mix them): the symmetric test separates them
    from csr_core.single_trip.tracking import regroup_observations

    rng = np.random.default_rng(4)
    t = np.linspace(-8.0, 8.0, 6)
    obs, frame, which = [], [], []
    for f in range(10):
        for k, angle in enumerate((0.0, np.radians(30.0))):
            u = np.array([np.cos(angle), np.sin(angle)])
            obs.append((t + 1.5 * f)[:, None] * u + rng.normal(0.0, 0.03, (6, 2)))
            frame.append(f)
            which.append(k)
    labels = regroup_observations(np.stack(obs), np.array(frame), 0.6, np.radians(20.0), 2, 12.0)
    which = np.array(which)
    assert len(np.unique(labels[which == 0])) == 1
    assert len(np.unique(labels[which == 1])) == 1
    assert labels[which == 0][0] != labels[which == 1][0]


def _with_crosswalks(trip, true_poses, outlines_w, sliding, slide_rng, box=(-15.0, 30.0, -15.0, 15.0)):
    """``trip`` with each world outline (4, 2) perceived (0.03 m noise) in every frame that has it
    whole inside ``box``; where ``sliding``, with vertices anywhere along its long sides (as a
    detector places them)."""
    import dataclasses

    from csr_core.types import PerceivedElement

    elements = []
    for f, frame_elements in enumerate(trip.elements):
        x, y, yaw = true_poses[f]
        c, s = np.cos(yaw), np.sin(yaw)
        extra = []
        for outline, slide in zip(outlines_w, sliding, strict=True):
            rel = outline - (x, y)
            v = np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]])
            if not ((v[:, 0] > box[0]) & (v[:, 0] < box[1]) & (v[:, 1] > box[2]) & (v[:, 1] < box[3])).all():
                continue
            if slide:  # three vertices along each of the sides 0-1 and 2-3
                a, b = np.sort(slide_rng.uniform(0.05, 0.95, (2, 3)), axis=1)
                v = np.vstack(
                    [
                        v[0],
                        v[0] + a[:, None] * (v[1] - v[0]),
                        v[1],
                        v[2],
                        v[2] + b[:, None] * (v[3] - v[2]),
                        v[3],
                    ]
                )
            extra.append(PerceivedElement(ElementType.CROSSWALK, v + slide_rng.normal(0.0, 0.03, v.shape)))
        elements.append(tuple(frame_elements) + tuple(extra))
    return dataclasses.replace(trip, elements=tuple(elements))


def test_crosswalk_with_sliding_vertices_is_not_taken_for_a_mixture():
    # four crosswalks across the road (the last two 1 m apart, as on both arms of a junction),
    # perceived whole; one is outlined with a vertex anywhere along each long side, the others
    # exactly. Its vertex residuals are far wider than the type's, yet it is one crosswalk: all
    # four come out, each on its truth (before: the sliding one was dropped as a "mixture")
    from csr_core.single_trip.pose_graph import SmoothedPoses

    spec = SynthSpec(length_m=300.0, seed=7)
    trip, true, frame = make_trip(spec)
    outlines = []
    for i, x0 in (
        (len(true) // 4, 10.0),
        (len(true) // 2, 10.0),
        (3 * len(true) // 4, 10.0),
        (3 * len(true) // 4, 15.0),
    ):
        x, y, yaw = true[i]
        along, across = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        outlines.append(
            np.array(
                [
                    (x, y) + a0 * along + b * across
                    for a0, b in ((x0, -5.0), (x0, 8.0), (x0 + 4.0, 8.0), (x0 + 4.0, -5.0))
                ]
            )
        )
    trip = _with_crosswalks(trip, true, outlines, (False, True, False, False), np.random.default_rng(1))
    n = len(true)
    rec = reconstruct_trip(
        trip, frame, smoothed=SmoothedPoses(true, np.zeros(n), np.zeros(n), np.ones(n, bool), np.zeros(3))
    )
    found = _instances(rec, ElementType.CROSSWALK)
    assert len(found) == len(outlines)
    for outline in outlines:
        got = min(
            (inst.points_xy_world.mean(0) for inst in found),
            key=lambda p: np.linalg.norm(p - outline.mean(0)),
        )
        assert np.linalg.norm(got - outline.mean(0)) < 0.6  # sliding vertices move the vertex mean


def test_duplicate_polygons_keep_the_one_fused_from_whole_outlines():
    from csr_core.single_trip import _without_duplicate_polygons
    from csr_core.types import TripInstance

    def cand(outline, n_obs):
        inst = TripInstance(
            type=ElementType.CROSSWALK,
            points_xy_world=outline,
            style=None,
            n_observations=n_obs,
            first_frame=0,
            last_frame=1,
        )
        return inst, np.zeros(0), np.zeros(0)

    whole = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 12.0], [0.0, 12.0]])
    clipped_rectangle = whole[:, :] * (1.0, 0.5) + (0.5, 0.0)  # only the part seen, from another pass
    other = whole + (10.0, 0.0)
    out = _without_duplicate_polygons(
        [cand(clipped_rectangle, 9), cand(whole, 6), cand(other, 3)], {id(whole): whole, id(other): other}
    )
    kept = [c[0].points_xy_world for c in out]
    assert len(kept) == 2
    assert any(k is whole for k in kept) and any(k is other for k in kept)


def _dash_observations(dashes, n_frames, rng, sigma_m=0.03, spacing_m=0.5):
    """Each dash ``(a (2,), b (2,))`` observed in ``n_frames`` frames: flat points, their observation."""
    obs = []
    for _ in range(n_frames):
        for a, b in dashes:
            n = int(np.hypot(*np.subtract(b, a)) / spacing_m) + 1
            obs.append(np.linspace(a, b, n) + rng.normal(0.0, sigma_m, (n, 2)))
    return np.concatenate(obs), np.repeat(np.arange(len(obs)), [len(o) for o in obs])


def _runs_along(line, points, obs_id):
    from csr_core.single_trip.params import DEFAULT
    from csr_core.single_trip.splicing import runs_along_observations

    return runs_along_observations(
        line,
        points,
        obs_id,
        np.unique(obs_id),
        DEFAULT.TRACK_MAX_ANGLE_RAD,
        DEFAULT.TRACK_GATE_M,
        DEFAULT.SPLICE_ACROSS_WINDOW_M,
    )


def test_splice_along_its_dashes_is_kept_whole_gaps_included():
    rng = np.random.default_rng(7)
    dashes = [((x, 0.0), (x + 3.0, 0.0)) for x in np.arange(0.0, 45.0, 9.0)]  # 6 m gaps, unobserved
    points, obs_id = _dash_observations(dashes, 6, rng)
    line = np.column_stack([np.linspace(0.0, 39.0, 79), np.zeros(79)])
    kept = _runs_along(line, points, obs_id)
    assert len(kept) == 1 and len(kept[0]) == len(line)


def test_splice_from_dash_end_to_dash_end_across_two_dividers_is_dropped():
    # two dashed dividers 7 m apart, their dashes mixed in one track (a junction); the splice ran
    # across from the end of a dash of one to the end of a dash of the other
    rng = np.random.default_rng(8)
    dashes = [((x, y), (x + 3.0, y)) for y in (0.0, 7.0) for x in np.arange(0.0, 30.0, 9.0)]
    points, obs_id = _dash_observations(dashes, 6, rng)
    line = np.column_stack([np.linspace(12.0, 12.5, 15), np.linspace(0.0, 7.0, 15)])
    assert _runs_along(line, points, obs_id) == []


def test_splice_running_on_past_its_end_is_cut_where_it_crosses_another_divider():
    # divider A (dashes along y = 0, x 0-30) ends; the splice runs on at 60 degrees through a dash
    # of divider B (along y = 4, x 28-40), mixed into A's track
    rng = np.random.default_rng(9)
    dashes = [((x, 0.0), (x + 3.0, 0.0)) for x in np.arange(0.0, 30.0, 9.0)] + [((28.0, 4.0), (40.0, 4.0))]
    points, obs_id = _dash_observations(dashes, 6, rng)
    head = np.column_stack([np.linspace(0.0, 30.0, 61), np.zeros(61)])
    turn = np.array([np.cos(np.radians(60.0)), np.sin(np.radians(60.0))])
    tail = (30.0, 0.0) + np.linspace(0.5, 5.5, 11)[:, None] * turn  # crosses B at 4.6 m
    kept = _runs_along(np.vstack([head, tail]), points, obs_id)
    longest = max(kept, key=len)
    assert longest[0] == pytest.approx(head[0])
    # the head, cut at most SPLICE_ACROSS_WINDOW_M + TRACK_GATE_M before B, not before A's last dash
    assert longest[-1, 0] >= 30.0 and longest[-1, 1] < 2.0
    for part in kept:  # nothing of the tail where it crosses B, nor beyond
        assert not ((part[:, 1] > 3.0) & (part[:, 0] > 30.0)).any()


@pytest.mark.parametrize(
    "params",
    [DEFAULT, replace(DEFAULT, INSTANCE_MIXTURE_MIN_SIGMA_M=0.0)],
    ids=["as shipped", "without the mixture floor"],
)
def test_noiseless_dashed_dividers_are_not_taken_for_mixtures(tmp_path, params):
    # a simulated highway trip without any sensor error: the solid lines' residuals are ~0 (the
    # type's sigma 2 mm), a dashed divider's a centimetre (its dashes chained into one line); only a
    # spread wider than half a painted line marks a mixture of two elements
    # (INSTANCE_MIXTURE_MIN_SIGMA_M). Without that floor, half the dividers went missing.
    simulate_scenario("highway", 1, "noiseless", 1, tmp_path, trip_length_m=600.0)
    meta = read_scenario_meta(tmp_path)
    truth_map = geo_features_to_local(read_map_geojson(tmp_path / "truth" / "map.geojson"), meta.frame)
    trip_file = list_trip_files(tmp_path)[0]
    true_xy = meta.frame.to_local(read_poses_dir(tmp_path / "truth" / "poses")[trip_file.key].lonlat_deg)
    rec = reconstruct_trip(load_trip(trip_file), meta.frame, params)
    scores = map_scores(
        [MapFeature(i.type, i.points_xy_world, i.style) for i in rec.instances], truth_map, true_xy
    )
    dividers = scores.per_type[ElementType.LANE_DIVIDER]
    dashed = [i for i in _instances(rec, ElementType.LANE_DIVIDER) if i.style == DividerStyle.DASHED]
    if params.INSTANCE_MIXTURE_MIN_SIGMA_M > 0:
        assert dashed
        assert dividers.completeness > 0.99
        assert dividers.cd < 0.01
    else:
        assert not dashed
        assert dividers.completeness < 0.6


def test_a_wide_sensor_keeps_instances_within_the_map_corridor():
    # a BEV of +-25 m: the boundary 20 m to the left is seen all along, but only its part within
    # INSTANCE_MAX_LATERAL_M (15 m, the corridor contract section 6 scores) of the path is kept:
    # here none of it; the lines within 15 m are kept whole
    far = SynthLine(ElementType.ROAD_BOUNDARY, 21.75)
    spec = SynthSpec(
        length_m=200.0, element_sigma_m=0.02, seed=3, bev_y_m=(-25.0, 25.0), lines=(*SynthSpec().lines, far)
    )
    trip, _, frame = make_trip(spec)
    far_truth = line_points_world(spec, far, 0.1)
    assert any(e.points_xy_vehicle[:, 1].min() > 18.0 for f in trip.elements for e in f)  # perceived
    for params, kept in ((DEFAULT, False), (replace(DEFAULT, INSTANCE_MAX_LATERAL_M=30.0), True)):
        rec = reconstruct_trip(trip, frame, params)
        near_far = [
            i
            for i in _instances(rec, ElementType.ROAD_BOUNDARY)
            if np.median(_dist_to_line(i.points_xy_world, far_truth)) < 0.5
        ]
        assert bool(near_far) == kept
        assert len(rec.instances) >= len(SynthSpec().lines)


def test_a_splice_across_its_observations_everywhere_is_regrouped_not_dropped(tmp_path):
    # a Karlsruhe trip past traffic islands, true poses: a kerb track that took in two legs of an
    # island (or both of its sides) splices into a line that runs along none of its observations.
    # Regrouped and spliced group by group, the kerbs come back (SPLICE_REGROUP_ACROSS); before, the
    # whole track was dropped
    from csr_core.se2 import heading_deg_to_yaw_rad
    from csr_core.single_trip.pose_graph import SmoothedPoses

    simulate_scenario("karlsruhe", 1, "standard", 3, tmp_path, trip_length_m=800.0)
    meta = read_scenario_meta(tmp_path)
    truth_map = geo_features_to_local(read_map_geojson(tmp_path / "truth" / "map.geojson"), meta.frame)
    trip_file = list_trip_files(tmp_path)[0]
    truth = read_poses_dir(tmp_path / "truth" / "poses")[trip_file.key]
    true_xy = meta.frame.to_local(truth.lonlat_deg)
    n = len(true_xy)
    poses = SmoothedPoses(
        np.column_stack([true_xy, heading_deg_to_yaw_rad(truth.heading_deg)]),
        np.zeros(n),
        np.zeros(n),
        np.ones(n, bool),
        np.zeros(3),
    )
    trip = load_trip(trip_file)
    boundaries = {}
    for regroup in (True, False):
        rec = reconstruct_trip(
            trip, meta.frame, replace(DEFAULT, SPLICE_REGROUP_ACROSS=regroup), smoothed=poses
        )
        scores = map_scores(
            [MapFeature(i.type, i.points_xy_world, i.style) for i in rec.instances], truth_map, true_xy
        )
        boundaries[regroup] = scores.per_type[ElementType.ROAD_BOUNDARY]
    assert boundaries[True].completeness > boundaries[False].completeness + 0.01
    assert boundaries[True].correctness >= boundaries[False].correctness - 0.002


def test_observed_points_densified_see_a_vertex_between_two_points_as_given():
    # observations 1 m apart along x; a vertex 0.3 m beside the middle of a step is 0.58 m from
    # both points as given, but 0.3 m from the observed line: within a 0.4 m gate once the
    # polyline is densified to 0.25 m, and not as given
    from csr_core.single_trip.paint_breaks import ObservedPoints

    points = np.column_stack([np.arange(0.0, 5.5, 1.0), np.zeros(6)])
    vertex = np.array([[2.5, 0.3], [2.0, 0.1], [2.5, 0.6]])
    assert ObservedPoints(points).seen(vertex, 0.4).tolist() == [False, True, False]
    assert ObservedPoints(points, np.array([0, 6]), 0.25).seen(vertex, 0.4).tolist() == [True, True, False]
    # two detections side by side: no step is inserted between one's last point and the next's first
    two = ObservedPoints(
        np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0], [6.0, 0.0]]), np.array([0, 2, 4]), 0.25
    )
    assert two.seen(np.array([[3.0, 0.0]]), 0.4).tolist() == [False]


def test_component_labels_number_components_as_scipy_does():
    # the union-find that regroups a track's observations must label exactly as scipy's
    # connected_components (the splice iterates the labels in order), isolated nodes included
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from csr_core.single_trip.tracking import component_labels

    rng = np.random.default_rng(3)
    for _ in range(300):
        m, e = int(rng.integers(1, 30)), int(rng.integers(0, 40))
        a, b = rng.integers(0, m, e), rng.integers(0, m, e)
        expected = connected_components(coo_matrix((np.ones(e), (a, b)), shape=(m, m)), directed=False)[1]
        assert component_labels(m, a, b).tolist() == expected.tolist()
    assert component_labels(4, np.array([3]), np.array([1])).tolist() == [0, 1, 2, 1]


def _piece(start, end, k=6):
    return np.linspace(start, end, k)


def test_one_continuation_per_end_keeps_a_lane_with_its_straightest_connector():
    # a lane's centreline ends where two connectors start (straight on, and bearing off 8.5
    # degrees): all three pairs pass a pairwise test, but the lane continues into one of them
    # only, and the two connectors start side by side: they do not continue each other
    from csr_core.single_trip.tracking import one_continuation_per_end

    pieces = np.stack(
        [_piece((-20.0, 0.0), (0.0, 0.0)), _piece((0.0, 0.0), (20.0, 0.0)), _piece((0.0, 0.0), (10.0, 1.5))]
    )
    a, b = np.array([0, 0, 1]), np.array([1, 2, 2])
    keep = one_continuation_per_end(pieces, a, b, np.array([0.05, 0.30, 0.20]), np.zeros(3, dtype=bool))
    assert keep.tolist() == [True, False, False]


def test_one_continuation_per_end_keeps_a_line_split_in_pieces_whole():
    # one line seen as three pieces end to end: each joint joins its two neighbours, the pair of
    # the outer pieces (20 m apart) is left out and the three stay one component
    from csr_core.single_trip.tracking import component_labels, one_continuation_per_end

    pieces = np.stack(
        [
            _piece((-30.0, 0.0), (-10.5, 0.0)),
            _piece((-10.0, 0.0), (10.0, 0.0)),
            _piece((10.5, 0.0), (30.0, 0.0)),
        ]
    )
    a, b = np.array([0, 0, 1]), np.array([1, 2, 2])
    exempt = np.array([False, False, True])  # kept as it is, whatever the others say
    keep = one_continuation_per_end(pieces, a, b, np.zeros(3), exempt)
    assert keep.tolist() == [True, False, True]
    assert len(set(component_labels(3, a[keep], b[keep]).tolist())) == 1


def test_a_lane_and_its_connectors_are_one_track_without_the_rule_and_two_with_it():
    # a lane's centreline ends at the origin, where two connectors start (straight on, and bearing
    # off 6 degrees); ten frames see all three, short enough that each pair passes the
    # within-frame test. Without the rule they make one track; with it the lane continues into
    # the straight connector and the other one is a track of its own
    from csr_core.single_trip.tracking import track_elements
    from csr_core.types import PerceivedElement

    world = [
        _piece((-12.0, 0.0), (0.0, 0.0)),
        _piece((0.0, 0.0), (10.0, 0.0)),
        _piece((0.0, 0.0), (10.0, 1.0)),
    ]
    poses = np.column_stack([-30.0 + 2.0 * np.arange(10), np.zeros(10), np.zeros(10)])
    elements = tuple(
        tuple(PerceivedElement(ElementType.CENTERLINE, w - pose[:2]) for w in world) for pose in poses
    )
    frames, travel = np.arange(10), 2.0 * np.arange(10)

    def tracks_of(params):
        pieces, tracks = track_elements(frames, poses, travel, elements, params)
        return sorted(sorted(set(pieces.element[t.pieces].tolist())) for t in tracks)

    assert tracks_of(DEFAULT) == [[0, 1, 2]]
    assert tracks_of(replace(DEFAULT, TRACK_MERGE_ONE_PER_END=True)) == [[0, 1], [2]]
