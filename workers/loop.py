"""A background thread that wakes on demand or every ``poll_interval_s``: the base of the outbox
relay and of the embedded pool's dispatcher. Each wake-up also schedules dirty tiles whose quiet
period has passed, and every ``CSR_RETENTION_CHECK_EVERY_S`` it deletes the raw uploads past
``CSR_RAW_RETENTION_DAYS`` (``services.retention``); several processes may do both: each is safe
against concurrency."""

from __future__ import annotations

import logging
import threading
import time

from sqlalchemy.orm import Session, sessionmaker

from services import retention
from services.db import repo
from services.settings import Settings

log = logging.getLogger(__name__)

SCHEDULE_EVERY_S = 1.0  # how often the quiet-period scheduler looks for due tiles


class BackgroundLoop:
    name = "csr-loop"

    def __init__(self, settings: Settings, session_factory: sessionmaker[Session]) -> None:
        self.settings = settings
        self.session_factory = session_factory
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._last_schedule = 0.0
        self._last_retention = float("-inf")  # the first round checks at once

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=30)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self.settings.poll_interval_s)
            self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self._schedule_due_tiles()
                self._purge_expired_uploads()
                self.tick()
            except Exception:
                log.exception("%s: iteration failed; retrying", self.name)
                time.sleep(self.settings.poll_interval_s)

    def _schedule_due_tiles(self) -> None:
        if time.monotonic() - self._last_schedule < SCHEDULE_EVERY_S:
            return
        self._last_schedule = time.monotonic()
        with self.session_factory.begin() as session:
            jobs = repo.schedule_dirty_tiles(
                session, last_marked_before=repo.quiet_before(self.settings.quiet_period_s)
            )
        if jobs:
            log.info("scheduled %d tile job(s) after the quiet period", len(jobs))

    def _purge_expired_uploads(self) -> None:
        days = self.settings.raw_retention_days
        if days is None or time.monotonic() - self._last_retention < self.settings.retention_check_every_s:
            return
        self._last_retention = time.monotonic()
        result = retention.purge_expired(self.session_factory, retention_days=days)
        if result.purged:
            log.info("deleted %d raw upload(s) received before %s", result.purged, result.cutoff.isoformat())

    def tick(self) -> None:
        """One round of work (subclasses)."""
