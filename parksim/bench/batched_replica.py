"""The ``serve.batch`` variant of ``SimReplica`` that ``parksim bench ray`` measures against the shipped one.

The jobs submitted to a replica's render pool while a batch renders go to its render thread together, as one task
(``serve.batch``, at most 8 jobs, 5 ms wait), rendered back to back: the renderer has no multi-pose kernel, so the
only saving is one hand-off to the render thread per batch instead of per request. The pool's own queueing and
limits are unchanged. Measured not faster (benchmarks: the ``ray`` suite), so it is not shipped. Importing this
module imports Ray.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from ray import serve

from ..server.ray_serve import SimReplica

__all__ = ["BatchedReplica"]


class _BatchExecutor:
    """Stands in for a replica's render-pool executor: jobs submitted while a batch renders go to its render
    thread together, as one task."""

    def __init__(self, executor: concurrent.futures.ThreadPoolExecutor) -> None:
        self.executor = executor

    @serve.batch(max_batch_size=8, batch_wait_timeout_s=0.005)
    async def _together(self, fns: list[Callable[[], Any]]) -> list[tuple[bool, Any]]:
        def run_all() -> list[tuple[bool, Any]]:
            out: list[tuple[bool, Any]] = []
            for fn in fns:
                try:
                    out.append((True, fn()))
                except Exception as e:   # handed back to that job's own request
                    out.append((False, e))
            return out

        return await asyncio.wrap_future(self.executor.submit(run_all))

    def submit(self, fn: Callable[[], Any]) -> concurrent.futures.Future[Any]:
        """Queue ``fn`` for the next batch; its future settles with its own result or exception."""
        future: concurrent.futures.Future[Any] = concurrent.futures.Future()

        def settle(task: asyncio.Task[Any]) -> None:
            error = task.exception()
            if error is not None:
                future.set_exception(error)
                return
            ok, value = task.result()
            if ok:
                future.set_result(value)
            else:
                future.set_exception(value)

        asyncio.ensure_future(self._together(fn)).add_done_callback(settle)
        return future


class BatchedReplica(SimReplica):
    """``SimReplica`` whose render pool batches concurrent jobs (the pool's own queueing and limits unchanged)."""

    def __serve_build_asgi_app__(self) -> FastAPI:
        app = super().__serve_build_asgi_app__()
        pool = app.state.pool
        pool._executor = _BatchExecutor(pool._executor)
        return app
