"""``parksim serve``: the simulator HTTP service (renders, scene info, metrics, web viewer) over scene bundles."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``serve`` (cheap: no heavy imports)."""
    p = subparsers.add_parser(
        "serve", help="serve renders of scene bundles over HTTP (GET /render?pose=x,y,yaw, web viewer at /)",
        description="Load every scene bundle under --scenes once and serve GET/POST /render, /scenes, /healthz, "
                    "/metrics and the web viewer at /. API docs at /docs. Listens on loopback by default; any "
                    "other interface needs an API key (--api-key or PARKSIM_API_KEY).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--scenes", required=True, help="folder of bundle folders (or one bundle folder)")
    p.add_argument("--host", default="127.0.0.1", help="interface to listen on")
    p.add_argument("--port", type=int, default=8000, help="TCP port")
    p.add_argument("--api-key", help="key clients must send (X-API-Key); default: $PARKSIM_API_KEY")
    p.add_argument("--workers", type=int, help="render threads (default 1: each render uses every core)")
    p.add_argument("--queue", type=int, dest="queue_size", help="requests that may wait before 503 (default 8)")
    p.add_argument("--max-scale", type=float, help="largest resolution factor (default 2.0)")
    p.add_argument("--max-batch", type=int, help="most poses per POST /render (default 16)")
    p.add_argument("--max-reply-mib", type=float, help="largest reply one request may ask for, counted before "
                   "rendering; larger: 413 (default 64)")
    p.add_argument("--reply-budget-mib", type=float, help="reply MiB rendered or being sent at once over all "
                   "clients; beyond: 503 (default 256)")
    return p


def run(args: argparse.Namespace) -> int:
    """Validate the bind policy, load the scenes, run uvicorn until interrupted."""
    import uvicorn

    from server import Settings, create_app
    from server.auth import check_bind

    settings = Settings.from_env(api_key=args.api_key, workers=args.workers, queue_size=args.queue_size,
                                 max_scale=args.max_scale, max_batch=args.max_batch,
                                 max_reply_bytes=_mib(args.max_reply_mib),
                                 reply_budget_bytes=_mib(args.reply_budget_mib))
    check_bind(args.host, settings.api_key)
    app = create_app(args.scenes, settings)
    print(f"serving {', '.join(app.state.registry.ids)} on http://{args.host}:{args.port} (viewer at /, docs at /docs)")
    uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    return 0


def _mib(value: float | None) -> int | None:
    return None if value is None else int(value * 2**20)
