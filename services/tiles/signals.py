"""Process-wide change counters for the caches of the tile fast path (``services.tiles.fastpath``).

``tiles`` moves on after the commit of a transaction that wrote a tile version (``versions.
write_tile_version`` marks its session with :func:`tiles_written`); ``keys`` after the commit of
one that updated or deleted ``api_keys`` rows (a revocation). A cache entry remembers the counter
it was made under and is stale once the counter moved. Writes in other processes reach the
counters through the fast path's own watchers (PostgreSQL ``LISTEN``, SQLite ``data_version``).
"""

from __future__ import annotations

import threading

from sqlalchemy import event
from sqlalchemy.orm import ORMExecuteState, Session


class Generation:
    """A counter that only grows (read without a lock: an int read is atomic)."""

    def __init__(self) -> None:
        self.value = 0
        self._lock = threading.Lock()

    def bump(self) -> None:
        with self._lock:
            self.value += 1


tiles = Generation()
keys = Generation()

_TILES_FLAG = "csr_tiles_written"
_KEYS_FLAG = "csr_keys_changed"


def tiles_written(session: Session) -> None:
    """Call in a transaction that writes a tile version: ``tiles`` moves on at its commit."""
    session.info[_TILES_FLAG] = True


@event.listens_for(Session, "do_orm_execute")
def _watch_key_statements(state: ORMExecuteState) -> None:
    if state.is_update or state.is_delete:
        table = getattr(state.statement, "table", None)
        if getattr(table, "name", None) == "api_keys":
            state.session.info[_KEYS_FLAG] = True


@event.listens_for(Session, "before_flush")
def _watch_key_objects(session: Session, _context, _instances) -> None:
    if any(getattr(o, "__tablename__", None) == "api_keys" for o in (*session.dirty, *session.deleted)):
        session.info[_KEYS_FLAG] = True


@event.listens_for(Session, "after_commit")
def _after_commit(session: Session) -> None:
    if session.info.pop(_TILES_FLAG, False):
        tiles.bump()
    if session.info.pop(_KEYS_FLAG, False):
        keys.bump()


@event.listens_for(Session, "after_rollback")
def _after_rollback(session: Session) -> None:
    session.info.pop(_TILES_FLAG, None)
    session.info.pop(_KEYS_FLAG, None)
