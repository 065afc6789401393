"""``parksim serve``: the simulator HTTP service (renders, scene info, metrics, web viewer) over scene bundles."""

from __future__ import annotations

import argparse
import contextlib
import signal
import socket
import time
from pathlib import Path
from typing import Any

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
    ray = p.add_argument_group("Ray Serve (needs parksim[ray]; docs/ray.md)",
                               "the same API from Ray Serve replicas, each loading the scenes itself (so --scenes "
                               "must be readable at the same path on every node); the limits above are per replica")
    ray.add_argument("--ray", action="store_true", help="serve through Ray Serve instead of one process")
    ray.add_argument("--address", metavar="HEAD:PORT",
                     help="join the Ray cluster with this head (as `ray start --head` prints it); default: start a "
                          "local Ray instance on this machine's cores")
    count = ray.add_mutually_exclusive_group()
    count.add_argument("--replicas", type=integer(1), help="fixed number of replicas (default 1)")
    count.add_argument("--autoscale", type=_span, metavar="MIN,MAX",
                       help="scale between MIN and MAX replicas (1 <= MIN <= MAX) on each replica's ongoing requests")
    ray.add_argument("--replica-cpus", type=integer(1),
                     help="CPUs each replica reserves and renders with (default 1)")
    return p


def _span(text: str) -> tuple[int, int]:
    """``MIN,MAX`` replicas with 1 <= MIN <= MAX."""
    try:
        low, high = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN,MAX like 1,4, got {text!r}") from None
    if not 1 <= low <= high:
        raise argparse.ArgumentTypeError(f"need 1 <= MIN <= MAX, got {text}")
    return low, high


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
    from parksim.server import Settings, create_app
    from parksim.server.auth import check_bind

    settings = Settings.from_env(api_key=args.api_key, workers=args.workers, queue_size=args.queue_size,
                                 max_scale=args.max_scale, max_batch=args.max_batch,
                                 max_reply_bytes=_mib(args.max_reply_mib),
                                 reply_budget_bytes=_mib(args.reply_budget_mib))
    check_bind(args.host, settings.api_key)
    if args.ray:
        return _run_ray(args, settings)
    given = [flag for flag in ("address", "replicas", "autoscale", "replica_cpus") if getattr(args, flag) is not None]
    if given:
        raise ValueError(f"--{given[0].replace('_', '-')} only applies with --ray")
    import uvicorn

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


def _run_ray(args: argparse.Namespace, settings: Any) -> int:
    """Deploy on Ray Serve (a local Ray instance, or the cluster at ``--address``) and serve until Ctrl-C or
    SIGTERM, then take the deployment (and a Ray this process started) down."""
    try:
        from parksim.server import ray_serve
    except ModuleNotFoundError as e:
        if e.name != "ray" and not str(e.name).startswith("ray."):
            raise
        raise ValueError("--ray needs Ray Serve, which is not installed: install parksim[ray] "
                         "(pip install 'parksim[ray]')") from None
    if not Path(args.scenes).is_dir():
        raise ValueError(f"scenes folder not found: {args.scenes}")
    for sock in bind(args.host, args.port):   # a busy port fails before Ray starts; Serve's proxy binds it next
        sock.close()
    scaling = ray_serve.Scaling(args.replicas or 1, args.autoscale, args.replica_cpus or 1)
    ray_serve.start(args.scenes, settings, scaling, args.host, args.port, args.address)
    try:
        size = (f"{args.autoscale[0]} to {args.autoscale[1]}" if args.autoscale else str(scaling.replicas))
        print(f"serving on http://{args.host}:{args.port} from {size} Ray Serve replica(s) of {scaling.cpus} CPU(s) "
              "(viewer at /, docs at /docs)", flush=True)
        wait_for_interrupt()
    finally:
        ray_serve.stop(own_ray=args.address is None)
    return 0


def wait_for_interrupt(poll_s: float = 0.5) -> None:
    """Block until SIGINT (Ctrl-C) or SIGTERM, which both stop the server as they stop uvicorn's.

    Both are taken here whatever the process inherited (call it after ``ray.init``, which sets its own SIGTERM
    handler): a background job of a non-interactive shell starts with SIGINT ignored, and Python keeps an ignored
    SIGINT ignored. The main thread wakes every ``poll_s`` seconds, so a signal the kernel hands to another thread
    (Ray runs many) is acted on too; a bare lock wait would sleep through it.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    with contextlib.suppress(KeyboardInterrupt):
        while True:
            time.sleep(poll_s)


def _mib(value: float | None) -> int | None:
    return None if value is None else int(value * 2**20)
