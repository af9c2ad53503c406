"""Contract section 4 commands and the migrations from the command line, on a fresh machine state."""

from __future__ import annotations

import stat
import subprocess
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa

from tests.integration.conftest import (
    BIN,
    REPO,
    Deployment,
    PgDatabases,
    Proc,
    base_env,
    free_port,
    wait_until,
)

pytestmark = pytest.mark.integration

TABLES = {
    "alembic_version",
    "api_keys",
    "trips",
    "trip_uploads",
    "trip_tiles",
    "dirty_tiles",
    "jobs",
    "trip_reconstructions",
    "trip_tile_alignments",
    "trip_poses",
    "match_pairs",
    "tile_versions",
    "tile_heads",
    "map_features",
    "corrections",
    "tile_renders",
    "tile_version_extents",
}


def test_serve_on_a_fresh_data_dir_generates_a_private_admin_key(tmp_path: Path):
    env = base_env(tmp_path)
    dep = Deployment("fresh", env, f"sqlite:///{tmp_path / 'data' / 'csr.sqlite3'}", admin_key="")
    try:
        dep.start_server()
        key_file = tmp_path / "data" / "admin.key"
        assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
        dep.admin_key = key_file.read_text().strip()
        with dep.admin() as http:
            assert http.post("/v1/keys", json={"role": "reader"}).status_code == 201
        assert httpx.get(dep.base_url + "/v1/jobs/summary").status_code == 401
    finally:
        dep.stop()


def test_serve_data_dir_serves_an_earlier_data_dir_again(tmp_path: Path):
    """``csr serve --data-dir DIR`` (``make serve DATA=DIR``) serves DIR whatever CSR_DATA_DIR says:
    how the demo's map (``data/demo/service``) is served again after ``csr demo --exit``."""
    earlier = tmp_path / "demo" / "service"
    first = Deployment(
        "earlier", base_env(tmp_path, CSR_DATA_DIR=str(earlier)), f"sqlite:///{earlier / 'csr.sqlite3'}", ""
    )
    try:
        first.start_server()
        first.admin_key = (earlier / "admin.key").read_text().strip()
        with first.admin() as http:
            reader = http.post("/v1/keys", json={"role": "reader"}).raise_for_status().json()["key"]
    finally:
        first.stop()
    port = free_port()
    again = Proc(
        ["serve", "--port", str(port), "--no-access-log", "--data-dir", str(earlier)],
        base_env(tmp_path),  # CSR_DATA_DIR: tmp_path / "data"
        "serve-data-dir",
    )
    try:
        base_url = f"http://127.0.0.1:{port}"

        def healthy() -> bool:
            assert again.alive(), f"csr serve exited:\n{again.log_tail()}"
            try:
                return httpx.get(base_url + "/healthz", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(healthy, timeout_s=90, what="csr serve --data-dir /healthz")
        # the key made on the earlier run is in the database it serves
        answer = httpx.get(base_url + "/v1/tiles.json", headers={"Authorization": f"Bearer {reader}"})
        assert answer.status_code == 200, answer.text
        assert not (tmp_path / "data").exists()  # CSR_DATA_DIR untouched
    finally:
        again.stop()


def test_worker_refuses_to_start_without_the_distributed_settings(tmp_path: Path):
    result = subprocess.run(
        [str(BIN / "csr"), "worker"], env=base_env(tmp_path), capture_output=True, text=True, timeout=120
    )
    assert result.returncode != 0
    assert "CSR_DATABASE_URL and CSR_REDIS_URL" in result.stderr


def _alembic(env: dict[str, str], *args: str) -> None:
    subprocess.run(
        [str(BIN / "alembic"), *args], env=env, cwd=REPO, check=True, capture_output=True, timeout=180
    )


def _tables(url: str) -> set[str]:
    engine = sa.create_engine(url)
    try:
        return set(sa.inspect(engine).get_table_names()) - {"spatial_ref_sys"}
    finally:
        engine.dispose()


@pytest.mark.parametrize("backend", ["sqlite", "postgis"])
def test_alembic_command_line_upgrades_and_downgrades_both_backends(
    tmp_path: Path, pg: PgDatabases, backend: str
):
    if backend == "postgis":
        url = pg.create()
        env = base_env(tmp_path, CSR_DATABASE_URL=url)
    else:
        env = base_env(tmp_path)
        url = f"sqlite:///{tmp_path / 'data' / 'csr.sqlite3'}"
    _alembic(env, "upgrade", "head")
    assert _tables(url) == TABLES
    _alembic(env, "downgrade", "base")
    assert _tables(url) == {"alembic_version"}
    _alembic(env, "upgrade", "head")
    assert _tables(url) == TABLES
