"""Fleet b (``csr_core.sim.fleet_b``): each sensor model's statistics against its stated
parameters, determinism, schema validity, and fleet a unchanged."""

import dataclasses
import gzip
import hashlib
import json
import pathlib

import jsonschema
import numpy as np
import orjson
import pytest

from csr_core.sim import simulate_scenario
from csr_core.sim.fleet_b.gnss import ReceiverB, simulate_gnss_b
from csr_core.sim.fleet_b.occluders import occluded_mask
from csr_core.sim.fleet_b.odometry import OdometerB, simulate_odometry_b
from csr_core.sim.fleet_b.params import FleetBParams, GnssParamsB, OdometryParamsB, PerceptionParamsB
from csr_core.sim.fleet_b.perception import (
    Tracker,
    build_truth_index_b,
    false_positives,
    miss_probability,
    perceive_lines,
    sigma_at_range_m,
)
from csr_core.sim.profiles import TrafficParams
from csr_core.sim.world import TruthElement
from csr_core.types import DividerStyle, ElementType, GnssStatus
from csr_core.upload import validate_upload_json

pytestmark = pytest.mark.unit

SCHEMA = pathlib.Path(__file__).resolve().parents[2] / "csr_core" / "schemas" / "trip-upload.schema.json"
# sha256 over (relative path, bytes) of every file of simulate_scenario("urban", 2, "standard", 5,
# trip_length_m=150.0), computed on the simulator before fleet b existed
FLEET_A_URBAN_2_SEED_5_HASH = "bab3dc809bd12c50d1723295a51aa557e3d09d4f1b7a8589d885f34382320a34"
NO_BOXES = np.zeros((0, 5))
NO_RIG = np.zeros(3)


def _folder_hash(folder: pathlib.Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _straight(n: int, speed_mps: float, dt_s: float = 0.1, heading_rad: float = 0.5):
    t = np.arange(n) * dt_s
    s = speed_mps * t
    poses = np.column_stack([s * np.cos(heading_rad), s * np.sin(heading_rad), np.full(n, heading_rad)])
    return t, poses


def _one_status(code: int) -> GnssParamsB:
    init = tuple(1.0 if k == code else 0.0 for k in range(4))
    return dataclasses.replace(
        GnssParamsB(),
        initial_probs=init,
        transition_rate_per_s=((0.0,) * 4,) * 4,
        multipath_rate_per_s=0.0,
        outage_rate_per_s=0.0,
    )


# --- GNSS -------------------------------------------------------------------------------------


@pytest.mark.parametrize("code", [0, 1, 2, 3])
def test_gnss_error_per_status_has_the_stated_sigmas(code):
    params = _one_status(code)
    model = params.status_errors[code]
    t, poses = _straight(400_000, 10.0)
    g = simulate_gnss_b(t, poses, params, np.zeros((0, 3)), np.random.default_rng(code), ReceiverB(True, 0.0))
    assert (g.status == code).all()
    total = np.hypot(model.bias_sigma_m, model.white_sigma_m)
    assert np.std(g.error_xy_m, axis=0) == pytest.approx([total, total], rel=0.15)
    # white part from first differences: var(diff) = 2 white^2 + 2 bias^2 (1 - phi)
    phi = np.exp(-0.1 / model.bias_reversion_s)
    white = np.sqrt(np.var(np.diff(g.error_xy_m, axis=0)) / 2.0 - model.bias_sigma_m**2 * (1.0 - phi))
    assert white == pytest.approx(model.white_sigma_m, rel=0.05)
    # reported std_m: the stated factor times the true 2-D RMS (median: the jitter is log-normal)
    honest_2d = np.sqrt(2.0) * total
    assert np.median(g.std_m) / honest_2d == pytest.approx(model.std_report_factor, rel=0.03)


def test_gnss_receiver_without_corrections_never_reports_rtk_and_outages_are_none():
    params = dataclasses.replace(GnssParamsB(), outage_rate_per_s=0.01)
    t, poses = _straight(100_000, 10.0)
    g = simulate_gnss_b(t, poses, params, np.zeros((0, 3)), np.random.default_rng(1), ReceiverB(False, 0.05))
    codes = set(np.unique(g.status).tolist())
    assert codes <= {GnssStatus.DGPS, GnssStatus.SINGLE, GnssStatus.NONE} and GnssStatus.NONE in codes
    none = g.status == GnssStatus.NONE
    assert np.isnan(g.std_m[none]).all() and np.isnan(g.course_deg[none]).all()
    assert not np.isnan(g.std_m[~none]).any()


def test_gnss_course_noise_scales_with_one_over_speed_and_is_absent_when_slow():
    params = _one_status(0)
    heading_rad = 0.5
    true_course_deg = np.degrees(np.pi / 2 - heading_rad)  # clockwise from north
    for speed in (2.0, 5.0, 20.0):
        t, poses = _straight(40_000, speed, heading_rad=heading_rad)
        g = simulate_gnss_b(
            t, poses, params, np.zeros((0, 3)), np.random.default_rng(3), ReceiverB(True, 0.0)
        )
        err_rad = np.angle(np.exp(1j * np.radians(g.course_deg[1:-1] - true_course_deg)))
        assert np.std(err_rad) * speed == pytest.approx(params.velocity_sigma_mps, rel=0.05)
    t, poses = _straight(1000, 0.5 * params.course_min_speed_mps)
    g = simulate_gnss_b(t, poses, params, np.zeros((0, 3)), np.random.default_rng(4), ReceiverB(True, 0.0))
    assert np.isnan(g.course_deg).mean() > 0.99


def test_gnss_multipath_bursts_start_at_the_stated_rate_and_cost_the_rtk_fix():
    params = dataclasses.replace(_one_status(0), multipath_rate_per_s=0.01)
    t, poses = _straight(200_000, 10.0)
    g = simulate_gnss_b(t, poses, params, np.zeros((0, 3)), np.random.default_rng(5), ReceiverB(True, 0.0))
    in_burst = g.multipath_m > 0.0
    starts = np.count_nonzero(np.diff(in_burst.astype(int)) == 1)
    # a burst starting inside another merges with it: exp(-rate x mean duration) are seen apart
    mean_s = np.mean(params.multipath_duration_s)
    expected = params.multipath_rate_per_s * t[-1] * np.exp(-params.multipath_rate_per_s * mean_s)
    assert abs(starts - expected) < 3.5 * np.sqrt(expected)
    assert g.multipath_m.max() <= params.multipath_max_m
    large = g.multipath_m > 0.5 * params.multipath_max_m  # only in bursts over multipath_unfix_m
    assert (g.status[large] == GnssStatus.RTK_FLOAT).all()
    assert np.mean(g.status[~in_burst] == GnssStatus.RTK_FIXED) > 0.999  # (a burst's first epoch has 0 m)


# --- odometry ---------------------------------------------------------------------------------


def test_odometry_scale_error_and_its_speed_dependence_are_recovered():
    params = dataclasses.replace(
        OdometryParamsB(),
        gyro_white_rad_s=0.0,
        gyro_bias_init_sigma_rad_s=0.0,
        gyro_bias_rw_rad_s_per_sqrt_s=0.0,
    )
    odometer = OdometerB(scale_error=0.004, scale_per_mps=3.0e-4, gyro_scale_error=0.0)
    ratios = []
    for speed in (5.0, 25.0):
        t, poses = _straight(20_000, speed)
        odom, _ = simulate_odometry_b(t, poses, params, np.random.default_rng(6), odometer)
        ratios.append(
            np.linalg.norm(odom[-1, :2] - odom[0, :2]) / np.linalg.norm(poses[-1, :2] - poses[0, :2])
        )
    k = (ratios[1] - ratios[0]) / 20.0
    e0 = ratios[0] - 1.0 - 5.0 * k
    assert k == pytest.approx(odometer.scale_per_mps, rel=0.02)
    assert e0 == pytest.approx(odometer.scale_error, abs=2e-5)


def test_gyro_bias_follows_a_random_walk_of_the_stated_rate():
    params = OdometryParamsB()
    t, poses = _straight(72_000, 10.0)  # 2 h at 10 m/s, heading constant
    odom, _ = simulate_odometry_b(t, poses, params, np.random.default_rng(7), OdometerB(0.0, 0.0, 0.0))
    yaw_err = np.unwrap(odom[:, 2])
    window_s = 20.0
    step = int(window_s / 0.1)
    bias_hat = np.diff(yaw_err[::step]) / window_s  # mean bias per window
    # consecutive window means of a random walk differ with var sigma^2 * 2 W / 3; white noise adds
    # 2 white^2 dt / W
    dt = 1.0 / params.integration_rate_hz
    var = np.var(np.diff(bias_hat)) - 2.0 * params.gyro_white_rad_s**2 * dt / window_s
    rw = np.sqrt(var / (2.0 * window_s / 3.0))
    assert rw == pytest.approx(params.gyro_bias_rw_rad_s_per_sqrt_s, rel=0.2)


def test_odometry_holds_heading_at_standstill_and_starts_at_a_random_pose():
    t = np.arange(600) * 0.1
    poses = np.zeros((600, 3))
    odom, _ = simulate_odometry_b(
        t, poses, OdometryParamsB(), np.random.default_rng(8), OdometerB(0.0, 0.0, 0.0)
    )
    assert np.ptp(odom, axis=0) == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    assert np.linalg.norm(odom[0, :2]) > 1.0


# --- perception -------------------------------------------------------------------------------


def _line(eid: int, xy, kind=ElementType.LANE_DIVIDER, style=DividerStyle.SOLID) -> TruthElement:
    return TruthElement(eid, kind, np.asarray(xy, float), style if kind == ElementType.LANE_DIVIDER else None)


def _quiet(**changes) -> PerceptionParamsB:
    """No noise, no misses, no false positives, no rig error, unless changed."""
    base = dict(
        point_sigma_base_m=0.0,
        point_sigma_quad_per_m2=0.0,
        offset_sigma_base_m=0.0,
        offset_sigma_quad_per_m2=0.0,
        track_bias_sigma_m=0.0,
        miss_prob_base=0.0,
        miss_prob_range=0.0,
        miss_prob_occlusion=0.0,
        small_element_miss_prob=0.0,
        false_positive_rate_per_frame=0.0,
        track_switch_prob=0.0,
        style_confusion_prob=0.0,
    )
    return dataclasses.replace(PerceptionParamsB(), **{**base, **changes})


def _frames(index, params, n, seed, pose=np.zeros(3), boxes=NO_BOXES):
    rng = np.random.default_rng(seed)
    tracker = Tracker(params, next_id=0)
    return [perceive_lines(index, pose, boxes, params, NO_RIG, tracker, k, rng) for k in range(n)]


def test_miss_rate_grows_with_range_as_stated():
    params = _quiet(miss_prob_base=0.02, miss_prob_range=0.2)
    xs = (4.0, 12.0, 20.0, 28.0)
    index = build_truth_index_b(tuple(_line(i, [[x, -2.0], [x, 2.0]]) for i, x in enumerate(xs)), params)
    n = 3000
    frames = _frames(index, params, n, seed=9)
    seen = np.zeros(len(xs))
    for els in frames:
        for e in els:
            seen[int(np.argmin([abs(np.mean(e["points"], axis=0)[0] - x) for x in xs]))] += 1
    for i, x in enumerate(xs):
        y = np.append(np.arange(0.0, 4.0, 0.5), 4.0) - 2.0
        p = miss_probability(float(np.mean(np.hypot(x, y))), 0.0, False, params)
        assert 1.0 - seen[i] / n == pytest.approx(p, abs=3.5 * np.sqrt(p * (1 - p) / n) + 1e-3)
    assert np.all(np.diff(seen) < 0)


def test_occluded_mask_hides_what_lies_behind_a_box():
    boxes = np.array([[10.0, 0.0, 0.0, 4.6, 1.9]])
    pts = np.array([[20.0, 0.0], [20.0, 5.0], [5.0, 0.0], [10.0, 0.0], [-20.0, 0.0], [30.0, 1.2]])
    assert occluded_mask(pts, boxes).tolist() == [True, False, False, True, False, True]
    inside = np.array([[0.0, 0.0, 0.3, 4.6, 1.9]])  # a box around the sensor hides nothing
    assert not occluded_mask(pts, inside).any()


def test_a_vehicle_ahead_hides_the_line_behind_it():
    params = _quiet()
    index = build_truth_index_b(
        (_line(1, [[0.0, 0.0], [29.0, 0.0]]), _line(2, [[0.0, 3.0], [29.0, 3.0]])), params
    )
    ahead = np.array([[12.0, 0.0, 0.0, 4.6, 1.9]])
    (els,) = _frames(index, params, 1, seed=10, boxes=ahead)
    on_axis = [np.asarray(e["points"]) for e in els if abs(np.mean(e["points"], axis=0)[1]) < 1.0]
    beside = [np.asarray(e["points"]) for e in els if abs(np.mean(e["points"], axis=0)[1] - 3.0) < 1.0]
    assert len(on_axis) == 1 and on_axis[0][:, 0].max() < 12.0 - 2.3 + 0.01  # cut at the box's rear
    assert len(beside) == 1 and beside[0][:, 0].max() > 28.9  # the other line is in full view
    between = np.array([[12.0, 1.5, 0.0, 4.6, 1.9]])  # a box between the lanes shadows the far line
    (els,) = _frames(index, params, 1, seed=10, boxes=between)
    beside = [np.asarray(e["points"]) for e in els if abs(np.mean(e["points"], axis=0)[1] - 3.0) < 1.0]
    assert len(beside) == 1 and beside[0][:, 0].max() < 12.0
    assert sum(abs(np.mean(e["points"], axis=0)[1]) < 1.0 for e in els) == 1


def test_noise_grows_quadratically_with_range():
    params = _quiet(point_sigma_base_m=0.03, point_sigma_quad_per_m2=2e-4)
    index = build_truth_index_b((_line(1, [[-30.0, 5.0], [30.0, 5.0]]),), params)
    pts = np.vstack([np.asarray(e["points"]) for els in _frames(index, params, 1500, seed=11) for e in els])
    r = np.hypot(pts[:, 0], 5.0)
    for lo, hi in ((5.0, 9.0), (14.0, 17.0), (24.0, 29.0)):
        sel = (r >= lo) & (r < hi)
        expected = np.sqrt(np.mean(sigma_at_range_m(0.03, 2e-4, r[sel]) ** 2))
        assert np.std(pts[sel, 1] - 5.0) == pytest.approx(expected, rel=0.1)


def test_false_positives_come_at_the_stated_rate_with_low_scores():
    params = PerceptionParamsB()
    rng = np.random.default_rng(12)
    tracker = Tracker(params, next_id=0)
    fps = [false_positives(params, NO_RIG, tracker, rng) for _ in range(20_000)]
    rate = np.mean([len(f) for f in fps])
    assert rate == pytest.approx(params.false_positive_rate_per_frame, rel=0.08)
    ids = [e["track_id"] for f in fps for e in f]
    assert len(set(ids)) == len(ids)
    a, b = params.spurious_score_beta
    assert np.mean([e["score"] for f in fps for e in f]) == pytest.approx(a / (a + b), abs=0.03)


def test_track_ids_are_stable_and_switch_at_the_stated_rate():
    params = _quiet(track_switch_prob=0.04)
    index = build_truth_index_b((_line(1, [[-25.0, 2.0], [25.0, 2.0]]),), params)
    n = 5000
    ids = [els[0]["track_id"] for els in _frames(index, params, n, seed=13)]
    switches = np.count_nonzero(np.diff(ids))
    expected = params.track_switch_prob * (n - 1)
    assert abs(switches - expected) < 4.0 * np.sqrt(expected)


def test_dashed_divider_is_reported_dash_by_dash_near_and_as_one_run_far():
    params = _quiet()
    index = build_truth_index_b((_line(1, [[-29.0, 1.7], [29.0, 1.7]], style=DividerStyle.DASHED),), params)
    (els,) = _frames(index, params, 1, seed=14)
    lengths = [float(np.ptp(np.asarray(e["points"])[:, 0])) for e in els]
    near = [
        ln for ln, e in zip(lengths, els, strict=True) if np.abs(np.asarray(e["points"])[:, 0]).max() < 19.0
    ]
    assert len(near) >= 3 and all(ln <= params.dash_length_m + 0.01 for ln in near)
    assert max(lengths) > 5.0  # beyond the merge range the dashes are one instance
    assert all(e["style"] == "dashed" for e in els)


def test_lines_are_clipped_at_the_bev_range():
    params = _quiet()
    index = build_truth_index_b((_line(1, [[-100.0, 0.5], [100.0, 0.5]]),), params)
    (els,) = _frames(index, params, 1, seed=15)
    (el,) = els
    xs = np.asarray(el["points"])[:, 0]
    assert xs.min() >= params.range_x_m[0] - 1e-6 and xs.max() <= params.range_x_m[1] + 1e-6
    assert xs.max() - xs.min() > params.range_x_m[1] - params.range_x_m[0] - 1.0
    assert len(el["points"]) == params.points_per_instance


# --- scenario ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fleet_b_scenario(tmp_path_factory):
    out = tmp_path_factory.mktemp("fleet_b") / "urban"
    meta = simulate_scenario("urban", 1, "standard", 7, out, trip_length_m=60.0, fleet="b")
    return out, meta


def test_fleet_b_uploads_validate_and_scenario_json_records_the_model(fleet_b_scenario):
    out, meta = fleet_b_scenario
    doc = json.loads((out / "scenario.json").read_text())
    assert doc["fleet"] == "b" and doc["profile"]["name"] == "fleet-b"
    assert len(doc["profile"]["gnss"]["status_errors"]) == 4 and "occluders" in doc["profile"]["perception"]
    validator = jsonschema.Draft202012Validator(
        json.loads(SCHEMA.read_text()), format_checker=jsonschema.FormatChecker()
    )
    for path in sorted((out / "trips").glob("*.json.gz")):
        body = gzip.decompress(path.read_bytes())
        validate_upload_json(body)
        upload = orjson.loads(body)
        validator.validate(upload)
        assert any(e.get("track_id") is not None for f in upload["frames"] for e in f["elements"])


def test_fleet_b_is_deterministic(fleet_b_scenario, tmp_path):
    out, _ = fleet_b_scenario
    simulate_scenario("urban", 1, "standard", 7, tmp_path / "again", trip_length_m=60.0, fleet="b")
    assert _folder_hash(tmp_path / "again") == _folder_hash(out)


def test_fleet_a_output_is_unchanged(tmp_path):
    simulate_scenario("urban", 2, "standard", 5, tmp_path / "a", trip_length_m=150.0)
    assert _folder_hash(tmp_path / "a") == FLEET_A_URBAN_2_SEED_5_HASH
    assert "fleet" not in json.loads((tmp_path / "a" / "scenario.json").read_text())


def test_fleet_b_traffic_stops_more_and_loops():
    b = FleetBParams().traffic
    assert b.red_light_prob > TrafficParams().red_light_prob and b.loop_route_share > 0.0


def test_unknown_fleet_or_a_fleet_a_profile_with_fleet_b_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="unknown fleet"):
        simulate_scenario("urban", 1, "standard", 0, tmp_path / "x", fleet="c")
    with pytest.raises(ValueError, match="own parameters"):
        simulate_scenario("urban", 1, "hard", 0, tmp_path / "y", fleet="b")


def test_csr_simulate_takes_the_fleet_option(tmp_path):
    from services.cli import main

    assert (
        main(
            [
                "simulate",
                "--world",
                "rural",
                "--trips",
                "1",
                "--trip-length-m",
                "60",
                "--seed",
                "2",
                "--fleet",
                "b",
                "--out",
                str(tmp_path / "s"),
            ]
        )
        == 0
    )
    assert json.loads((tmp_path / "s" / "scenario.json").read_text())["fleet"] == "b"
