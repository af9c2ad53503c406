"""GNSS-bias messages between tiles: another alignment's estimate of a trip's bias as a prior on
its bias chain (csr_core.alignment.bias_messages)."""

from __future__ import annotations

import numpy as np
import pytest

from csr_core.alignment import GnssBiasMessage, bias_message
from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.pose_graph import optimize_submap_poses
from tests.unit.test_alignment_synthetic import (
    make_trip,
    submaps_every_20_frames,
    truth_elements,
    truth_trajectory,
)

pytestmark = pytest.mark.unit

PARAMS = AlignmentParams(gnss_bias_tau_s=300.0)
OFFSET_XY_M = (0.8, 0.5)


def _lone_trip():
    """One trip on a 400 m road with a constant GNSS offset, nothing to register with."""
    rng = np.random.default_rng(0)
    truth = truth_trajectory(0, False, rng, 400.0)
    trip = make_trip("veh0__t0", truth, truth_elements(400.0), rng, offset_xy=OFFSET_XY_M, perception=False)
    subs, _ = submaps_every_20_frames([trip])
    return trip, truth, subs


def _mean_error_xy(res, subs, truth) -> np.ndarray:
    return np.mean([res.poses_xyyaw[s.submap_id][:2] - truth[s.anchor_frame][:2] for s in subs], axis=0)


def test_a_message_from_a_tile_that_knew_the_bias_moves_a_lone_trip_onto_the_truth():
    trip, truth, subs = _lone_trip()
    alone = _mean_error_xy(optimize_submap_poses([trip], subs, [], PARAMS), subs, truth)
    assert np.linalg.norm(alone) > 0.8  # held by nothing but its own GNSS: the offset stays
    t_mid = float(np.median(trip.trip.timestamps_s))
    told = GnssBiasMessage(t_mid, (-OFFSET_XY_M[0], -OFFSET_XY_M[1]), 0.01**2)  # 10 trips agreed elsewhere
    moved = _mean_error_xy(
        optimize_submap_poses([trip], subs, [], PARAMS, bias_messages={trip.trip.key: [told]}), subs, truth
    )
    assert np.linalg.norm(moved) < 0.25 * np.linalg.norm(alone)
    # a message about the same trip an hour away says nothing about its bias now (Gauss-Markov decay)
    stale = GnssBiasMessage(t_mid + 3600.0, told.bias_xy_m, told.variance_m2)
    unmoved = _mean_error_xy(
        optimize_submap_poses([trip], subs, [], PARAMS, bias_messages={trip.trip.key: [stale]}), subs, truth
    )
    assert np.allclose(unmoved, alone, atol=1e-6)


def test_a_weak_message_moves_the_trip_less_than_a_firm_one():
    trip, truth, subs = _lone_trip()
    t_mid = float(np.median(trip.trip.timestamps_s))
    shift = {}
    for n_trips in (1, 20):
        msg = bias_message(
            np.full(5, t_mid),
            np.zeros((5, 2)),
            np.tile(-np.array(OFFSET_XY_M), (5, 1)),
            np.ones(5),
            n_trips,
            PARAMS,
        )
        res = optimize_submap_poses([trip], subs, [], PARAMS, bias_messages={trip.trip.key: [msg]})
        shift[n_trips] = np.linalg.norm(_mean_error_xy(res, subs, truth) - np.array(OFFSET_XY_M))
    assert shift[1] < shift[20]  # one trip's word against twenty trips' consensus
    assert shift[20] > 0.8 * np.linalg.norm(OFFSET_XY_M)


def test_the_message_of_a_tile_is_its_weighted_mean_shift_and_its_consensus_variance():
    own = np.zeros((4, 2))
    aligned = np.array([[1.0, 0.0], [1.0, 0.0], [3.0, 2.0], [9.0, 9.0]])
    msg = bias_message(
        np.array([10.0, 20.0, 30.0, 40.0]), own, aligned, np.array([1.0, 1.0, 2.0, 0.0]), 4, PARAMS
    )
    assert msg.bias_xy_m == pytest.approx((2.0, 1.0))
    assert msg.t_s == pytest.approx(22.5)
    assert msg.variance_m2 == pytest.approx(PARAMS.gnss_bias_share * PARAMS.gnss_sigma_base_xy_m**2 / 4)
    assert bias_message(np.zeros(2), own[:2], aligned[:2], np.zeros(2), 4, PARAMS) is None
