"""A background thread that wakes on demand or every ``poll_interval_s``: the base of the outbox
relay and of the embedded pool's dispatcher. Each wake-up also schedules dirty tiles whose quiet
period has passed (several processes may do it: scheduling is safe against concurrency)."""

from __future__ import annotations

import logging
import threading
import time

from sqlalchemy.orm import Session, sessionmaker

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

    def tick(self) -> None:
        """One round of work (subclasses)."""
