"""Service configuration: one pydantic-settings class, built once by the entry point (never at import).

Every field is read from the environment with the ``CSR_`` prefix (``CSR_DATABASE_URL`` ...).
With no ``CSR_DATABASE_URL`` the service runs on the embedded default: a SQLite file under
``CSR_DATA_DIR``. With no ``CSR_REDIS_URL`` jobs run in-process on a background thread pool;
with it they go through Celery on Redis.
"""

from __future__ import annotations

import logging
import os
import secrets
from functools import cache
from pathlib import Path

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

log = logging.getLogger(__name__)

MIB = 1024 * 1024


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="CSR_", extra="ignore")

    database_url: str | None = Field(
        None, description="postgresql+psycopg://... (PostGIS); unset: SQLite in data_dir"
    )
    redis_url: str | None = Field(None, description="redis://...; unset: jobs run in-process")
    admin_key: SecretStr | None = Field(
        None, description="bootstrap admin key; unset: generated into data_dir/admin.key"
    )
    data_dir: Path = Path("./data")
    max_body_bytes: int = Field(32 * MIB, gt=0, description="limit on the body as sent")
    max_decompressed_bytes: int = Field(
        256 * MIB, gt=0, description="limit on the body after gzip decompression"
    )
    max_upload_bytes_in_flight: int = Field(
        256 * MIB,
        gt=0,
        description="decompressed bytes of all uploads being checked at once; an upload that would pass it "
        "answers 503 with Retry-After (at least max_decompressed_bytes)",
    )
    max_frames_per_trip: int = Field(
        200_000, ge=2, description="frames of one trip upload (200000: 5.5 h at 10 Hz); more answer 413"
    )
    tile_zoom: int = Field(16, ge=0, le=22, description="web-mercator zoom of the tiles a trip marks dirty")
    tile_halo_m: float = Field(
        150.0, gt=0, description="a tile job also aligns the trips' frames this close to the tile (seams)"
    )
    tile_checkerboard: bool = Field(
        True,
        description="a tile's first alignment waits for its edge neighbours of the other colour (x + y even "
        "first), so that every seam is aligned once against a map",
    )
    certificate_target_m: float = Field(
        0.10,
        gt=0,
        description="the absolute lateral error (metres, RMS over a tile) whose passes a tile's accuracy "
        "certificate counts (`passes_needed`)",
    )
    publish_min_quality: float = Field(
        0.8,
        ge=0,
        le=1,
        description="a merged tile version is a candidate for review, not live, when the share of its elements "
        "whose trips contradict each other exceeds 1 minus this",
    )
    quiet_period_s: float = Field(
        300.0, ge=0, description="a dirty tile is processed this long after its last new trip"
    )
    embedded_workers: int = Field(
        2,
        ge=0,
        description="threads of the in-process job pool (no CSR_REDIS_URL); 0: jobs wait in the database",
    )
    job_time_limit_s: int = Field(1800, gt=0, description="hard limit of one job (Celery task_time_limit)")
    visibility_timeout_s: int = Field(
        3600, gt=0, description="Redis re-delivers an unacknowledged job after this"
    )
    redispatch_after_s: float = Field(
        3600.0, gt=0, description="re-send a queued job whose message may be lost"
    )
    job_lease_s: float = Field(
        60.0,
        gt=0,
        description="a running job's lease: its runner renews it every third of this while it works; the outbox "
        "relay queues a job again once its lease has run out (its worker or its broker message is gone)",
    )
    poll_interval_s: float = Field(0.5, gt=0, description="outbox relay / embedded pool poll interval")
    worker_concurrency: int = Field(1, ge=1, description="csr worker: processes per worker")
    sqlite_busy_timeout_s: float = Field(
        60.0,
        gt=0,
        description="embedded default: how long a write waits for SQLite's write lock before the API answers 503",
    )
    metrics_key_file: Path | None = Field(
        None,
        description="a file holding a key that GET /metrics accepts besides reader and admin keys "
        "(the one Prometheus reads with credentials_file)",
    )
    public_map: bool = Field(
        False,
        description="tiles, map and versions are sent Cache-Control: public (shared caches may keep them); "
        "unset: private (only the caller's own cache)",
    )
    raw_retention_days: float | None = Field(
        None,
        gt=0,
        description="raw uploads are deleted this many days after they were received (the trip, its "
        "reconstruction and the map stay); unset: kept for ever",
    )
    retention_check_every_s: float = Field(
        600.0, gt=0, description="how often the background loop deletes the raw uploads past their retention"
    )
    reader_sees_traces: bool = Field(
        True,
        description="reader keys may read trips' traces (poses, track.geojson, the raw upload); false: "
        "only the trip's own vehicle key and admin keys may",
    )
    test_merge_delay_s: float = Field(
        0.0, ge=0, description="TEST ONLY: sleep in the first attempt of a merge job, before it writes"
    )
    test_purge_delay_s: float = Field(
        0.0, ge=0, description="TEST ONLY: csr purge sleeps this long before it commits its erasure"
    )
    test_ingest_delay_s: float = Field(
        0.0, ge=0, description="TEST ONLY: sleep in the first attempt of an ingest job"
    )

    @field_validator("database_url")
    @classmethod
    def _known_database(cls, value: str | None) -> str | None:
        if value is not None and not value.startswith(("postgresql+psycopg://", "sqlite:///")):
            raise ValueError("CSR_DATABASE_URL must start with postgresql+psycopg:// or sqlite:///")
        return value or None

    @model_validator(mode="after")
    def _limits_consistent(self) -> Settings:
        if self.max_upload_bytes_in_flight < self.max_decompressed_bytes:
            raise ValueError(
                f"CSR_MAX_UPLOAD_BYTES_IN_FLIGHT ({self.max_upload_bytes_in_flight}) must be at least "
                f"CSR_MAX_DECOMPRESSED_BYTES ({self.max_decompressed_bytes}), or the largest uploads never fit"
            )
        if self.redis_url and self.visibility_timeout_s <= self.job_time_limit_s:
            raise ValueError(
                f"CSR_VISIBILITY_TIMEOUT_S ({self.visibility_timeout_s}) must exceed CSR_JOB_TIME_LIMIT_S "
                f"({self.job_time_limit_s}), or Redis re-delivers jobs that are still running"
            )
        return self

    @property
    def sqlalchemy_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'csr.sqlite3').resolve()}"

    @property
    def embedded_jobs(self) -> bool:
        """Jobs run on the in-process pool (no broker configured)."""
        return not self.redis_url

    def ensure_data_dir(self) -> Path:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        return self.data_dir

    def admin_secret(self) -> str:
        """The bootstrap admin key: ``CSR_ADMIN_KEY``, else one generated once into ``data_dir/admin.key``."""
        if self.admin_key is not None and self.admin_key.get_secret_value():
            return self.admin_key.get_secret_value()
        path = self.ensure_data_dir() / "admin.key"
        if not path.exists():
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write("csr_" + secrets.token_urlsafe(32) + "\n")
            log.warning("CSR_ADMIN_KEY is not set: generated an admin key into %s", path.resolve())
        return path.read_text().strip()

    def metrics_secret(self) -> str | None:
        """The key of ``CSR_METRICS_KEY_FILE`` (surrounding whitespace removed), or ``None``."""
        if self.metrics_key_file is None:
            return None
        try:
            secret = self.metrics_key_file.read_text().strip()
        except OSError as exc:
            raise ValueError(f"CSR_METRICS_KEY_FILE: cannot read {self.metrics_key_file}: {exc}") from exc
        if len(secret) < 16:
            raise ValueError(f"CSR_METRICS_KEY_FILE: {self.metrics_key_file} holds fewer than 16 characters")
        return secret


@cache
def get_settings() -> Settings:
    """The process's settings, read from the environment on first use."""
    return Settings()
