"""Baselines (csr_core.baselines) on the hand-made toy road: known answers where the noise is off,
and the ICP baseline beating GNSS-only where trips disagree by a GNSS bias."""

import dataclasses

import numpy as np
import pytest

from csr_core.baselines.gnss_only import reconstruct_gnss_only
from csr_core.baselines.gnss_poses import gnss_poses_xyyaw
from csr_core.baselines.naive_fusion import fuse_naively, keyframe_indices
from csr_core.baselines.roadmap_icp import reconstruct_roadmap_icp
from csr_core.bench.toy import ToySpec, make_toy_trips
from csr_core.errors import ReconstructionError
from csr_core.metrics import evaluate, map_scores
from csr_core.se2 import wrap_angle
from csr_core.types import ElementType, GnssStatus

pytestmark = pytest.mark.unit

EXACT = ToySpec(
    n_trips=1,
    length_m=200.0,
    gnss_bias_sigma_m=0.0,
    gnss_noise_m=0.0,
    perception_noise_m=0.0,
    odom_noise_m=0.0,
)


def test_gnss_poses_equal_the_truth_when_gnss_is_perfect():
    trips, true_by_key, _, frame = make_toy_trips(EXACT)
    poses = gnss_poses_xyyaw(trips[0], frame)
    truth = true_by_key[trips[0].key]
    np.testing.assert_allclose(poses[:, :2], truth[:, :2], atol=1e-6)
    assert np.abs(wrap_angle(poses[:, 2] - truth[:, 2])).max() < 0.03  # toy heading noise 0.005 rad


def test_a_gnss_outage_is_bridged_by_odometry():
    spec = dataclasses.replace(EXACT, outage=(60, 120), odom_noise_m=0.001)
    trips, true_by_key, _, frame = make_toy_trips(spec)
    assert (trips[0].gnss_status[60:120] == GnssStatus.NONE).all()
    poses = gnss_poses_xyyaw(trips[0], frame)
    err = np.linalg.norm(poses[:, :2] - true_by_key[trips[0].key][:, :2], axis=1)
    # 60 m bridged from the end poses, whose GNSS yaw is off by the toy's 0.005 rad heading noise
    assert err[60:120].max() < 0.25
    assert err[:60].max() < 1e-6 and err[120:].max() < 1e-6


def test_a_trip_without_any_fix_fails_alone():
    trips, *_, frame = make_toy_trips(dataclasses.replace(EXACT, n_trips=2))
    dead = dataclasses.replace(trips[1], gnss_status=np.full(trips[1].n_frames, GnssStatus.NONE, np.uint8))
    with pytest.raises(ReconstructionError):
        gnss_poses_xyyaw(dead, frame)
    recon = reconstruct_gnss_only([trips[0], dead], frame)
    assert set(recon.poses_xyyaw_world) == {trips[0].key} and set(recon.failed) == {dead.key}


def test_naive_fusion_with_perfect_poses_reproduces_the_truth():
    trips, true_by_key, truth, _ = make_toy_trips(EXACT)
    features = fuse_naively(trips, true_by_key)
    assert features, "no map features"
    scores = map_scores(features, truth, true_by_key[trips[0].key])
    for etype in (ElementType.LANE_DIVIDER, ElementType.CENTERLINE, ElementType.ROAD_BOUNDARY):
        assert scores.per_type[etype].cd < 0.02, etype
        assert scores.per_type[etype].completeness > 0.97, etype
    assert scores.per_type[ElementType.CROSSWALK].cd < 0.02
    # one stitched polyline per tracked line, not one per keyframe
    n_lines = sum(1 for f in truth if not f.type.is_polygon)
    assert len([f for f in features if not f.type.is_polygon]) <= 2 * n_lines


def test_keyframes_are_spaced_by_travel():
    trips, *_ = make_toy_trips(EXACT)
    kf = keyframe_indices(trips[0], 5.0)
    assert kf[0] == 0 and np.all(np.abs(np.diff(kf) - 5) <= 1)  # ~1 m per frame in the toy


def test_roadmap_icp_pulls_biased_trips_together():
    # Per-trip GNSS biases (0.6 m per axis) put the trips' copies of the road up to ~2 m apart.
    spec = ToySpec(n_trips=4, length_m=300.0, gnss_bias_sigma_m=0.6, gnss_noise_m=0.05, seed=3)
    trips, true_by_key, truth, frame = make_toy_trips(spec)
    gnss = reconstruct_gnss_only(trips, frame)
    icp = reconstruct_roadmap_icp(trips, frame)
    assert icp.diagnostics["chunks_registered"] >= 10

    def mean_offsets(recon):
        return np.array(
            [(recon.poses_xyyaw_world[k][:, :2] - v[:, :2]).mean(axis=0) for k, v in true_by_key.items()]
        )

    # The toy road runs along x: ICP on parallel lines fixes the lateral (y) offset between trips
    # and is blind along the road (x); the GNSS gauge puts the registered trips where GNSS puts
    # them on average.
    off_gnss, off_icp = mean_offsets(gnss), mean_offsets(icp)
    assert off_gnss[:, 1].std() > 0.3
    assert off_icp[:, 1].std() < 0.1 * off_gnss[:, 1].std()
    assert abs(off_icp[:, 1].mean() - off_gnss[:, 1].mean()) < 0.1
    true_xy = {k: v[:, :2] for k, v in true_by_key.items()}

    def mcd(recon):
        est = {k: v[:, :2] for k, v in recon.poses_xyyaw_world.items()}
        return evaluate(true_xy, est, truth, recon.map_features).map_aligned.mcd

    assert mcd(icp) < 0.8 * mcd(gnss)


def test_the_gnss_gauge_moves_registered_trips_to_the_mean_gnss_placement():
    from csr_core.baselines.roadmap_icp import gnss_gauge

    x = np.arange(0.0, 300.0, 1.0)
    road = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    gnss = {"a": road + [0.0, 1.0, 0.0], "b": road + [0.0, -0.5, 0.0], "c": road + [0.0, 0.1, 0.0]}
    registered = {k: gnss["a"].copy() for k in gnss}  # all snapped onto trip a (its GNSS error: +1 m)
    out = gnss_gauge(registered, gnss)
    for k in gnss:
        np.testing.assert_allclose(out[k][:, 1], (1.0 - 0.5 + 0.1) / 3, atol=1e-9)
        np.testing.assert_allclose(out[k][:, [0, 2]], road[:, [0, 2]], atol=1e-9)
