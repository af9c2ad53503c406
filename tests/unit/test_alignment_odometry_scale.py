"""Each trip's odometry scale as a variable of the pose graph (e^sm scaled by 1 + k)."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import K, S

from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.pose_graph import (
    build_factor_graph,
    gauss_newton,
    optimize_submap_poses,
    scaled_chain_factor,
)
from tests.unit.test_alignment_synthetic import (
    make_trip,
    submaps_every_20_frames,
    true_registration,
    truth_elements,
    truth_trajectory,
)

pytestmark = pytest.mark.unit

SCALED = AlignmentParams(odom_scale_sigma=0.003)
FIXED_SCALE = replace(SCALED, odom_scale_sigma=0.0)


def test_scaled_chain_jacobians_match_numerical_derivatives():
    factor = scaled_chain_factor(
        S(0), S(1), K(0), np.array([20.0, 3.0, 0.3]), gtsam.noiseModel.Unit.Create(3)
    )
    values = gtsam.Values()
    values.insert(S(0), gtsam.Pose2(1.0, 2.0, 0.4))
    values.insert(S(1), gtsam.Pose2(15.0, 14.0, 0.8))
    values.insert(K(0), np.array([0.01]))
    analytic, _ = factor.linearize(values).jacobian()
    dims = ((S(0), 3), (S(1), 3), (K(0), 1))
    numeric = []
    for key, dim in dims:
        for d in range(dim):
            delta = gtsam.VectorValues()
            for other, n in dims:
                step = np.zeros(n)
                if other == key:
                    step[d] = 1e-6
                delta.insert(other, step)
            numeric.append(
                (factor.unwhitenedError(values.retract(delta)) - factor.unwhitenedError(values)) / 1e-6
            )
    np.testing.assert_allclose(analytic, np.array(numeric).T, atol=1e-4)


def _two_trips_one_stretched(scale_error: float):
    """Two trips along the same 400 m road, registered (true relative pose) at every sub-map; the
    second trip's smoothed trajectory is stretched by ``1 + scale_error`` about its start (its
    odometry scale off, as its single-trip calibration left it)."""
    rng = np.random.default_rng(2)
    elements = truth_elements(400.0)
    truths = [truth_trajectory(lane, False, rng, 400.0) for lane in (0, 1)]
    trips = [make_trip(f"veh{k}__t{k}", truths[k], elements, rng, perception=False) for k in range(2)]
    poses = trips[1].poses_xyyaw_world.copy()
    poses[:, :2] = poses[0, :2] + (1.0 + scale_error) * (poses[:, :2] - poses[0, :2])
    trips[1] = replace(trips[1], poses_xyyaw_world=poses)
    subs, by_trip = submaps_every_20_frames(trips)
    matches = [
        true_registration(si, sj, truths, n)
        for n, (si, sj) in enumerate(zip(by_trip[0], by_trip[1], strict=False))
    ]
    return trips, truths, subs, by_trip, matches


def _spread_m(res, truths, by_trip) -> float:
    """RMS over trip 1's sub-maps of its error relative to trip 0's nearest one (what a stretch
    leaves: the trips disagree more and more along the road)."""
    out = []
    for s0, s1 in zip(by_trip[0], by_trip[1], strict=False):
        e0 = res.poses_xyyaw[s0.submap_id][:2] - truths[0][s0.anchor_frame][:2]
        e1 = res.poses_xyyaw[s1.submap_id][:2] - truths[1][s1.anchor_frame][:2]
        out.append(np.sum(np.square(e1 - e0)))
    return float(np.sqrt(np.mean(out)))


def test_a_trip_stretched_by_its_odometry_scale_is_brought_back_by_the_registrations():
    trips, truths, subs, by_trip, matches = _two_trips_one_stretched(0.004)  # 1.5 m over the road
    scaled = optimize_submap_poses(trips, subs, matches, SCALED)
    fixed = optimize_submap_poses(trips, subs, matches, FIXED_SCALE)
    # the registrations say trip 1 is 0.4 % too long; its scale variable takes it (shared with
    # trip 0, whose own scale may move the other way: the GNSS priors fix the sum)
    k0, k1 = scaled.odom_scale_correction[0], scaled.odom_scale_correction[1]
    assert (1.0 + k1) * 1.004 / (1.0 + k0) == pytest.approx(1.0, abs=5e-4)
    assert _spread_m(scaled, truths, by_trip) < 0.01
    # with the scale fixed, the stiff e^sm chain holds the stretch against the registrations
    assert _spread_m(fixed, truths, by_trip) > 0.02


def test_without_registrations_the_scale_stays_at_its_prior():
    trips, _, subs, _, _ = _two_trips_one_stretched(0.004)
    res = optimize_submap_poses(trips, subs, [], SCALED)
    assert abs(res.odom_scale_correction[0]) < 1e-3 and abs(res.odom_scale_correction[1]) < 1e-3


def test_hand_gauss_newton_reaches_the_levenberg_marquardt_minimum_of_the_scaled_graph():
    trips, _, subs, _, matches = _two_trips_one_stretched(0.004)
    graph, initial, _, _, _ = build_factor_graph(trips, subs, matches, SCALED, with_scale=True)
    lm = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams()).optimize()
    gn = gauss_newton(graph, initial)
    assert graph.error(gn) == pytest.approx(graph.error(lm), rel=1e-6)
    assert graph.error(gn) < 0.01 * graph.error(initial)
    for key in (K(0), K(1)):
        assert gn.atVector(key)[0] == pytest.approx(lm.atVector(key)[0], abs=1e-6)
    # at the minimum no step lowers the error: the values come back unchanged
    again = gauss_newton(graph, gn)
    assert graph.error(again) == pytest.approx(graph.error(gn), rel=1e-9)
