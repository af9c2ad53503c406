"""A trip held by nothing but its own GNSS is marked failed; a registered one is not.

Known answers on small graphs: three trips on a straight road along x, each with a chain of
sub-maps; registrations either observe both directions (well constrained) or only across the
road (a straight road without landmarks: along-track unobservable)."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.alignment.association import PairMatch
from csr_core.alignment.graph_matching import ElementSet
from csr_core.alignment.observability import UNOBSERVABLE, own_gnss_error_m, unobservable_reason
from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.pose_graph import optimize_submap_poses
from csr_core.alignment.registration import register_elements
from csr_core.types import ElementType
from tests.unit.test_alignment_synthetic import make_scenario, submaps_every_20_frames

pytestmark = pytest.mark.unit

P = AlignmentParams(mark_unobservable=True)  # the gain is computed only when marking is on
FULL = np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.002**2])
ACROSS_ONLY = np.diag([1 / 20.0**2, 1 / 0.05**2, 1 / 0.002**2])  # lines along x: no along-track information


def _graph(along_info_for_trip2: np.ndarray, leak_along: float = 0.0):
    """Trips 0, 1, 2 with a sub-map every 20 frames; trips 0-1 registered with full information,
    trip 2 to both with ``along_info_for_trip2``; ``leak_along``: share of the start pose the
    trip-2 registrations keep along the road (``PairMatch.prior_sensitivity``)."""
    trips, _ = make_scenario(3, seed=3, length_m=150.0, perception=False)
    subs, by_trip = submaps_every_20_frames(trips)
    matches = []
    for n in range(min(len(v) for v in by_trip.values())):
        for i, j, info in ((0, 1, FULL), (0, 2, along_info_for_trip2), (1, 2, along_info_for_trip2)):
            si, sj = by_trip[i][n], by_trip[j][n]
            leak = np.diag([leak_along, 0.0, 0.0]) if j == 2 else np.zeros((3, 3))
            matches.append(
                PairMatch(
                    si.submap_id,
                    sj.submap_id,
                    i,
                    j,
                    n,
                    si.world_T_submap[:2].copy(),
                    np.zeros(3),
                    info,
                    ((0, 0),),
                    ((0, 0),),
                    np.full(1, 0.9),
                    0.9,
                    0.03,
                    1.0,
                    prior_sensitivity=leak,
                )
            )
    return trips, subs, matches


def _gain_along_across(res, subs, trip):
    g = np.array([res.own_gnss_gain[s.submap_id] for s in subs if s.trip_index == trip])
    yaw = np.array([s.world_T_submap[2] for s in subs if s.trip_index == trip])
    along = np.array([[np.cos(y), np.sin(y)] for y in yaw])
    # response along the road to a shift along the road, across to across
    ga = np.einsum("ni,nij,nj->n", along, g, along)
    across = np.column_stack([-along[:, 1], along[:, 0]])
    gc = np.einsum("ni,nij,nj->n", across, g, across)
    return float(np.median(ga)), float(np.median(gc))


def test_own_gnss_gain_is_one_along_an_unobserved_road_and_shared_across():
    trips, subs, matches = _graph(ACROSS_ONLY)
    res = optimize_submap_poses(trips, subs, matches, P)
    along, across = _gain_along_across(res, subs, 2)
    assert along == pytest.approx(1.0, abs=0.05)  # only its own GNSS holds it along the road
    assert across < 0.5  # the registrations share it with the other two trips
    along0, across0 = _gain_along_across(res, subs, 0)
    assert along0 < 0.7 and across0 < 0.5


def test_own_gnss_gain_is_shared_when_registrations_observe_both_directions():
    trips, subs, matches = _graph(FULL)
    res = optimize_submap_poses(trips, subs, matches, P)
    along, across = _gain_along_across(res, subs, 2)
    assert along == pytest.approx(1 / 3, abs=0.1) and across == pytest.approx(1 / 3, abs=0.1)


def test_a_registration_that_repeats_the_gnss_along_the_road_does_not_count_as_holding_it():
    """Full information, but the registration kept the start (GNSS) pose along the road: the
    trip is as unobserved along the road as without it."""
    trips, subs, matches = _graph(FULL, leak_along=1.0)
    res = optimize_submap_poses(trips, subs, matches, P)
    along, _ = _gain_along_across(res, subs, 2)
    assert along == pytest.approx(1.0, abs=0.1)


def test_trip_held_only_by_its_gnss_is_marked_and_a_registered_trip_is_not():
    trips, subs, matches = _graph(ACROSS_ONLY)
    for t in trips:  # single fixes with a reported 0.6 m per axis (hard profile)
        t.trip.gnss_std_m[:] = 0.6
    res = optimize_submap_poses(trips, subs, matches, P)
    err = own_gnss_error_m(trips, subs, res.own_gnss_gain, {s.submap_id for s in subs})
    # unobserved along: ~0.6 m left along, a third of it across
    assert err[2].rms_m > P.max_own_gnss_error_m
    assert err[0].rms_m < P.max_own_gnss_error_m and err[1].rms_m < P.max_own_gnss_error_m
    assert unobservable_reason(err[2], P.max_own_gnss_error_m).startswith(UNOBSERVABLE + ":")
    res_full = optimize_submap_poses(trips, subs, _graph(FULL)[2], P)
    err_full = own_gnss_error_m(trips, subs, res_full.own_gnss_gain, {s.submap_id for s in subs})
    assert all(e.rms_m < P.max_own_gnss_error_m for e in err_full.values())


def test_registration_keeps_the_start_pose_along_parallel_lines_and_not_across():
    x = np.linspace(-20, 20, 41)
    lines = tuple(np.column_stack([x, np.full_like(x, y)]) for y in (-3.5, 0.0, 3.5))
    target = ElementSet((ElementType.LANE_DIVIDER,) * 3, lines)
    source = ElementSet(target.types, tuple(p + np.array([1.5, 0.3]) for p in lines))
    reg = register_elements(target, source, [(0, 0), (1, 1), (2, 2)], 0.1, P, landmarks=None)
    L = reg.prior_sensitivity
    assert L[0, 0] == pytest.approx(1.0, abs=1e-3)  # along the lines: the start pose stays
    assert abs(L[1, 1]) < 1e-2  # across: measured
    assert reg.delta_xyyaw[1] == pytest.approx(-0.3, abs=1e-3)
