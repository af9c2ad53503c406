"""Known answers of lane instance topology generation (paper III-E): association, robust
fusion, polygons, styles."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from csr_core.single_trip.splicing import resample_polyline
from csr_core.topology import generate_topology
from csr_core.topology.association import Member, associate_lines
from csr_core.topology.fusion import _consensus, absorb_pieces, fuse_group, project_on_polyline
from csr_core.topology.instances import is_zigzag, make_members
from csr_core.topology.params import DEFAULT
from csr_core.types import DividerStyle, ElementNoise, ElementType, TripInstance

pytestmark = pytest.mark.unit

LD = ElementType.LANE_DIVIDER
NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}


def _curve(x: np.ndarray, offset_m: float = 0.0) -> np.ndarray:
    """A gently curving road (y = 0.002 x^2), shifted left by ``offset_m`` along its normal."""
    y = 0.002 * x**2
    t = np.column_stack([np.ones_like(x), 0.004 * x])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return np.column_stack([x, y]) + offset_m * np.column_stack([-t[:, 1], t[:, 0]])


def _noisy(points: np.ndarray, rng: np.random.Generator, sigma_m: float, bias_m: float = 0.0) -> np.ndarray:
    """Correlated trip error: a lateral bias plus white noise per point."""
    return points + rng.normal(0.0, sigma_m, points.shape) + bias_m * np.array([0.0, 1.0])


def _distance_to(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    dense = np.column_stack(
        [np.interp(np.linspace(0, 1, 4000), np.linspace(0, 1, len(line)), line[:, i]) for i in (0, 1)]
    )
    _, d = project_on_polyline(points, dense)
    return np.abs(d)


def _trips(lines_per_trip: list[list[np.ndarray]], etype: ElementType = LD, styles=None) -> dict:
    out = {}
    for k, lines in enumerate(lines_per_trip):
        st = styles[k] if styles is not None else DividerStyle.SOLID
        out[f"veh-1__t{k:02d}"] = [TripInstance(etype, p, st, n_observations=10) for p in lines]
    return out


def _noise(trips: dict) -> dict:
    return {k: NOISE for k in trips}


def test_fusion_of_noisy_copies_converges_to_the_line() -> None:
    """N copies with a per-trip lateral bias (sigma 8 cm) and white noise: the fused line sits
    at the trips' mean bias (the weighted mean, equal weights) and the error shrinks as
    1 / sqrt(N)."""
    rng = np.random.default_rng(0)
    truth = _curve(np.arange(0.0, 120.0, 1.0))
    dense = np.column_stack(
        [np.interp(np.linspace(0, 1, 4000), np.linspace(0, 1, len(truth)), truth[:, i]) for i in (0, 1)]
    )
    for n_trips in (2, 8, 32):
        biases = rng.normal(0.0, 0.08, n_trips)
        trips = _trips([[_noisy(truth, rng, 0.05, b)] for b in biases])
        res = generate_topology(trips, _noise(trips))
        assert len(res.features) == 1
        f = res.features[0]
        assert f.properties["support_trips"] == n_trips
        _, d = project_on_polyline(f.points_xy_world, dense)
        # y-bias of a trip is its lateral offset times cos(slope) ~ the bias itself here
        assert np.mean(d) == pytest.approx(np.mean(biases), abs=0.015)
        assert np.mean(np.abs(d)) < 0.015 + 3 * 0.08 / np.sqrt(n_trips)


def test_partial_overlaps_fuse_into_one_instance_covering_the_whole() -> None:
    rng = np.random.default_rng(1)
    x = np.arange(0.0, 200.0, 1.0)
    truth = _curve(x)
    parts = [(0, 120), (40, 160), (80, 200)]  # each trip sees a different 60 %
    trips = _trips([[_noisy(truth[a:b], rng, 0.04, 0.03 * (k - 1))] for k, (a, b) in enumerate(parts)])
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) == 1
    f = res.features[0].points_xy_world
    length = float(np.linalg.norm(np.diff(f, axis=0), axis=1).sum())
    true_length = float(np.linalg.norm(np.diff(truth, axis=0), axis=1).sum())
    assert length == pytest.approx(true_length, rel=0.03)
    assert np.max(_distance_to(f, truth)) < 0.15


def test_parallel_dividers_a_lane_apart_stay_two() -> None:
    rng = np.random.default_rng(2)
    x = np.arange(0.0, 100.0, 1.0)
    trips = _trips([[_noisy(_curve(x), rng, 0.05), _noisy(_curve(x, 3.5), rng, 0.05)] for _ in range(4)])
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) == 2
    assert all(f.properties["support_trips"] == 4 for f in res.features)


def test_robust_fit_ignores_one_trip_bent_by_a_metre() -> None:
    rng = np.random.default_rng(3)
    x = np.arange(0.0, 150.0, 1.0)
    truth = _curve(x)
    lines = [_noisy(truth, rng, 0.04) for _ in range(5)]
    bent = lines[0].copy()
    # one trip's alignment bent sideways by 1 m over 30 m (5 m ramps): a plain mean moves 20 cm
    bent[:, 1] += np.clip(np.minimum(x - 55.0, 95.0 - x) / 5.0, 0.0, 1.0)
    lines[0] = bent
    trips = _trips([[p] for p in lines])
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) >= 1
    main = max(res.features, key=lambda f: f.properties["support_trips"])
    assert main.properties["support_trips"] == 5
    d = _distance_to(main.points_xy_world, truth)
    assert np.max(d) < 0.08
    assert np.mean(d) < 0.02


def test_noisy_crosswalk_rectangles_fuse_into_one() -> None:
    rng = np.random.default_rng(4)
    rect = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 10.0], [0.0, 10.0]])
    polys = []
    for k in range(7):
        p = rect + rng.normal(0.0, 0.08, rect.shape) + rng.normal(0.0, 0.05, 2)
        polys.append([np.roll(p, k % 4, axis=0)])  # vertex order differs per trip
    trips = _trips(polys, ElementType.CROSSWALK, styles=[None] * 7)
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) == 1
    out = res.features[0].points_xy_world
    assert out.shape == (4, 2)
    err = np.min(np.linalg.norm(out[:, None] - rect[None], axis=2), axis=1)
    assert np.max(err) < 0.15
    assert res.features[0].properties["support_trips"] == 7


def test_divider_style_by_weighted_vote() -> None:
    rng = np.random.default_rng(5)
    truth = _curve(np.arange(0.0, 80.0, 1.0))
    styles = [
        DividerStyle.DASHED,
        DividerStyle.DASHED,
        DividerStyle.SOLID,
        DividerStyle.UNKNOWN,
        DividerStyle.DASHED,
    ]
    trips = _trips([[_noisy(truth, rng, 0.05)] for _ in styles], styles=styles)
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) == 1
    assert res.features[0].style == DividerStyle.DASHED
    assert res.features[0].properties["style"] == "dashed"


def test_properties_support_uncertainty_and_times() -> None:
    rng = np.random.default_rng(6)
    truth = _curve(np.arange(0.0, 60.0, 1.0))
    trips = _trips([[_noisy(truth, rng, 0.05)] for _ in range(3)])
    times = {k: f"2026-11-0{i + 1}T10:00:00Z" for i, k in enumerate(trips)}
    res = generate_topology(trips, _noise(trips), trip_times=times)
    p = res.features[0].properties
    assert p["support_observations"] == 30
    assert p["first_seen"] == "2026-11-01T10:00:00Z" and p["last_confirmed"] == "2026-11-03T10:00:00Z"
    # three trips of sigma hypot(0.05, 0.10): standard error about 0.11 / sqrt(3)
    assert 0.03 < p["uncertainty_m"] < 0.12


def test_reposition_instances_round_trip() -> None:
    """Instances placed with one set of poses, moved to another related by a known rigid
    correction, land where that correction puts them; moving back restores them."""
    from csr_core.se2 import compose, transform_points
    from csr_core.topology import reposition_instances

    x = np.arange(0.0, 100.0, 1.0)
    from_poses = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    correction = np.array([0.7, -0.4, 0.01])  # to_T_from
    to_poses = np.array([compose(correction, p) for p in from_poses])
    inst = TripInstance(LD, np.column_stack([x[10:60], np.full(50, 3.5)]), DividerStyle.SOLID, 5, 8, 62)
    (moved,) = reposition_instances([inst], from_poses, to_poses)
    np.testing.assert_allclose(
        moved.points_xy_world, transform_points(correction, inst.points_xy_world), atol=1e-9
    )
    (back,) = reposition_instances([moved], to_poses, from_poses)
    np.testing.assert_allclose(back.points_xy_world, inst.points_xy_world, atol=1e-9)
    assert moved.style == DividerStyle.SOLID and moved.n_observations == 5


def test_a_zigzag_trip_instance_is_left_out() -> None:
    """A splice that hopped between two neighbouring lines (a sideways oscillation of 3 m every
    10 m) is not a road shape: it is rejected before association, the others fuse."""
    rng = np.random.default_rng(7)
    x = np.arange(0.0, 100.0, 1.0)
    truth = _curve(x)
    lines = [[_noisy(truth, rng, 0.04)] for _ in range(3)]
    zigzag = truth + np.column_stack([np.zeros_like(x), 1.5 + 1.5 * np.sin(2 * np.pi * x / 10.0)])
    trips = _trips([*lines, [zigzag]])
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) == 1 and res.features[0].properties["support_trips"] == 3
    assert [m.trip_key for m in res.rejected_members] == ["veh-1__t03"]


def _drive(segments: list[tuple[float, float]], step_m: float = 0.5) -> np.ndarray:
    """A line from (length m, curvature 1/m) pieces, heading integrated from the origin."""
    kappa = np.concatenate([np.full(int(length / step_m), k) for length, k in segments])
    heading = np.concatenate([[0.0], np.cumsum(kappa * step_m)])
    return np.vstack(
        [[0.0, 0.0], np.cumsum(step_m * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)]
    )


def test_a_roundabout_pass_and_corners_are_road_shapes_not_zigzags() -> None:
    """Roads curve, and a line through a roundabout turns right, left round the island and right
    again: 3.4 rad over 58 m with little net turning (the rule before this one, turning per metre
    and total / net turning, rejected such lines). With centimetres of noise it keeps its turning
    when smoothed and is not rejected, nor is a boundary with corners; a sideways wobble of 0.7 m
    every 12 m is."""
    rng = np.random.default_rng(11)
    roundabout = _drive([(10.0, 0.0), (7.0, -0.1), (24.0, 1.0 / 12.0), (7.0, -0.1), (10.0, 0.0)])
    corners = resample_polyline(
        np.array([[0.0, 0.0], [20.0, 0.0], [35.0, -8.0], [50.0, -12.0], [58.0, -25.0]]), 0.5
    )
    for line in (roundabout, corners):
        assert not is_zigzag(line + rng.normal(0.0, 0.03, line.shape), DEFAULT)
    x = np.arange(0.0, 60.0, 0.5)
    wobble = np.column_stack([x, 0.7 * np.sin(2 * np.pi * x / 12.0)])
    assert is_zigzag(wobble + rng.normal(0.0, 0.03, wobble.shape), DEFAULT)


def test_crosswalk_outlines_with_different_vertex_counts_still_associate() -> None:
    """Trips splice outlines with 4, 5 or 6 vertices: association must not need equal counts."""
    rng = np.random.default_rng(6)
    rect = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 10.0], [0.0, 10.0]])
    polys = []
    for k in range(6):
        p = rect + rng.normal(0.0, 0.05, rect.shape)
        rows = [p[0], (p[0] + p[1]) / 2, p[1], p[2], (p[2] + p[3]) / 2, p[3]]  # midpoints: same shape
        drop = {0: [1, 4], 1: [4], 2: []}[k % 3]
        polys.append([np.array([r for i, r in enumerate(rows) if i not in drop])])
    trips = _trips(polys, ElementType.CROSSWALK, styles=[None] * 6)
    res = generate_topology(trips, _noise(trips))
    assert len(res.features) == 1
    import shapely

    outline = shapely.Polygon(rect).exterior
    out = shapely.points(res.features[0].points_xy_world)
    assert np.max(shapely.distance(out, outline)) < 0.15


def test_neighbour_searches_do_not_depend_on_the_block_size(monkeypatch) -> None:
    import csr_core.topology.association as association

    rng = np.random.default_rng(11)
    x = np.linspace(0.0, 60.0, 61)
    members = [
        association.Member(
            f"veh-1__t{k:02d}",
            0,
            TripInstance(LD, _noisy(_curve(x, lane * 3.5), rng, 0.05), DividerStyle.SOLID, n_observations=10),
            0.05,
        )
        for k in range(12)
        for lane in (0, 1)
    ]
    samples = association.sample_members(members, 1.0)
    gates = np.full(len(members), 0.3)
    one_block = association.nearest_offsets(samples, 2.0, 1.0, False, 0.3)
    consensus = _consensus(samples.points_xy, samples.owner, gates, len(members))
    monkeypatch.setattr(association, "NEIGHBOUR_BLOCK_SAMPLES", 37)
    small_blocks = association.nearest_offsets(samples, 2.0, 1.0, False, 0.3)
    np.testing.assert_array_equal(
        _consensus(samples.points_xy, samples.owner, gates, len(members)), consensus
    )
    # a sample agrees with at most the 11 other copies of its lane (never its own member, never
    # the other lane), and most samples with most of them
    per_sample = (consensus - 1e-3 * np.bincount(samples.owner)) / np.bincount(samples.owner)
    assert per_sample.max() <= 11.0 + 1e-9 and np.median(per_sample) > 8.0
    for whole, blocked in zip(one_block, small_blocks, strict=True):
        np.testing.assert_array_equal(whole, blocked)
    a, member, lateral, inside = one_block
    # every sample sees the other 11 copies of its own lane (the other lane is 3.5 m away) ...
    assert set(np.bincount(a, minlength=len(samples.owner))) == {11}
    assert np.all(member % 2 == samples.owner[a] % 2)
    # ... a few centimetres across (two 5 cm noisy copies)
    assert np.median(lateral[inside]) < 0.1


def _rounded(nodes: list[tuple[float, float]], corner_m: float = 10.0) -> np.ndarray:
    """A path through ``nodes`` (metres), sampled every metre, its corners rounded (a quadratic
    Bezier over ``corner_m`` either side): a lane centreline through a turn."""
    out = [np.asarray(nodes[0], float)[None]]
    for k in range(1, len(nodes)):
        a, b = np.asarray(nodes[k - 1], float), np.asarray(nodes[k], float)
        d = (b - a) / np.linalg.norm(b - a)
        start = a + (corner_m * d if k > 1 else 0.0)
        stop = b - (corner_m * d if k < len(nodes) - 1 else 0.0)
        t = np.arange(1.0, np.linalg.norm(stop - start) + 1e-9, 1.0)[:, None]
        out.append(start + t * d)
        if k < len(nodes) - 1:
            nxt = np.asarray(nodes[k + 1], float)
            e = (nxt - b) / np.linalg.norm(nxt - b)
            u = np.linspace(0.0, 1.0, 17)[1:-1, None]
            p0, p2 = b - corner_m * d, b + corner_m * e
            out.append((1 - u) ** 2 * p0 + 2 * u * (1 - u) * b + u**2 * p2)
    return np.vstack(out)


def test_a_street_grid_chained_by_turns_fuses_into_one_line_per_street() -> None:
    """A 6 x 6 street grid: trips see parts of its twelve streets, and at junctions trips turning
    from a street into the crossing one see the turn's centreline, which overlaps both streets:
    every street and turn is one association group (as in a city). One fusion of that group
    gives many streets at once, not one; and in the map each block two or more trips saw comes
    out as exactly one line on it, supported by each of those trips."""
    rng = np.random.default_rng(5)
    block, size, n = 100.0, 500.0, 6
    trips = {}
    seen: dict[tuple[int, int], set[str]] = {}
    for k in range(96):
        key = f"veh-1__t{k:02d}"
        if k < 60:  # a part of one street, either way
            street, c = k % (2 * n), block * (k % n)
            a0 = float(rng.uniform(0.0, 0.4 * size))
            a1 = float(rng.uniform(a0 + 0.5 * size, size))
            along = np.arange(a0, a1, 1.0)
            line = (
                np.column_stack([along, np.full_like(along, c)])
                if street < n
                else np.column_stack([np.full_like(along, c), along])
            )
            line = line[::-1] if rng.random() < 0.5 else line
            for b in range(n - 1):  # the blocks whose middle it saw
                if a0 <= (b + 0.25) * block and a1 >= (b + 0.75) * block:
                    seen.setdefault((street, b), set()).add(key)
        else:  # a turn at a junction: 25 m of a row, the corner, 25 m of a column
            x, y = block * rng.integers(1, n - 1), block * rng.integers(1, n - 1)
            line = _rounded([(x - 25.0, y), (x, y), (x, y + 25.0)])
        trips[key] = [
            TripInstance(
                ElementType.CENTERLINE,
                _noisy(line, rng, 0.03, rng.normal(0.0, 0.05)),
                None,
                n_observations=10,
            )
        ]

    def one_line_per_block(lines: list[np.ndarray], trips_of_line: list[set[str]], among: set[str]) -> int:
        checked = 0
        for (street, b), keys in seen.items():
            keys = keys & among
            if len(keys) < 2:
                continue
            along = np.linspace((b + 0.25) * block, (b + 0.75) * block, 51)
            c = np.full_like(along, block * (street % n))
            middle = shapely.points(np.column_stack([along, c] if street < n else [c, along]))
            on_it = [
                k
                for k, line in enumerate(lines)
                if np.median(shapely.distance(middle, shapely.LineString(line))) < 0.5
            ]
            assert len(on_it) == 1, (street, b, len(on_it))
            assert np.max(shapely.distance(middle, shapely.LineString(lines[on_it[0]]))) < 0.15
            assert trips_of_line[on_it[0]] >= keys
            checked += 1
        return checked

    members = make_members(trips, _noise(trips), DEFAULT)[0][ElementType.CENTERLINE]
    group = max(associate_lines(members, ElementType.CENTERLINE, DEFAULT), key=len)
    assert len(group) >= 0.75 * len(members)
    # one fusion of the group gives the streets that do not cross each other (the crossing ones
    # were offered those lines at the junctions and wait for the next round)
    fused, _ = fuse_group([members[k] for k in group], ElementType.CENTERLINE, DEFAULT)
    streets = [f.points_xy_world for f in fused if shapely.LineString(f.points_xy_world).length > 0.5 * size]
    assert len(streets) >= n // 2
    for xy in streets:  # each along one street: straight, on the grid
        assert min(np.ptp(xy[:, 0]), np.ptp(xy[:, 1])) < 1.0
        assert (
            np.min(np.abs(np.median(xy, axis=0) / block - np.round(np.median(xy, axis=0) / block))) * block
            < 0.2
        )
    result = generate_topology(trips, _noise(trips))
    lines = [f for f in result.features if f.type == ElementType.CENTERLINE]
    assert (
        one_line_per_block(
            [f.points_xy_world for f in lines], [set(f.properties["trips"]) for f in lines], set(trips)
        )
        >= 30
    )


def test_a_peeled_piece_along_a_fused_line_joins_it_and_others_stay() -> None:
    """``absorb_pieces``: a piece within its gate of a fused line and parallel to it joins that
    line; one a lane away, one crossing it, and one only half along it stay pieces; one that
    runs on past the line's end joins it and leaves what lies past the end as a piece."""
    x = np.arange(0.0, 80.0, 1.0)
    line = np.column_stack([x, np.zeros_like(x)])
    other = np.column_stack([x, np.full_like(x, 10.0)])

    def piece(xy: np.ndarray) -> Member:
        return Member("veh-1__t00", 0, TripInstance(ElementType.CENTERLINE, xy, None, n_observations=5), 0.1)

    xs = np.arange(20.0, 50.0, 1.0)
    along = piece(np.column_stack([xs, np.full_like(xs, 0.1)]))
    lane_away = piece(np.column_stack([xs, np.full_like(xs, 3.0)]))
    crossing = piece(np.column_stack([np.full_like(xs, 40.0), xs - 35.0]))
    half = piece(np.column_stack([np.arange(60.0, 100.0, 1.0), np.zeros(40)]))
    on_other = piece(np.column_stack([xs, np.full_like(xs, 9.95)]))
    runs_on = piece(np.column_stack([np.arange(40.0, 90.0, 1.0), np.zeros(50)]))  # 10 m past the end
    absorbed, rest = absorb_pieces(
        [along, lane_away, crossing, half, on_other, runs_on], [line, other], DEFAULT
    )
    assert absorbed == [(0, 0), (4, 1), (5, 0)]
    assert rest[:3] == [lane_away, crossing, half]
    # what runs on past the line's end stays a piece, to be fused with whatever else goes on there
    assert len(rest) == 4 and rest[3].trip_key == runs_on.trip_key
    assert (
        8.0 <= np.ptp(rest[3].instance.points_xy_world[:, 0]) <= 10.0
        and rest[3].instance.points_xy_world[:, 0].min() > 79.0
    )


def test_a_line_fused_twice_becomes_one_and_its_turn_stays() -> None:
    """``merge_twins``: a twin (the lane again, 0.2 m off, then a turn off it) gives its trips to
    the better supported lane and keeps only the turn; a twin of a line one trip saw, and a
    line a lane away, stay as they are."""
    from csr_core.topology.fusion import FusedInstance, merge_twins

    def fused(xy: np.ndarray, trips: range) -> tuple[FusedInstance, tuple[Member, ...]]:
        mem = tuple(
            Member(
                f"veh-1__t{k:02d}", 0, TripInstance(ElementType.CENTERLINE, xy, None, n_observations=5), 0.2
            )
            for k in trips
        )
        return FusedInstance(
            ElementType.CENTERLINE, xy, None, tuple(range(len(mem))), (), 0.05, 1.0, 0.0, (), 0.0
        ), mem

    x = np.arange(0.0, 100.5, 0.5)
    lane = fused(np.column_stack([x, np.zeros_like(x)]), range(0, 6))
    angle = np.linspace(0.0, np.pi / 2, 32)[1:]  # a right turn of 10 m radius at x = 100
    turn = np.column_stack([100.0 + 10.0 * np.sin(angle), -10.0 + 10.0 * np.cos(angle) + 0.2])
    xs = np.arange(40.0, 100.5, 0.5)
    twin = fused(np.vstack([np.column_stack([xs, np.full_like(xs, 0.2)]), turn]), range(6, 9))
    next_lane = fused(np.column_stack([x, np.full_like(x, 3.5)]), range(9, 12))
    out = merge_twins([lane, twin, next_lane], DEFAULT)
    assert len(out) == 3
    (f_lane, m_lane), (f_next, m_next), (f_turn, m_turn) = out
    assert f_lane is lane[0] and {m.trip_key for m in m_lane} == {f"veh-1__t{k:02d}" for k in range(9)}
    assert f_next is next_lane[0] and m_next == next_lane[1]
    # the turn is what is left of the twin: it starts near the lane's end and bends away
    assert m_turn == twin[1] and f_turn.points_xy_world[0, 0] > 95.0 and f_turn.points_xy_world[-1, 1] < -8.0
    # the best supported of two twins seen by one trip each is no evidence: both stay
    single = merge_twins([(lane[0], lane[1][:1]), (twin[0], twin[1][:1])], DEFAULT)
    assert len(single) == 2
