"""Start a deployment of the service on this machine for a benchmark or a demo: the embedded
default (``csr serve`` alone, SQLite under a scratch data dir), or the distributed one (``csr
serve`` + ``csr worker`` processes on a scratch PostGIS database and a Redis database)."""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def scratch_postgis(admin_url: str, name: str) -> str:
    """(Re)create database ``name`` with PostGIS; its SQLAlchemy URL."""
    import psycopg

    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        conn.execute(f'CREATE DATABASE "{name}"')
    base = admin_url.rsplit("/", 1)[0]
    with psycopg.connect(f"{base}/{name}", autocommit=True) as conn:
        conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    return f"{base.replace('postgresql://', 'postgresql+psycopg://')}/{name}"


@dataclass
class LocalDeployment:
    """``kind``: ``embedded`` or ``distributed`` (then ``database_url`` and ``redis_url``);
    ``workers``: Celery worker processes (distributed)."""

    kind: str
    database_url: str | None = None
    redis_url: str | None = None
    workers: int = 1
    extra_env: dict[str, str] = field(default_factory=dict)
    admin_key: str = field(default_factory=lambda: "local-" + secrets.token_hex(8))
    base_url: str = ""
    _procs: list[subprocess.Popen] = field(default_factory=list)
    _tmp: tempfile.TemporaryDirectory | None = None

    def __enter__(self) -> LocalDeployment:
        self._tmp = tempfile.TemporaryDirectory(prefix="csr-local-")
        env = {k: v for k, v in os.environ.items() if not k.startswith("CSR_")}
        env.update(
            {
                "CSR_ADMIN_KEY": self.admin_key,
                "CSR_DATA_DIR": self._tmp.name,
                "CSR_QUIET_PERIOD_S": "3600",
                "CSR_POLL_INTERVAL_S": "0.2",
                "OPENBLAS_NUM_THREADS": "1",
                **self.extra_env,
            }
        )
        if self.kind == "distributed":
            if not (self.database_url and self.redis_url):
                raise ValueError("a distributed deployment needs a database URL and a Redis URL")
            env.update({"CSR_DATABASE_URL": self.database_url, "CSR_REDIS_URL": self.redis_url})
            import redis

            redis.Redis.from_url(self.redis_url).flushdb()
        port = free_port()
        self.base_url = f"http://127.0.0.1:{port}"
        log = open(Path(self._tmp.name) / "serve.log", "wb")  # noqa: SIM115 (closed with the dir)
        self._procs.append(
            subprocess.Popen(
                [str(BIN / "csr"), "serve", "--port", str(port), "--no-access-log"],
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
        self._wait_healthy()
        if self.kind == "distributed":
            for k in range(self.workers):
                wlog = open(Path(self._tmp.name) / f"worker-{k}.log", "wb")  # noqa: SIM115
                self._procs.append(
                    subprocess.Popen(
                        [str(BIN / "csr"), "worker", "--concurrency", "1"],
                        env=env,
                        stdout=wlog,
                        stderr=subprocess.STDOUT,
                    )
                )
            time.sleep(6)  # the workers are up before anything is measured
        return self

    @property
    def server_pid(self) -> int:
        """The process id of ``csr serve``."""
        return self._procs[0].pid

    @property
    def effective_database_url(self) -> str:
        if self.kind == "distributed":
            assert self.database_url is not None, "a distributed deployment needs a database URL"
            return self.database_url
        assert self._tmp is not None, "the deployment is not running"
        return f"sqlite:///{Path(self._tmp.name) / 'csr.sqlite3'}"

    def job_seconds(self) -> dict[str, float]:
        """Total run time of the finished jobs so far, per job kind."""
        import sqlalchemy as sa

        engine = sa.create_engine(self.effective_database_url)
        with engine.connect() as conn:
            rows = conn.execute(
                sa.text("SELECT kind, sum(duration_s) FROM jobs WHERE duration_s IS NOT NULL GROUP BY kind")
            ).all()
        engine.dispose()
        return {r[0]: float(r[1]) for r in rows}

    def _wait_healthy(self, timeout_s: float = 90.0) -> None:
        assert self._tmp is not None
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._procs[0].poll() is not None:
                raise RuntimeError(f"csr serve exited: see {self._tmp.name}/serve.log")
            try:
                if httpx.get(self.base_url + "/healthz", timeout=1).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.3)
        raise RuntimeError("csr serve did not become healthy")

    def __exit__(self, *exc) -> None:
        for proc in reversed(self._procs):
            proc.terminate()
        for proc in self._procs:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
        if self._tmp is not None:
            self._tmp.cleanup()
