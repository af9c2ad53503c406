"""The compiled steps of the splicing stage (``csr_core.single_trip.compiled``) against plain
numpy and scipy on random inputs: each kernel replaced numpy code and must compute the same."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import label
from scipy.spatial import cKDTree

from csr_core.single_trip.compiled import checks, growth, observations, polyline, profile, search

pytestmark = pytest.mark.unit

SEEDS = (0, 1, 2)


def _wiggly_line(rng: np.random.Generator, n: int = 60, step_m: float = 0.5) -> np.ndarray:
    heading = np.cumsum(rng.normal(0.0, 0.05, n))
    return np.cumsum(step_m * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)


@pytest.mark.parametrize("seed", SEEDS)
def test_project_measures_arclength_and_offset_from_the_nearest_backbone_point(seed):
    rng = np.random.default_rng(seed)
    backbone = _wiggly_line(rng)
    columns, arclength = polyline.geometry_columns(backbone)
    points = backbone[rng.integers(0, len(backbone), 200)] + rng.normal(0, 1.0, (200, 2))
    s, d = polyline.project(points, columns, arclength)

    nearest = ((points[:, None, :] - backbone[None]) ** 2).sum(-1).argmin(1)
    tangent = np.gradient(backbone, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    rel = points - backbone[nearest]
    np.testing.assert_allclose(s, arclength[nearest] + (rel * tangent[nearest]).sum(1), atol=1e-12)
    np.testing.assert_allclose(
        d, tangent[nearest, 0] * rel[:, 1] - tangent[nearest, 1] * rel[:, 0], atol=1e-12
    )
    s_at, d_at = polyline.project_at(points, cKDTree(backbone).query(points)[1], columns, arclength)
    np.testing.assert_allclose(s_at, s, atol=1e-12)
    np.testing.assert_allclose(d_at, d, atol=1e-12)


def test_geometry_columns_are_the_points_and_their_unit_gradient():
    backbone = _wiggly_line(np.random.default_rng(3), 30)
    columns, arclength = polyline.geometry_columns(backbone)
    tangent = np.gradient(backbone, axis=0)
    np.testing.assert_allclose(columns[:2].T, backbone)
    np.testing.assert_allclose(columns[2:].T, tangent / np.linalg.norm(tangent, axis=1)[:, None], atol=1e-12)
    np.testing.assert_allclose(
        arclength, np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(backbone, axis=0), axis=1))]
    )


@pytest.mark.parametrize("seed", SEEDS)
def test_resample_polyline_keeps_the_ends_and_equal_steps(seed):
    line = _wiggly_line(np.random.default_rng(seed), 25, 1.3)
    out = polyline.resample_polyline(line, 0.5)
    steps = np.linalg.norm(np.diff(out, axis=0), axis=1)
    np.testing.assert_allclose(out[[0, -1]], line[[0, -1]])
    assert steps.max() <= 0.5 + 1e-9
    s = polyline.arclength(line)
    n = int(np.ceil(s[-1] / 0.5)) + 1
    q = np.linspace(0.0, s[-1], n)
    np.testing.assert_allclose(
        out, np.column_stack([np.interp(q, s, line[:, 0]), np.interp(q, s, line[:, 1])]), atol=1e-9
    )
    np.testing.assert_array_equal(polyline.resample_polyline(np.ones((3, 2)), 0.5), np.ones((1, 2)))


@pytest.mark.parametrize("seed", SEEDS)
def test_cluster_sd_labels_cells_as_scipy_does(seed):
    rng = np.random.default_rng(seed)
    # three lines side by side, one with a gap longer than the reach, and scattered points
    s = np.concatenate(
        [rng.uniform(0, 80, 300), rng.uniform(0, 30, 100), rng.uniform(60, 90, 100), rng.uniform(0, 90, 20)]
    )
    d = np.concatenate([rng.normal(0, 0.05, 300), rng.normal(3.5, 0.05, 200), rng.uniform(-6, 8, 20)])
    bin_m, cell_m, reach = 1.0, 0.5, 7
    labels = profile.cluster_sd(s, d, bin_m, cell_m, reach)

    sb = np.floor((s - s.min()) / bin_m).astype(int)
    db = np.floor((d - d.min()) / cell_m).astype(int)
    grid = np.zeros((sb.max() + 1, db.max() + 1), dtype=bool)
    grid[sb, db] = True
    grown = np.zeros_like(grid)
    for a in range(grid.shape[0]):
        grown[a] = grid[max(a - reach, 0) : a + reach + 1].any(0)
    expected, _ = label(grown, structure=np.ones((3, 3), dtype=bool))
    np.testing.assert_array_equal(labels, expected[sb, db] - 1)
    assert len(np.unique(labels)) >= 3


@pytest.mark.parametrize("seed", SEEDS)
def test_binned_profile_takes_the_upper_middle_value_per_bin(seed):
    rng = np.random.default_rng(seed)
    s = rng.uniform(5, 40, 400)
    d = rng.normal(0, 0.3, 400)
    bins, n_bins, med = profile.binned_profile(s, d, 1.0)
    np.testing.assert_array_equal(bins, np.floor(s - s.min()).astype(int))
    assert n_bins == bins.max() + 1
    for b in range(n_bins):
        values = np.sort(d[bins == b])
        assert np.isnan(med[b]) if len(values) == 0 else med[b] == values[len(values) // 2]
    dev = np.abs(d - med[bins])
    assert profile.mixture_sigma(d, bins, med) == pytest.approx(1.4826 * np.median(dev), rel=1e-12)


def test_robust_ends_pool_the_observations_near_the_extremes():
    # four observations; ids out of order; the lowest starts 0.0, 0.5, 1.0 (within 1.5 m) and 9.0
    s = np.array([0.0, 10.0, 0.5, 11.0, 1.0, 11.2, 9.0, 30.0])
    obs_id = np.array([0, 0, 2, 2, 1, 1, 3, 3])
    s_lo, s_hi = profile.robust_ends(s, obs_id, 1.5)
    assert s_lo == pytest.approx(0.5)
    assert s_hi == pytest.approx(30.0)
    assert profile.robust_ends(np.empty(0), np.empty(0, dtype=np.int64), 1.5) == (0.0, 0.0)


def test_fit_profile_recovers_an_offset_line_and_rejects_outliers():
    rng = np.random.default_rng(4)
    backbone = np.column_stack([np.arange(0.0, 40.5, 0.5), np.zeros(81)])
    columns, arclength = polyline.geometry_columns(backbone)
    s = rng.uniform(2, 38, 500)
    d = 0.3 + rng.normal(0, 0.03, 500)
    d[:10] += 2.0  # ghost points
    obs_id = np.sort(rng.integers(0, 20, 500))
    bins, n_bins, med = profile.binned_profile(s, d, 1.0)
    kernel = np.exp(-0.5 * (np.arange(-8, 9) / 2.0) ** 2)
    kernel /= kernel.sum()
    ok, line, inl, s_lo, s_hi, d_fit = profile.fit_profile(
        s, d, obs_id, bins, n_bins, med, 3.0, 1.0, kernel, 0.5, columns, arclength
    )
    assert ok
    assert not inl[:10].any() and inl[10:].mean() > 0.97
    assert abs(line[len(line) // 2, 1] - 0.3) < 0.02
    assert 2.0 <= s_lo < 4.0 and 36.0 < s_hi <= 38.0
    assert np.abs(d_fit[10:] - 0.3).max() < 0.1


@pytest.mark.parametrize("seed", SEEDS)
def test_nearest_index_agrees_with_a_kd_tree(seed):
    rng = np.random.default_rng(seed)
    points = rng.uniform(0, 20, (150, 2))
    for ref in (rng.uniform(0, 20, (60, 2)), _wiggly_line(rng) + 5.0, _wiggly_line(rng)[:, ::-1] + 5.0):
        dist, idx = cKDTree(ref).query(points)
        nearest, dist2 = search.nearest_index(points, ref[:, 0].copy(), ref[:, 1].copy())
        np.testing.assert_array_equal(nearest, idx)
        np.testing.assert_allclose(np.sqrt(dist2), dist, atol=1e-12)
    # the first of equals, as argmin over all pairs
    nearest, _ = search.nearest_index(
        np.zeros((1, 2)), np.array([1.0, -1.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0, 0.0])
    )
    assert nearest[0] == 0


@pytest.mark.parametrize("seed", SEEDS)
def test_frames_near_and_in_range_agree_with_numpy(seed):
    rng = np.random.default_rng(seed)
    samples = _wiggly_line(rng, 20, 2.0) + 10.0
    poses = np.column_stack([rng.uniform(-40, 60, (300, 2)), rng.uniform(-np.pi, np.pi, 300)])
    frames = np.arange(0, 300, 2)
    reach, corner = 30.0, 33.5
    pos = poses[frames, :2]
    lo, hi = samples.min(0) - reach, samples.max(0) + reach
    in_box = ((pos >= lo) & (pos <= hi)).all(1)
    near = np.linalg.norm(pos[:, None] - samples[None], axis=2).min(1) <= corner
    np.testing.assert_array_equal(
        checks.frames_near(samples, poses, frames, reach, corner), np.flatnonzero(in_box & near)
    )

    box = np.array([-13.0, 28.0, -13.0, 13.0])
    rel = samples[None] - poses[:, None, :2]
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    xv, yv = c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]
    inside = ((xv >= box[0]) & (xv <= box[1]) & (yv >= box[2]) & (yv <= box[3])).any(1)
    np.testing.assert_array_equal(checks.frames_in_range(samples, poses, box), inside)
    assert inside.any() and not inside.all()


def test_runs_along_is_one_along_the_backbone_and_zero_across():
    backbone = np.column_stack([np.arange(0.0, 50.5, 0.5), np.zeros(101)])
    columns, arclength = polyline.geometry_columns(backbone)
    along = np.column_stack([np.tile(np.arange(10.0, 20.0), 3), np.repeat([0.1, 0.2, 0.3], 10)])
    across = np.column_stack([np.full(30, 25.0), np.tile(np.arange(-5.0, 5.0), 3)])
    obs_id = np.repeat([2, 0, 1], 10)  # not sorted
    for points, expected in ((along, 1.0), (across, 0.0)):
        s, _ = polyline.project(points, columns, arclength)
        assert profile.runs_along(s, points, obs_id) == pytest.approx(expected, abs=0.06)
    short = np.column_stack([np.arange(3.0) * 0.5, np.zeros(3)])
    assert profile.runs_along(np.zeros(3), short, np.zeros(3, dtype=np.int64)) == 1.0


@pytest.mark.parametrize("seed", SEEDS)
def test_pair_distance_agrees_with_densely_sampled_segments(seed):
    rng = np.random.default_rng(seed)
    polys = np.stack([_wiggly_line(rng, 8, 1.5) for _ in range(40)])
    points = polys[:, [0, 3, 7]] + rng.normal(0, 0.8, (40, 3, 2))
    got = observations.pair_distance(points, polys, 0.0, 5.0)
    t = np.linspace(0, 1, 2001)[:, None]
    for m in range(40):
        dense = np.concatenate([a + t * (b - a) for a, b in zip(polys[m, :-1], polys[m, 1:], strict=True)])
        expected = np.minimum(cKDTree(dense).query(points[m])[0], 5.0)
        np.testing.assert_allclose(got[m], expected, atol=2e-3)


def test_track_observations_densify_detections_and_move_them_into_the_world():
    raw = np.array(
        [
            [0.0, 0.0],
            [2.5, 0.0],
            [3.0, 0.0],  # piece 0: a 2.5 m step, then 0.5 m
            [5.0, 1.0],
            [5.0, 4.0],  # piece 1: one 3 m step
            [9.0, 9.0],
        ]
    )  # piece 2 (not in the track)
    offsets = np.array([0, 3, 5, 6])
    yaw = np.array([0.0, np.pi / 2])
    pose_x, pose_y = np.array([10.0, 0.0]), np.array([0.0, 20.0])
    points_v, obs_offsets, original, points_w, obs_id = observations.track_observations(
        raw, offsets, np.array([0, 1]), np.cos(yaw), np.sin(yaw), pose_x, pose_y, 1.0
    )
    np.testing.assert_array_equal(obs_offsets, [0, 5, 9])  # 3 + 1 + 1 points, then 3 + 1
    np.testing.assert_allclose(points_v[:5, 0], [0.0, 2.5 / 3, 5.0 / 3, 2.5, 3.0])
    np.testing.assert_array_equal(original, [True, False, False, True, True, True, False, False, True])
    np.testing.assert_array_equal(obs_id, [0] * 5 + [1] * 4)
    np.testing.assert_allclose(points_w[:5], points_v[:5] + [10.0, 0.0])
    np.testing.assert_allclose(
        points_w[5:], np.column_stack([-points_v[5:, 1], points_v[5:, 0]]) + [0.0, 20.0], atol=1e-12
    )
    # polygons (no step limit): the vertices as sent
    points_v, obs_offsets, original, _, _ = observations.track_observations(
        raw, offsets, np.array([1, 2]), np.ones(2), np.zeros(2), np.zeros(2), np.zeros(2), 0.0
    )
    np.testing.assert_array_equal(points_v, raw[3:])
    assert original.all() and list(obs_offsets) == [0, 2, 3]


@pytest.mark.parametrize("seed", SEEDS)
def test_sorted_points_within_agree_with_a_kd_tree(seed):
    rng = np.random.default_rng(seed)
    path = search.SortedPoints(_wiggly_line(rng, 200, 1.0))
    points = rng.uniform(-20, 120, (300, 2))
    dist, _ = cKDTree(np.column_stack([path.x, path.y])).query(points)
    np.testing.assert_array_equal(path.within(points, 12.0), dist <= 12.0)
    assert 0 < (dist <= 12.0).sum() < len(points)


def test_grow_backbone_extends_the_first_observation_along_and_round_a_bend():
    # three observations of a line, the middle one first, the last reversed: the backbone covers all, in order
    xs = [np.arange(10.0, 20.5, 0.5), np.arange(0.0, 12.5, 0.5), np.arange(30.0, 17.5, -0.5)]
    points = np.concatenate([np.column_stack([x, np.zeros(len(x))]) for x in xs])
    ends = np.cumsum([len(x) for x in xs])
    obs_ends = np.column_stack([np.r_[0, ends[:-1]], ends - 1])
    grown = growth.grow_backbone(points, obs_ends, 0.5, 4.0, 1.0, 0.15, 15.0, False)
    assert grown[0, 0] == 0.0 and grown[-1, 0] == 30.0
    assert np.all(np.diff(grown[:, 0]) > 0) and np.abs(grown[:, 1]).max() == 0.0
    # a dashed line round a 20 m radius bend: its next dash is off the straight tangent, on the arc
    angle = [np.linspace(a, a + 0.15, 6) for a in (0.0, 0.3, 0.6)]
    arcs = [np.column_stack([20.0 * np.sin(a), 20.0 - 20.0 * np.cos(a)]) for a in angle]
    points = np.concatenate(arcs)
    obs_ends = np.array([[0, 5], [6, 11], [12, 17]])
    straight = growth.grow_backbone(points, obs_ends, 0.5, 4.0, 0.2, 0.0, 15.0, False)
    bent = growth.grow_backbone(points, obs_ends, 0.5, 4.0, 0.2, 0.0, 15.0, True)
    assert len(straight) == 6 and len(bent) == 18
    centre, r2 = growth.kasa_circle(points)
    np.testing.assert_allclose(centre, [0.0, 20.0], atol=1e-9)
    assert np.sqrt(r2) == pytest.approx(20.0)


def test_the_warm_up_compiles_the_kernels_the_pipeline_calls():
    # in a fresh process: the tests above call kernels directly, which would compile them here
    import json
    import subprocess
    import sys

    script = (
        "import json\nfrom csr_core.single_trip.compiled.warm_up import kernels, main\nassert main() == 0\n"
        "print(json.dumps({name: len(k.signatures) for name, k in kernels().items()}))"
    )
    run = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=600
    )
    compiled = json.loads(run.stdout.strip().splitlines()[-1])
    called_from_python = (
        "checks.frames_in_range",
        "checks.frames_near",
        "checks.runs_along_observations",
        "growth.grow_backbone",
        "observations.pair_distance",
        "observations.track_observations",
        "polyline.geometry_columns",
        "polyline.project_at",
        "polyline.resample_polyline",
        "profile.binned_profile",
        "profile.cluster_sd",
        "profile.fit_profile",
        "profile.robust_ends",
        "profile.splice_residuals",
        "search.nearest_in_sorted",
        "search.seen_within",
        "search.sort_along_wider_axis",
        "search.within_radius",
    )
    assert set(called_from_python) <= set(compiled)
    assert [name for name in called_from_python if not compiled[name]] == []
