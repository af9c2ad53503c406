"""Eq. 2's last solve with the GNSS error as a Gauss-Markov state (single_trip/gnss_bias.py)."""

import dataclasses

import gtsam
import numpy as np
import pytest

from csr_core import metrics
from csr_core.single_trip.gnss_bias import (
    _bias_key,
    add_gauss_markov_chain,
    run_sigmas_m,
    white_sigma_m,
    white_sigmas_m,
)
from csr_core.single_trip.params import DEFAULT
from csr_core.single_trip.pose_graph import integrate_increments, smooth_poses
from csr_core.types import GnssStatus

pytestmark = pytest.mark.unit


def _gauss_markov(n: int, dt_s: float, tau_s: float, sigma_m: float, rng: np.random.Generator) -> np.ndarray:
    phi = np.exp(-dt_s / tau_s)
    out = np.zeros((n, 2))
    out[0] = sigma_m * rng.standard_normal(2)
    for i in range(1, n):
        out[i] = phi * out[i - 1] + np.sqrt(1 - phi**2) * sigma_m * rng.standard_normal(2)
    return out


def test_the_chain_is_the_gauss_markov_prior_exactly():
    """Biases held by the chain and by direct measurements: the same solution as the normal
    equations of the first-order Gauss-Markov prior, written out by hand."""
    rng = np.random.default_rng(1)
    n, tau, meas_sigma = 40, 20.0, 0.3
    t = np.cumsum(rng.uniform(0.5, 1.5, n))
    sigma = rng.uniform(0.3, 0.8, n)  # the stationary sigma may change from node to node
    z = rng.normal(size=(n, 2)) + 1.0
    g, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    add_gauss_markov_chain(
        g, t, sigma, np.zeros(n, int), rng.normal(size=(n, 2)), tau
    )  # any linearisation point
    for k in range(n):
        values.insert(_bias_key(k), gtsam.Pose2())
        g.add(
            gtsam.PriorFactorPose2(
                _bias_key(k),
                gtsam.Pose2(z[k, 0], z[k, 1], 0.0),
                gtsam.noiseModel.Diagonal.Sigmas(np.array([meas_sigma, meas_sigma, 1e3])),
            )
        )
    result = gtsam.LevenbergMarquardtOptimizer(g, values).optimize()
    got = np.array([[result.atPose2(_bias_key(k)).x(), result.atPose2(_bias_key(k)).y()] for k in range(n)])

    info = np.zeros((n, n))
    info[0, 0] = 1 / sigma[0] ** 2
    phi = np.exp(-np.diff(t) / tau)
    for k in range(n - 1):
        row = np.zeros(n)
        row[k], row[k + 1] = phi[k] / sigma[k], -1 / sigma[k + 1]
        info += np.outer(row, row) / (1 - phi[k] ** 2)
    info += np.eye(n) / meas_sigma**2
    expected = np.linalg.solve(info, z / meas_sigma**2)
    assert np.abs(got - expected).max() < 1e-8


def test_a_new_fix_status_starts_a_new_bias():
    """Biases measured in the first run only: in one run the next ones follow the last measured
    bias back to 0 at the chain's pace; after a status change they are a new draw, at 0 at once."""
    n, tau = 20, 100.0
    t = np.arange(n, dtype=float)
    solved = {}
    for name, run in (
        ("one run", np.zeros(n, int)),
        ("two runs", np.r_[np.zeros(10, int), np.ones(10, int)]),
    ):
        g, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        add_gauss_markov_chain(g, t, np.full(n, 0.5), run, np.zeros((n, 2)), tau)
        for k in range(n):
            values.insert(_bias_key(k), gtsam.Pose2())
        for k in range(10):
            g.add(
                gtsam.PriorFactorPose2(
                    _bias_key(k),
                    gtsam.Pose2(1.0, 0.0, 0.0),
                    gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 1e3])),
                )
            )
        result = gtsam.LevenbergMarquardtOptimizer(g, values).optimize()
        solved[name] = np.array([result.atPose2(_bias_key(k)).x() for k in range(n)])
    assert solved["one run"][10] == pytest.approx(np.exp(-1 / tau), abs=0.02)
    assert abs(solved["two runs"][10]) < 1e-6


def test_a_status_run_keeps_one_bias_sigma():
    status = np.array([3, 3, 3, 2, 2, 3, 3])
    std = np.array([0.5, 0.7, 0.6, 0.4, np.inf, 0.9, 0.8])
    out = run_sigmas_m(status, std)
    assert out[:3] == pytest.approx([0.6] * 3)
    assert out[3] == pytest.approx(0.4) and np.isinf(out[4])  # no fix stays without one
    assert out[5:] == pytest.approx([0.85, 0.85])


def test_the_white_sigma_is_measured_between_consecutive_fixes():
    rng = np.random.default_rng(2)
    n = 3000
    t = np.arange(n) * 0.1
    model = np.column_stack([t * 10.0, np.sin(t / 10.0)])
    gnss = model + _gauss_markov(n, 0.1, 60.0, 0.6, rng) + 0.05 * rng.standard_normal((n, 2))
    kept = np.ones(n, bool)
    kept[500:600] = False  # a gap: the fixes either side of it are not consecutive
    assert white_sigma_m(t, model, gnss, kept, DEFAULT) == pytest.approx(0.05, rel=0.15)


def test_each_fix_status_gets_its_own_white_sigma():
    """An RTK-fixed spell's centimetre and a single-point spell's decimetres in one trip: each
    status's fixes are weighed with their own white sigma, not the trip's pooled one."""
    rng = np.random.default_rng(3)
    n = 2000
    t = np.arange(n) * 0.1
    model = np.column_stack([t * 8.0, np.zeros(n)])
    status = np.where(np.arange(n) < 800, int(GnssStatus.RTK_FIXED), int(GnssStatus.SINGLE))
    white = np.where(status == GnssStatus.RTK_FIXED, 0.01, 0.08)
    gnss = model + white[:, None] * rng.standard_normal((n, 2))
    got = white_sigmas_m(t, status, model, gnss, np.ones(n, bool), DEFAULT)
    assert np.median(got[:800]) == pytest.approx(0.01, rel=0.2)
    assert np.median(got[800:]) == pytest.approx(0.08, rel=0.2)


def _wander_trip(seed: int):
    """A 220 s urban drive at 7 m/s, 10 Hz, with a 90-degree turn every 30 s; odometry with a
    little white noise; GNSS of a single-point receiver: a Gauss-Markov bias (0.6 m, 600 s) and
    0.05 m white noise, its std_m reported honestly."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 220.0, 0.1)
    turning = (t % 30.0) < 5.0
    yaw = np.cumsum(np.where(turning, (np.pi / 2) / 50.0, 0.0) * np.where((t // 30.0) % 2 == 0, 1.0, -1.0))
    incr = np.column_stack([np.full(len(t), 0.7), np.zeros(len(t)), np.r_[np.diff(yaw), 0.0]])[:-1]
    true = integrate_increments(np.zeros(3), incr)
    noisy = incr + np.column_stack(
        [
            0.002 * np.sqrt(0.7) * rng.standard_normal(len(incr)),
            np.zeros(len(incr)),
            0.0002 * rng.standard_normal(len(incr)),
        ]
    )
    odom = integrate_increments(np.array([3.0, -2.0, 0.4]), noisy)
    gnss = true[:, :2] + _gauss_markov(len(t), 0.1, 600.0, 0.6, rng) + 0.05 * rng.standard_normal((len(t), 2))
    status = np.full(len(t), int(GnssStatus.SINGLE), np.uint8)
    return t, true, odom, gnss, status, np.full(len(t), 0.6)


def test_a_wandering_gnss_bias_does_not_bend_the_trajectory() -> None:
    """Within one trip, what the bias does over minutes is not the road's shape: with the bias as
    a state the smoothed trajectory keeps more of the odometry's shape than the white model (fixes
    inflated by their correlation time), which follows the wander. Trip-aligned error (each
    trip's own rigid offset removed, the single-trip measure) over four trips."""
    models = {
        "state": dataclasses.replace(DEFAULT, GNSS_BIAS_STATE=True),
        "white": dataclasses.replace(DEFAULT, GNSS_BIAS_STATE=False),
    }
    errors: dict[str, list[np.ndarray]] = {"state": [], "white": []}
    for seed in range(4):
        t, true, odom, gnss, status, std = _wander_trip(seed)
        for name, params in models.items():
            est = smooth_poses(t, gnss, status, std, np.full(len(t), np.nan), odom, params).poses_xyyaw_world[
                :, :2
            ]
            aligned = metrics.apply_se2(metrics.umeyama_se2(est, true[:, :2]), est)
            errors[name].append(metrics.position_errors(aligned, true[:, :2]))
    rms = {k: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for k, v in errors.items()}
    assert rms["state"] < 0.85 * rms["white"], rms


def test_the_bias_state_keeps_the_white_solve_for_the_alignment_s_chain():
    """With the bias state the stage returns two trajectories: its own (the bias state's) and the
    white-noise solve before it, exactly what the stage gives with the bias state off; the
    alignment's e^sm chain takes a trip's relative poses from the second
    (``TripReconstruction.white_poses_xyyaw_world``)."""
    t, _, odom, gnss, status, std = _wander_trip(0)
    heading = np.full(len(t), np.nan)
    on = smooth_poses(t, gnss, status, std, heading, odom, dataclasses.replace(DEFAULT, GNSS_BIAS_STATE=True))
    off = smooth_poses(
        t, gnss, status, std, heading, odom, dataclasses.replace(DEFAULT, GNSS_BIAS_STATE=False)
    )
    assert off.white_poses_xyyaw_world is None
    np.testing.assert_allclose(on.white_poses_xyyaw_world, off.poses_xyyaw_world, atol=1e-9)
    moved = np.linalg.norm(on.poses_xyyaw_world[:, :2] - on.white_poses_xyyaw_world[:, :2], axis=1)
    assert np.median(moved) > 0.01  # the bias state did change the trajectory


def test_median_per_node_is_numpys_median_of_each_nodes_fixes():
    from csr_core.single_trip.gnss_bias import median_per_node

    rng = np.random.default_rng(5)
    for trial in range(100):
        n_nodes, m = int(rng.integers(1, 15)), int(rng.integers(1, 40))
        nodes = rng.integers(0, n_nodes, m)
        values = rng.normal(size=(m, 2)) if trial % 2 else rng.normal(size=m)
        got = median_per_node(nodes, values, n_nodes)
        for k in range(n_nodes):
            if (nodes == k).any():
                assert np.array_equal(got[k], np.median(values[nodes == k], axis=0))
            else:
                assert np.isnan(got[k]).all()
