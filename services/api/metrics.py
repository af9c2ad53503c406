"""Prometheus metrics of one API process (docs/operations.md lists every series).

- Counted in this process: uploads, HTTP requests by route template (:class:`HttpMetrics`), tile
  answers by where their body came from, and the process itself (CPU, memory, file descriptors).
- Read from the database at scrape time, so that they include the work of every Celery worker:
  queues, jobs, dirty tiles, the map's size and version, and the latency from upload to map.

No label takes a value per tile, trip or raw path: the number of series does not grow with the map.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable, Iterator, MutableMapping
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.gc_collector import GCCollector
from prometheus_client.platform_collector import PlatformCollector
from prometheus_client.process_collector import ProcessCollector
from sqlalchemy.orm import Session, sessionmaker

from services.db import ops_stats, repo
from services.tiles.render import TileSource

log = logging.getLogger(__name__)

JOB_DURATION_BUCKETS_S = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0)
HTTP_DURATION_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
# the quiet period (300 s by default) and the tile jobs after it dominate
UPLOAD_TO_PUBLISHED_BUCKETS_S = (
    10.0,
    30.0,
    60.0,
    120.0,
    300.0,
    600.0,
    900.0,
    1800.0,
    3600.0,
    7200.0,
    21600.0,
)
# the series of a metric family of each type (prometheus_client's text exposition)
SERIES_SUFFIXES = {
    "counter": ("_total", "_created"),
    "histogram": ("_bucket", "_count", "_sum", "_created"),
    "summary": ("", "_count", "_sum", "_created"),
}
# methods outside this set are counted as "other" (a client could otherwise invent series)
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
# the route label of a request that matched no route (its raw path is never a label)
UNMATCHED_ROUTE = "unmatched"
# a middleware in front of the router that answers a request itself names its route template here
ROUTE_TEMPLATE_SCOPE_KEY = "csr.route_template"


class _DatabaseCollector:
    """Job, tile and latency figures, read from the database at every scrape."""

    def __init__(self, session_factory: sessionmaker[Session]) -> None:
        self.session_factory = session_factory

    def describe(self) -> Iterator[Metric]:
        """The families :meth:`collect` yields, without values (and without asking the database)."""
        yield GaugeMetricFamily("csr_queue_depth", "Jobs waiting to run, per queue", labels=["queue"])
        yield GaugeMetricFamily("csr_jobs", "Jobs per queue and state", labels=["queue", "state"])
        yield GaugeMetricFamily("csr_dirty_tiles", "Tiles with trips not yet processed")
        yield HistogramMetricFamily("csr_job_duration_seconds", "Duration of finished jobs", labels=["kind"])
        for name in ("csr_tiles", "csr_published_tiles", "csr_map_version"):
            yield GaugeMetricFamily(name, "")
        yield GaugeMetricFamily("csr_tile_last_update_timestamp_seconds", "")
        yield HistogramMetricFamily("csr_upload_to_published_seconds", "")

    def collect(self) -> Iterator[Metric]:
        with self.session_factory() as session:
            counts = repo.job_counts(session)
            summary = repo.job_summary(session)
            durations = repo.job_duration_stats(session, buckets=JOB_DURATION_BUCKETS_S)
            tiles = ops_stats.tile_stats(session)
            to_map = ops_stats.upload_to_published(session, buckets_s=UPLOAD_TO_PUBLISHED_BUCKETS_S)
        depth = GaugeMetricFamily("csr_queue_depth", "Jobs waiting to run, per queue", labels=["queue"])
        queued = {q: 0 for q in repo.QUEUES}
        jobs = GaugeMetricFamily("csr_jobs", "Jobs per queue and state", labels=["queue", "state"])
        for queue, state, n in counts:
            jobs.add_metric([queue, state], n)
            if state == "queued":
                queued[queue] = queued.get(queue, 0) + n
        for queue, n in queued.items():
            depth.add_metric([queue], n)
        yield depth
        yield jobs
        yield GaugeMetricFamily(
            "csr_dirty_tiles", "Tiles with trips not yet processed", value=summary["dirty_tiles"]
        )
        hist = HistogramMetricFamily("csr_job_duration_seconds", "Duration of finished jobs", labels=["kind"])
        for kind, (cumulative, count, total) in durations.items():
            hist.add_metric([kind], _buckets(JOB_DURATION_BUCKETS_S, cumulative, count), total)
        yield hist
        yield GaugeMetricFamily("csr_tiles", "Tiles with at least one version", value=tiles.tiles)
        yield GaugeMetricFamily(
            "csr_published_tiles", "Tiles with a live (published) version", value=tiles.published_tiles
        )
        yield GaugeMetricFamily(
            "csr_map_version", "The map version: the newest tile version id", value=tiles.map_version
        )
        if tiles.last_update_unix_s is not None:
            yield GaugeMetricFamily(
                "csr_tile_last_update_timestamp_seconds",
                "When a tile last got a new version (Unix time)",
                value=tiles.last_update_unix_s,
            )
        latency = HistogramMetricFamily(
            "csr_upload_to_published_seconds",
            "From a trip's upload until every tile it crosses has a live version made after its tile job",
        )
        latency.add_metric(
            [], _buckets(UPLOAD_TO_PUBLISHED_BUCKETS_S, to_map.cumulative_counts, to_map.count), to_map.sum_s
        )
        yield latency


def _buckets(bounds: tuple[float, ...], cumulative: list[int], count: int) -> list[tuple[str, float]]:
    """prometheus_client's buckets of a histogram family: ``(upper bound, cumulative count)``."""
    return [(str(b), float(c)) for b, c in zip(bounds, cumulative, strict=True)] + [("+Inf", float(count))]


class Metrics:
    """The metrics of one app (its own registry, so several apps can live in one process).
    ``scrape_key``: a key accepted by ``GET /metrics`` only (``CSR_METRICS_KEY_FILE``)."""

    def __init__(self, session_factory: sessionmaker[Session], *, scrape_key: str | None = None) -> None:
        self.scrape_key = scrape_key
        self.registry = CollectorRegistry()
        self.uploads = Counter(
            "csr_uploads",
            "Accepted uploads (duplicate: an idempotent replay)",
            ["result"],
            registry=self.registry,
        )
        self.upload_bytes = Counter(
            "csr_upload_bytes",
            "Bytes of accepted uploads, as sent and decompressed",
            ["form"],
            registry=self.registry,
        )
        self.rejects = Counter(
            "csr_upload_rejects", "Rejected uploads by reason", ["reason"], registry=self.registry
        )
        self.upload_seconds = Histogram(
            "csr_upload_duration_seconds",
            "Time to accept an upload after its body arrived",
            registry=self.registry,
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0),
        )
        self.http_requests = Counter(
            "csr_http_requests",
            "HTTP requests answered, by route template, method and status code",
            ["route", "method", "status"],
            registry=self.registry,
        )
        self.http_seconds = Histogram(
            "csr_http_request_duration_seconds",
            "From a request's arrival until its answer was sent, by route template and method",
            ["route", "method"],
            registry=self.registry,
            buckets=HTTP_DURATION_BUCKETS_S,
        )
        self._http_children: dict[tuple[str, str, int], tuple[Any, Any]] = {}
        self.tile_requests = Counter(
            "csr_tile_requests",
            "Tile answers (.mvt, .geojson) by where the body came from (encoded: a cache miss)",
            ["source"],
            registry=self.registry,
        )
        for source in TileSource:
            self.tile_requests.labels(source.value)
        # process_* (CPU, memory, open files, start time), python_info, python_gc_*: the same
        # collectors prometheus_client registers on its global registry
        self._in_process: list[Any] = [
            self.uploads,
            self.upload_bytes,
            self.rejects,
            self.upload_seconds,
            self.http_requests,
            self.http_seconds,
            self.tile_requests,
            ProcessCollector(registry=self.registry),
            PlatformCollector(registry=self.registry),
            GCCollector(registry=self.registry),
        ]
        self._database = _DatabaseCollector(session_factory)
        self.registry.register(self._database)

    def series_names(self) -> set[str]:
        """The names of the series a scrape can show (``csr_uploads_total``, ``..._bucket``), found
        without asking the database: what a dashboard's queries may name."""
        families = [f for c in self._in_process for f in c.collect()] + list(self._database.describe())
        return {f.name + suffix for f in families for suffix in SERIES_SUFFIXES.get(f.type, ("",))}

    def http_series(self, route: str, method: str, status: int) -> tuple[Any, Any]:
        """The request counter and latency histogram of these labels. Kept: ``labels()`` costs a
        lock and a few lookups per call; the label values are bounded, so is this cache."""
        key = (route, method, status)
        series = self._http_children.get(key)
        if series is None:
            series = (
                self.http_requests.labels(route, method, str(status)),
                self.http_seconds.labels(route, method),
            )
            self._http_children[key] = series
        return series

    def count_tile(self, source: TileSource) -> None:
        self.tile_requests.labels(source.value).inc()


Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


class HttpMetrics:
    """ASGI middleware (outermost): counts every HTTP request and times it until its answer is
    sent, labelled by the route template that matched (``/v1/trips/{trip_pk}``), never the raw path."""

    def __init__(self, app: ASGIApp, fastapi_app: Any) -> None:
        self.app = app
        self.fastapi_app = fastapi_app  # its ``state.ctx.metrics`` exists once started

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        ctx = getattr(self.fastapi_app.state, "ctx", None)
        if scope["type"] != "http" or ctx is None:
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = 500  # an exception before the answer started: what the server sends

        async def send_and_note(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_note)
        finally:
            route = self._route_template(scope)
            method = scope["method"] if scope["method"] in HTTP_METHODS else "other"
            count, seconds = ctx.metrics.http_series(route, method, status)
            count.inc()
            seconds.observe(time.perf_counter() - started)

    def _route_template(self, scope: Scope) -> str:
        template = scope.get(ROUTE_TEMPLATE_SCOPE_KEY)
        if template is not None:
            return template
        route = scope.get("route")  # set by FastAPI's router on the request it matched
        if route is None:  # Starlette's own routes (/docs, /openapi.json) do not set it
            from starlette.routing import Match

            route = next(
                (r for r in self.fastapi_app.router.routes if r.matches(scope)[0] == Match.FULL), None
            )
        return getattr(route, "path_format", None) or getattr(route, "path", None) or UNMATCHED_ROUTE
