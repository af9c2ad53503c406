"""Simulator sensor models: GNSS statistics, odometry errors, noiseless perception = truth."""

import dataclasses

import numpy as np
import pytest
import shapely

from csr_core import se2
from csr_core.sim import load_world
from csr_core.sim.gnss import Receiver, simulate_gnss
from csr_core.sim.odometry import simulate_odometry
from csr_core.sim.perception import build_truth_index, perceive_trip
from csr_core.sim.profiles import GnssParams, OdometryParams, get_profile, hard, noiseless, standard
from csr_core.sim.routes import drive, random_route
from csr_core.types import ElementType, GnssStatus

pytestmark = pytest.mark.unit

SINGLE = 3
AT_EPOCH = Receiver("rtk", 0.0, 0.0, (0, 1, 2, 3))


def _single_only(params: GnssParams) -> GnssParams:
    stay = tuple(tuple(0.0 for _ in range(4)) for _ in range(4))
    return dataclasses.replace(params, initial_probs=(0.0, 0.0, 0.0, 1.0), transition_probs=stay)


def segment_tree(lines: list[np.ndarray]) -> shapely.STRtree:
    """An STRtree of the 2-point segments of polylines (fast nearest-distance queries)."""
    segs = np.concatenate([np.stack([ln[:-1], ln[1:]], axis=1) for ln in lines])  # (S, 2, 2)
    return shapely.STRtree(shapely.linestrings(segs))


def _straight(n: int, speed_mps: float, dt_s: float = 0.1):
    t = np.arange(n) * dt_s
    poses = np.column_stack([speed_mps * t, np.zeros(n), np.zeros(n)])
    return t, poses, np.full(n, speed_mps)


def test_single_status_error_matches_the_model_parameters():
    base = _single_only(standard().gnss)
    # the standard tau (minutes) would need hours of samples; the model code is what is tested
    model = dataclasses.replace(base.status_models[SINGLE], bias_tau_s=20.0)
    params = dataclasses.replace(base, status_models=base.status_models[:SINGLE] + (model,))
    t, poses, speed = _straight(30000, 0.0)  # at rest: no latency lag; 3000 s, ~30 bias time constants
    errors, stds = [], []
    for seed in range(6):
        g = simulate_gnss(t, poses, speed, params, np.zeros((0, 3)), np.random.default_rng(seed), AT_EPOCH)
        assert (g.status == GnssStatus.SINGLE).all()
        errors.append(g.error_xy_m)
        stds.append(g.std_m)
    err = np.vstack(errors)
    expected = np.hypot(model.bias_sigma_m, model.white_sigma_m)
    np.testing.assert_allclose(err.std(axis=0), expected, rtol=0.2)
    np.testing.assert_allclose(np.median(np.concatenate(stds)), expected, rtol=0.05)  # honest std_m
    # Gauss-Markov: correlation after one time constant is about 1/e
    e = errors[0][:, 0] - errors[0][:, 0].mean()
    lag = int(model.bias_tau_s / 0.1)
    rho = np.corrcoef(e[:-lag], e[lag:])[0, 1]
    assert 0.15 < rho < 0.6


def test_latency_shows_as_along_track_lag():
    params = _single_only(standard().gnss)
    t, poses, speed = _straight(6000, 20.0)
    consumer = Receiver("consumer", params.latency_mean_s, params.latency_jitter_s, (2, 3))
    g = simulate_gnss(t, poses, speed, params, np.zeros((0, 3)), np.random.default_rng(1), consumer)
    along = g.error_xy_m[10:, 0]
    assert np.mean(along) == pytest.approx(-20.0 * params.latency_mean_s, abs=0.5)
    assert np.nanmedian(np.abs((g.heading_deg - 90.0 + 180) % 360 - 180)) < 1.0  # course east = 90 deg


def test_hard_profile_canyons_give_jumps_and_outages():
    params = hard().gnss
    t, poses, speed = _straight(6000, 10.0)
    zone = np.array([[3000.0, 0.0, 5000.0]])
    g = simulate_gnss(t, poses, speed, params, zone, np.random.default_rng(2))
    assert (g.status == GnssStatus.NONE).any()
    assert (g.status[g.status != GnssStatus.NONE] == GnssStatus.SINGLE).all()
    assert np.isnan(g.std_m[g.status == GnssStatus.NONE]).all()
    assert np.nanmax(np.linalg.norm(g.error_xy_m, axis=1)) > 3.0


def test_odometry_scale_error_and_noiseless_identity():
    t, poses, _ = _straight(1000, 10.0)
    poses[:, 1] = 5 * np.sin(poses[:, 0] / 50.0)
    poses[:, 2] = np.arctan2(np.gradient(poses[:, 1]), np.gradient(poses[:, 0]))
    odom, info = simulate_odometry(
        t, poses, OdometryParams(0.0, 0.0, 0.0, 0.0, 0.0), np.random.default_rng(0)
    )
    rel = se2.between(np.repeat(poses[:1], len(poses), 0), poses)
    np.testing.assert_allclose(odom, rel, atol=1e-9)
    odom, info = simulate_odometry(t, poses, OdometryParams(0.01, 0.0, 0.0, 0.0), np.random.default_rng(3))
    ratio = (
        np.linalg.norm(np.diff(odom[:, :2], axis=0), axis=1).sum()
        / np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1).sum()
    )
    assert ratio == pytest.approx(1 + info["scale_error"], rel=1e-9)
    assert info["scale_error"] != 0.0


@pytest.mark.parametrize("world_name", ["urban", "highway"])
def test_noiseless_perception_reproduces_truth_geometry(world_name: str) -> None:
    world = load_world(world_name)
    prof = noiseless()
    rng = np.random.default_rng(5)
    route = random_route(world, rng, 250.0, prof.traffic)
    truth = drive(route, rng, prof.traffic)
    index = build_truth_index(world, prof.perception)
    frames = perceive_trip(index, truth.poses_xyyaw_world, prof.perception, rng)

    trees = {
        t: segment_tree([e.points_xy_world for e in world.elements_of(t)])
        for t in (
            ElementType.LANE_DIVIDER,
            ElementType.ROAD_BOUNDARY,
            ElementType.CENTERLINE,
            ElementType.STOP_LINE,
        )
        if world.elements_of(t)
    }
    crosswalks = world.elements_of(ElementType.CROSSWALK)
    if crosswalks:
        # clipped at the range edge a crosswalk gains corners inside the truth polygon
        trees[ElementType.CROSSWALK] = shapely.STRtree(
            [shapely.Polygon(e.points_xy_world) for e in crosswalks]
        )
    p = prof.perception
    points_by_type: dict[ElementType, list[np.ndarray]] = {t: [] for t in trees}
    n_seen = 0
    for pose, items in zip(truth.poses_xyyaw_world, frames, strict=True):
        for item in items:
            pts_v = np.asarray(item["points"])
            assert 2 <= len(pts_v) <= 200
            assert (pts_v[:, 0] >= p.range_x_m[0] - 1e-6).all() and (
                pts_v[:, 0] <= p.range_x_m[1] + 1e-6
            ).all()
            assert (np.abs(pts_v[:, 1]) <= p.range_y_m[1] + 1e-6).all()
            points_by_type[ElementType(item["type"])].append(se2.transform_points(pose, pts_v))
            if item.get("style") == "dashed":
                assert np.linalg.norm(np.diff(pts_v, axis=0), axis=1).sum() <= p.dash_length_m + 0.01
            n_seen += 1
    for t, chunks in points_by_type.items():
        if chunks:
            _, dist = trees[t].query_nearest(shapely.points(np.vstack(chunks)), return_distance=True)
            # 3 cm: range-edge points are interpolated on 1 m chords (tight curb corners: R 6 m)
            assert dist.max() < 0.03, (t, dist.max())
    assert n_seen > 100


def test_profiles_hold_every_parameter_and_are_frozen():
    for name in ("standard", "hard", "noiseless"):
        prof = get_profile(name)
        d = prof.to_dict()
        assert d["name"] == name and {"gnss", "odometry", "perception", "traffic"} <= d.keys()
        with pytest.raises(dataclasses.FrozenInstanceError):
            prof.gnss.latency_mean_s = 1.0  # type: ignore[misc]


def test_docs_list_every_parameter_of_every_profile():
    import pathlib

    from csr_core.sim.profiles import parameter_table_markdown

    doc = pathlib.Path(__file__).resolve().parents[2] / "docs" / "simulator.md"
    text = doc.read_text()
    missing = [row for row in parameter_table_markdown().splitlines()[2:] if row not in text]
    assert missing == [], "docs/simulator.md is out of date; regenerate its parameter table"


def test_gnss_calibration_reproduces_the_real_ublox_figures():
    from csr_core.sim import gnss_calibration as cal

    ref = cal.load_reference()
    real = cal.error_stats(ref.t_s, ref.xy_m, ref.fix_t_s, ref.fix_xy_m)
    assert real["median_m"] == pytest.approx(1.44, abs=0.05)  # shared/realdata/README.md
    assert real["p95_m"] == pytest.approx(1.87, abs=0.05)
    assert real["latency_s"] == pytest.approx(0.082, abs=0.01)
    model = cal.model_stats(ref, standard().gnss, n_runs=20)
    assert model["median_m"]["p05"] < real["median_m"] < model["median_m"]["p95"]
    assert model["latency_s"]["median"] == pytest.approx(standard().gnss.latency_mean_s, abs=0.02)


def test_fleet_mixes_rtk_and_consumer_receivers():
    from csr_core.sim.gnss import draw_receiver, status_sequence

    params = standard().gnss
    rng = np.random.default_rng(4)
    receivers = [draw_receiver(params, rng) for _ in range(400)]
    rtk = [r for r in receivers if r.kind == "rtk"]
    assert len(rtk) / len(receivers) == pytest.approx(params.rtk_receiver_share, abs=0.07)
    assert all(r.latency_s == 0.0 for r in rtk)
    consumer = next(r for r in receivers if r.kind == "consumer")
    assert consumer.latency_s > 0
    seq = status_sequence(params, 20000, 0.1, rng, consumer.statuses)
    assert set(np.unique(seq).tolist()) <= {int(GnssStatus.DGPS), int(GnssStatus.SINGLE)}


def test_perception_noise_grows_with_distance_and_is_larger_for_boundaries() -> None:
    world = load_world("highway")
    prof = standard()
    rng = np.random.default_rng(8)
    route = random_route(world, rng, 600.0, prof.traffic)
    truth = drive(route, rng, prof.traffic)
    index = build_truth_index(world, prof.perception)
    frames = perceive_trip(index, truth.poses_xyyaw_world, prof.perception, rng)
    trees = {
        t: segment_tree([e.points_xy_world for e in world.elements_of(t)])
        for t in (ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY)
    }
    resid: dict[tuple[ElementType, bool], list[float]] = {}
    for pose, items in zip(truth.poses_xyyaw_world, frames, strict=True):
        for item in items:
            t = ElementType(item["type"])
            if t not in trees or item["score"] < 0.65:  # skip ghosts and false positives
                continue
            pts_v = np.asarray(item["points"])
            _, d = trees[t].query_nearest(
                shapely.points(se2.transform_points(pose, pts_v)), return_distance=True
            )
            far = np.hypot(pts_v[:, 0], pts_v[:, 1]) > 20.0
            for is_far in (False, True):
                resid.setdefault((t, is_far), []).extend(d[far == is_far].tolist())
    med = {k: float(np.median(v)) for k, v in resid.items()}
    div, bnd = ElementType.LANE_DIVIDER, ElementType.ROAD_BOUNDARY
    assert med[(div, True)] > med[(div, False)] and med[(bnd, True)] > med[(bnd, False)]
    assert med[(bnd, False)] > 1.5 * med[(div, False)]
    assert 0.02 < med[(div, False)] < 0.3
