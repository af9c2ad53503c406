"""Engine, sessions and migrations for both backends (PostGIS and the embedded SQLite file).

On SQLite (WAL journal) a transaction that writes begins ``IMMEDIATE``: it takes the one write
lock at its start, so concurrent writers queue on the busy timeout instead of failing to upgrade
a read lock. A read-only session (:func:`read_only`) begins ``DEFERRED`` under
``PRAGMA query_only``: it reads its WAL snapshot without any lock a writer holds, so a long write
never delays a read, and a write attempted in it fails at once instead of upgrading. A
best-effort session (:func:`without_waiting`) writes only when the lock is free at once.
"""

from __future__ import annotations

import logging
import os
import time
from functools import cache
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.orm import Session, sessionmaker

log = logging.getLogger(__name__)

# Alembic's scripts in the source tree; an installed package (the image) names them with
# CSR_MIGRATIONS_DIR (:func:`migrations_dir`)
SOURCE_MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"
# Any constant: serialises concurrent `alembic upgrade` of several processes on one PostgreSQL.
_MIGRATION_LOCK_ID = 0x435352
# Execution options of the read-only and best-effort sessions' engines (module docstring).
READ_ONLY = "csr_read_only"
NO_WAIT = "csr_no_wait"
_MODE = "csr_mode"  # a pooled SQLite connection's current (read_only, no_wait) pragmas
SQLITE_BUSY_TIMEOUT_S = 60.0  # how long a SQLite writer waits for the write lock before it fails
SLOW_WRITE_S = 5.0  # a SQLite write transaction holding the lock longer is logged (others wait meanwhile)
_BEGUN = "csr_write_begun"  # monotonic start of a connection's open write transaction


def make_engine(url: str, *, busy_timeout_s: float = SQLITE_BUSY_TIMEOUT_S) -> Engine:
    """An engine for ``url``. SQLite gets WAL, a busy timeout of ``busy_timeout_s`` (SQLite's own
    bounded retry of a locked database) and the transaction modes of the module docstring."""
    if url.startswith("sqlite"):
        return _sqlite_engine(url, busy_timeout_s)
    return create_engine(url, pool_size=10, max_overflow=10, pool_pre_ping=True)


def _sqlite_engine(url: str, busy_timeout_s: float) -> Engine:
    Path(url.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(
        url, connect_args={"check_same_thread": False, "timeout": busy_timeout_s}, pool_size=8
    )

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        dbapi_connection.isolation_level = None  # the begin listener issues BEGIN
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_s * 1000)}")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Any) -> None:
        options = conn.get_execution_options()
        mode = (bool(options.get(READ_ONLY, False)), bool(options.get(NO_WAIT, False)))
        if conn.info.get(_MODE) != mode:  # pooled connections serve every kind of session
            conn.exec_driver_sql(f"PRAGMA query_only={int(mode[0])}")
            conn.exec_driver_sql(f"PRAGMA busy_timeout={0 if mode[1] else int(busy_timeout_s * 1000)}")
            conn.info[_MODE] = mode
        conn.exec_driver_sql("BEGIN DEFERRED" if mode[0] else "BEGIN IMMEDIATE")
        if not mode[0]:
            conn.info[_BEGUN] = time.monotonic()

    @event.listens_for(engine, "commit")
    @event.listens_for(engine, "rollback")
    def _on_end(conn: Any) -> None:
        begun = conn.info.pop(_BEGUN, None)
        if begun is not None and (held := time.monotonic() - begun) > SLOW_WRITE_S:
            log.warning("a write transaction held SQLite's write lock for %.1f s", held, stack_info=True)

    return engine


def make_session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions that may write (on SQLite each transaction holds the write lock: keep them short)."""
    return sessionmaker(engine, expire_on_commit=False)


@cache
def read_only(session_factory: sessionmaker[Session]) -> sessionmaker[Session]:
    """Sessions over the same engine that only read (module docstring): for API reads and for the
    read phases of jobs, which must not hold the write lock while they load and compute."""
    engine = session_factory.kw["bind"]
    return sessionmaker(engine.execution_options(**{READ_ONLY: True}), expire_on_commit=False)


@cache
def without_waiting(session_factory: sessionmaker[Session]) -> sessionmaker[Session]:
    """Sessions over the same engine whose writes fail at once (``OperationalError``) when SQLite's
    write lock is taken: for optional writes, such as keeping a tile render, that must not make a
    read wait for a job."""
    engine = session_factory.kw["bind"]
    return sessionmaker(engine.execution_options(**{NO_WAIT: True}), expire_on_commit=False)


def migrations_dir() -> Path:
    """``CSR_MIGRATIONS_DIR`` if set (a non-editable install has no source tree), else the source tree's."""
    return Path(os.environ.get("CSR_MIGRATIONS_DIR") or SOURCE_MIGRATIONS_DIR)


def migrate(engine: Engine) -> None:
    """``alembic upgrade head`` on ``engine`` (run at every start; a no-op when up to date)."""
    config = Config()
    config.set_main_option("script_location", str(migrations_dir()))
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:id)"), {"id": _MIGRATION_LOCK_ID})
        config.attributes["connection"] = conn
        command.upgrade(config, "head")
    log.info("database schema is at head (%s)", engine.url.render_as_string(hide_password=True))
