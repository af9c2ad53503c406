"""The bench's fleet-density figure (trips per place) and the ``dense`` set built on it."""

import numpy as np
import pytest

from csr_core.bench.evaluate import SAME_ROAD_RADIUS_M, trips_per_place
from csr_core.bench.sets import DENSE_TRIPS, VALIDATOR_FLEETS, WORLDS, scenario_set

pytestmark = pytest.mark.unit


def _straight(y_m: float, x0_m: float, x1_m: float) -> np.ndarray:
    x = np.arange(x0_m, x1_m, 1.0)
    return np.column_stack([x, np.full_like(x, y_m)])


def test_trips_per_place_counts_the_trips_that_drive_within_the_radius():
    # three trips on one two-way road (lanes 3.5 m apart) and one on a road 50 m away
    paths = {
        "a": _straight(0.0, 0.0, 200.0),
        "b": _straight(3.5, 0.0, 200.0),
        "c": _straight(0.0, 0.0, 200.0),
        "far": _straight(50.0, 0.0, 200.0),
    }
    # frames of a, b, c see 3 trips, the far trip's frames 1: median over the four equal-length paths
    assert trips_per_place(paths) == 3.0
    assert trips_per_place({"far": paths["far"]}) == 1.0
    # a road farther than the radius does not count
    assert trips_per_place({"a": paths["a"], "x": _straight(SAME_ROAD_RADIUS_M + 0.5, 0.0, 200.0)}) == 1.0


def test_trips_per_place_counts_only_where_the_trips_overlap():
    # two trips that share the first 50 m of 200: most frames see only their own trip
    paths = {
        "a": _straight(0.0, 0.0, 200.0),
        "b": np.vstack([_straight(0.0, 0.0, 50.0), _straight(30.0, 50.0, 200.0)]),
    }
    assert trips_per_place(paths) == 1.0
    assert np.isnan(trips_per_place({}))


def test_the_dense_set_is_every_world_at_its_dense_fleet_size():
    specs = scenario_set("dense")
    assert [s.world for s in specs] == list(WORLDS)
    assert [s.trips for s in specs] == [DENSE_TRIPS[w] for w in WORLDS]
    assert all(s.profile == "standard" and s.trips >= 20 for s in specs)


def test_the_validator_set_is_the_six_hard_fleets_it_has_been_measured_on():
    specs = scenario_set("validator")
    assert [(s.world, s.seed) for s in specs] == list(VALIDATOR_FLEETS)
    assert all(s.profile == "hard" and s.trips == 8 and s.trip_length_m == 1500.0 for s in specs)
    assert specs[0].name == "urban-hard-8x-1500m-s5"


def test_the_real_map_set_is_every_shipped_real_map_at_both_profiles_and_three_seeds():
    from csr_core.bench.sets import REAL_MAP_WORLDS, STANDARD_SEEDS
    from csr_core.sim.worlds import WORLD_NAMES

    assert set(REAL_MAP_WORLDS) <= set(WORLD_NAMES)
    specs = scenario_set("real-maps")
    assert {(s.world, s.profile, s.seed, s.fleet) for s in specs} == {
        (w, p, seed, f)
        for w in REAL_MAP_WORLDS
        for p in ("standard", "hard")
        for seed in STANDARD_SEEDS
        for f in ("a", "b")
    }
    assert len({s.name for s in specs}) == len(specs)
    quick = scenario_set("real-maps-quick")
    assert [(s.world, s.fleet) for s in quick] == [(w, f) for f in ("a", "b") for w in REAL_MAP_WORLDS]
    assert quick[0].name == "karlsruhe-standard-10x-1500m-s1" and quick[-1].name.endswith(
        "-fleetb-10x-1500m-s1"
    )
    assert all(s.profile == "loops" for s in scenario_set("loops"))


def test_the_worst_trip_is_the_largest_raw_per_trip_rmse():
    from types import SimpleNamespace

    from csr_core.bench.tables import worst_trip_rmse_m

    truth = {"a": _straight(0.0, 0.0, 10.0), "b": _straight(0.0, 0.0, 10.0)}
    est = {"a": truth["a"] + [0.0, 0.3], "b": truth["b"] + [4.0, 0.0]}
    ev = SimpleNamespace(true_xy_by_key=truth, est_xy_by_key=est)
    assert worst_trip_rmse_m(ev) == pytest.approx(4.0)
    assert np.isnan(worst_trip_rmse_m(SimpleNamespace(true_xy_by_key=truth, est_xy_by_key={})))
