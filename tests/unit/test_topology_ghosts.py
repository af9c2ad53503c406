"""Negative evidence against ghosts (paper III-E, automatic validation): a line that several
trips drove alongside without seeing is held back from the map (``TopologyResult.suppressed``)
until more trips confirm it; a line on a road only one trip drove, or one the others only crossed,
stays."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.topology import DEFAULT, generate_topology
from csr_core.topology.instances import path_probes
from csr_core.topology.validation import passing_counts
from csr_core.types import DividerStyle, ElementNoise, ElementType, MapFeature, TripInstance

pytestmark = pytest.mark.unit

LD = ElementType.LANE_DIVIDER
NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}
X = np.arange(0.0, 200.0 + 1e-9, 1.0)


def _along_x(y_m: float, x0: float = 0.0, x1: float = 200.0) -> np.ndarray:
    x = X[(X >= x0) & (X <= x1)]
    return np.column_stack([x, np.full_like(x, y_m)])


def _along_y(x_m: float) -> np.ndarray:
    return np.column_stack([np.full_like(X, x_m), X - 100.0])


def _instances(lines: list[np.ndarray]) -> list[TripInstance]:
    return [TripInstance(LD, p, DividerStyle.SOLID, n_observations=10) for p in lines]


def _topology(instances: dict[str, list[np.ndarray]], paths: dict[str, np.ndarray]):
    return generate_topology(
        {k: _instances(v) for k, v in instances.items()},
        {k: NOISE for k in instances},
        paths_xy_per_trip=paths,
    )


def _near(features, y_m: float, x_m: float = 100.0) -> list[MapFeature]:
    out = []
    for f in features:
        p = np.asarray(f.points_xy_world)
        if np.min(np.hypot(p[:, 0] - x_m, p[:, 1] - y_m)) < 0.5:
            out.append(f)
    return out


def test_a_line_one_trip_saw_and_three_drove_alongside_without_seeing_is_held_back() -> None:
    # four trips drive the road (path y = 0); all see the dividers at y = +-1.75, one also a
    # ghost copy at y = 5.25 (a lane further out)
    real = [_along_x(1.75), _along_x(-1.75)]
    instances = {f"veh-1__t{k}": list(real) for k in range(4)}
    instances["veh-1__t0"] = [*real, _along_x(5.25, 60.0, 140.0)]
    paths = {k: _along_x(0.0) for k in instances}
    result = _topology(instances, paths)
    assert not _near(result.features, 5.25), "the ghost is published"
    held = _near(result.suppressed, 5.25)
    assert len(held) == 1 and held[0].properties["passed_trips"] == 3
    assert len(_near(result.features, 1.75)) == 1 and len(_near(result.features, -1.75)) == 1


def test_held_back_needs_enough_trips_alongside() -> None:
    # the same ghost with only two other trips on the road: not enough evidence, published (flagged)
    real = [_along_x(1.75), _along_x(-1.75)]
    instances = {f"veh-1__t{k}": list(real) for k in range(3)}
    instances["veh-1__t0"] = [*real, _along_x(5.25, 60.0, 140.0)]
    result = _topology(instances, {k: _along_x(0.0) for k in instances})
    ghost = _near(result.features, 5.25)
    assert len(ghost) == 1 and ghost[0].properties["passed_trips"] == 2
    assert "low_support" in ghost[0].properties["flags"]


def test_a_line_of_a_road_only_one_trip_drove_stays_in_the_map() -> None:
    # trip 0 drives along y = 0 and sees its divider; three other trips cross that road at x = 100
    # (paths along x = 100): they passed the line but never had it alongside
    instances = {"veh-1__t0": [_along_x(1.75)]}
    paths = {"veh-1__t0": _along_x(0.0)}
    for k in range(1, 4):
        instances[f"veh-2__t{k}"] = [_along_y(101.75)]
        paths[f"veh-2__t{k}"] = _along_y(100.0)
    result = _topology(instances, paths)
    line = _near(result.features, 1.75)
    assert len(line) == 1 and line[0].properties["passed_trips"] == 0
    assert not result.suppressed


def test_passing_counts_want_the_path_alongside_within_reach() -> None:
    line = MapFeature(LD, _along_x(1.75, 50.0, 150.0), DividerStyle.SOLID, "f", {"trips": ["seen"]})
    paths = path_probes(
        {
            "seen": _along_x(0.0),  # saw it: never counted
            "alongside": _along_x(-3.5),  # 5.25 m beside it, same direction
            "opposite": _along_x(8.0)[::-1],  # 6.25 m beside it, driving the other way
            "far": _along_x(1.75 + DEFAULT.PASS_LATERAL_M + 5.0),  # beyond the lateral reach
            "crossing": _along_y(100.0),  # crosses it
            "short": _along_x(0.0, 0.0, 70.0),  # alongside a fifth of it only
        }
    )
    assert passing_counts([line], paths, DEFAULT) == [2]
    crosswalk = MapFeature(ElementType.CROSSWALK, np.array([[0.0, 0], [4, 0], [4, 3], [0, 3]]), None, "c", {})
    assert passing_counts([crosswalk], paths, DEFAULT) == [0]  # polygons: no along-the-road evidence
