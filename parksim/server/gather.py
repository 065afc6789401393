"""Concurrent single-pose requests for the same views of a scene, rendered together as one batch.

On a GPU one render of B poses (``LocalSim.render_batch``: one kernel launch, one rasterizer call for all their
cameras) costs little more than one render of one pose, so 16 clients each asking ``GET /render`` are served
faster by one batched render than by 16 renders in turn. The gatherer holds each such job for at most
``window_s`` (or until ``max_batch`` have come), renders the group on the pool as one job, and hands each request
its own reply (its own encoding, metadata and timings, ``gathered`` saying how many shared the render). On a CPU
a render already uses every core and a batch is no faster, so ``Settings.gather`` "auto" gathers only for scenes
on a GPU.
"""

from __future__ import annotations

import asyncio
from collections.abc import Hashable

from .jobs import RenderJob, Reply, render_together
from .pool import RenderPool

__all__ = ["Gatherer"]


class Gatherer:
    """Groups gatherable jobs by scene and view set; one pool job renders each group."""

    def __init__(self, pool: RenderPool, window_s: float, max_batch: int, jpeg_quality: int) -> None:
        """Args:
            pool: where the grouped render runs (one pool slot per group).
            window_s: how long the first job of a group waits for others.
            max_batch: a group is rendered at once when it has this many jobs.
            jpeg_quality: of single-view JPEG replies.
        """
        self.pool, self.window_s, self.max_batch, self.jpeg_quality = pool, window_s, max_batch, jpeg_quality
        self._pending: dict[Hashable, list[tuple[RenderJob, asyncio.Future[Reply]]]] = {}

    @staticmethod
    def _key(job: RenderJob) -> Hashable:
        return id(job.sim), tuple(job.cameras), job.bev, job.scale, job.depth

    async def run(self, job: RenderJob) -> Reply:
        """Render ``job`` with whatever jobs of the same scene and views arrive within the window.

        Args:
            job: a single-pose job.

        Returns:
            Its reply, as ``job.run`` would give it (but for the timings and ``gathered``).
        """
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Reply] = loop.create_future()
        key = self._key(job)
        group = self._pending.setdefault(key, [])
        group.append((job, future))
        if len(group) >= self.max_batch:
            self._flush(key)
        elif len(group) == 1:
            loop.call_later(self.window_s, self._flush, key)
        return await future

    def _flush(self, key: Hashable) -> None:
        group = self._pending.pop(key, None)
        if group:
            asyncio.ensure_future(self._render(group))

    async def _render(self, group: list[tuple[RenderJob, asyncio.Future[Reply]]]) -> None:
        jobs = [job for job, _ in group]
        try:
            replies, queued = await self.pool.run(lambda: render_together(jobs, self.jpeg_quality))
        except BaseException as error:   # every request of the group gets the error (503, 413, ...)
            for _, future in group:
                if not future.done():
                    future.set_exception(error)
            return
        for (_, future), reply in zip(group, replies):
            reply.meta.timings_ms["queue"] = round(queued * 1000, 3)
            if not future.done():   # a client that left
                future.set_result(reply)
