"""Stable ids, incremental updates, the lane graph and automatic validation (paper III-E)."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.errors import ReconstructionError
from csr_core.topology import DEFAULT, generate_topology, update_topology
from csr_core.topology.lane_graph import build_lane_graph
from csr_core.types import DividerStyle, ElementNoise, ElementType, MapFeature, TripInstance

pytestmark = pytest.mark.unit

NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}


def _road(x0: float, length_m: float = 150.0, n_lines: int = 3) -> list[tuple[ElementType, np.ndarray]]:
    """A straight road along x: boundaries at y = 0 and y = 3.5 * (n_lines - 1), dividers between."""
    x = np.arange(x0, x0 + length_m, 1.0)
    out = []
    for k in range(n_lines):
        etype = ElementType.ROAD_BOUNDARY if k in (0, n_lines - 1) else ElementType.LANE_DIVIDER
        out.append((etype, np.column_stack([x, np.full_like(x, 3.5 * k)])))
    return out


def _trip(elements, rng: np.random.Generator, shift_y_m: float = 0.0) -> list[TripInstance]:
    bias = rng.normal(0.0, 0.05)
    return [
        TripInstance(
            t,
            p + rng.normal(0.0, 0.04, p.shape) + [0.0, bias + shift_y_m],
            DividerStyle.DASHED if t == ElementType.LANE_DIVIDER else None,
            n_observations=12,
        )
        for t, p in elements
    ]


def _build(n_trips: int, seed: int, start: int = 0) -> tuple[dict, dict]:
    rng = np.random.default_rng(seed)
    trips = {f"veh-1__t{start + k:02d}": _trip(_road(0.0), rng) for k in range(n_trips)}
    return trips, {k: NOISE for k in trips}


def test_stable_ids_survive_adding_trips_rebuild_and_incremental() -> None:
    trips, noise = _build(3, seed=10)
    first = generate_topology(trips, noise, trip_times={k: k for k in trips})
    assert len(first.features) == 3
    more, more_noise = _build(3, seed=11, start=3)
    # rebuild with all trips, ids continue
    rebuilt = generate_topology(
        {**trips, **more},
        {**noise, **more_noise},
        previous=first,
        trip_times={k: k for k in {**trips, **more}},
    )
    assert sorted(f.feature_id for f in rebuilt.features) == sorted(f.feature_id for f in first.features)
    assert all(f.properties["support_trips"] == 6 for f in rebuilt.features)
    # incremental update, ids continue, first_seen kept, last_confirmed moves on
    updated = update_topology(first, more, more_noise, trip_times={k: k for k in more})
    by_id = {f.feature_id: f for f in updated.features}
    assert set(by_id) == {f.feature_id for f in first.features}
    for f in first.features:
        g = by_id[f.feature_id]
        assert g.properties["support_trips"] == 6
        assert g.properties["first_seen"] == "veh-1__t00"
        assert g.properties["last_confirmed"] == "veh-1__t05"


def test_incremental_update_leaves_untouched_instances_alone() -> None:
    rng = np.random.default_rng(12)
    trips = {f"veh-1__t{k}": _trip(_road(0.0), rng) + _trip(_road(500.0), rng) for k in range(3)}
    noise = {k: NOISE for k in trips}
    first = generate_topology(trips, noise)
    assert len(first.features) == 6
    new = {"veh-2__t0": _trip(_road(500.0), rng)}  # only the second road
    updated = update_topology(first, new, {"veh-2__t0": NOISE})
    old = {f.feature_id: f for f in first.features}
    for f in updated.features:
        if f.points_xy_world[:, 0].mean() < 250:
            assert f.points_xy_world is old[f.feature_id].points_xy_world
            assert f.properties["support_trips"] == 3
        else:
            assert f.properties["support_trips"] == 4
    assert updated.timings_s["refit_features"] == 3


def test_a_trip_already_in_the_map_cannot_be_added_again() -> None:
    trips, noise = _build(2, seed=13)
    first = generate_topology(trips, noise)
    with pytest.raises(ReconstructionError):
        update_topology(first, {"veh-1__t00": trips["veh-1__t00"]}, noise)


def _cl(fid: str, points: np.ndarray) -> MapFeature:
    return MapFeature(ElementType.CENTERLINE, points, None, fid, {})


def test_split_and_merge_are_in_the_lane_graph() -> None:
    x = np.arange(0.0, 200.0, 1.0)
    main = _cl("main", np.column_stack([x, np.zeros_like(x)]))
    # a turn lane leaves the main lane at x = 100 (tangent at first), bends off to the right
    t = np.arange(0.0, 60.0, 1.0)
    turn = _cl("turn", np.column_stack([100.0 + t, -0.004 * t**2]))
    # an on-ramp joins the main lane at x = 150, arriving tangentially from the left
    r = np.arange(-60.0, 0.5, 1.0)
    ramp = _cl("ramp", np.column_stack([150.0 + r, 0.004 * r**2]))
    # a parallel lane on the left, same direction
    left = _cl("left", np.column_stack([x, np.full_like(x, 3.5)]))
    # a lane continuing the main one after a junction gap of 1 m
    x2 = np.arange(201.0, 260.0, 1.0)
    after = _cl("after", np.column_stack([x2, np.zeros_like(x2)]))
    lg = build_lane_graph([main, turn, ramp, left, after], DEFAULT)
    main_lanes = lg.lanes_of("main")
    assert len(main_lanes) == 3  # cut at the split (100 m) and the merge (150 m)
    first, middle, last = sorted(main_lanes)
    assert set(lg.successors(first)) == {middle, "turn#0"}
    assert set(lg.predecessors(last)) == {middle, "ramp#0"}
    assert lg.successors(last) == ["after#0"]
    assert lg.predecessors("after#0") == [last]
    assert len(lg.split_points_xy) == 1 and np.allclose(lg.split_points_xy[0], [100.0, 0.0], atol=1.0)
    assert len(lg.merge_points_xy) == 1 and np.allclose(lg.merge_points_xy[0], [150.0, 0.0], atol=1.0)
    assert lg.neighbour(first, "left") == "left#0"
    assert lg.neighbour("left#0", "right") in main_lanes


def test_a_split_just_after_a_merge_hands_over_from_the_right_pieces() -> None:
    # a ramp joins the main lane at x = 99.6 and a turn lane leaves it at x = 100: the two cuts
    # are one bound (closer than 1 m); the turn leaves from the piece ending there, not the next
    x = np.arange(0.0, 200.0, 1.0)
    main = _cl("main", np.column_stack([x, np.zeros_like(x)]))
    r = np.arange(-60.0, 0.5, 1.0)
    ramp = _cl("ramp", np.column_stack([99.6 + r, 0.004 * r**2]))
    t = np.arange(0.0, 60.0, 1.0)
    turn = _cl("turn", np.column_stack([100.0 + t, -0.004 * t**2]))
    lg = build_lane_graph([main, ramp, turn], DEFAULT)
    first, second = sorted(lg.lanes_of("main"))
    assert set(lg.successors(first)) == {second, "turn#0"}
    assert lg.successors(second) == []
    assert second in lg.successors("ramp#0")  # (and the turn: it starts where the ramp ends)


def test_tile_with_a_planted_bad_trip_is_flagged() -> None:
    rng = np.random.default_rng(14)
    trips = {}
    for k in range(6):
        # road A in tile (0, 0); road B in tile (2, 0); trip 0 is misaligned by 1.2 m on road A
        trips[f"veh-1__t{k}"] = _trip(_road(10.0), rng, 1.2 if k == 0 else 0.0) + _trip(_road(420.0), rng)
    res = generate_topology(trips, {k: NOISE for k in trips})
    good, bad = res.tile_quality[(2, 0)], res.tile_quality[(0, 0)]
    assert good.score == 1.0 and good.flags == ()
    assert bad.score < 0.9
    kinds = {fl.kind for fl in res.flags if fl.tile == (0, 0)}
    assert {"low_support", "implausible_lane_width"} <= kinds
    # the six-trip instances of road A stay right; the bad trip's copies are the flagged ones
    for f in res.features:
        if f.points_xy_world[:, 0].mean() < 200:
            suspect = bool(f.properties["flags"])
            assert suspect == (f.properties["trips"] == ["veh-1__t0"])


def test_a_match_pair_with_a_high_residual_flags_the_instances_near_it() -> None:
    from types import SimpleNamespace

    trips, noise = _build(4, seed=15)
    pair = SimpleNamespace(
        centre_xy_world=(70.0, 3.0), residual_rms_m=0.5, trip_key_i="veh-1__t00", trip_key_j="veh-1__t01"
    )  # alignment.MatchPairRecord fields used
    fine = SimpleNamespace(
        centre_xy_world=(70.0, 3.0), residual_rms_m=0.1, trip_key_i="veh-1__t00", trip_key_j="veh-1__t01"
    )
    flagged = generate_topology(trips, noise, match_pairs=[pair])
    assert all("high_residual_pair" in f.properties["flags"] for f in flagged.features)
    clean = generate_topology(trips, noise, match_pairs=[fine])
    assert not any("high_residual_pair" in f.properties["flags"] for f in clean.features)
