"""Contract section 4 commands and the migrations from the command line, on a fresh machine state."""

from __future__ import annotations

import stat
import subprocess
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa

from tests.integration.conftest import BIN, REPO, Deployment, PgDatabases, base_env

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
