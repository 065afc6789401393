"""Ray Serve's HTTP proxy answers a request whose replica died under it with the server's 503 JSON, not 500 text.

When a replica process dies while it holds a request (killed, out of memory, its node lost), Serve's proxy gets a
``RayActorError`` for it and stops sending: before the reply's first message, uvicorn answers ``500 Internal Server
Error`` in text/plain; after it, the client gets headers and a body cut short. A client can tell neither from a bug,
and does not retry. :class:`ReplicaLost` wraps the proxy's ASGI app, holds each reply until its last message (up to
:data:`HOLD_BYTES`), and answers a request whose reply did not complete as the app answers a full render queue: 503,
``Retry-After``, ``{"detail": ...}``. Serve loads it in every
proxy process from ``RAY_SERVE_HTTP_PROXY_CALLBACK_IMPORT_PATH`` (set by :func:`proxy_env`); this module imports only
Starlette, so the proxy does not load the renderer.
"""

from __future__ import annotations

import os

from starlette.middleware import Middleware
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["ReplicaLost", "middlewares", "proxy_env", "HOLD_BYTES", "RETRY_AFTER_ENV"]

HOLD_BYTES = 64 << 20
"""Reply bytes the proxy holds back until the reply completes (a render batch larger than this streams through)."""
RETRY_AFTER_ENV = "PARKSIM_RAY_RETRY_AFTER_S"
"""Environment variable of the proxy process: the ``Retry-After`` seconds (the replicas' ``retry_after_s``)."""


class ReplicaLost:
    """ASGI middleware: an HTTP reply is passed on once complete; a request the wrapped app returned from before its
    reply completed gets 503 JSON with ``Retry-After: retry_after_s`` instead. Serve's proxy returns so only when the
    request failed in Ray (its replica died, or Serve could not run it): a replica's own error replies, 408, 429 and
    503 complete and pass through untouched.

    A reply is held until its last body message, so a replica that dies between the reply's headers and its body
    (a window of Serve's message stream) still gets the 503, not a cut body. Once a reply holds more than
    ``hold_bytes`` it is passed on as it comes, and a failure after that can only cut it short.
    """

    def __init__(self, app: ASGIApp, retry_after_s: int = 1, hold_bytes: int = HOLD_BYTES) -> None:
        self.app, self.retry_after_s, self.hold_bytes = app, retry_after_s, hold_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        held: list[Message] = []
        size, passed, complete = 0, False, False

        async def hold(message: Message) -> None:
            nonlocal size, passed, complete
            complete = complete or (message["type"] == "http.response.body" and not message.get("more_body", False))
            if passed:
                await send(message)
                return
            held.append(message)
            size += len(message.get("body", b""))
            if complete or size > self.hold_bytes:
                passed = True
                for m in held:
                    await send(m)
                held.clear()

        await self.app(scope, receive, hold)
        if not passed:   # uvicorn would answer 500 text/plain (and ignores this send if the client has gone)
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
