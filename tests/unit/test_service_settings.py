"""Service settings: defaults of the contract, the embedded default, consistency checks."""

from __future__ import annotations

import stat

import pytest
from pydantic import ValidationError

from services.settings import Settings

pytestmark = pytest.mark.unit


def test_defaults_accept_the_contract_sizes(tmp_path, monkeypatch):
    for var in (
        "CSR_DATABASE_URL",
        "CSR_REDIS_URL",
        "CSR_MAX_BODY_BYTES",
        "CSR_MAX_DECOMPRESSED_BYTES",
        "CSR_TILE_ZOOM",
    ):
        monkeypatch.delenv(var, raising=False)
    settings = Settings(data_dir=tmp_path)
    assert settings.max_body_bytes >= 32 * 1024 * 1024
    assert settings.max_decompressed_bytes >= 256 * 1024 * 1024
    assert settings.tile_zoom == 16
    assert settings.embedded_jobs
    assert settings.sqlalchemy_url == f"sqlite:///{(tmp_path / 'csr.sqlite3').resolve()}"


def test_environment_configures_the_limits(monkeypatch):
    monkeypatch.setenv("CSR_MAX_BODY_BYTES", "1000")
    monkeypatch.setenv("CSR_DATABASE_URL", "postgresql+psycopg://u@h/db")
    settings = Settings()
    assert settings.max_body_bytes == 1000
    assert settings.sqlalchemy_url == "postgresql+psycopg://u@h/db"


def test_visibility_timeout_must_exceed_the_job_time_limit():
    with pytest.raises(ValidationError, match="VISIBILITY"):
        Settings(redis_url="redis://x", visibility_timeout_s=60, job_time_limit_s=60)


def test_unknown_database_scheme_is_refused():
    with pytest.raises(ValidationError):
        Settings(database_url="mysql://x/y")


def test_generated_admin_key_is_kept_private_and_stable(tmp_path, monkeypatch):
    monkeypatch.delenv("CSR_ADMIN_KEY", raising=False)
    settings = Settings(data_dir=tmp_path)
    key = settings.admin_secret()
    assert key.startswith("csr_") and Settings(data_dir=tmp_path).admin_secret() == key
    assert stat.S_IMODE((tmp_path / "admin.key").stat().st_mode) == 0o600
    assert Settings(data_dir=tmp_path, admin_key="given").admin_secret() == "given"
