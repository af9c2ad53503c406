"""Unit tests of ``topology.unseen_tails``: a fused line's end stretch that one trip alone saw."""

import numpy as np
import pytest

from csr_core.topology.association import Member
from csr_core.topology.instances import path_probes
from csr_core.topology.params import DEFAULT
from csr_core.topology.unseen_tails import TypePoints, trim_unseen_tails
from csr_core.types import DividerStyle, ElementType, MapFeature, TripInstance

pytestmark = pytest.mark.unit


def _line(x0: float, x1: float, y: float = 0.0) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, 1.0)
    return np.column_stack([x, np.full(len(x), y)])


def _member(trip: str, x0: float, x1: float) -> Member:
    inst = TripInstance(
        ElementType.LANE_DIVIDER,
        _line(x0, x1),
        DividerStyle.DASHED,
        n_observations=10,
        first_frame=0,
        last_frame=9,
    )
    return Member(trip, 0, inst, 0.1)


def _fused(x0: float, x1: float, trips: list[str]) -> MapFeature:
    return MapFeature(
        ElementType.LANE_DIVIDER,
        _line(x0, x1),
        DividerStyle.DASHED,
        "ld-1",
        {"trips": trips, "support_trips": len(trips)},
    )


def test_type_points_count_the_trips_that_cover_each_vertex():
    support, trips = TypePoints([_member("a", 0.0, 10.0), _member("b", 5.0, 10.0)], 0.5).support(
        _line(0.0, 10.0)
    )
    assert support.tolist() == [1] * 5 + [2] * 6
    assert trips[0] == ["a"] and trips[10] == ["a", "b"]


@pytest.mark.parametrize(("others_drive_past", "head_x"), [(True, 20.0), (False, 0.0)])
def test_a_tail_one_trip_saw_is_cut_only_where_others_drove_past_unseen(others_drive_past, head_x):
    # five trips saw the line from x = 20 to 60; trip "a" alone saw it from x = 0. Where the others
    # also drove along x = 0..20 (their paths 3 m beside it) and saw nothing there, that stretch
    # goes; where they joined the road at x = 20 (a side road), it stays
    trips = ["a", "b", "c", "d", "e"]
    members = {"ld-1": tuple([_member("a", 0.0, 60.0)] + [_member(t, 20.0, 60.0) for t in trips[1:]])}
    start = -10.0 if others_drive_past else 20.0
    paths = path_probes({t: _line(-10.0 if t == "a" else start, 70.0, 3.0) for t in trips})
    out, n_cut = trim_unseen_tails([_fused(0.0, 60.0, trips)], members, paths, DEFAULT, DEFAULT.END_WINDOW_M)
    assert out[0].points_xy_world[0, 0] == pytest.approx(head_x)
    assert n_cut == int(others_drive_past)
    assert out[0].points_xy_world[-1, 0] == pytest.approx(60.0)


def test_a_tail_other_trips_saw_in_pieces_of_their_own_stays():
    # as above with the others driving past, but two of them saw x = 0..20 as a piece of their
    # own, fused into another feature: the stretch was seen by three trips, not one
    trips = ["a", "b", "c", "d", "e"]
    members = {
        "ld-1": tuple([_member("a", 0.0, 60.0)] + [_member(t, 20.0, 60.0) for t in trips[1:]]),
        "ld-2": (_member("b", 0.0, 19.0), _member("c", 0.0, 19.0)),
    }
    paths = path_probes({t: _line(-10.0, 70.0, 3.0) for t in trips})
    out, n_cut = trim_unseen_tails([_fused(0.0, 60.0, trips)], members, paths, DEFAULT, DEFAULT.END_WINDOW_M)
    assert n_cut == 0
    assert out[0].points_xy_world[0, 0] == pytest.approx(0.0)
