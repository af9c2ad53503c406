"""Alignment Steps 3-4 and the pose graph: Eq. 8 votes, the maximum clique, Eq. 11 weights,
GNC rejection of a wrong registration, and distributing sub-map poses to frames."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from csr_core.alignment.association import PairMatch
from csr_core.alignment.inter_trip import inter_trip_consistency, max_consistent_set
from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.pose_graph import (
    frame_poses_from_submaps,
    gnss_weight,
    optimize_submap_poses,
    registration_variance_factors,
)
from csr_core.alignment.submaps import Submap
from csr_core.alignment.temporal import vote_instances
from tests.unit.test_alignment_synthetic import LANE_W, make_scenario

pytestmark = pytest.mark.unit

P = AlignmentParams()


def pair(i, j, ti, tj, centre_x, dxy, conf=0.9, info=None, inst=((0, 0),), confs=(0.9,)) -> PairMatch:
    info = np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.002**2]) if info is None else info
    return PairMatch(
        i,
        j,
        ti,
        tj,
        0,
        np.array([centre_x, 0.0]),
        np.array([dxy[0], dxy[1], 0.0]),
        info,
        ((0, 0),) * len(inst),
        tuple(inst),
        np.asarray(confs),
        conf,
        0.03,
        1.0,
    )


def test_clique_rejects_outlier_match_pairs():
    rng = np.random.default_rng(0)
    true = np.array([0.8, -1.1])
    good = [pair(2 * n, 2 * n + 1, 0, 1, 25.0 * n, true + rng.normal(0, 0.03, 2)) for n in range(10)]
    bad = [
        pair(100, 101, 0, 1, 60.0, true + [0.0, LANE_W]),
        pair(102, 103, 0, 1, 140.0, true + [0.0, -LANE_W], conf=1.0),
    ]
    group = good[:5] + bad[:1] + good[5:] + bad[1:]
    kept = max_consistent_set(group, P)
    assert [group[k] for k in kept] == good[:5] + good[5:]
    # reversed pairs (trip 1 -> trip 0) are compared through the inverse correction
    rev = pair(200, 201, 1, 0, 75.0, -true)
    assert len(inter_trip_consistency(group + [rev], P)) == 11


def test_clique_does_not_reject_a_registration_that_is_only_uninformative_along_the_road():
    true = np.array([0.8, -1.1])
    weak_along = np.diag([1 / 5.0**2, 1 / 0.05**2, 1 / 0.002**2])  # straight road along x
    group = [
        pair(0, 1, 0, 1, 0.0, true),
        pair(2, 3, 0, 1, 25.0, true + [2.5, 0.0], info=weak_along),
        pair(4, 5, 0, 1, 50.0, true),
    ]
    assert max_consistent_set(group, P) == [0, 1, 2]


def test_eq8_votes_pick_the_partner_with_most_confidence():
    ps = [
        pair(0, 1, 0, 1, 0.0, (0, 0), inst=((7, 3),), confs=(0.9,)),
        pair(2, 3, 0, 1, 25.0, (0, 0), inst=((7, 3),), confs=(0.8,)),
        pair(4, 5, 0, 1, 50.0, (0, 0), inst=((7, 4),), confs=(0.95,)),
    ]
    best_j, best_i = vote_instances(ps)
    assert best_j[7] == 3 and best_i[3] == 7 and best_i[4] == 7


def test_eq11_gnss_weight_follows_status_table_and_deviation():
    trips, _ = make_scenario(1, seed=0, length_m=150.0, perception=False)
    t = trips[0]
    zero = np.zeros(t.trip.n_frames)
    w_dgps = gnss_weight(t, 0, 50, zero, P)
    assert w_dgps == pytest.approx(P.gnss_status_weights[2])
    jumpy = zero.copy()
    jumpy[10:20] = 0.1
    assert gnss_weight(t, 0, 50, jumpy, P) < w_dgps


def _chain_submaps(poses: np.ndarray, every: int, trip: int = 0) -> list[Submap]:
    return [
        Submap(n, n, trip, "v__t", a, max(a - every, 0), a + every, poses[a].copy(), ())
        for n, a in enumerate(range(0, len(poses), every))
    ]


def test_frames_follow_their_sub_maps_and_blend_between_anchors():
    trips, _ = make_scenario(1, seed=0, length_m=150.0, perception=False)
    t = trips[0]
    subs = _chain_submaps(t.poses_xyyaw_world, 20)
    same = frame_poses_from_submaps(t, subs, {s.submap_id: s.world_T_submap for s in subs})
    np.testing.assert_allclose(same, t.poses_xyyaw_world, atol=1e-9)
    shift = np.array([0.5, -0.3, 0.0])
    moved = {s.submap_id: s.world_T_submap + shift for s in subs}
    out = frame_poses_from_submaps(t, subs, moved)
    np.testing.assert_allclose(
        out[:, :2] - t.poses_xyyaw_world[:, :2], np.tile(shift[:2], (len(out), 1)), atol=1e-9
    )
    # one sub-map moved: frames between it and its neighbours get part of the move, linearly
    moved = {s.submap_id: s.world_T_submap.copy() for s in subs}
    moved[2] = moved[2] + np.array([0.0, 1.0, 0.0])
    out = frame_poses_from_submaps(t, subs, moved)
    dy = out[:, 1] - t.poses_xyyaw_world[:, 1]
    assert dy[40] == pytest.approx(1.0) and 0.3 < dy[30] < 0.7 and dy[0] == pytest.approx(0.0)


def test_pose_graph_gnc_rejects_a_wrong_registration_and_keeps_the_right_ones():
    """Three trips' sub-maps on one straight road; GNSS errors 1 m; one registration claims
    a lane-width offset that contradicts the cycle through the third trip."""
    trips, _ = make_scenario(3, seed=1, length_m=120.0, perception=False)
    bias = [np.array([0.0, 0.0, 0.0]), np.array([1.0, -0.5, 0.0]), np.array([-0.7, 0.8, 0.0])]
    subs = []
    for k, t in enumerate(trips):
        a = 50
        subs.append(Submap(k, 0, k, t.trip.key, a, a - 20, a + 20, t.poses_xyyaw_world[a] + bias[k], ()))
    info = np.diag([1 / 0.05**2, 1 / 0.05**2, 1 / 0.002**2])

    def reg(i, j, extra=(0.0, 0.0)):
        # the registration measures the true correction of j onto i in the world: bias_i - bias_j
        d = bias[i][:2] - bias[j][:2] + np.asarray(extra)
        c = subs[i].world_T_submap[:2]
        return PairMatch(
            i,
            j,
            i,
            j,
            0,
            c.copy(),
            np.array([d[0], d[1], 0.0]),
            info,
            ((0, 0),) * 3,
            ((0, 0),) * 3,
            np.full(3, 0.9),
            0.9,
            0.03,
            1.0,
        )

    matches = [reg(0, 1), reg(1, 2), reg(0, 2, extra=(0.0, LANE_W)), reg(0, 1)]
    res = optimize_submap_poses(trips, subs, matches, P)
    assert res.registration_inlier.tolist() == [True, True, False, True]
    rel = [res.poses_xyyaw[k][:2] - (subs[k].world_T_submap[:2] - bias[k][:2]) for k in range(3)]
    # within two pair sigmas (0.05 m, times sqrt(2): 4 pairs measure 2 relative poses in this circle,
    # registration_variance_factors) of each other, against GNSS 1 m apart
    assert np.linalg.norm(rel[1] - rel[0]) < 0.1 and np.linalg.norm(rel[2] - rel[0]) < 0.1


def test_pairs_of_one_circle_count_their_sub_maps_once():
    """Three sub-maps of one circle, paired in a cycle: three pairs, two independent relative
    poses, so each pair holds 3/2 of its variance; a circle with one pair keeps it."""
    cycle = [replace(pair(i, j, i, j, 0.0, (0.0, 0.0)), circle_id=0) for i, j in ((0, 1), (1, 2), (0, 2))]
    alone = replace(pair(3, 4, 0, 1, 50.0, (0.0, 0.0)), circle_id=1)
    np.testing.assert_allclose(registration_variance_factors([*cycle, alone], P), [1.5, 1.5, 1.5, 1.0])
    off = AlignmentParams(reg_circle_redundancy=False)
    np.testing.assert_allclose(registration_variance_factors([*cycle, alone], off), [1.0] * 4)


def test_a_pair_that_fits_worse_than_the_batch_is_held_looser():
    """Each pair in its own circle: the median residual (0.1 m) is the batch's typical fit; a
    pair at 0.3 m holds 9 x its variance, a better one keeps its own; a human's pair is as given."""
    rms = [0.1, 0.1, 0.05, 0.1, 0.3]
    pairs = [
        replace(pair(2 * k, 2 * k + 1, 0, 1, 50.0 * k, (0.0, 0.0)), circle_id=k, residual_rms_m=r)
        for k, r in enumerate(rms)
    ]
    human = replace(pair(10, 11, 0, 1, 500.0, (0.0, 0.0)), circle_id=9, residual_rms_m=0.5, human=True)
    np.testing.assert_allclose(registration_variance_factors([*pairs, human], P), [1, 1, 1, 1, 9, 1])
    off = AlignmentParams(reg_residual_variance=False)
    np.testing.assert_allclose(registration_variance_factors([*pairs, human], off), [1.0] * 6)
