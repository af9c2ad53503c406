"""Known answers of the centrelines derived from dividers, boundaries and the trips' paths
(``topology.derived_centerlines``, ``topology.derived_connectors``): a fleet whose perception
reports no centrelines still gets one per lane, beside kerbs as well as between painted lines,
and connectors where trips drove from one lane to the next."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from csr_core.topology import DEFAULT, generate_topology, update_topology
from csr_core.topology.derived_centerlines import derive_centerlines, is_derived
from csr_core.topology.instances import path_probes
from csr_core.topology.lane_graph import build_lane_graph
from csr_core.types import DividerStyle, ElementNoise, ElementType, MapFeature, TripInstance

pytestmark = pytest.mark.unit

LD, RB, CL = ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY, ElementType.CENTERLINE
NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}
LANE_M, SHOULDER_M = 3.5, 0.5


def _line(y_m: float, x0: float = 0.0, x1: float = 200.0) -> np.ndarray:
    x = np.arange(x0, x1 + 0.5, 1.0)
    return np.column_stack([x, np.full(len(x), y_m)])


def _two_way_road(x0: float = 0.0, x1: float = 200.0) -> list[MapFeature]:
    """Two lanes each way (3.5 m): a solid centre line, a dashed line between the lanes of each
    direction, kerbs half a metre beyond the outer lanes. ``support_trips`` 5, 4, 3, 2, 1 from
    the centre line out."""
    kerb = 2 * LANE_M + SHOULDER_M

    def f(
        etype: ElementType, y: float, fid: str, support: int, style: DividerStyle | None = None
    ) -> MapFeature:
        return MapFeature(
            etype, _line(y, x0, x1), style, fid, {"uncertainty_m": 0.05, "support_trips": support}
        )

    return [
        f(LD, 0.0, "ld-centre", 5, DividerStyle.SOLID),
        f(LD, -LANE_M, "ld-right", 4, DividerStyle.DASHED),
        f(LD, LANE_M, "ld-left", 3, DividerStyle.DASHED),
        f(RB, -kerb, "rb-right", 2),
        f(RB, kerb, "rb-left", 1),
    ]


def _wander(path: np.ndarray, seed: int, sigma_m: float = 0.15) -> np.ndarray:
    """A driver's slow wander across the lane (zero mean over the road)."""
    rng = np.random.default_rng(seed)
    x = path[:, 0]
    phase = rng.uniform(0, 2 * np.pi, 2)
    off = (
        sigma_m
        * (np.sin(2 * np.pi * x / 70 + phase[0]) + np.sin(2 * np.pi * x / 130 + phase[1]))
        / np.sqrt(2)
    )
    return path + np.column_stack([np.zeros(len(x)), off])


def _centrelines(features: list[MapFeature]) -> list[MapFeature]:
    return [f for f in features if f.type == CL]


def test_a_two_way_road_without_centrelines_gets_one_per_lane() -> None:
    """Eastbound trips in both lanes of their side: each of them gets a centreline, the inner one
    midway between its dividers, the kerb-side one half a painted lane in from its divider (the
    kerb's shoulder measured from where the trips drove, not assumed), pointing east. Of the
    other side only the lane between two dividers: assumed to run the same way; its kerb-side
    strip, which nobody drove, could be parking or a cycle lane. Each lane is as well supported
    as its less supported edge."""
    inner, outer = -LANE_M / 2, -1.5 * LANE_M
    paths = {f"veh__t{k}": _wander(_line(inner if k < 3 else outer), seed=k) for k in range(5)}
    derived = derive_centerlines(_two_way_road(), path_probes(paths), DEFAULT)
    by_y = sorted(derived, key=lambda f: float(np.mean(f.points_xy_world[:, 1])))
    assert len(by_y) == 3
    kerb_side, driven, assumed = by_y
    for f, y_true in ((kerb_side, outer), (driven, inner), (assumed, -inner)):
        y = f.points_xy_world[:, 1]
        assert float(np.max(np.abs(y - y_true))) < 0.05, (y_true, float(np.max(np.abs(y - y_true))))
        assert f.points_xy_world[-1, 0] - f.points_xy_world[0, 0] > 150  # runs along the road, eastwards
    assert kerb_side.properties["shoulder_m"] == pytest.approx(SHOULDER_M, abs=0.05)
    assert kerb_side.properties["derived_from"] == ["ld-right", "rb-right"]
    assert sorted(driven.properties["derived_from"]) == ["ld-centre", "ld-right"]
    assert [f.properties["direction"] for f in by_y] == ["driven", "driven", "assumed"]
    assert driven.properties["support_trips"] == 4 and len(driven.properties["trips"]) == 5
    assert kerb_side.properties["support_trips"] == 2 and assumed.properties["support_trips"] == 3


def test_a_perceived_centreline_takes_precedence() -> None:
    """A lane that has a perceived centreline gets no derived one; the lane beside it still does."""
    road = _two_way_road() + [MapFeature(CL, _line(-LANE_M / 2 + 0.1), None, "cl-seen", {})]
    derived = derive_centerlines(road, path_probes({"veh__t0": _line(-LANE_M / 2)}), DEFAULT)
    assert len(derived) == 1
    assert float(np.mean(derived[0].points_xy_world[:, 1])) == pytest.approx(LANE_M / 2, abs=0.05)


def test_a_strip_wider_than_a_lane_is_left_alone() -> None:
    """Divider and kerb 8 m apart (a divider missing, or a parking strip): no centreline guessed."""
    road = [
        MapFeature(LD, _line(0.0), DividerStyle.SOLID, "ld", {}),
        MapFeature(RB, _line(-8.0), None, "rb", {}),
    ]
    assert derive_centerlines(road, path_probes({"veh__t0": _line(-2.0)}), DEFAULT) == []


def _turn_path(radius_m: float = 12.0) -> np.ndarray:
    """East along y = -1.75 to x = 100, a left quarter turn, north along x = 100 + radius."""
    y0 = -LANE_M / 2
    a = np.linspace(-np.pi / 2, 0.0, 40)
    arc = np.column_stack([100 + radius_m * np.cos(a), y0 + radius_m + radius_m * np.sin(a)])
    north = np.column_stack(
        [np.full(100, 100 + radius_m), np.linspace(y0 + radius_m, y0 + radius_m + 100, 100)]
    )
    return np.vstack([_line(y0, 0.0, 100.0), arc[1:], north[1:]])


def test_a_junction_connector_from_the_trips_that_turned() -> None:
    """Two perceived lanes ending and starting 19 m apart around a corner, and trips that drove
    from one to the other: a connector along their mean path, from the first lane's end to the
    second's start, which the lane graph links as a successor of the one and predecessor of the
    other."""
    r, y0 = 12.0, -LANE_M / 2
    east = MapFeature(CL, _line(y0, 0.0, 95.0), None, "cl-east", {"uncertainty_m": 0.05})
    north_xy = np.column_stack([np.full(96, 100 + r), np.linspace(y0 + r + 5, y0 + r + 100, 96)])
    north = MapFeature(CL, north_xy, None, "cl-north", {"uncertainty_m": 0.05})
    paths = {f"veh__t{k}": _turn_path(r) for k in range(2)}
    derived = derive_centerlines([east, north], path_probes(paths), DEFAULT)
    assert len(derived) == 1
    c = derived[0]
    assert c.properties["derived_from"] == ["cl-east", "cl-north"] and c.properties["support_trips"] == 2
    assert np.linalg.norm(c.points_xy_world[0] - east.points_xy_world[-1]) < 1.1
    assert np.linalg.norm(c.points_xy_world[-1] - north.points_xy_world[0]) < 1.1
    # on the turn: its distance from the corner's centre stays near the radius
    inner = c.points_xy_world[(c.points_xy_world[:, 0] > 100.5) & (c.points_xy_world[:, 1] < y0 + r - 0.5)]
    radius = np.linalg.norm(inner - np.array([100.0, y0 + r]), axis=1)
    assert len(inner) > 5 and float(np.max(np.abs(radius - r))) < 0.1
    graph = build_lane_graph([east, north, replace(c, feature_id="cl-turn")], DEFAULT)
    assert graph.successors("cl-east#0") == ["cl-turn#0"] and graph.successors("cl-turn#0") == ["cl-north#0"]


def test_a_lane_change_is_no_connector() -> None:
    """Two same-direction lanes with perceived centrelines; a trip changes from one to the other
    in their middles: nothing to connect (the lane graph's neighbours say it)."""
    lanes = [MapFeature(CL, _line(-1.75), None, "cl-a", {}), MapFeature(CL, _line(1.75), None, "cl-b", {})]
    x = np.arange(0.0, 200.5, 1.0)
    y = -1.75 + 3.5 * np.clip((x - 80) / 30, 0, 1)
    assert derive_centerlines(lanes, path_probes({"veh__t0": np.column_stack([x, y])}), DEFAULT) == []


def _fleet(keys: list[str], y_path: float) -> tuple[dict, dict, dict, dict]:
    """Trips that saw the two-way road's divider and kerbs (no centreline) and drove its right lane."""
    inst, noise, times, paths = {}, {}, {}, {}
    for k, key in enumerate(keys):
        inst[key] = [
            TripInstance(f.type, f.points_xy_world.copy(), f.style, n_observations=20)
            for f in _two_way_road()
        ]
        noise[key], times[key] = NOISE, f"2026-01-0{k + 1}T00:00:00Z"
        paths[key] = _wander(_line(y_path), seed=k)
    return inst, noise, times, paths


def test_derived_centrelines_in_the_map_keep_their_ids_and_follow_updates() -> None:
    """Through ``generate_topology`` and ``update_topology``: the derived lanes are map features
    (lane graph included), keep their ids when a trip is added, and their support grows."""
    inst, noise, times, paths = _fleet(["veh__t0", "veh__t1"], -LANE_M / 2)
    first = generate_topology(inst, noise, trip_times=times, paths_xy_per_trip=paths)
    lanes = [f for f in _centrelines(list(first.features)) if is_derived(f)]
    assert len(lanes) == 2 and len(first.lane_graph.graph) >= 2
    inst2, noise2, times2, paths2 = _fleet(["veh__t2"], -LANE_M / 2)
    times2 = {"veh__t2": "2026-01-09T00:00:00Z"}
    second = update_topology(first, inst2, noise2, trip_times=times2, paths_xy_per_trip=paths2)
    again = [f for f in _centrelines(list(second.features)) if is_derived(f)]
    assert sorted(f.feature_id for f in again) == sorted(f.feature_id for f in lanes)
    driven = next(f for f in again if f.properties["direction"] == "driven")
    assert driven.properties["support_trips"] == 3
    assert driven.properties["last_confirmed"] == "2026-01-09T00:00:00Z"
    rebuilt = generate_topology(
        {**inst, **inst2},
        {**noise, **noise2},
        previous=second,
        trip_times={**times, **times2},
        paths_xy_per_trip={**paths, **paths2},
    )
    assert sorted(f.feature_id for f in _centrelines(list(rebuilt.features)) if is_derived(f)) == sorted(
        f.feature_id for f in lanes
    )
