"""The process's budget of upload bytes in flight: a cap on the memory that concurrent uploads take.

Every upload being checked holds a :class:`Reservation` of its decompressed bytes, taken step by
step while it inflates (a gzip bomb holds at most what it produced before it was stopped) and
given back when its request ends. A step that would take the process past
``CSR_MAX_UPLOAD_BYTES_IN_FLIGHT`` is refused: the upload answers 503 ``busy`` with
``Retry-After`` and the client sends it again later. Checking an upload takes about 1.5 times its
decompressed size (the body and one frame batch, :mod:`csr_core.upload_frames`), so the memory
of all uploads together stays within a small multiple of the budget.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache

from services.api.errors import ApiError

RETRY_AFTER_S = 2  # a refused upload's Retry-After: checking a large upload takes about a second


class UploadBudget:
    """Bytes in flight, shared by the threads that check uploads."""

    def __init__(self, capacity_bytes: int) -> None:
        self.capacity_bytes = capacity_bytes
        self._lock = threading.Lock()
        self._used_bytes = 0

    @property
    def used_bytes(self) -> int:
        with self._lock:
            return self._used_bytes

    def take(self, n_bytes: int) -> None:
        """Take ``n_bytes`` more; 503 ``busy`` (nothing taken) when they do not fit."""
        with self._lock:
            if self._used_bytes + n_bytes > self.capacity_bytes:
                in_flight = self._used_bytes
            else:
                self._used_bytes += n_bytes
                return
        raise ApiError(
            503,
            "busy",
            f"the server is checking {in_flight} bytes of other uploads; {n_bytes} more would pass its limit of "
            f"{self.capacity_bytes} bytes in flight: send the upload again after Retry-After",
            location="body",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        )

    def give_back(self, n_bytes: int) -> None:
        with self._lock:
            self._used_bytes -= n_bytes


class Reservation:
    """One upload's share of the budget."""

    def __init__(self, budget: UploadBudget) -> None:
        self._budget = budget
        self.held_bytes = 0

    def grow(self, n_bytes: int) -> None:
        self._budget.take(n_bytes)
        self.held_bytes += n_bytes


@cache
def budget_for(capacity_bytes: int) -> UploadBudget:
    """The process's budget (one per configured capacity: the process has one)."""
    return UploadBudget(capacity_bytes)


@contextmanager
def reservation(budget: UploadBudget) -> Iterator[Reservation]:
    held = Reservation(budget)
    try:
        yield held
    finally:
        budget.give_back(held.held_bytes)
