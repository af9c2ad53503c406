"""Prometheus metrics: upload counters of this process, and job state read from the database at
scrape time (so that the figures include the work of every Celery worker)."""

from __future__ import annotations

import logging
from datetime import UTC

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, HistogramMetricFamily
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.db import repo
from services.db.models import TileHead

log = logging.getLogger(__name__)

JOB_DURATION_BUCKETS_S = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0)


class _JobCollector:
    def __init__(self, session_factory: sessionmaker[Session]) -> None:
        self.session_factory = session_factory

    def collect(self):
        with self.session_factory() as session:
            counts = repo.job_counts(session)
            summary = repo.job_summary(session)
            durations = repo.job_duration_stats(session, buckets=JOB_DURATION_BUCKETS_S)
            heads = session.execute(
                select(TileHead.z, TileHead.x, TileHead.y, TileHead.latest_version, TileHead.updated_at)
            ).all()
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
            buckets = [(str(b), c) for b, c in zip(JOB_DURATION_BUCKETS_S, cumulative, strict=True)] + [
                ("+Inf", count)
            ]
            hist.add_metric([kind], buckets, total)
        yield hist
        updated = GaugeMetricFamily(
            "csr_tile_last_update_timestamp_seconds",
            "When each tile last got a new version (Unix time)",
            labels=["tile"],
        )
        version = GaugeMetricFamily("csr_tile_version", "Each tile's latest version number", labels=["tile"])
        for z, x, y, latest, at in heads:
            tile = f"{z}/{x}/{y}"
            at = at if at.tzinfo else at.replace(tzinfo=UTC)
            updated.add_metric([tile], at.timestamp())
            version.add_metric([tile], latest)
        yield updated
        yield version


class Metrics:
    """The metrics of one app (its own registry, so several apps can live in one process)."""

    def __init__(self, session_factory: sessionmaker[Session]) -> None:
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
        self.registry.register(_JobCollector(session_factory))
