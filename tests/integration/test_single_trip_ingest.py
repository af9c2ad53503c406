"""The ingest job runs single-trip reconstruction and stores its result per trip
(``trip_reconstructions``), idempotently; ``csr reprocess`` recomputes it from the kept upload;
a trip that cannot be reconstructed fails with its reason. Both deployments, real processes."""

from __future__ import annotations

import gzip
import secrets
import subprocess
from typing import Any

import numpy as np
import orjson
import pytest
import sqlalchemy as sa

from csr_core import se2
from csr_core.geo import LocalFrame, region_frame_for
from csr_core.sim import simulate_scenario
from csr_core.single_trip.pose_graph import integrate_increments
from services.reconstructions import ALGORITHM_VERSION, decode_arrays
from tests.integration.conftest import (
    BIN,
    REPO,
    Deployment,
    moving_trip,
    unique_trip,
    wait_until,
)

pytestmark = pytest.mark.integration


@pytest.fixture(scope="session")
def simulated_doc(tmp_path_factory) -> dict[str, Any]:
    """One simulated 400 m urban trip (standard sensor profile), as its vehicle uploads it."""
    out = tmp_path_factory.mktemp("sim")
    simulate_scenario("urban", n_trips=1, profile="standard", seed=3, out_dir=out, trip_length_m=400.0)
    (path,) = sorted((out / "trips").glob("*.json.gz"))
    return orjson.loads(gzip.decompress(path.read_bytes()))


def _trip(dep: Deployment, trip_pk: str) -> dict[str, Any]:
    with dep.admin() as http:
        return http.get(f"/v1/trips/{trip_pk}").raise_for_status().json()


def _upload_and_wait(dep: Deployment, doc: dict[str, Any], status: str = "processing") -> str:
    response = dep.upload(doc, gzipped=True)
    assert response.status_code == 202, response.text
    trip_pk = response.json()["id"]
    wait_until(lambda: _trip(dep, trip_pk)["status"] == status, timeout_s=90, what=f"trip {status}")
    return trip_pk


def _json(value: Any) -> Any:  # JSON columns: parsed by psycopg, text on SQLite
    return orjson.loads(value) if isinstance(value, str) else value


def _stored(dep: Deployment, trip_pk: str) -> list[dict[str, Any]]:
    rows = dep.rows(
        "SELECT algorithm_version, origin_lat, origin_lon, n_frames, n_keyframes, n_instances, arrays, "
        "instances, noise, created_at FROM trip_reconstructions WHERE trip_pk = :p",
        p=trip_pk,
    )
    out = []
    for r in rows:
        row = dict(r._mapping)
        row["arrays"] = decode_arrays(bytes(row["arrays"]))
        row["instances"], row["noise"] = _json(row["instances"]), _json(row["noise"])
        out.append(row)
    return out


def _execute(dep: Deployment, sql: str, **params: Any) -> None:
    assert dep.engine is not None
    with dep.engine.begin() as conn:
        conn.execute(sa.text(sql), params)


def _reprocess(dep: Deployment, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "csr"), "reprocess", *args],
        env=dep.env,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=180,
    )


def test_ingest_stores_smoothed_poses_instances_and_noise(deployment: Deployment, simulated_doc):
    doc = {**simulated_doc, "trip_id": "sim-" + secrets.token_hex(4)}
    trip_pk = _upload_and_wait(deployment, doc)

    (row,) = _stored(deployment, trip_pk)
    n = len(doc["frames"])
    assert row["algorithm_version"] == ALGORITHM_VERSION
    assert row["n_frames"] == n
    poses = row["arrays"]["poses_xyyaw_world"]
    assert poses.shape == (n, 3) and np.isfinite(poses).all()
    assert row["arrays"]["pose_sigma_xy_m"].shape == (n,)
    keyframes = row["arrays"]["keyframe_indices"]
    assert len(keyframes) == row["n_keyframes"] > 1 and np.all(np.diff(keyframes) > 0)

    # the frame is the region frame of the first fix; poses are within a few metres of the raw GNSS
    first = doc["frames"][0]["gnss"]
    region = region_frame_for([first["lon"], first["lat"]])
    assert (row["origin_lat"], row["origin_lon"]) == pytest.approx((region.origin_lat, region.origin_lon))
    fixes = [(i, f["gnss"]) for i, f in enumerate(doc["frames"]) if f["gnss"]["status"] != "none"]
    gnss_xy = LocalFrame(row["origin_lat"], row["origin_lon"]).to_local(
        np.array([(g["lon"], g["lat"]) for _, g in fixes])
    )
    offsets_m = np.linalg.norm(poses[[i for i, _ in fixes], :2] - gnss_xy, axis=1)
    assert np.median(offsets_m) < 2.0 and np.percentile(offsets_m, 95) < 5.0, offsets_m

    # instances: non-empty, typed, near the trajectory
    assert row["n_instances"] == len(row["instances"]) > 0
    for instance in row["instances"]:
        points = np.asarray(instance["points_xy"])
        assert points.ndim == 2 and points.shape[1] == 2 and len(points) >= 2
        assert instance["n_observations"] > 0
        assert np.min(np.linalg.norm(points[:, None] - poses[None, :, :2], axis=2)) < 40.0
    assert set(row["noise"]) >= {"lane_divider", "road_boundary"}

    trip = _trip(deployment, trip_pk)
    summary = trip["reconstruction"]
    assert summary["algorithm_version"] == ALGORITHM_VERSION
    assert (summary["frames"], summary["keyframes"], summary["instances"]) == (
        n,
        row["n_keyframes"],
        row["n_instances"],
    )
    assert summary["noise"]["lane_divider"]["lateral_sigma_m"] > 0
    assert summary["frame"] == {"origin_lat": row["origin_lat"], "origin_lon": row["origin_lon"]}
    # a trip whose GNSS is good passes the integrity test at the first solve
    assert trip["quality"]["verdict"] == "ok" and trip["quality"]["degraded"] is False
    assert trip["quality"]["median_offset_m"] < 1.5 * trip["quality"]["gnss_median_expected_m"]
    with deployment.admin() as http:
        poses_answer = http.get(f"/v1/trips/{trip_pk}/poses")
    assert poses_answer.status_code == 409 and poses_answer.json()["error"] == "not_aligned"


def _with_gyro_bias(doc: dict[str, Any], bias_deg_s: float) -> dict[str, Any]:
    """``doc`` with its odometry re-integrated from increments whose yaw carries a constant
    gyro bias (a runaway heading for a smoother that trusts the odometry's yaw)."""
    odom = np.array([[f["odom"]["x"], f["odom"]["y"], f["odom"]["yaw"]] for f in doc["frames"]])
    t = np.array([f["t"] for f in doc["frames"]])
    incr = se2.between(odom[:-1], odom[1:])
    incr[:, 2] += np.radians(bias_deg_s) * np.diff(t)
    biased = integrate_increments(odom[0], incr)
    frames = [
        {**f, "odom": {"x": round(float(p[0]), 3), "y": round(float(p[1]), 3), "yaw": round(float(p[2]), 6)}}
        for f, p in zip(doc["frames"], biased, strict=True)
    ]
    return {**doc, "frames": frames}


def test_a_runaway_heading_is_caught_and_reported_on_the_trip(deployment: Deployment, simulated_doc):
    """A gyro bias of 3 deg/s planted in the upload: the poses fail the test against the trip's
    own GNSS; the trip says so in ``quality`` (repaired, or degraded with GNSS-anchored poses)
    and its stored poses stay within its GNSS error."""
    doc = _with_gyro_bias({**simulated_doc, "trip_id": "runaway-" + secrets.token_hex(4)}, 3.0)
    trip_pk = _upload_and_wait(deployment, doc)
    quality = _trip(deployment, trip_pk)["quality"]
    assert quality["verdict"] in ("repaired", "degraded"), quality
    assert "from the trip's GNSS" in quality["reason"] or "off the trip's GNSS" in quality["reason"]
    assert quality["degraded"] == (quality["verdict"] == "degraded")
    assert quality["median_offset_m"] <= 1.5 * quality["gnss_median_expected_m"]


def test_a_rerun_ingest_job_leaves_exactly_one_row(deployment: Deployment):
    trip_pk = _upload_and_wait(deployment, moving_trip())
    (before,) = _stored(deployment, trip_pk)
    job_id = deployment.scalar("SELECT id FROM jobs WHERE subject = :p", p=trip_pk)
    # as if the job's message came again and the job had to run again
    _execute(deployment, "UPDATE jobs SET state = 'queued', dispatched_at = NULL WHERE id = :j", j=job_id)
    wait_until(
        lambda: (
            [tuple(r) for r in deployment.rows("SELECT state, attempts FROM jobs WHERE id = :j", j=job_id)]
            == [("done", 2)]
        ),
        timeout_s=60,
        what="the ingest job to run again",
    )
    (after,) = _stored(deployment, trip_pk)
    assert str(after["created_at"]) > str(before["created_at"])  # rewritten, not duplicated
    np.testing.assert_allclose(after["arrays"]["poses_xyyaw_world"], before["arrays"]["poses_xyyaw_world"])


def test_reprocess_recomputes_a_trip_from_its_raw_upload(deployment: Deployment):
    trip_pk = _upload_and_wait(deployment, moving_trip(length_m=200.0))
    (before,) = _stored(deployment, trip_pk)
    _execute(deployment, "DELETE FROM trip_reconstructions WHERE trip_pk = :p", p=trip_pk)
    assert _trip(deployment, trip_pk)["reconstruction"] is None

    done = _reprocess(deployment, "--trip", trip_pk, "--wait", "90")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "1 ingest job(s) scheduled for 1 trip(s)" in done.stdout
    (after,) = _stored(deployment, trip_pk)
    np.testing.assert_allclose(after["arrays"]["poses_xyyaw_world"], before["arrays"]["poses_xyyaw_world"])
    assert after["instances"] == before["instances"]
    trip = _trip(deployment, trip_pk)
    assert trip["status"] == "processing" and trip["reconstruction"]["frames"] == before["n_frames"]
    jobs = deployment.rows("SELECT kind, state FROM jobs WHERE subject = :p ORDER BY created_at", p=trip_pk)
    assert [tuple(r) for r in jobs] == [("ingest_trip", "done"), ("ingest_trip", "done")]

    unknown = _reprocess(deployment, "--trip", "no-such-trip")
    assert unknown.returncode == 2 and "no-such-trip" in unknown.stderr


def test_a_trip_that_cannot_be_reconstructed_fails_with_its_reason(deployment: Deployment):
    # the contract example: 1 s of a standing vehicle without GNSS course; nothing can orient it
    trip_pk = _upload_and_wait(deployment, unique_trip(), status="failed")
    trip = _trip(deployment, trip_pk)
    assert trip["error"].startswith("single-trip reconstruction failed: ")
    assert trip["reconstruction"] is None
    assert _stored(deployment, trip_pk) == []
    jobs = deployment.rows("SELECT state, attempts, error FROM jobs WHERE subject = :p", p=trip_pk)
    assert [tuple(r)[:2] for r in jobs] == [("failed", 1)]  # not retried
    assert "single-trip reconstruction failed" in jobs[0][2]


def test_reprocess_stale_recomputes_missing_results_and_reports_failures(make_isolated):
    dep = make_isolated("embedded")
    dep.start_server()
    good = _upload_and_wait(dep, moving_trip())
    bad = _upload_and_wait(dep, unique_trip(), status="failed")
    _execute(dep, "DELETE FROM trip_reconstructions")

    done = _reprocess(dep, "--stale", "--wait", "90")
    assert done.returncode == 1, done.stdout + done.stderr  # the unreconstructable trip fails again
    assert "2 ingest job(s) scheduled for 2 trip(s)" in done.stdout and "1 done, 1 failed" in done.stdout
    assert len(_stored(dep, good)) == 1 and _stored(dep, bad) == []
    assert _trip(dep, good)["status"] == "processing" and _trip(dep, bad)["status"] == "failed"
    again = _reprocess(dep, "--stale")  # only the failed trip still lacks a result
    assert again.returncode == 0 and "1 ingest job(s) scheduled for 1 trip(s)" in again.stdout
    dep.wait_idle()
