"""Single-trip pose smoothing (Eq. 2): known answers on hand-made trips."""

import dataclasses

import numpy as np
import pytest

from csr_core.errors import ReconstructionError
from csr_core.geo import LocalFrame
from csr_core.single_trip import reconstruct_trip
from csr_core.single_trip.keyframes import select_keyframes
from csr_core.single_trip.params import DEFAULT
from csr_core.single_trip.pose_graph import (
    estimate_latency_s,
    estimate_yaw_rate_bias,
    integrate_increments,
    smooth_poses,
)
from csr_core.single_trip.synthetic import SynthSpec, make_trip
from csr_core.types import GnssStatus

pytestmark = pytest.mark.unit


def _smooth(trip, frame):
    xy = frame.to_local(trip.gnss_lonlat_deg)
    return smooth_poses(
        trip.timestamps_s,
        xy,
        trip.gnss_status,
        trip.gnss_std_m,
        trip.gnss_heading_deg,
        trip.odom_xyyaw,
        DEFAULT,
    ), xy


def test_local_frame_round_trip_is_far_below_a_millimetre():
    rng = np.random.default_rng(1)
    frame = LocalFrame(origin_lat=31.2, origin_lon=121.5)
    xy = rng.uniform(-5000, 5000, size=(1000, 2))
    back = frame.to_local(frame.to_lonlat(xy))
    assert np.abs(back - xy).max() < 1e-6


def test_noiseless_trip_reproduces_the_truth():
    trip, true, frame = make_trip(SynthSpec(length_m=300.0, gnss_sigma_m=0.0, curvature_1pm=0.004))
    smoothed, _ = _smooth(trip, frame)
    err = np.linalg.norm(smoothed.poses_xyyaw_world[:, :2] - true[:, :2], axis=1)
    assert err.max() < 1e-3
    yaw_err = np.angle(np.exp(1j * (smoothed.poses_xyyaw_world[:, 2] - true[:, 2])))
    assert np.abs(yaw_err).max() < 1e-4


def test_straight_drive_is_not_bent_by_a_gnss_jump():
    # 8 m jump for 10 s on a straight 600 m drive with 0.3 m GNSS noise
    spec = SynthSpec(length_m=600.0, gnss_sigma_m=0.3, gnss_jumps=((200, 300, 6.0, -5.3),), seed=3)
    trip, true, frame = make_trip(spec)
    smoothed, gnss_xy = _smooth(trip, frame)
    err = np.linalg.norm(smoothed.poses_xyyaw_world[:, :2] - true[:, :2], axis=1)
    raw = np.linalg.norm(gnss_xy - true[:, :2], axis=1)
    assert raw[200:301].min() > 6.0
    assert err[200:301].max() < 0.5
    assert not smoothed.gnss_inlier[200:301].any()
    assert smoothed.gnss_inlier[:190].mean() > 0.95


def test_gnss_outage_is_bridged_by_odometry():
    spec = SynthSpec(
        length_m=600.0,
        gnss_sigma_m=0.2,
        gnss_outages=((250, 400),),
        curvature_1pm=0.002,
        odom_sigma_per_m=0.002,
        seed=4,
    )
    trip, true, frame = make_trip(spec)
    assert (trip.gnss_status[250:401] == GnssStatus.NONE).all()
    smoothed, _ = _smooth(trip, frame)
    err = np.linalg.norm(smoothed.poses_xyyaw_world[:, :2] - true[:, :2], axis=1)
    assert err[250:401].max() < 0.5
    # the marginal sigma is larger inside the outage than for the same drive with every fix
    full, _ = _smooth(make_trip(dataclasses.replace(spec, gnss_outages=()))[0], frame)
    assert smoothed.sigma_xy_m[325] > full.sigma_xy_m[325]


def test_trip_without_fix_raises():
    spec = SynthSpec(length_m=100.0, gnss_outages=((0, 10_000),))
    trip, _, frame = make_trip(spec)
    with pytest.raises(ReconstructionError):
        reconstruct_trip(trip, frame)


def _held_at(trip, period_frames: int):
    """``trip`` as a receiver at 1 / ``period_frames`` of the frame rate logs it: each epoch's
    fix (position, status, std) copied into the frames up to the next epoch."""
    epoch = (np.arange(trip.n_frames) // period_frames) * period_frames
    return dataclasses.replace(
        trip,
        gnss_lonlat_deg=trip.gnss_lonlat_deg[epoch],
        gnss_status=trip.gnss_status[epoch],
        gnss_std_m=trip.gnss_std_m[epoch],
    )


def test_a_fix_held_over_the_frames_between_epochs_is_one_measurement():
    # 10 Hz frames, a 1 Hz receiver whose fix the log repeats: at 12 m/s a repeated fix is up to
    # 10.8 m behind; taken as ten measurements it drags the trajectory along a staircase
    spec = SynthSpec(length_m=900.0, speed_mps=12.0, gnss_sigma_m=0.3, curvature_1pm=0.002, seed=5)
    trip, true, frame = make_trip(spec)
    held = _held_at(trip, 10)
    assert held.held_fix.sum() == trip.n_frames - len(range(0, trip.n_frames, 10))
    assert not held.held_fix[::10].any() and not trip.held_fix.any()
    epochs_only = dataclasses.replace(
        trip,
        gnss_status=np.where(
            np.arange(trip.n_frames) % 10 == 0, trip.gnss_status, np.uint8(GnssStatus.NONE)
        ).astype(np.uint8),
    )

    def rmse(t):
        return float(
            np.sqrt(
                np.mean(
                    np.sum((reconstruct_trip(t, frame).poses_xyyaw_world[:, :2] - true[:, :2]) ** 2, axis=1)
                )
            )
        )

    assert rmse(held) == pytest.approx(rmse(epochs_only), abs=0.01)
    assert rmse(held) < 0.3


def _winding_drive(
    t: np.ndarray, speed_mps: np.ndarray, yaw_rad: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(true poses (N, 3), body-frame increments (N-1, 3))`` of a drive at 10 Hz with the given
    speed and heading profiles."""
    incr = np.column_stack([speed_mps * 0.1, np.zeros_like(t), np.r_[np.diff(yaw_rad), 0.0]])[:-1]
    return integrate_increments(np.zeros(3), incr), incr


def test_latency_and_odometry_scale_are_recovered():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 200.0, 0.1)
    # a winding drive with speed changes: latency is visible where the velocity changes
    true, incr = _winding_drive(t, 8.0 + 4.0 * np.sin(t / 15.0), 0.6 * np.sin(t / 20.0))
    latency = 0.12
    gnss = np.column_stack([np.interp(t - latency, t, true[:, 0]), np.interp(t - latency, t, true[:, 1])])
    gnss += rng.normal(scale=0.05, size=gnss.shape)
    odom = integrate_increments(np.zeros(3), incr * [1.01, 1.01, 1.0])
    lat, scale = estimate_latency_s(t, odom, gnss, np.ones(len(t), bool), 20.0, 0.5)
    assert lat == pytest.approx(latency, abs=0.01)
    assert scale == pytest.approx(1 / 1.01, abs=5e-4)


def test_a_multipath_jump_in_one_window_does_not_set_the_scale():
    """The hard highway trip (hard profile): a fast window (30 m/s, 600 m)
    with a 6 m multipath excursion for 5 s outweighs the others in an ordinary least-squares
    scale (weights ~ extent squared) and took the scale 1.3 % off and the latency to 0. Each
    window weighted by its own residual variance, the jump's window counts little."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 100.0, 0.1)
    speed = np.where((t > 20) & (t < 40), 30.0, 12.0 + 4.0 * np.sin(t / 7.0))
    true, incr = _winding_drive(t, speed, 0.3 * np.sin(t / 11.0))
    latency = 0.1
    gnss = np.column_stack([np.interp(t - latency, t, true[:, 0]), np.interp(t - latency, t, true[:, 1])])
    gnss += rng.normal(scale=0.05, size=gnss.shape)
    jump = (t > 22.0) & (t < 27.0)  # inside the fast window, ramped like the simulator's multipath
    ramp = np.minimum(1.0, np.minimum(t - 22.0, 27.0 - t) / 0.3)
    gnss[jump] += np.outer(np.clip(ramp[jump], 0.0, 1.0), [4.5, 4.5])
    odom = integrate_increments(np.zeros(3), incr * [1.01, 1.01, 1.0])
    lat, scale = estimate_latency_s(t, odom, gnss, np.ones(len(t), bool), 20.0, 0.5)
    assert scale == pytest.approx(1 / 1.01, abs=1e-3)
    assert lat == pytest.approx(latency, abs=0.02)


def test_correlated_gnss_error_is_not_taken_for_a_latency():
    """Fixes time-tagged at the epoch (latency 0) with a slowly wandering error (Gauss-Markov bias,
    as dgps/single fixes): counted as independent fixes, the chi-square test alone keeps a spurious
    latency on many trips; with the windows as independent clusters it is 0 on nearly all."""
    t = np.arange(0.0, 120.0, 0.1)
    true, incr = _winding_drive(t, 12.0 + 5.0 * np.sin(t / 9.0), 0.5 * np.sin(t / 14.0))
    spurious_chi2, spurious = 0, 0
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        bias = np.zeros((len(t), 2))
        phi = np.exp(-0.1 / 60.0)  # tau 60 s, sigma 0.6 m per axis
        for i in range(1, len(t)):
            bias[i] = phi * bias[i - 1] + np.sqrt(1 - phi**2) * 0.6 * rng.standard_normal(2)
        gnss = true[:, :2] + bias + rng.normal(scale=0.3, size=(len(t), 2))
        inlier = np.ones(len(t), bool)
        spurious_chi2 += estimate_latency_s(t, true, gnss, inlier, 20.0, 0.5, robust_z=0.0)[0] > 0
        spurious += estimate_latency_s(t, true, gnss, inlier, 20.0, 0.5)[0] > 0
    assert spurious <= 1 < spurious_chi2, (spurious, spurious_chi2)


def test_keyframes_by_distance_and_time():
    t = np.arange(0.0, 60.0, 0.1)
    x = np.where(t < 30.0, t * 10.0, 300.0)  # drives 300 m, then stands 30 s
    poses = np.column_stack([x, np.zeros_like(t), np.zeros_like(t)])
    kf = select_keyframes(poses, t, distance_m=5.0, period_s=5.0)
    moving = kf[t[kf] < 30.0]
    assert np.allclose(np.diff(x[moving]), 5.0, atol=1.01)
    standing = kf[t[kf] > 30.5]
    assert np.allclose(np.diff(t[standing]), 5.0, atol=0.11)
    assert kf[0] == 0 and kf[-1] == len(t) - 1


def test_yaw_rate_bias_is_recovered_in_full():
    """The chord estimator is not shrunk by the smoother: the slope of smoothed-minus-odometry
    yaw was (the odometry factors keep part of the drift; 15-25 % short on simulated trips)."""
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 150.0, 0.1)
    true, incr = _winding_drive(t, 10.0 + 3.0 * np.sin(t / 17.0), 0.8 * np.sin(t / 25.0))
    bias_rad_s = np.radians(0.04)
    biased = incr.copy()
    biased[:, 2] += bias_rad_s * 0.1
    odom = integrate_increments(np.zeros(3), biased)
    gnss = true[:, :2] + rng.normal(scale=0.3, size=(len(t), 2))
    sigma = np.full(len(t), 0.3)
    assert estimate_yaw_rate_bias(t, odom, gnss, sigma, np.ones(len(t), bool), 100.0)[0] == pytest.approx(
        bias_rad_s, rel=0.05
    )
    smoothed = smooth_poses(
        t,
        gnss,
        np.full(len(t), int(GnssStatus.RTK_FLOAT), np.uint8),
        sigma,
        np.full(len(t), np.nan),
        odom,
        DEFAULT,
    )
    assert smoothed.odom_yaw_rate_bias_rad_s == pytest.approx(bias_rad_s, rel=0.05)
