"""From a validated ``RenderJob`` to its HTTP reply, under the reply budget.

The reply's bytes are reserved before rendering and released only once its body has been handed to the
server in full (or the client has gone): the body goes out in ``CHUNK``-byte pieces, so a client that does
not read stalls the send at the socket, with at most one piece buffered, instead of the whole reply being
queued in user space and counted as sent.
"""

from __future__ import annotations

from dataclasses import dataclass

from fastapi.responses import Response
from starlette.types import Receive, Scope, Send

from .budget import ReplyBudget, Reservation
from .gather import Gatherer
from .jobs import RenderJob
from .metrics import Metrics
from .pool import RenderPool

__all__ = ["Renderer", "BudgetedResponse", "CHUNK", "TIMING_HEADERS"]

CHUNK = 1 << 20
TIMING_HEADERS = {
    "X-Render-Timings": "server time per stage of this job: 'queue=..ms, views=..ms, bev=..ms, encode=..ms'",
    "X-Render-Time-Ms": "rendering time (views + BEV) in milliseconds",
}


class BudgetedResponse(Response):
    """A reply sent in ``CHUNK``-byte pieces that releases its budget ``reservation`` when the send ends."""

    def __init__(self, body: bytes, reservation: Reservation, media_type: str, headers: dict[str, str]) -> None:
        super().__init__(body, media_type=media_type, headers=headers)
        self.reservation = reservation

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
            view = memoryview(self.body)
            for start in range(0, max(len(view), 1), CHUNK):
                await send({"type": "http.response.body", "body": view[start:start + CHUNK],
                            "more_body": start + CHUNK < len(view)})
        finally:
            self.reservation.release()


@dataclass(frozen=True)
class Renderer:
    """Runs jobs on the pool with their reply bytes reserved in the budget; records stage times.

    A single-pose job goes through ``gatherer`` (rendered together with concurrent ones) when ``gather`` is "on",
    or "auto" and its scene is on a GPU.
    """

    pool: RenderPool
    budget: ReplyBudget
    metrics: Metrics
    jpeg_quality: int
    gatherer: Gatherer | None = None
    gather: str = "off"

    def _gathers(self, job: RenderJob) -> bool:
        if self.gatherer is None or job.batch or len(job.poses) != 1 or self.gather == "off":
            return False
        return self.gather == "on" or job.sim.device.type == "cuda"

    async def respond(self, job: RenderJob) -> Response:
        """Render ``job`` and answer it; ``BudgetFull`` or ``PoolBusy`` (503) when there is no room for it now."""
        reservation = self.budget.reserve(job.reply_bytes)
        try:
            reply = await (self.gatherer.run(job) if self.gatherer is not None and self._gathers(job)
                           else job.run(self.pool, self.jpeg_quality))
        except BaseException:
            reservation.release()
            raise
        t = reply.meta.timings_ms
        n_images = len(reply.meta.cameras) + int(reply.meta.bev)
        self.metrics.render({k: v / 1000 for k, v in t.items()}, n_images * len(reply.meta.poses))
        headers = {"X-Render-Timings": ", ".join(f"{k}={v:.1f}ms" for k, v in t.items()),
                   "X-Render-Time-Ms": f"{t.get('views', 0) + t.get('bev', 0):.1f}", "Cache-Control": "no-store"}
        return BudgetedResponse(reply.body, reservation, reply.media_type, headers)
