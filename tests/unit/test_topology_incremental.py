"""Known answers of the incremental map update (``topology.incremental``): the map's instance
stands for its members, so adding trips one by one must give the map a batch fusion gives,
keep curves, carry the statistics over, and reject a bad new trip."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.topology import generate_topology, update_topology
from csr_core.topology.fusion import project_on_polyline
from csr_core.types import DividerStyle, ElementNoise, ElementType, TripInstance

pytestmark = pytest.mark.unit

LD = ElementType.LANE_DIVIDER
CL = ElementType.CENTERLINE
NOISE = {t: ElementNoise(0.05, 0.2, 100) for t in ElementType}


def _arc(radius_m: float, start_rad: float, stop_rad: float, step_m: float = 1.0) -> np.ndarray:
    n = int(abs(stop_rad - start_rad) * radius_m / step_m) + 1
    a = np.linspace(start_rad, stop_rad, n)
    return radius_m * np.column_stack([np.cos(a), np.sin(a)])


def _dense(line: np.ndarray) -> np.ndarray:
    u = np.linspace(0, 1, len(line))
    return np.column_stack([np.interp(np.linspace(0, 1, 8000), u, line[:, i]) for i in (0, 1)])


def _lateral_to(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    return np.abs(project_on_polyline(points, _dense(line))[1])


def _trip(
    key: str, lines: list[np.ndarray], etype: ElementType = LD, t: str = "2026-01-01T00:00:00Z"
) -> tuple:
    return (
        {key: [TripInstance(etype, p, DividerStyle.SOLID, n_observations=10) for p in lines]},
        {key: NOISE},
        {key: t},
    )


def _noisy_copy(truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A trip's view: a lateral bias of 6 cm (1 sigma) and 3 cm white noise."""
    tan = np.gradient(truth, axis=0)
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    normal = np.column_stack([-tan[:, 1], tan[:, 0]])
    return truth + rng.normal(0.0, 0.06) * normal + rng.normal(0.0, 0.03, truth.shape)


def _only(result, etype: ElementType = LD):
    feats = [f for f in result.features if f.type == etype]
    assert len(feats) == 1, [f.properties["support_trips"] for f in feats]
    return feats[0]


def test_adding_trips_one_by_one_keeps_a_tight_curve() -> None:
    """A 25 m radius quarter circle, 3 trips then 30 more one at a time: the line stays on the
    arc (smoothing the map's line again at every update would pull it inwards a little more
    each time) and as close to it as the batch fusion of all 33 trips."""
    rng = np.random.default_rng(3)
    truth = _arc(25.0, 0.0, np.pi / 2)
    trips = [
        _trip(f"veh-1__t{k:02d}", [_noisy_copy(truth, rng)], t=f"2026-01-01T00:{k:02d}:00Z")
        for k in range(33)
    ]

    def merged(parts) -> tuple[dict, dict, dict]:
        inst: dict = {}
        noise: dict = {}
        times: dict = {}
        for i, n, t in parts:
            inst.update(i), noise.update(n), times.update(t)
        return inst, noise, times

    batch = generate_topology(*merged(trips[:33])[:2], trip_times=merged(trips)[2])
    state = generate_topology(*merged(trips[:3])[:2], trip_times=merged(trips[:3])[2])
    for inst, noise, times in trips[3:]:
        state = update_topology(state, inst, noise, trip_times=times)
    line, ref = _only(state).points_xy_world, _only(batch).points_xy_world
    inner = slice(5, -5)  # ends: where each trip happened to stop
    err = _lateral_to(line[inner], truth)
    assert float(np.sqrt(np.mean(err**2))) < 0.04, float(np.sqrt(np.mean(err**2)))
    radius = np.linalg.norm(line[inner], axis=1)
    assert abs(float(np.median(radius)) - 25.0) < 0.03  # not flattened inwards
    assert float(np.max(_lateral_to(line[inner], ref))) < 0.05
    props = _only(state).properties
    assert props["support_trips"] == 33 and len(props["trips"]) == 33
    assert props["first_seen"] == "2026-01-01T00:00:00Z" and props["last_confirmed"] == "2026-01-01T00:32:00Z"
    assert props["uncertainty_m"] < 0.03  # about 6 cm / sqrt(33), not one trip's sigma
    assert 0.5 < props["scatter_ratio"] < 2.0


def test_a_new_trip_a_metre_off_is_rejected_and_does_not_move_the_line() -> None:
    rng = np.random.default_rng(5)
    truth = np.column_stack([np.arange(0.0, 80.0), np.zeros(80)])
    parts = [_trip(f"veh-1__t{k:02d}", [_noisy_copy(truth, rng)]) for k in range(10)]
    inst = {k: v for p in parts for k, v in p[0].items()}
    state = generate_topology(inst, {k: NOISE for k in inst})
    before = _only(state).points_xy_world
    bent = truth.copy()
    bent[30:50, 1] += 1.0  # a metre off over 20 m (e.g. a wrongly spliced detection)
    state = update_topology(state, *_trip("veh-9__bad", [bent])[:2])
    # the bent run is peeled off and stands alone, flagged; the divider keeps its line
    main, *rest = sorted(
        (f for f in state.features if f.type == LD), key=lambda f: -f.properties["support_trips"]
    )
    assert float(np.max(_lateral_to(main.points_xy_world[3:-3], before))) < 0.02
    assert main.properties["support_trips"] == 11
    assert all(
        f.properties["trips"] == ["veh-9__bad"] and set(f.properties["flags"]) - {"outlier_trip"}
        for f in rest
    )
    stray = np.concatenate([f.points_xy_world for f in rest]) if rest else np.zeros((0, 2))
    assert len(stray) and float(np.median(stray[:, 1])) > 0.8  # what was peeled off is the bent run


def test_trips_chained_through_lane_changes_fuse_with_their_kind() -> None:
    """Trip centrelines are paths: trips that change lanes chain the lanes into one association
    group, and the lane-change trips are outnumbered by each lane's own. Each lane is fused from
    its trips, and the lane-change paths with each other: none is left on its own (the profile
    along a backbone comes from the samples alongside it, not from the lane next to it)."""
    rng = np.random.default_rng(7)
    x = np.arange(0.0, 200.0, 1.0)
    lane_a, lane_b, lane_c = (np.column_stack([x, np.full_like(x, y)]) for y in (0.0, 3.5, 7.0))
    change_ab = np.column_stack([x, np.clip((x - 90.0) / 20.0, 0.0, 1.0) * 3.5])
    change_bc = np.column_stack([x, 3.5 + np.clip((x - 90.0) / 20.0, 0.0, 1.0) * 3.5])
    paths = [lane_a] * 6 + [change_ab] * 4 + [lane_b] * 12 + [change_bc] * 4 + [lane_c] * 14
    inst = {
        f"veh-1__t{k:02d}": [TripInstance(CL, p + rng.normal(0.0, 0.04, p.shape), None, 10)]
        for k, p in enumerate(paths)
    }
    result = generate_topology(inst, {k: NOISE for k in inst})
    long_ones = [f for f in result.features if f.type == CL and len(f.points_xy_world) > 40]
    assert min(f.properties["support_trips"] for f in long_ones) >= 4, sorted(
        f.properties["support_trips"] for f in long_ones
    )
    for lane, n_trips in ((lane_a, 6), (lane_b, 12), (lane_c, 14)):
        on = [
            f
            for f in long_ones
            if float(np.percentile(_lateral_to(f.points_xy_world, lane), 90)) < 0.1
            and len(f.points_xy_world) > 150
        ]
        assert on, f"no fused centreline along the lane at y={lane[0, 1]}"
        assert max(f.properties["support_trips"] for f in on) >= n_trips
