"""Looping routes: an approach, laps of the shortest loop of the lane graph, a standstill at the
start and stops anywhere."""

import numpy as np
import pytest

from csr_core.sim import profiles
from csr_core.sim.routes import drive, looping_route
from csr_core.sim.worlds import load_world

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("world_name", ["roundabout", "urban"])
def test_a_looping_route_laps_a_short_loop_after_a_short_approach(world_name):
    world = load_world(world_name)
    traffic = profiles.loops().traffic
    route = looping_route(world, np.random.default_rng(3), 2000.0, traffic)
    path = route.path_xy
    length_m = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    assert 1900.0 < length_m <= 2000.0
    # laps: the path comes back to where it was a loop earlier, many times
    cell = {tuple(c) for c in np.floor(path / 5.0).astype(int).tolist()}
    visited_m = 5.0 * len(cell)
    assert visited_m < 0.6 * length_m
    # the first stop is a standstill at the start, within the profile's range
    assert route.stops_s_m[0] == 0.0
    assert traffic.start_standstill_s[0] <= route.stops_wait_s[0] <= traffic.start_standstill_s[1]
    truth = drive(route, np.random.default_rng(4), traffic)
    still = truth.speed_mps[: int(traffic.start_standstill_s[0] * traffic.frame_rate_hz)]
    assert np.all(still < 0.05)


def test_profiles_other_than_loops_draw_no_looping_route():
    for name in ("standard", "hard", "noiseless"):
        assert profiles.get_profile(name).traffic.loop_route_share == 0.0


def test_a_world_without_a_loop_gives_an_ordinary_route():
    world = load_world("a9")  # one carriageway, one direction
    route = looping_route(world, np.random.default_rng(5), 800.0, profiles.loops().traffic)
    assert float(np.linalg.norm(np.diff(route.path_xy, axis=0), axis=1).sum()) > 700.0
