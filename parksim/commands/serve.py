"""``parksim serve``: the simulator HTTP service (renders, scene info, metrics, web viewer) over scene bundles."""

from __future__ import annotations

import argparse

from ..device import DEVICE_HELP
from .argtypes import integer, number, tcp_port

__all__ = ["add_parser", "run"]


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``serve`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "serve", help="serve renders of scene bundles over HTTP (GET /render?pose=x,y,yaw, web viewer at /)",
        description="Load every scene bundle under --scenes once (refusing, with a warning, any that does not "
                    "load, unless --strict; exit status 2 when none loads) and serve GET/POST /render, /scenes, "
                    "/healthz, /metrics and the web viewer at /. API docs at /docs. Listens on loopback by default; "
                    "any other interface needs an API key (--api-key-file or PARKSIM_API_KEY; --api-key shows the key "
                    "in `ps`), which clients send as the X-API-Key header. Only requests whose Host is a loopback "
                    "name or --host are answered, unless --host is 0.0.0.0 or ::. The port is bound before the "
                    "scenes load, so a busy port fails at once.")
    p.add_argument("--scenes", required=True, help="folder of bundle folders (or one bundle folder)")
    p.add_argument("--strict", action="store_true",
                   help="exit (status 2) on the first bundle that does not load; by default such a bundle is refused "
                        "with a warning, listed in /scenes and /healthz, and the others are served")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on")
    p.add_argument("--port", type=tcp_port, default=8000, help="TCP port, 1 to 65535")
    key = p.add_mutually_exclusive_group()
    key.add_argument("--api-key-file", metavar="PATH",
                     help="file holding the key clients must send as X-API-Key (one trailing newline ignored); "
                          "default: $PARKSIM_API_KEY")
    key.add_argument("--api-key", help="the key itself; visible to every user in `ps`: prefer --api-key-file or "
                                       "$PARKSIM_API_KEY")
    p.add_argument("--workers", type=integer(1), help="render threads (default 1: each render uses every core)")
    p.add_argument("--queue", type=integer(0), dest="queue_size",
                   help="requests that may wait before 503 (default 8)")
    p.add_argument("--max-scale", type=number(0, open_low=True), help="largest resolution factor (default 2.0)")
    p.add_argument("--max-batch", type=integer(1), help="most poses per POST /render (default 16)")
    p.add_argument("--max-reply-mib", type=number(0, open_low=True),
                   help="largest reply one request may ask for, counted before rendering; larger: 413 (default 64)")
    p.add_argument("--reply-budget-mib", type=number(0, open_low=True),
                   help="reply MiB rendered or being sent at once over all clients; beyond: 503 (default 256)")
    p.add_argument("--gather", choices=("auto", "on", "off"),
                   help="render concurrent single-pose GET requests for the same views together, as one batch "
                        "(default auto: for scenes on a GPU, where a batch costs little more than one render)")
    p.add_argument("--gather-window-ms", type=number(0), metavar="MS",
                   help="how long a request waits for others to render with (default 2)")
    p.add_argument("--max-episodes", type=integer(1),
                   help="live scenario episodes (POST /episodes) at once; more: 503 (default 16)")
    p.add_argument("--episode-ttl", type=number(0, open_low=True), dest="episode_ttl_s", metavar="SECONDS",
                   help="an episode untouched this long is dropped (default 300)")
    p.add_argument("--device", default="auto",
                   help=DEVICE_HELP + "; with --ray each replica resolves it on its node (cuda needs --replica-gpus)")
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
    ray.add_argument("--replica-gpus", type=number(0),
                     help="GPUs each replica reserves, fractions allowed (0.25: four replicas share one GPU); "
                          "default 0: Ray shows the replica no GPU, so --device auto renders on its CPUs")
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


def run(args: argparse.Namespace) -> int:
    """Check the flags, build the settings, and serve until interrupted (``parksim.server.launch``)."""
    from parksim.server import Settings
    from parksim.server.launch import serve, serve_ray
    from parksim.server.settings import read_key_file

    api_key = read_key_file(args.api_key_file) if args.api_key_file is not None else args.api_key
    settings = Settings.from_env(api_key=api_key, workers=args.workers, queue_size=args.queue_size,
                                 max_scale=args.max_scale, max_batch=args.max_batch,
                                 max_reply_bytes=_mib(args.max_reply_mib),
                                 reply_budget_bytes=_mib(args.reply_budget_mib), device=args.device,
                                 gather=args.gather, gather_window_ms=args.gather_window_ms,
                                 max_episodes=args.max_episodes, episode_ttl_s=args.episode_ttl_s)
    if args.ray:
        serve_ray(args.scenes, settings, args.host, args.port, args.replicas or 1, args.autoscale,
                  args.replica_cpus or 1, args.address, strict=args.strict, replica_gpus=args.replica_gpus or 0.0)
        return 0
    given = [flag for flag in ("address", "replicas", "autoscale", "replica_cpus", "replica_gpus")
             if getattr(args, flag) is not None]
    if given:
        raise ValueError(f"--{given[0].replace('_', '-')} only applies with --ray")
    serve(args.scenes, settings, args.host, args.port, strict=args.strict)
    return 0


def _mib(value: float | None) -> int | None:
    return None if value is None else int(value * 2**20)
