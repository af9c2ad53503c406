"""Retention of raw uploads, erasure of a vehicle's data and who reads trip traces, on both
deployments (the embedded SQLite default with in-process jobs; PostGIS, Redis and a Celery worker):
raw uploads deleted after ``CSR_RAW_RETENTION_DAYS`` while the map stays, ``csr purge`` and
``DELETE /v1/vehicles/{id}/data`` erasing every row of a vehicle and re-merging its tiles without
it, idempotently, and ``CSR_READER_SEES_TRACES``."""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import sqlalchemy as sa

from tests.integration.conftest import BIN, REPO, Deployment, RedisServer, base_env, moving_trip, wait_until

pytestmark = pytest.mark.integration

KINDS = ["embedded", "distributed"]
# every table keyed by a trip: (table, column holding the trip's server id)
TRIP_TABLES = (
    ("trips", "id"),
    ("trip_uploads", "trip_pk"),
    ("trip_reconstructions", "trip_pk"),
    ("trip_tiles", "trip_pk"),
    ("trip_tile_alignments", "trip_pk"),
    ("trip_poses", "trip_pk"),
    ("match_pairs", "trip_pk_i"),
    ("match_pairs", "trip_pk_j"),
    ("jobs", "subject"),
)


def _start(make_isolated: Callable[..., Deployment], kind: str, redis_url: str, **env: str) -> Deployment:
    dep = make_isolated(kind, redis_url=redis_url if kind == "distributed" else "", **env)
    dep.start_server()
    if dep.distributed:
        dep.start_worker()
    return dep


def _csr(dep: Deployment, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "csr"), *args], env=dep.env, cwd=REPO, capture_output=True, text=True, timeout=300
    )


def _upload_and_process(dep: Deployment, vehicles: list[str]) -> list[str]:
    """One moving trip per entry (same road), processed into the map; the trips' ids."""
    pks = []
    for vehicle in vehicles:
        response = dep.upload(moving_trip(vehicle, length_m=200.0))
        assert response.status_code == 202, response.text
        pks.append(response.json()["id"])
    dep.wait_idle(timeout_s=300)
    with dep.admin() as http:
        http.post("/v1/process").raise_for_status()
    dep.wait_idle(timeout_s=600)
    with dep.admin() as http:
        statuses = [http.get(f"/v1/trips/{pk}").json()["status"] for pk in pks]
    assert statuses == ["aligned"] * len(pks)
    return pks


def _map(dep: Deployment) -> list[dict]:
    with dep.admin() as http:
        response = http.get("/v1/map", params={"bbox": "11.56,48.13,11.59,48.14"})
        response.raise_for_status()
        return response.json()["features"]


def _rows_of(dep: Deployment, trip_pks: list[str]) -> dict[str, int]:
    counts = {}
    for table, column in TRIP_TABLES:
        n = 0
        for pk in trip_pks:
            n += dep.scalar(f"SELECT count(*) FROM {table} WHERE {column} = :pk", pk=pk)
        counts[f"{table}.{column}"] = n
    return counts


def _version_trips(dep: Deployment) -> list[str]:
    """Every trip id named in any tile version's provenance."""
    import json

    out: list[str] = []
    for (trips,) in dep.rows("SELECT trips FROM tile_versions"):
        out += trips if isinstance(trips, list) else json.loads(trips)
    return out


# --- the migration ------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["sqlite", "postgis"])
def test_migration_0008_adds_and_drops_raw_purged_at(tmp_path: Path, pg, backend: str) -> None:
    if backend == "postgis":
        url = pg.create()
        env = base_env(tmp_path, CSR_DATABASE_URL=url)
    else:
        env = base_env(tmp_path)
        url = f"sqlite:///{tmp_path / 'data' / 'csr.sqlite3'}"

    def alembic(*args: str) -> None:
        subprocess.run([str(BIN / "alembic"), *args], env=env, cwd=REPO, check=True, capture_output=True)

    def columns() -> set[str]:
        engine = sa.create_engine(url)
        try:
            return {c["name"] for c in sa.inspect(engine).get_columns("trips")}
        finally:
            engine.dispose()

    alembic("upgrade", "head")
    assert "raw_purged_at" in columns()
    alembic("downgrade", "0007")
    assert "raw_purged_at" not in columns() and "track" in columns()
    alembic("upgrade", "head")
    assert "raw_purged_at" in columns()


# --- retention ----------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_retention_deletes_raw_uploads_past_their_time_and_keeps_the_map(
    make_isolated, private_redis: RedisServer, kind: str
) -> None:
    dep = _start(
        make_isolated, kind, private_redis.url, CSR_RAW_RETENTION_DAYS="1", CSR_RETENTION_CHECK_EVERY_S="0.5"
    )
    old, recent = _upload_and_process(dep, ["veh-r1", "veh-r2"])
    features_before = _map(dep)
    assert features_before, "the two trips make a map"
    # received two days ago: past the one-day retention
    assert dep.engine is not None
    with dep.engine.begin() as conn:
        conn.execute(
            sa.text("UPDATE trips SET received_at = :t WHERE id = :pk"),
            {"t": datetime.now(UTC) - timedelta(days=2), "pk": old},
        )
    wait_until(
        lambda: dep.scalar("SELECT count(*) FROM trip_uploads WHERE trip_pk = :pk", pk=old) == 0,
        timeout_s=120,  # a check every 0.5 s; the loop shares a loaded machine with the jobs
        what="the old upload to be deleted",
    )
    assert dep.scalar("SELECT count(*) FROM trip_uploads WHERE trip_pk = :pk", pk=recent) == 1
    with dep.admin() as http:
        trip = http.get(f"/v1/trips/{old}").json()
        assert trip["status"] == "aligned" and trip["raw_purged_at"] is not None
        assert trip["reconstruction"] is not None
        assert http.get(f"/v1/trips/{recent}").json()["raw_purged_at"] is None
        gone = http.get(f"/v1/trips/{old}/upload")
        assert gone.status_code == 410 and gone.json()["error"] == "purged"
        assert http.get(f"/v1/trips/{recent}/upload").status_code == 200
        assert http.get(f"/v1/trips/{old}/poses").status_code == 200
    assert _map(dep) == features_before
    # reprocessing a trip without its raw upload says why
    result = _csr(dep, "reprocess", "--trip", old)
    assert result.returncode == 2
    assert f"trip {old} has no raw upload to recompute from" in result.stderr
    assert "CSR_RAW_RETENTION_DAYS" in result.stderr
    result = _csr(dep, "reprocess", "--all")
    assert result.returncode == 0, result.stderr
    assert "1 trip(s) left out: their raw uploads were deleted" in result.stdout
    assert "1 ingest job(s) scheduled for 1 trip(s)" in result.stdout


# --- erasure ------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_purge_erases_every_row_of_a_vehicle_and_remerges_its_tiles(
    make_isolated, private_redis: RedisServer, kind: str
) -> None:
    dep = _start(make_isolated, kind, private_redis.url)
    pks = _upload_and_process(dep, ["veh-gone", "veh-stay", "veh-gone", "veh-stay"])
    gone, stay = [pks[0], pks[2]], [pks[1], pks[3]]
    assert set(gone) <= set(_version_trips(dep))
    assert all(n > 0 for k, n in _rows_of(dep, gone).items() if not k.startswith("match_pairs")), _rows_of(
        dep, gone
    )
    latest_before = dep.scalar("SELECT max(id) FROM tile_versions")

    dry = _csr(dep, "purge", "--vehicle", "veh-gone", "--dry-run")
    assert dry.returncode == 0, dry.stderr
    assert all(f"trip {pk}" in dry.stdout for pk in gone) and "nothing changed" in dry.stdout
    assert dep.scalar("SELECT count(*) FROM trips WHERE vehicle_id = 'veh-gone'") == 2

    result = _csr(dep, "purge", "--vehicle", "veh-gone")
    assert result.returncode == 0, result.stderr
    assert "erased 2 trip(s)" in result.stdout and "merge job(s) queued" in result.stdout
    assert "purge veh-gone" in result.stderr  # the progress bar
    assert all(n == 0 for n in _rows_of(dep, gone).values()), _rows_of(dep, gone)
    # no stored provenance names them any more, in old versions either
    assert not set(gone) & set(_version_trips(dep))
    dep.wait_idle(timeout_s=600)

    # new versions of the touched tiles, rebuilt from the vehicle that stays
    new = dep.rows(
        "SELECT z, x, y, reason, trips, state IS NOT NULL AS has_state FROM tile_versions WHERE id > :v",
        v=latest_before,
    )
    assert new and {r.reason for r in new} == {"erasure"}
    import json

    named = {t for r in new for t in (r.trips if isinstance(r.trips, list) else json.loads(r.trips))}
    assert named == set(stay)
    # earlier versions keep no topology state (it held the erased trips' points)
    for r in new:
        assert (
            dep.scalar(
                "SELECT count(*) FROM tile_versions WHERE z = :z AND x = :x AND y = :y AND id <= :v "
                "AND state IS NOT NULL",
                z=r.z,
                x=r.x,
                y=r.y,
                v=latest_before,
            )
            == 0
        )
    assert _map(dep), "the other vehicle's trips still make a map"
    with dep.admin() as http:
        for pk in stay:
            assert http.get(f"/v1/trips/{pk}").json()["status"] == "aligned"
            assert http.get(f"/v1/trips/{pk}/poses").status_code == 200
        for pk in gone:
            assert http.get(f"/v1/trips/{pk}").status_code == 404

    # a second purge is a no-op answer, and changes nothing
    versions = dep.scalar("SELECT count(*) FROM tile_versions")
    again = _csr(dep, "purge", "--vehicle", "veh-gone")
    assert again.returncode == 0 and "has no trips: nothing to erase" in again.stdout
    with dep.admin() as http:
        answer = http.delete("/v1/vehicles/veh-gone/data")
    assert answer.status_code == 200
    assert answer.json()["trips"] == 0 and answer.json()["merge_jobs"] == []
    assert dep.scalar("SELECT count(*) FROM tile_versions") == versions

    # the endpoint erases the last vehicle: the tiles become empty versions
    with dep.admin() as http:
        dry_answer = http.delete("/v1/vehicles/veh-stay/data", params={"dry_run": "true"}).json()
        assert dry_answer["dry_run"] and sorted(dry_answer["trip_ids"]) == sorted(stay)
        assert dep.scalar("SELECT count(*) FROM trips") == 2
        erased = http.delete("/v1/vehicles/veh-stay/data").json()
        assert erased["trips"] == 2 and erased["merge_jobs"]
    dep.wait_idle(timeout_s=300)
    assert all(n == 0 for n in _rows_of(dep, stay).values())
    assert _map(dep) == []
    assert _version_trips(dep) == []


def test_erasure_endpoint_checks_its_input_and_role(make_isolated) -> None:
    dep = _start(make_isolated, "embedded", "")
    with dep.admin() as http:
        bad = http.delete("/v1/vehicles/bad vehicle!/data")
        assert bad.status_code == 422
        assert bad.json()["location"] == "path.vehicle_id" and "vehicle_id" in bad.json()["message"]
        reader = http.post("/v1/keys", json={"role": "reader"}).json()["key"]
    with dep.client(reader) as http:
        assert http.delete("/v1/vehicles/veh-1/data").status_code == 403


@pytest.mark.parametrize("kind", KINDS)
def test_purge_killed_before_its_commit_erases_nothing(
    make_isolated, private_redis: RedisServer, tmp_path: Path, kind: str
) -> None:
    """The erasure is one transaction: a purge killed after erasing every trip, before its commit,
    leaves every row; the next purge erases them all."""
    import os
    import signal

    dep = _start(make_isolated, kind, private_redis.url, CSR_EMBEDDED_WORKERS="0")
    for _ in range(3):
        assert dep.upload(moving_trip("veh-k")).status_code == 202
    log = tmp_path / "purge.log"
    with log.open("wb") as err:
        proc = subprocess.Popen(
            [str(BIN / "csr"), "purge", "--vehicle", "veh-k"],
            env={**dep.env, "CSR_TEST_PURGE_DELAY_S": "60"},
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=err,
            start_new_session=True,
        )
        wait_until(
            lambda: "3/3" in log.read_text(errors="replace"), timeout_s=60, what="the purge's bar at 3/3"
        )
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    assert dep.scalar("SELECT count(*) FROM trips WHERE vehicle_id = 'veh-k'") == 3
    assert (
        dep.scalar(
            "SELECT count(*) FROM trip_uploads u JOIN trips t ON t.id = u.trip_pk WHERE t.vehicle_id = 'veh-k'"
        )
        == 3
    )
    result = _csr(dep, "purge", "--vehicle", "veh-k")
    assert result.returncode == 0 and "erased 3 trip(s)" in result.stdout, result.stderr
    assert dep.scalar("SELECT count(*) FROM trips WHERE vehicle_id = 'veh-k'") == 0


# --- who reads traces ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_reader_keys_see_traces_only_when_the_setting_allows(
    make_isolated, private_redis: RedisServer, kind: str
) -> None:
    dep = _start(make_isolated, kind, private_redis.url, CSR_READER_SEES_TRACES="false")
    (pk,) = _upload_and_process(dep, ["veh-t"])
    with dep.admin() as http:
        reader = http.post("/v1/keys", json={"role": "reader"}).json()["key"]
        own = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-t"}).json()["key"]
        other = http.post("/v1/keys", json={"role": "vehicle", "vehicle_id": "veh-x"}).json()["key"]
    traces = (f"/v1/trips/{pk}/poses", f"/v1/trips/{pk}/track.geojson", f"/v1/trips/{pk}/upload")
    with dep.client(reader) as http:
        for path in traces:
            denied = http.get(path)
            assert denied.status_code == 403, path
            assert (
                denied.json()["error"] == "forbidden" and "CSR_READER_SEES_TRACES" in denied.json()["message"]
            )
        assert http.get(f"/v1/trips/{pk}").status_code == 200  # the trip's status stays readable
        assert _map_with(http)
    for key in (own, dep.admin_key):
        with dep.client(key) as http:
            for path in traces:
                assert http.get(path).status_code == 200, path
            poses = http.get(traces[0]).json()
            assert len(poses["frames"]) > 10
            raw = http.get(traces[2])
            assert raw.headers["content-encoding"] == "gzip" and raw.json()["vehicle_id"] == "veh-t"
    with dep.client(other) as http:
        assert all(http.get(path).status_code == 403 for path in traces)


def _map_with(http) -> list[dict]:
    response = http.get("/v1/map", params={"bbox": "11.56,48.13,11.59,48.14"})
    response.raise_for_status()
    return response.json()["features"]


def test_reader_keys_see_traces_by_default(make_isolated) -> None:
    """The contract lets readers read poses: the default keeps it."""
    dep = _start(make_isolated, "embedded", "")
    (pk,) = _upload_and_process(dep, ["veh-d"])
    with dep.admin() as http:
        reader = http.post("/v1/keys", json={"role": "reader"}).json()["key"]
    with dep.client(reader) as http:
        for path in (f"/v1/trips/{pk}/poses", f"/v1/trips/{pk}/track.geojson", f"/v1/trips/{pk}/upload"):
            assert http.get(path).status_code == 200, path


# --- storage: topology states -------------------------------------------------------------------


def test_only_the_newest_and_live_versions_keep_their_topology_state(make_isolated) -> None:
    """A state holds every trip's probe points: older versions drop theirs (their held-back lines
    answer 409), so storage per km stays flat as passes accumulate."""
    dep = _start(make_isolated, "embedded", "")
    _upload_and_process(dep, ["veh-s1"])
    _upload_and_process(dep, ["veh-s2"])
    rows = dep.rows("SELECT z, x, y, version, state IS NOT NULL AS has_state FROM tile_versions ORDER BY id")
    by_tile: dict[tuple[int, int, int], list] = {}
    for r in rows:
        by_tile.setdefault((r.z, r.x, r.y), []).append(r)
    twice = {t: vs for t, vs in by_tile.items() if len(vs) >= 2}
    assert twice, rows
    with dep.admin() as http:
        for (z, x, y), vs in twice.items():
            assert [bool(v.has_state) for v in vs] == [False] * (len(vs) - 1) + [True]
            old = http.get(f"/v1/tiles/{z}/{x}/{y}/held-back", params={"version": vs[0].version})
            assert old.status_code == 409 and old.json()["error"] == "state_unavailable"
            assert http.get(f"/v1/tiles/{z}/{x}/{y}/held-back").status_code == 200
