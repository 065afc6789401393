"""Bounded render pool: renders run on worker threads, off the event loop; a full queue answers 503 at once.

At most ``workers + queue_size`` jobs are admitted; a job's slot is freed when its thread finishes
(even if the request already timed out), so the server never queues more work than it can do.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

__all__ = ["RenderPool", "PoolBusy"]

T = TypeVar("T")


class PoolBusy(RuntimeError):
    """The render queue is full, or a render ran past the timeout: retry after ``retry_after`` seconds."""

    def __init__(self, message: str, retry_after: int) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class RenderPool:
    """``workers`` render threads and room for ``queue_size`` waiting jobs."""

    def __init__(self, workers: int, queue_size: int, timeout_s: float, retry_after_s: int) -> None:
        self.workers, self.capacity = workers, workers + queue_size
        self.timeout_s, self.retry_after_s = timeout_s, retry_after_s
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="render")
        self._lock = threading.Lock()
        self.in_flight = 0
        self.rejected = 0

    def stats(self) -> dict[str, int]:
        return {"workers": self.workers, "capacity": self.capacity, "in_flight": self.in_flight,
                "rejected": self.rejected}

    def _release(self, _future: object) -> None:
        with self._lock:
            self.in_flight -= 1

    async def run(self, fn: Callable[[], T]) -> tuple[T, float]:
        """Run ``fn`` on a render thread; returns its result and the seconds it waited in the queue."""
        with self._lock:
            if self.in_flight >= self.capacity:
                self.rejected += 1
                raise PoolBusy(f"render queue full ({self.capacity} requests in flight); retry after "
                               f"{self.retry_after_s} s", self.retry_after_s)
            self.in_flight += 1
        submitted = time.perf_counter()
        started: list[float] = []

        def job() -> T:
            started.append(time.perf_counter())
            return fn()

        future = self._executor.submit(job)
        future.add_done_callback(self._release)
        try:
            result = await asyncio.wait_for(asyncio.wrap_future(future), self.timeout_s)
        except asyncio.TimeoutError:
            raise PoolBusy(f"render did not finish within {self.timeout_s:g} s; retry after "
                           f"{self.retry_after_s} s", self.retry_after_s) from None
        return result, started[0] - submitted
