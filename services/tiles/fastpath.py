"""A plain ASGI fast path in front of FastAPI for ``GET /v1/tiles/{z}/{x}/{y}.mvt`` and ``.geojson``.

It answers only what it can answer exactly as the FastAPI route would (200, 204, 304 for a valid
tile and an accepted ``reader``/``admin`` key) and hands every other request to FastAPI unchanged:
other methods and paths, extra query parameters, bad coordinates, a missing, unknown, revoked or
under-privileged key, a pinned version beyond the current map version. The route stays the one
definition of the errors and of the OpenAPI schema.

A warm request costs no database query and no thread hop: three in-process caches, each entry
valid until a change counter (``services.tiles.signals``) moves or its time-to-live runs out:

- **keys**: the SHA-256 of an accepted key -> its role, for :data:`KEY_TTL_S`. Only accepted
  keys are kept; a revocation in this process drops them at its commit, one in another process
  at its ``NOTIFY csr_keys`` (PostgreSQL) or its commit (SQLite ``data_version``), and in any
  case within :data:`KEY_TTL_S`.
- **ETags of live tiles**: (kind, z, x, y) -> ETag, for :data:`LIVE_TTL_S`, dropped when a tile
  version is written (this process: at the commit; others: ``NOTIFY csr_tiles`` from
  ``write_tile_version``, or SQLite's ``data_version``). A live URL may so lag a new version
  written in another API or worker process by at most :data:`LIVE_TTL_S` (typically a few ms).
  ETags of pinned tiles (``?v=N``) never change and are kept in the route's own cache.
- **bodies**: the route's LRU by ETag (``render.TileCache``).

A miss runs the route's code (``render.render``: the ETag from the tile heads, then the LRU, then
``tile_renders``, and only then an encoding) on a worker thread.
"""

from __future__ import annotations

import logging
import re
import sqlite3
import threading
import time
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

import anyio.to_thread
from sqlalchemy.orm import configure_mappers

from services.api.errors import DATABASE_ERRORS, database_error, error_response
from services.api.metrics import ROUTE_TEMPLATE_SCOPE_KEY
from services.db import repo
from services.tiles import render, signals, store
from services.tiles.http import CORS_HEADERS, cache_control, caches
from services.tiles.mercator import MAX_ZOOM, valid_tile

log = logging.getLogger(__name__)

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

# How long an accepted key is trusted without asking the database (the longest a revocation made
# in another process can take to reach a tile read when its notification is lost).
KEY_TTL_S = 1.0
# How long a live tile's ETag is trusted without asking the database (likewise for a new version).
LIVE_TTL_S = 1.0
# Entries of the key and live-ETag caches before they are emptied (a few MB).
MAX_KEYS, MAX_LIVE_ENTRIES = 10_000, 100_000
READ_ROLES = ("reader", "admin")
MEDIA = {"mvt": b"application/vnd.mapbox-vector-tile", "geojson": b"application/geo+json"}
# the routes whose answers this gives (the label of its requests in csr_http_requests_total)
ROUTE_TEMPLATES = {kind: f"/v1/tiles/{{z}}/{{x}}/{{y}}.{kind}" for kind in MEDIA}

_PATH = re.compile(r"/v1/tiles/(\d{1,2})/(\d{1,7})/(\d{1,7})\.(mvt|geojson)")
_PINNED = re.compile(rb"v=(\d{1,15})")
_CORS = [(k.lower().encode(), v.encode()) for k, v in CORS_HEADERS.items()]


class TileFastPath:
    """ASGI middleware: the tile GETs it can answer from its caches, everything else to ``app``."""

    def __init__(self, app: ASGIApp, fastapi_app: Any) -> None:
        self.app = app
        self.fastapi_app = fastapi_app  # its ``state.ctx`` (AppContext) exists once started
        self._keys: dict[str, tuple[str, float, int]] = {}  # digest -> role, expiry, generation
        self._live: dict[tuple, tuple[str, float, int]] = {}  # (kind, z, x, y) -> etag, expiry, gen
        self._map_version = 0  # highest map version seen: pinned versions up to it exist
        self._watcher: _Watcher | None = None
        self._watcher_lock = threading.Lock()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            await self.app(scope, receive, self._lifespan_send(send))
            return
        if scope["type"] != "http" or scope["method"] != "GET":
            await self.app(scope, receive, send)
            return
        match = _PATH.fullmatch(scope["path"])
        if match is None:
            await self.app(scope, receive, send)
            return
        try:
            answered = await self._answer(scope, send, match)
        except DATABASE_ERRORS as exc:  # the route would answer the same 503
            await error_response(database_error(exc))(scope, receive, send)
            return
        if not answered:
            await self.app(scope, receive, send)

    def _lifespan_send(self, send: Send) -> Send:
        async def wrapped(message: Message) -> None:
            if message["type"] == "lifespan.startup.complete":
                await anyio.to_thread.run_sync(self._warm_up)
            if message["type"] == "lifespan.shutdown.complete" and self._watcher is not None:
                self._watcher.stop()
            await send(message)

        return wrapped

    def _warm_up(self) -> None:
        """Do once at start what the first tile request would otherwise pay for (~0.1-0.25 s:
        the ORM's mapper configuration, the first compilation of the key and tile queries)."""
        ctx = getattr(self.fastapi_app.state, "ctx", None)
        if ctx is None:
            return
        try:
            configure_mappers()
            _key_role(ctx, "csr-warm-up")
            _map_version(ctx)
            with ctx.read_session_factory() as session:
                etag, _ = render.tile_etag(session, kind="mvt", z=MAX_ZOOM, x=0, y=0, map_version=None)
                store.lookup(session, etag)
            self._watch(ctx)
        except Exception:  # never keep the service from starting
            log.exception("tile fast path: warm-up failed")

    # --- one request ----------------------------------------------------------------------------

    async def _answer(self, scope: Scope, send: Send, match: re.Match) -> bool:
        """Answer the request, or ``False`` to leave it to FastAPI."""
        z, x, y, kind = int(match[1]), int(match[2]), int(match[3]), match[4]
        if not valid_tile(z, x, y):
            return False
        query = scope.get("query_string", b"")
        pinned: int | None = None
        if query:
            q = _PINNED.fullmatch(query)
            if q is None:
                return False
            pinned = int(q[1])
        authorization = if_none_match = None
        for name, value in scope["headers"]:
            if name == b"authorization" and authorization is None:
                authorization = value.decode("latin-1")
            elif name == b"if-none-match" and if_none_match is None:
                if_none_match = value.decode("latin-1")
        ctx = getattr(self.fastapi_app.state, "ctx", None)
        if ctx is None or authorization is None:
            return False
        self._watch(ctx)
        if not await self._accepted(ctx, authorization):
            return False
        if pinned is not None and pinned > self._map_version:
            self._map_version = max(self._map_version, await anyio.to_thread.run_sync(_map_version, ctx))
            if pinned > self._map_version:
                return False  # 404 from the route
        cache, pinned_etags = caches(_RequestLike(self.fastapi_app))
        etag = self._cached_etag(kind, z, x, y, pinned, pinned_etags)
        body: bytes | None = None
        not_modified = False
        source = render.TileSource.FAST_PATH
        if etag is not None and if_none_match and render.etag_matches(if_none_match, etag):
            not_modified = True
        else:
            hit = False
            if etag is not None:
                hit, body = cache.get(etag)
            if not hit:
                generation = signals.tiles.value
                tile, not_modified = await anyio.to_thread.run_sync(
                    _render, ctx, cache, pinned_etags, kind, z, x, y, pinned, if_none_match
                )
                etag, body, source = tile.etag, tile.body, tile.source
                if pinned is None:
                    if len(self._live) > MAX_LIVE_ENTRIES:
                        self._live.clear()
                    self._live[(kind, z, x, y)] = (etag, time.monotonic() + LIVE_TTL_S, generation)
        assert etag is not None
        ctx.metrics.count_tile(source)
        scope[ROUTE_TEMPLATE_SCOPE_KEY] = ROUTE_TEMPLATES[kind]
        await _respond(
            send,
            kind,
            etag,
            body,
            pinned=pinned,
            public_map=ctx.settings.public_map,
            not_modified=not_modified,
        )
        return True

    async def _accepted(self, ctx: Any, authorization: str) -> bool:
        scheme, _, secret = authorization.partition(" ")
        secret = secret.strip()
        if scheme.lower() != "bearer" or not secret:
            return False
        digest = repo.hash_key(secret)
        entry = self._keys.get(digest)
        if entry is not None and entry[2] == signals.keys.value and entry[1] > time.monotonic():
            return True
        generation = signals.keys.value
        role = await anyio.to_thread.run_sync(_key_role, ctx, secret)
        if role not in READ_ROLES:
            self._keys.pop(digest, None)
            return False
        if len(self._keys) > MAX_KEYS:
            self._keys.clear()
        self._keys[digest] = (role, time.monotonic() + KEY_TTL_S, generation)
        return True

    def _cached_etag(
        self, kind: str, z: int, x: int, y: int, pinned: int | None, pinned_etags: render.TileCache
    ) -> str | None:
        if pinned is not None:
            hit, raw = pinned_etags.get(f"{kind}|{z}/{x}/{y}|{pinned}")
            return raw.decode() if hit and raw else None
        entry = self._live.get((kind, z, x, y))
        if entry is None or entry[2] != signals.tiles.value or entry[1] <= time.monotonic():
            return None
        return entry[0]

    def _watch(self, ctx: Any) -> None:
        """Start the watcher of other processes' writes (once); on SQLite, poll it now."""
        if self._watcher is None:
            with self._watcher_lock:
                if self._watcher is None:
                    self._watcher = _Watcher.start(ctx.engine)
        self._watcher.poll()


class _RequestLike:
    """What ``http.caches`` reads of a request: ``.app.state``."""

    def __init__(self, app: Any) -> None:
        self.app = app


# --- on a worker thread ----------------------------------------------------------------------------


def _key_role(ctx: Any, secret: str) -> str | None:
    with ctx.read_session_factory() as session:
        row = repo.active_key(session, secret=secret)
        return row.role if row is not None else None


def _map_version(ctx: Any) -> int:
    from services.db import versions as vs

    with ctx.read_session_factory() as session:
        return vs.current_map_version(session)


def _render(
    ctx: Any,
    cache: render.TileCache,
    pinned_etags: render.TileCache,
    kind: str,
    z: int,
    x: int,
    y: int,
    pinned: int | None,
    if_none_match: str | None,
) -> tuple[render.Tile, bool]:
    return render.render_then_keep(
        ctx.session_factory,
        cache,
        kind=kind,
        z=z,
        x=x,
        y=y,
        map_version=pinned,
        if_none_match=if_none_match,
        pinned_etags=pinned_etags,
    )


# --- the answer ------------------------------------------------------------------------------------


async def _respond(
    send: Send,
    kind: str,
    etag: str,
    body: bytes | None,
    *,
    pinned: int | None,
    public_map: bool,
    not_modified: bool,
) -> None:
    """The headers and body ``http.tile_response`` gives (Starlette's ``Response``)."""
    headers = [
        *_CORS,
        (b"etag", etag.encode()),
        (b"cache-control", cache_control(pinned=pinned is not None, public_map=public_map).encode()),
    ]
    if pinned is not None:
        headers.append((b"x-map-version", str(pinned).encode()))
    if not_modified or body is None:
        await send(
            {"type": "http.response.start", "status": 304 if not_modified else 204, "headers": headers}
        )
        await send({"type": "http.response.body", "body": b""})
        return
    headers += [(b"content-length", str(len(body)).encode()), (b"content-type", MEDIA[kind])]
    await send({"type": "http.response.start", "status": 200, "headers": headers})
    await send({"type": "http.response.body", "body": body})


# --- other processes' writes ---------------------------------------------------------------------------


class _Watcher:
    """Moves the change counters on writes of other processes: ``LISTEN csr_tiles, csr_keys`` on
    PostgreSQL (a thread), ``PRAGMA data_version`` on SQLite (polled per request: it changes when
    another connection committed; a few microseconds)."""

    @staticmethod
    def start(engine: Any) -> _Watcher:
        if engine.dialect.name == "postgresql":
            return _PgListener(engine)
        if engine.dialect.name == "sqlite" and engine.url.database:
            return _SqliteDataVersion(engine.url.database)
        return _Watcher()

    def poll(self) -> None:
        pass

    def stop(self) -> None:
        pass


class _SqliteDataVersion(_Watcher):
    def __init__(self, path: str) -> None:
        self._conn = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        self._seen = self._version()

    def _version(self) -> int:
        with self._lock:
            return int(self._conn.execute("PRAGMA data_version").fetchone()[0])

    def poll(self) -> None:
        version = self._version()
        if version != self._seen:
            self._seen = version
            signals.tiles.bump()
            signals.keys.bump()

    def stop(self) -> None:
        with self._lock:
            self._conn.close()


class _PgListener(_Watcher):
    def __init__(self, engine: Any) -> None:
        self._dsn = engine.url.set(drivername="postgresql").render_as_string(hide_password=False)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="csr-tile-listener", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import psycopg

        while not self._stop.is_set():
            try:
                with psycopg.connect(self._dsn, autocommit=True, connect_timeout=5) as conn:
                    conn.execute("LISTEN csr_tiles")
                    conn.execute("LISTEN csr_keys")
                    # anything written while not listening: forget it all
                    signals.tiles.bump()
                    signals.keys.bump()
                    while not self._stop.is_set():
                        for note in conn.notifies(timeout=1.0):
                            (signals.keys if note.channel == "csr_keys" else signals.tiles).bump()
            except Exception as exc:  # the database went away: caches expire by their TTL meanwhile
                log.warning("tile cache listener: %s; reconnecting", exc)
                signals.tiles.bump()
                signals.keys.bump()
                self._stop.wait(1.0)

    def stop(self) -> None:
        self._stop.set()
