"""Check (and prepare) the local servers the test suite and the distributed dev deployment use:
PostgreSQL reachable with PostGIS available, a ``csr`` database with the ``postgis`` extension,
Redis reachable. Run by ``make test`` before pytest; prints what is missing and how to fix it.

    python -m services.devsetup
"""

from __future__ import annotations

import os
import sys

PG_ADMIN_URL = os.environ.get("CSR_TEST_PG_ADMIN_URL", "postgresql://postgres@127.0.0.1:5432/postgres")
REDIS_URL = os.environ.get("CSR_TEST_REDIS_URL", "redis://127.0.0.1:6379/0")
DEV_DATABASE = "csr"


def main() -> int:
    import psycopg
    import redis

    problems = []
    try:
        with psycopg.connect(PG_ADMIN_URL, autocommit=True, connect_timeout=5) as conn:
            if not conn.execute("SELECT 1 FROM pg_available_extensions WHERE name = 'postgis'").fetchone():
                problems.append("PostGIS is not installed: apt-get install -y postgresql-15-postgis-3")
            elif not conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (DEV_DATABASE,)).fetchone():
                conn.execute(f'CREATE DATABASE "{DEV_DATABASE}"')
        if not problems:
            base = PG_ADMIN_URL.rsplit("/", 1)[0]
            with psycopg.connect(f"{base}/{DEV_DATABASE}", autocommit=True, connect_timeout=5) as conn:
                conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    except psycopg.OperationalError as exc:
        problems.append(
            f"PostgreSQL is not reachable at {PG_ADMIN_URL} ({exc}); start it, e.g. "
            "pg_ctlcluster --skip-systemctl-redirect 15 main start"
        )
    try:
        redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3).ping()
    except redis.RedisError as exc:
        problems.append(
            f"Redis is not reachable at {REDIS_URL} ({exc}); start it, e.g. redis-server --daemonize yes"
        )
    for problem in problems:
        sys.stderr.write(f"devsetup: {problem}\n")
    if not problems:
        sys.stderr.write(f"devsetup: PostgreSQL + PostGIS ({DEV_DATABASE} database ready) and Redis are up\n")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
