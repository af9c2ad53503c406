"""GNSS bias chain of the pose graph (Eq. 9 e^g with the trip's GNSS error as a Gauss-Markov bias)."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest

from csr_core import se2
from csr_core.alignment.params import AlignmentParams
from csr_core.alignment.pose_graph import add_gnss_bias_chain, optimize_submap_poses
from csr_core.alignment.submaps import Submap
from tests.unit.test_alignment_synthetic import (
    make_scenario,
    make_trip,
    submaps_every_20_frames,
    true_registration,
    truth_elements,
    truth_trajectory,
)

pytestmark = pytest.mark.unit

BIAS = AlignmentParams(gnss_bias_tau_s=300.0)
INDEPENDENT = replace(BIAS, gnss_bias_tau_s=0.0)


def _two_trips_registered_only_at_the_start(n_registered: int = 3):
    """Two trips on the same 400 m road (both lanes), one sub-map every 20 m, each trip with its
    own constant GNSS offset; their sub-maps registered (true relative pose, full information) only over the
    first ``n_registered`` pairs: the rest of the road each drives 'alone'."""
    rng = np.random.default_rng(0)
    elements = truth_elements(400.0)
    truths = [truth_trajectory(lane, False, rng, 400.0) for lane in (0, 1)]
    trips = [
        make_trip(f"veh{k}__t{k}", truths[k], elements, rng, offset_xy=off, perception=False)
        for k, off in enumerate(((0.8, 0.5), (-0.6, -0.4)))
    ]
    subs, by_trip = submaps_every_20_frames(trips)
    matches = [true_registration(by_trip[0][n], by_trip[1][n], truths, n) for n in range(n_registered)]
    return trips, truths, subs, by_trip, matches


def _relative_error_m(res, truths, by_trip, which: slice) -> float:
    """Mean |error of trip 1 - error of trip 0| over the sub-map pairs ``which`` (the offset a
    trip keeps against the other: what no global transform removes)."""
    out = []
    for s0, s1 in list(zip(by_trip[0], by_trip[1], strict=False))[which]:
        e0 = res.poses_xyyaw[s0.submap_id][:2] - truths[0][s0.anchor_frame][:2]
        e1 = res.poses_xyyaw[s1.submap_id][:2] - truths[1][s1.anchor_frame][:2]
        out.append(np.linalg.norm(e1 - e0))
    return float(np.mean(out))


def test_a_gnss_offset_learnt_where_trips_overlap_carries_along_the_stretch_driven_alone():
    trips, truths, subs, by_trip, matches = _two_trips_registered_only_at_the_start()
    offset = np.linalg.norm(
        (trips[1].poses_xyyaw_world[100] - truths[1][100])[:2]
        - (trips[0].poses_xyyaw_world[100] - truths[0][100])[:2]
    )
    assert offset > 1.0  # the two trips' GNSS disagree by more than a metre
    far = slice(-5, None)  # the last 100 m, 200+ m past the last registration
    biased = optimize_submap_poses(trips, subs, matches, BIAS)
    independent = optimize_submap_poses(trips, subs, matches, INDEPENDENT)
    assert _relative_error_m(biased, truths, by_trip, slice(0, 3)) < 0.05 * offset  # registered: together
    assert _relative_error_m(independent, truths, by_trip, slice(0, 3)) < 0.05 * offset
    # far from the overlap, independent per-sub-map priors pull each trip back to its own GNSS;
    # the bias chain keeps the correction (bias correlated over minutes, the stretch is 30 s)
    assert _relative_error_m(independent, truths, by_trip, far) > 0.5 * offset
    assert _relative_error_m(biased, truths, by_trip, far) < 0.15 * offset


def test_bias_chain_step_is_the_gauss_markov_difference_and_a_status_change_frees_it():
    trips, _ = make_scenario(1, seed=1, length_m=200.0, perception=False)
    t = trips[0]
    subs = [
        Submap(n, n, 0, t.trip.key, a, a - 5, a + 5, t.poses_xyyaw_world[a].copy(), ())
        for n, a in enumerate((10, 30, 50))
    ]
    g = gtsam.NonlinearFactorGraph()
    weights = {0: 2.0, 1: 2.0, 2: 400.0}  # DGPS, DGPS, then RTK fixed (Eq. 11 weights)
    added = add_gnss_bias_chain(g, t, subs, weights, BIAS)
    assert added == [0, 1, 2]
    sigma = lambda w: np.sqrt(BIAS.gnss_bias_share) * BIAS.gnss_sigma_base_xy_m / np.sqrt(w)  # noqa: E731
    first = np.asarray(g.at(0).noiseModel().sigmas())
    assert first[0] == pytest.approx(sigma(2.0))
    dt = t.trip.timestamps_s[30] - t.trip.timestamps_s[10]
    phi = np.exp(-dt / BIAS.gnss_bias_tau_s)
    same = np.asarray(g.at(1).noiseModel().sigmas())[0]
    assert same == pytest.approx(np.sqrt(2 * sigma(2.0) ** 2 * (1 - phi)))
    assert same < 0.15 * sigma(2.0)  # two seconds apart: almost the same bias
    changed = np.asarray(g.at(2).noiseModel().sigmas())[0]
    assert changed > 0.8 * sigma(2.0)  # to RTK fixed: the old bias does not constrain the new one


def _with_white_solve(subs, rng):
    """The sub-maps with a white-noise solve that differs from their contents' poses: shifted by
    (0.4, -0.3) m and bent by a few centimetres per sub-map."""
    shift = np.array([0.4, -0.3, 0.0])
    return [
        replace(
            s, white_world_T_submap=s.world_T_submap + shift + np.r_[0.05 * rng.standard_normal(2), 0.01 * k]
        )
        for k, s in enumerate(subs)
    ]


@pytest.mark.parametrize("params", [BIAS, INDEPENDENT], ids=["bias-chain", "independent"])
def test_e_g_holds_the_smoothed_anchor_and_the_chain_the_white_solve_s_relative_pose(params):
    """A trip that carries the single-trip white solve beside its bias-state poses: e^g holds each
    sub-map at its (bias-state) anchor pose, the e^sm chain holds consecutive sub-maps at the white
    solve's relative pose (``submap_chain_from_white_solve``); ``gnss_prior_from_white_solve``
    moves e^g to the white solve too, and with nothing registered the sub-maps then sit on it."""
    trips, _ = make_scenario(1, seed=1, length_m=200.0, perception=False)
    subs, _ = submaps_every_20_frames(trips)
    both = _with_white_solve(subs, np.random.default_rng(5))
    res = optimize_submap_poses(trips, both, [], params)
    got = np.array([res.poses_xyyaw[s.submap_id] for s in both])
    # the chain (centimetres) is far stiffer than the GNSS priors (a metre): the shape is the white
    # solve's, placed where the smoothed anchors are on average (not 0.5 m off with the white solve)
    for k in range(len(both) - 1):
        want = se2.between(both[k].white_world_T_submap, both[k + 1].white_world_T_submap)
        np.testing.assert_allclose(se2.between(got[k], got[k + 1]), want, atol=5e-3)
    smoothed_mean = np.mean([s.world_T_submap[:2] for s in both], axis=0)
    assert np.linalg.norm(got[:, :2].mean(axis=0) - smoothed_mean) < 0.05
    on_white = replace(params, gnss_prior_from_white_solve=True)
    res = optimize_submap_poses(trips, both, [], on_white)
    for s in both:
        np.testing.assert_allclose(res.poses_xyyaw[s.submap_id], s.white_world_T_submap, atol=2e-3)
    plain = optimize_submap_poses(trips, subs, [], params)
    for s in subs:  # without a white solve: the contents' own poses
        np.testing.assert_allclose(plain.poses_xyyaw[s.submap_id], s.world_T_submap, atol=2e-3)
