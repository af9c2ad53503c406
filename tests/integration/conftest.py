"""Real parts for the integration tests: a fresh PostGIS database per session (and per test
that needs its own), a Redis database chosen for the session, private redis-server processes
that a test may stop, `csr serve` and `csr worker` (Celery) subprocesses.

Environment (all optional): CSR_TEST_PG_ADMIN_URL (default postgresql://postgres@127.0.0.1:5432/postgres),
CSR_TEST_REDIS_HOST / CSR_TEST_REDIS_PORT (default 127.0.0.1:6379).
"""

from __future__ import annotations

import gzip
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import orjson
import psycopg
import pytest
import redis
import sqlalchemy as sa

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
EXAMPLE = REPO / "tests" / "data" / "example-trip.json"
PG_ADMIN_URL = os.environ.get("CSR_TEST_PG_ADMIN_URL", "postgresql://postgres@127.0.0.1:5432/postgres")
REDIS_HOST = os.environ.get("CSR_TEST_REDIS_HOST", "127.0.0.1")
REDIS_PORT = int(os.environ.get("CSR_TEST_REDIS_PORT", "6379"))
ARTIFACTS = REPO / "test-artifacts"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(
    predicate: Callable[[], Any],
    *,
    timeout_s: float = 60.0,
    interval_s: float = 0.2,
    what: str | Callable[[], str] = "",
) -> Any:
    """Poll until ``predicate()`` is truthy; ``what`` (or what it returns) names it in the failure."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(
                f"timed out after {timeout_s} s waiting for {(what() if callable(what) else what) or predicate}"
            )
        time.sleep(interval_s)


# --- uploads ------------------------------------------------------------------------------------


def example_doc(**overrides: Any) -> dict[str, Any]:
    doc = orjson.loads(EXAMPLE.read_bytes())
    doc.update(overrides)
    return doc


def unique_trip(vehicle_id: str = "veh-0001") -> dict[str, Any]:
    """The contract example under a new ``trip_id``: 1 s of a standing vehicle, valid as an upload
    but not reconstructable (single-trip reconstruction cannot orient it: its ingest fails)."""
    return example_doc(vehicle_id=vehicle_id, trip_id="t-" + secrets.token_hex(6))


def moving_trip(vehicle_id: str = "veh-0001", length_m: float = 150.0) -> dict[str, Any]:
    """A short generated drive (straight, 10 Hz, four elements per frame) whose ingest succeeds.
    Westwards: up to ~360 m it stays in the one zoom-16 tile of the contract example."""
    from services.cli.bench_ingest import straight_trip

    return straight_trip(
        vehicle_id=vehicle_id, trip_id="m-" + secrets.token_hex(6), length_m=length_m, heading_deg=270.0
    )


# --- PostgreSQL ---------------------------------------------------------------------------------


class PgDatabases:
    """Creates ``csr_test_<random>`` databases with PostGIS; drops them all at the end."""

    def __init__(self) -> None:
        self.names: list[str] = []

    def _admin(self) -> psycopg.Connection:
        return psycopg.connect(PG_ADMIN_URL, autocommit=True)

    def create(self) -> str:
        name = "csr_test_" + secrets.token_hex(5)
        with self._admin() as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        self.names.append(name)
        base = PG_ADMIN_URL.rsplit("/", 1)[0]
        with psycopg.connect(f"{base}/{name}", autocommit=True) as conn:
            conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
        return f"{base.replace('postgresql://', 'postgresql+psycopg://', 1)}/{name}"

    def drop_all(self) -> None:
        with self._admin() as conn:
            for name in self.names:
                conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture(scope="session")
def pg() -> Iterator[PgDatabases]:
    dbs = PgDatabases()
    yield dbs
    dbs.drop_all()


# --- Redis --------------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def shared_redis_url() -> Iterator[str]:
    """An empty database of the machine's Redis for this session (flushed at the end)."""
    for db in range(15, 0, -1):
        client = redis.Redis(host=REDIS_HOST, port=REDIS_PORT, db=db)
        if client.dbsize() == 0:
            client.set("csr-test-session", os.getpid())
            yield f"redis://{REDIS_HOST}:{REDIS_PORT}/{db}"
            client.flushdb()
            return
    raise RuntimeError("no empty Redis database for the tests")


class RedisServer:
    """A private redis-server on a spare loopback port, that a test may stop and start again."""

    def __init__(self, workdir: Path) -> None:
        self.port = free_port()
        self.workdir = workdir
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [
                shutil.which("redis-server") or "redis-server",
                "--port",
                str(self.port),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
                "--appendonly",
                "no",
                "--dir",
                str(self.workdir),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        wait_until(self._ping, timeout_s=10, what="private redis-server")

    def _ping(self) -> bool:
        try:
            return bool(redis.Redis(port=self.port, socket_connect_timeout=0.5).ping())
        except redis.ConnectionError:
            return False

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(timeout=10)
        self.proc = None


@pytest.fixture
def private_redis(tmp_path: Path) -> Iterator[RedisServer]:
    server = RedisServer(tmp_path)
    server.start()
    yield server
    server.stop()


# --- service processes --------------------------------------------------------------------------


class Proc:
    """A `csr` subprocess in its own process group, its output in test-artifacts/."""

    def __init__(self, args: list[str], env: dict[str, str], log_name: str) -> None:
        ARTIFACTS.mkdir(exist_ok=True)
        self.log_path = ARTIFACTS / f"{log_name}-{secrets.token_hex(3)}.log"
        self._log = self.log_path.open("wb")
        self.proc = subprocess.Popen(
            [str(BIN / "csr"), *args],
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=REPO,
            start_new_session=True,
        )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill_group(self, sig: int = signal.SIGKILL) -> None:
        try:
            os.killpg(self.proc.pid, sig)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.alive():
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.kill_group()
        self._log.close()

    def log_tail(self, n: int = 4000) -> str:
        return self.log_path.read_bytes()[-n:].decode(errors="replace")


@dataclass
class Deployment:
    """One running deployment: an API server (and Celery worker), how to reach and inspect it."""

    name: str
    env: dict[str, str]
    db_url: str
    admin_key: str
    procs: list[Proc] = field(default_factory=list)
    base_url: str = ""
    engine: sa.Engine | None = None

    @property
    def distributed(self) -> bool:
        return "CSR_REDIS_URL" in self.env

    def client(self, key: str | None = None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return httpx.Client(base_url=self.base_url, headers=headers, timeout=120.0)

    def admin(self) -> httpx.Client:
        return self.client(self.admin_key)

    def start_server(self, **extra_env: str) -> Proc:
        port = free_port()
        self.base_url = f"http://127.0.0.1:{port}"
        server = Proc(
            ["serve", "--port", str(port), "--no-access-log"], {**self.env, **extra_env}, f"serve-{self.name}"
        )
        self.procs.append(server)

        def healthy() -> bool:
            assert server.alive(), f"csr serve exited:\n{server.log_tail()}"
            try:
                return httpx.get(self.base_url + "/healthz", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(healthy, timeout_s=90, what="csr serve /healthz")
        self.engine = self.engine or sa.create_engine(self.db_url)
        return server

    def start_worker(self, **extra_env: str) -> Proc:
        worker = Proc(["worker", "--concurrency", "1"], {**self.env, **extra_env}, f"worker-{self.name}")
        self.procs.append(worker)
        return worker

    def stop(self) -> None:
        for proc in reversed(self.procs):
            proc.stop()
        if self.engine is not None:
            self.engine.dispose()

    # --- uploads and inspection

    def upload(
        self, doc: dict[str, Any] | bytes, *, key: str | None = None, gzipped: bool = False
    ) -> httpx.Response:
        body = doc if isinstance(doc, bytes) else orjson.dumps(doc)
        headers = {"Content-Type": "application/json"}
        if gzipped:
            body, headers["Content-Encoding"] = gzip.compress(body), "gzip"
        with self.client(key or self.admin_key) as http:
            return http.post("/v1/trips", content=body, headers=headers)

    def scalar(self, sql: str, **params: Any) -> Any:
        assert self.engine is not None, "start_server first"
        with self.engine.connect() as conn:
            return conn.execute(sa.text(sql), params).scalar()

    def rows(self, sql: str, **params: Any) -> list[sa.Row]:
        assert self.engine is not None, "start_server first"
        with self.engine.connect() as conn:
            return list(conn.execute(sa.text(sql), params))

    def summary(self) -> dict[str, int]:
        with self.admin() as http:
            return http.get("/v1/jobs/summary").raise_for_status().json()

    def wait_idle(self, timeout_s: float = 90.0) -> dict[str, int]:
        """Until no job is queued or running."""
        return wait_until(
            lambda: (s := self.summary())["queued"] == 0 and s["running"] == 0 and s,
            timeout_s=timeout_s,
            what=f"{self.name}: jobs to finish",
        )


def base_env(tmp: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CSR_")}
    env.update(
        {
            "CSR_DATA_DIR": str(tmp / "data"),
            "CSR_QUIET_PERIOD_S": "3600",
            "CSR_POLL_INTERVAL_S": "0.2",
            "PYTHONUNBUFFERED": "1",
        }
    )
    env.update(extra)
    return env


def make_deployment(kind: str, tmp: Path, pg: PgDatabases, redis_url: str, **extra: str) -> Deployment:
    admin_key = "test-admin-" + secrets.token_hex(8)
    if kind == "embedded":
        env = base_env(tmp, CSR_ADMIN_KEY=admin_key, **extra)
        db_url = f"sqlite:///{(tmp / 'data' / 'csr.sqlite3').resolve()}"
    else:
        db_url = pg.create()
        env = base_env(
            tmp, CSR_ADMIN_KEY=admin_key, CSR_DATABASE_URL=db_url, CSR_REDIS_URL=redis_url, **extra
        )
    return Deployment(kind, env, db_url, admin_key)


@pytest.fixture(scope="session", params=["embedded", "distributed"])
def deployment(request, tmp_path_factory, pg: PgDatabases, shared_redis_url: str) -> Iterator[Deployment]:
    """Both deployments, each started once per session: the embedded default (SQLite file, in-process
    jobs) and the distributed one (PostGIS, Redis, a real `csr worker` Celery process)."""
    dep = make_deployment(request.param, tmp_path_factory.mktemp(request.param), pg, shared_redis_url)
    try:
        dep.start_server()
        if dep.distributed:
            dep.start_worker()
        yield dep
    finally:
        dep.stop()


@pytest.fixture
def make_isolated(tmp_path: Path, pg: PgDatabases) -> Iterator[Callable[..., Deployment]]:
    """A deployment of its own for one test (own database, own Redis), stopped at the end."""
    created: list[Deployment] = []

    def factory(kind: str, *, redis_url: str = "", **extra: str) -> Deployment:
        dep = make_deployment(kind, tmp_path / f"{kind}-{len(created)}", pg, redis_url, **extra)
        created.append(dep)
        return dep

    yield factory
    for dep in created:
        dep.stop()
