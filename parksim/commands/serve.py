"""``parksim serve``: the simulator HTTP service (renders, scene info, metrics, web viewer) over scene bundles."""

from __future__ import annotations

import argparse
import contextlib
import socket

from .argtypes import integer, number, tcp_port

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``serve`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "serve", help="serve renders of scene bundles over HTTP (GET /render?pose=x,y,yaw, web viewer at /)",
        description="Load every scene bundle under --scenes once and serve GET/POST /render, /scenes, /healthz, "
                    "/metrics and the web viewer at /. API docs at /docs. Listens on loopback by default; any "
                    "other interface needs an API key (--api-key or PARKSIM_API_KEY). The port is bound before the "
                    "scenes load, so a busy port fails at once.")
    p.add_argument("--scenes", required=True, help="folder of bundle folders (or one bundle folder)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on")
    p.add_argument("--port", type=tcp_port, default=8000, help="TCP port, 1 to 65535")
    p.add_argument("--api-key", help="key clients must send (X-API-Key); default: $PARKSIM_API_KEY")
    p.add_argument("--workers", type=integer(1), help="render threads (default 1: each render uses every core)")
    p.add_argument("--queue", type=integer(0), dest="queue_size",
                   help="requests that may wait before 503 (default 8)")
    p.add_argument("--max-scale", type=number(0, open_low=True), help="largest resolution factor (default 2.0)")
    p.add_argument("--max-batch", type=integer(1), help="most poses per POST /render (default 16)")
    p.add_argument("--max-reply-mib", type=number(0, open_low=True),
                   help="largest reply one request may ask for, counted before rendering; larger: 413 (default 64)")
    p.add_argument("--reply-budget-mib", type=number(0, open_low=True),
                   help="reply MiB rendered or being sent at once over all clients; beyond: 503 (default 256)")
    return p


def bind(host: str, port: int) -> list[socket.socket]:
    """Bind ``host:port`` as uvicorn would (every address ``host`` resolves to, SO_REUSEADDR, IPv6 only on IPv6
    sockets), so a busy port fails before the scenes load; uvicorn then serves on these sockets (no race)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as e:
        raise ValueError(f"--host {host}: {e.strerror}") from None
    sockets: list[socket.socket] = []
    try:
        for family, kind, proto, _, address in dict.fromkeys(infos):
            sock = socket.socket(family, kind, proto)
            sockets.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                sock.bind(address)
            except OSError as e:
                raise OSError(e.errno, f"cannot listen there: {e.strerror}", f"{host}:{port}") from None
    except BaseException:
        for sock in sockets:
            sock.close()
        raise
    return sockets


def run(args: argparse.Namespace) -> int:
    """Validate the settings and bind policy, bind the port, load the scenes, serve until interrupted."""
    import uvicorn

    from server import Settings, create_app
    from server.auth import check_bind

    settings = Settings.from_env(api_key=args.api_key, workers=args.workers, queue_size=args.queue_size,
                                 max_scale=args.max_scale, max_batch=args.max_batch,
                                 max_reply_bytes=_mib(args.max_reply_mib),
                                 reply_budget_bytes=_mib(args.reply_budget_mib))
    check_bind(args.host, settings.api_key)
    sockets = bind(args.host, args.port)
    try:
        app = create_app(args.scenes, settings)
        print(f"serving {', '.join(app.state.registry.ids)} on http://{args.host}:{args.port} "
              "(viewer at /, docs at /docs)", flush=True)
        server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
        with contextlib.suppress(KeyboardInterrupt):   # Ctrl-C is the way to stop it, as with uvicorn.run
            server.run(sockets=sockets)
    finally:
        for sock in sockets:
            sock.close()
    return 0


def _mib(value: float | None) -> int | None:
    return None if value is None else int(value * 2**20)
