"""The per-tile pipeline end to end: a simulated fleet uploaded over HTTP, processed by
the real job runners (in-process on the embedded default, a Celery worker on PostGIS + Redis),
read back as poses, map, vector tiles and versions, and scored like ``csr reconstruct``; then an
incremental trip, two merges racing for one tile, and a worker killed in the middle of a merge."""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import mapbox_vector_tile
import numpy as np
import pytest
from sqlalchemy import create_engine
from sqlalchemy.orm import sessionmaker

from csr_core.bench.evaluate import evaluate_output
from services import fleet
from services.settings import Settings
from tests.integration.conftest import BIN, Deployment, RedisServer, wait_until
from workers import tile_jobs

pytestmark = pytest.mark.integration


def _csr(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "csr"), *args],
        capture_output=True,
        text=True,
        check=True,
        env={
            "OPENBLAS_NUM_THREADS": "1",
            "PATH": str(Path(sys.executable).parent),
            **{k: v for k, v in os.environ.items() if k == "PYTHONPATH"},  # the code under test
        },
    )


@pytest.fixture(scope="module")
def fleet_dirs(tmp_path_factory) -> dict[str, Path]:
    """Four urban trips: the first three are the fleet, the fourth arrives later (incremental)."""
    root = tmp_path_factory.mktemp("fleet")
    _csr(
        "simulate",
        "--world",
        "urban",
        "--trips",
        "4",
        "--profile",
        "standard",
        "--seed",
        "21",
        "--trip-length-m",
        "450",
        "--out",
        str(root / "all"),
    )
    trips = sorted((root / "all" / "trips").iterdir())
    dirs = {}
    for name, chosen in (("first", trips[:3]), ("late", trips[3:])):
        d = root / name
        shutil.copytree(root / "all", d, ignore=shutil.ignore_patterns("*.json.gz"))
        for t in chosen:
            shutil.copy(t, d / "trips" / t.name)
        keep = {t.name.removesuffix(".json.gz") for t in chosen}
        for truth in (d / "truth" / "poses").iterdir():
            if truth.name.removesuffix(".csv") not in keep:
                truth.unlink()
        dirs[name] = d
    dirs["all"] = root / "all"
    dirs["reconstruct"] = root / "reconstructed"
    _csr("reconstruct", str(dirs["first"]), "--out", str(dirs["reconstruct"]))
    return dirs


def _run_fleet(dep: Deployment, scenario: Path, out: Path) -> dict[str, dict[str, str]]:
    with fleet.client_for(dep.base_url, dep.admin_key) as http:
        ids = fleet.upload_scenario(http, scenario, progress=False)
        statuses = fleet.wait_until_processed(http, ids, timeout_s=600, progress=False)
        fleet.download_results(http, ids, out, fleet.scenario_bbox(scenario))
    return {"ids": ids, "statuses": statuses}


@pytest.mark.parametrize("kind", ["embedded", "distributed"])
def test_a_fleet_uploaded_over_http_is_aligned_and_mapped_like_csr_reconstruct(
    kind, make_isolated, request, fleet_dirs, tmp_path
):
    # a Redis of its own: workers of another deployment on the same Redis would take its jobs
    redis_url = request.getfixturevalue("private_redis").url if kind == "distributed" else ""
    dep = make_isolated(kind, redis_url=redis_url)
    dep.start_server()
    if dep.distributed:
        dep.start_worker()
    run = _run_fleet(dep, fleet_dirs["first"], tmp_path / "service")
    assert set(run["statuses"].values()) == {"aligned"}, run["statuses"]

    service = evaluate_output(fleet_dirs["first"], tmp_path / "service").evaluation
    batch = evaluate_output(fleet_dirs["first"], fleet_dirs["reconstruct"]).evaluation
    assert service.coverage == 1.0
    # the same algorithm per tile as in one batch: the same accuracy (the benchmark measures it closely)
    assert service.aligned.ate.rmse <= 1.25 * batch.aligned.ate.rmse + 0.05, (service.aligned, batch.aligned)
    assert service.aligned.rpe.rmse <= 1.25 * batch.aligned.rpe.rmse + 0.02, (service.aligned, batch.aligned)
    assert service.map_aligned.mcd <= 1.25 * batch.map_aligned.mcd + 0.05, (
        service.map_aligned.mcd,
        batch.map_aligned.mcd,
    )

    tiles = dep.rows("SELECT z, x, y, version, status, n_features FROM tile_versions ORDER BY id")
    assert tiles and all(t.version == 1 and t.status == "published" for t in tiles), tiles
    _check_bias_messages(dep)
    # seams: where an element crosses a tile edge, the neighbour's half continues it
    qualities = [
        q if isinstance(q, dict) else json.loads(q) for (q,) in dep.rows("SELECT quality FROM tile_versions")
    ]
    seams = [q["seams"] for q in qualities if q.get("seams", {}).get("checked")]
    assert seams, "no element crossing a tile edge was checked against its neighbour"
    assert max(s["median_gap_m"] for s in seams) < 0.15, seams
    # lines held back from a version (trips drove alongside them without seeing them) are counted
    assert all(isinstance(q["held_back"], dict) for q in qualities), qualities
    busiest = max(tiles, key=lambda t: t.n_features)
    with dep.admin() as http:
        mvt = http.get(f"/v1/tiles/{busiest.z}/{busiest.x}/{busiest.y}.mvt")
        assert mvt.status_code == 200, mvt.text
        layers = mapbox_vector_tile.decode(mvt.content)
        assert sum(len(layer["features"]) for layer in layers.values()) >= busiest.n_features * 0.9
        metrics = http.get("/metrics").text  # ops: the map's size and version, no series per tile
        assert f"csr_published_tiles {float(len(tiles))}" in metrics
        assert f"csr_map_version {float(max(dep.rows('SELECT id FROM tile_versions'))[0])}" in metrics
        assert "csr_tile_last_update_timestamp_seconds " in metrics and 'tile="' not in metrics
        history = (
            http.get(f"/v1/tiles/{busiest.z}/{busiest.x}/{busiest.y}/versions").raise_for_status().json()
        )
        assert [v["version"] for v in history["versions"]] == [1]
        # every element has its absolute sigma: above its relative one, within its trips' GNSS bias
        tile_features = (
            http.get(f"/v1/tiles/{busiest.z}/{busiest.x}/{busiest.y}.geojson").raise_for_status().json()
        )["features"]
        biases = [
            (d if isinstance(d, dict) else json.loads(d))["gnss_bias_sigma_m"]
            for (d,) in dep.rows("SELECT diagnostics FROM trip_reconstructions")
        ]
        for f in tile_features:
            p = f["properties"]
            assert (
                p["uncertainty_m"] < p["sigma_abs_m"] <= math.hypot(p["uncertainty_m"], max(biases)) + 1e-3
            ), p
        cert = (
            http.get(f"/v1/tiles/{busiest.z}/{busiest.x}/{busiest.y}/certificate").raise_for_status().json()
        )
        merged = dep.rows(
            "SELECT DISTINCT trip_pk FROM trip_tile_alignments WHERE z = :z AND x = :x AND y = :y "
            "AND merged_version_id IS NOT NULL",
            z=busiest.z,
            x=busiest.x,
            y=busiest.y,
        )
        assert cert["n_features"] > 0 and cert["trips"] == len(merged) > 0, cert
        assert cert["expected_relative_error_m"] < cert["expected_absolute_error_m"], cert
    batch_map = json.loads((fleet_dirs["reconstruct"] / "map.geojson").read_text())["features"]
    assert batch_map and all(
        f["properties"]["sigma_abs_m"] >= f["properties"]["uncertainty_m"] for f in batch_map
    )

    # incremental: one more trip updates the tiles it crosses; element ids carry over
    v1_ids = {r.feature_id for r in dep.rows("SELECT feature_id FROM map_features WHERE change != 'removed'")}
    run = _run_fleet(dep, fleet_dirs["late"], tmp_path / "late")
    assert set(run["statuses"].values()) == {"aligned"}, run["statuses"]
    newer = dep.rows("SELECT id, changes FROM tile_versions WHERE version = 2")
    assert newer, "the new trip made no new tile version"
    v2_ids = {
        r.feature_id
        for r in dep.rows(
            "SELECT f.feature_id FROM map_features f JOIN tile_versions v ON v.id = f.tile_version_id "
            "WHERE v.version = 2 AND f.change != 'removed'"
        )
    }
    assert len(v2_ids & v1_ids) >= 0.5 * len(v2_ids), "element ids did not survive the new trip"
    late_trip = run["ids"][next(iter(run["ids"]))]
    assert all(r.changes for r in newer)
    assert all(
        late_trip in str(r.trips) for r in dep.rows("SELECT trips FROM tile_versions WHERE version = 2")
    )


def test_two_merges_of_one_tile_one_writes_the_other_retries(
    make_isolated, private_redis: RedisServer, fleet_dirs, tmp_path
):
    """Both read version 1 and fuse the same new trip; the first writes version 2, the second finds
    version 2 where it expected 1 (the OSM API's 409) and is retried: then nothing is left to merge."""
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    dep.start_worker()
    _run_fleet(dep, fleet_dirs["first"], tmp_path / "service")
    z, x, y = max(dep.rows("SELECT z, x, y, n_features FROM tile_versions"), key=lambda r: r.n_features)[:3]
    # make the tile's alignments look unmerged again, as if a new trip had just been aligned
    with dep.engine.begin() as conn:
        conn.exec_driver_sql(
            "UPDATE trip_tile_alignments SET merged_version_id = NULL WHERE z = %s AND x = %s AND y = %s",
            (z, x, y),
        )
    factory = sessionmaker(create_engine(dep.db_url), expire_on_commit=False)
    settings = Settings()
    first = tile_jobs.compute_merge_tile(factory, settings, z, x, y)
    second = tile_jobs.compute_merge_tile(factory, settings, z, x, y)
    assert first.expected_latest == second.expected_latest == 1 and first.trips
    with factory.begin() as session:
        tile_jobs.persist_merge_tile(session, "job-a", z, x, y, first)
    with pytest.raises(tile_jobs.RetryJob), factory.begin() as session:
        tile_jobs.persist_merge_tile(session, "job-b", z, x, y, second)
    written = dep.rows(
        "SELECT version, job_id FROM tile_versions WHERE z = :z AND x = :x AND y = :y ORDER BY version",
        z=z,
        x=x,
        y=y,
    )
    assert [r.version for r in written] == [1, 2] and written[1].job_id == "job-a"
    again = tile_jobs.compute_merge_tile(factory, settings, z, x, y)
    assert again.nothing_to_do and again.expected_latest == 2


def test_a_worker_killed_mid_merge_leaves_the_old_version_and_the_merge_is_redone(
    make_isolated, private_redis: RedisServer, fleet_dirs, tmp_path
):
    dep = make_isolated("distributed", redis_url=private_redis.url)
    dep.start_server()
    worker = dep.start_worker()
    _run_fleet(dep, fleet_dirs["first"], tmp_path / "service")
    before = [tuple(r) for r in dep.rows("SELECT id, z, x, y, version FROM tile_versions ORDER BY id")]
    worker.stop()

    slow = dep.start_worker(CSR_TEST_MERGE_DELAY_S="120")
    with fleet.client_for(dep.base_url, dep.admin_key) as http:
        fleet.upload_scenario(http, fleet_dirs["late"], progress=False)
        wait_until(
            lambda: (
                dep.scalar("SELECT count(*) FROM jobs WHERE kind = 'ingest_trip' AND state = 'done'") == 4
            ),
            timeout_s=120,
            what="the late trip's ingest",
        )
        http.post("/v1/process").raise_for_status()
    wait_until(
        lambda: dep.scalar("SELECT count(*) FROM jobs WHERE kind = 'merge_tile' AND state = 'running'"),
        timeout_s=180,
        what=lambda: f"a merge to start; worker log:\n{slow.log_tail()}",
    )
    slow.kill_group(signal.SIGKILL)
    assert [
        tuple(r) for r in dep.rows("SELECT id, z, x, y, version FROM tile_versions ORDER BY id")
    ] == before

    rescuer = dep.start_worker(CSR_VISIBILITY_TIMEOUT_S="4", CSR_JOB_TIME_LIMIT_S="3")
    wait_until(
        lambda: dep.scalar("SELECT count(*) FROM jobs WHERE kind = 'merge_tile' AND state != 'done'") == 0,
        timeout_s=240,
        what=lambda: f"the merges to be redone; worker log:\n{rescuer.log_tail()}",
    )
    assert dep.scalar("SELECT count(*) FROM jobs WHERE state = 'failed'") == 0
    assert dep.scalar("SELECT max(attempts) FROM jobs WHERE kind = 'merge_tile'") == 2
    after = dep.rows("SELECT z, x, y, version FROM tile_versions WHERE version = 2")
    assert after, "the killed merge was not redone"
    assert [
        tuple(r)
        for r in dep.rows("SELECT id, z, x, y, version FROM tile_versions WHERE version = 1 ORDER BY id")
    ] == before


def _check_bias_messages(dep: Deployment) -> None:
    """A tile's alignment hears what the other tiles found of its trips' GNSS biases: one message
    per trip and other tile that aligned it, the mean shift that tile gave the trip's frames."""
    from sqlalchemy.orm import Session

    from csr_core.geo import LocalFrame
    from csr_core.tiling import reframe_poses
    from services.db.models import TripTileAlignment
    from services.reconstructions import decode_arrays
    from services.tile_frames import tile_frame
    from workers.tile_jobs import _load_reconstruction, bias_messages_of

    rows = dep.rows("SELECT trip_pk, z, x, y FROM trip_tile_alignments WHERE failed_reason IS NULL")
    tiles_of: dict[str, set[tuple[int, int, int]]] = {}
    for r in rows:
        tiles_of.setdefault(r.trip_pk, set()).add((r.z, r.x, r.y))
    pk, tiles = max(tiles_of.items(), key=lambda kv: len(kv[1]))
    assert len(tiles) >= 2, "no trip crosses two tiles: nothing to pass"
    here, there = sorted(tiles)[:2]
    frame = tile_frame(*here)
    with Session(dep.engine) as session:
        recon = _load_reconstruction(session, pk, frame)
        assert recon is not None
        messages = bias_messages_of(session, {pk: recon}, *here, frame)[pk]
        assert len(messages) == len(tiles) - 1  # every other tile, not this one
        other = session.get(TripTileAlignment, (pk, *there))
        assert other is not None
        arrays = decode_arrays(other.arrays)
        idx, w = arrays["frame_indices"].astype(int), arrays["weights"]
        aligned = reframe_poses(arrays["poses_xyyaw"], LocalFrame(other.origin_lat, other.origin_lon), frame)[
            :, :2
        ]
        shift = ((aligned - recon.poses_xyyaw_world[idx, :2]) * w[:, None]).sum(0) / w.sum()
    assert any(np.allclose(m.bias_xy_m, shift, atol=1e-6) for m in messages), (messages, shift)
    assert all(0 < m.variance_m2 < 1.0 for m in messages)
