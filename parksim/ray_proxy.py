"""Ray Serve's HTTP proxy answers a request whose replica died under it with the server's 503 JSON, not 500 text.

When a replica process dies while it holds a request (killed, out of memory, its node lost), Serve's proxy gets a
``RayActorError`` for it and sends nothing, so uvicorn answers ``500 Internal Server Error`` in text/plain: a client
cannot tell that from a bug, and does not retry. :class:`ReplicaLost` wraps the proxy's ASGI app and answers such a
request as the app answers a full render queue: 503, ``Retry-After``, ``{"detail": ...}``. Serve loads it in every
proxy process from ``RAY_SERVE_HTTP_PROXY_CALLBACK_IMPORT_PATH`` (set by :func:`proxy_env`); this module imports only
Starlette, so the proxy does not load the renderer.
"""

from __future__ import annotations

import os

from starlette.middleware import Middleware
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["ReplicaLost", "middlewares", "proxy_env", "RETRY_AFTER_ENV"]

RETRY_AFTER_ENV = "PARKSIM_RAY_RETRY_AFTER_S"
"""Environment variable of the proxy process: the ``Retry-After`` seconds (the replicas' ``retry_after_s``)."""


class ReplicaLost:
    """ASGI middleware: an HTTP request the wrapped app returned from without starting a response gets 503 JSON
    with ``Retry-After: retry_after_s``. Serve's proxy returns so only when the request failed in Ray (its replica
    died, or Serve could not run it): a replica's own error replies, 408, 429 and 503 start a response and pass
    through untouched."""

    def __init__(self, app: ASGIApp, retry_after_s: int = 1) -> None:
        self.app, self.retry_after_s = app, retry_after_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def watch(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        await self.app(scope, receive, watch)
        if not started:   # uvicorn would answer 500 text/plain (and ignores this send if the client has gone)
            detail = (f"the Ray Serve replica serving this request stopped before it answered (Serve restarts it): "
                      f"retry after {self.retry_after_s} s")
            reply = JSONResponse({"detail": detail}, status_code=503, headers={"Retry-After": str(self.retry_after_s)})
            await reply(scope, receive, send)


def middlewares() -> list[Middleware]:
    """What Serve's proxy calls (named by :func:`proxy_env`) for the middlewares around its app.

    Returns:
        :class:`ReplicaLost` with the ``Retry-After`` of :data:`RETRY_AFTER_ENV` (1 s when unset).
    """
    return [Middleware(ReplicaLost, retry_after_s=int(os.environ.get(RETRY_AFTER_ENV, "1")))]


def proxy_env(retry_after_s: int) -> dict[str, str]:
    """The environment variables that make Serve's proxies load :func:`middlewares`, for a ``runtime_env``.

    Args:
        retry_after_s: seconds for ``Retry-After``.

    Returns:
        ``RAY_SERVE_HTTP_PROXY_CALLBACK_IMPORT_PATH`` and :data:`RETRY_AFTER_ENV`.
    """
    return {"RAY_SERVE_HTTP_PROXY_CALLBACK_IMPORT_PATH": f"{__name__}:middlewares",
            RETRY_AFTER_ENV: str(retry_after_s)}
