"""SQLite's transaction modes (services.db.engine): a read-only session reads while another
connection holds the write lock and refuses to write; a best-effort session gives up at once."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import pytest
from sqlalchemy import text
from sqlalchemy.exc import OperationalError

from services.db.engine import make_engine, make_session_factory, read_only, without_waiting

pytestmark = pytest.mark.unit


@pytest.fixture
def sessions(tmp_path: Path):
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite3'}", busy_timeout_s=5.0)
    factory = make_session_factory(engine)
    with factory.begin() as session:
        session.execute(text("CREATE TABLE t (v INTEGER)"))
        session.execute(text("INSERT INTO t VALUES (1)"))
    yield factory, tmp_path / "db.sqlite3"
    engine.dispose()


def _hold_write_lock(path: Path) -> sqlite3.Connection:
    conn = sqlite3.connect(path, isolation_level=None)
    conn.execute("BEGIN IMMEDIATE")
    conn.execute("INSERT INTO t VALUES (2)")
    return conn


def test_a_read_only_session_reads_its_snapshot_while_the_write_lock_is_held(sessions) -> None:
    factory, path = sessions
    writer = _hold_write_lock(path)
    try:
        started = time.monotonic()
        with read_only(factory)() as session:
            assert session.execute(text("SELECT v FROM t")).scalars().all() == [1]
        assert time.monotonic() - started < 1.0  # no wait for the busy timeout (5 s)
    finally:
        writer.execute("ROLLBACK")
        writer.close()


def test_a_read_only_session_refuses_to_write(sessions) -> None:
    factory, _ = sessions
    with pytest.raises(OperationalError, match="readonly"), read_only(factory).begin() as session:
        session.execute(text("INSERT INTO t VALUES (3)"))
    with factory.begin() as session:  # the pooled connection writes again in a writing session
        session.execute(text("INSERT INTO t VALUES (3)"))
        assert session.execute(text("SELECT count(*) FROM t")).scalar() == 2


def test_a_best_effort_write_gives_up_at_once_when_the_lock_is_taken(sessions) -> None:
    factory, path = sessions
    writer = _hold_write_lock(path)
    try:
        started = time.monotonic()
        with pytest.raises(OperationalError, match="locked"), without_waiting(factory).begin() as session:
            session.execute(text("INSERT INTO t VALUES (4)"))
        assert time.monotonic() - started < 1.0
    finally:
        writer.execute("ROLLBACK")
        writer.close()
