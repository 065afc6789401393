"""``parksim serve --ray``: the simulator app of ``create_app`` served by Ray Serve replicas.

Each replica builds the same FastAPI app itself (``__serve_build_asgi_app__`` runs in the replica), so it loads the
scene bundles from a path every node can read: only that path and the ``Settings`` travel from the driver, never a
scene tensor. Importing this module imports Ray; the single-process server never does.
"""

from __future__ import annotations

import logging
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray
from fastapi import FastAPI
from ray import serve
from ray.exceptions import RayError
from ray.serve.deployment import Application
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ..ray_proxy import proxy_env
from .app import create_app
from .settings import Settings

__all__ = ["SimReplica", "PicklableBodies", "Scaling", "application", "start", "stop", "check_reachable", "APP_NAME",
           "HEADROOM", "QUIET"]

APP_NAME = "parksim"
QUIET = {"log_level": "WARNING", "enable_access_log": False}
"""Serve's logging: warnings and errors only, no line per request (the app's /metrics counts requests)."""
HEADROOM = 4
"""Requests a replica accepts beyond its render pool (workers + queue), so /healthz and /metrics still get in
while the pool is full and the app itself answers 503 for renders, as the single-process server does."""


@serve.ingress()
class SimReplica:
    """One Serve replica: the simulator app over the scenes folder ``scenes``, loaded here at replica start-up
    (refusing bundles that do not load as ``create_app`` does, or failing on one when ``strict``)."""

    def __init__(self, scenes: str, settings: Settings, strict: bool = False) -> None:
        self.scenes, self.settings, self.strict = scenes, settings, strict

    def __serve_build_asgi_app__(self) -> FastAPI:
        app = create_app(self.scenes, self.settings, self.strict)
        app.add_middleware(PicklableBodies)
        return app


class PicklableBodies:
    """ASGI middleware turning ``memoryview`` response bodies into ``bytes``: Serve pickles every message a replica
    sends to its HTTP proxy, and the app streams replies as memoryview slices (``parksim.server.replies``)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def send_bytes(message: Message) -> None:
            body = message.get("body")
            await send({**message, "body": body.tobytes()} if isinstance(body, memoryview) else message)

        await self.app(scope, receive, send_bytes)


@dataclass(frozen=True)
class Scaling:
    """A fixed number of ``replicas``, or ``autoscale=(min, max)``; each replica reserves ``cpus`` Ray CPUs and
    renders with that many threads, and ``gpus`` Ray GPUs (a fraction shares one GPU; 0: none visible to it)."""

    replicas: int = 1
    autoscale: tuple[int, int] | None = None
    cpus: int = 1
    gpus: float = 0.0

    def options(self, settings: Settings) -> dict[str, Any]:
        """``Deployment.options`` for this scaling: replicas or autoscaling, CPUs, GPUs and threads per replica.

        A replica that reserves no GPU is shown none (``CUDA_VISIBLE_DEVICES`` empty): Ray leaves every GPU visible
        to such a worker, and ``--device auto`` would then render on a GPU it never reserved.
        """
        threads = str(self.cpus)
        env = {"OMP_NUM_THREADS": threads, "NUMBA_NUM_THREADS": threads}
        if self.gpus == 0:
            env["CUDA_VISIBLE_DEVICES"] = ""
        out: dict[str, Any] = {
            "ray_actor_options": {"num_cpus": self.cpus, "num_gpus": self.gpus, "runtime_env": {"env_vars": env}},
            "max_ongoing_requests": settings.workers + settings.queue_size + HEADROOM,
            "max_constructor_retry_count": 1}
        if self.autoscale is None:
            out["num_replicas"] = self.replicas
        else:
            low, high = self.autoscale
            out["autoscaling_config"] = {"min_replicas": low, "initial_replicas": low, "max_replicas": high,
                                         "target_ongoing_requests": 2 * settings.workers}
        return out


def application(scenes: str | Path, settings: Settings, scaling: Scaling, strict: bool = False) -> Application:
    """The Serve application of ``SimReplica`` over the absolute path of ``scenes``."""
    deployment = serve.deployment(name="SimReplica")(SimReplica).options(**scaling.options(settings))
    return deployment.bind(str(Path(scenes).resolve()), settings, strict)


def start(scenes: str | Path, settings: Settings, scaling: Scaling, host: str, port: int,
          address: str | None = None, strict: bool = False) -> None:
    """Start Ray on this machine's cores, or join the cluster at ``address``; start Serve's HTTP proxy on
    ``host:port`` and deploy. Returns once every replica has loaded the scenes; ``ValueError`` with one line when
    the cluster cannot be reached or a replica fails to start, with everything started here taken down again.

    This driver's job carries :func:`parksim.ray_proxy.proxy_env`, which the Serve controller and the proxies it
    starts inherit: a request whose replica dies under it gets 503 JSON with ``Retry-After``, not 500 text. A Serve
    that already runs on the cluster keeps the proxies it has (see docs/ray.md)."""
    logging.getLogger("ray.serve").setLevel(logging.WARNING)
    if address is not None:
        check_reachable(address)
    try:   # replica logs stay in Ray's session log folder (log_to_driver=False)
        ray.init(address=address, num_cpus=(os.cpu_count() or 1) if address is None else None,
                 include_dashboard=False if address is None else None, logging_level=logging.ERROR,
                 log_to_driver=False, runtime_env={"env_vars": proxy_env(settings.retry_after_s)})
    except ConnectionError as e:
        raise ValueError(f"cannot join the Ray cluster at {address}: {str(e).splitlines()[0]}") from None
    try:
        try:
            serve.start(http_options={"host": host, "port": port}, logging_config=QUIET)
        except (RayError, TimeoutError) as e:   # seen with 2 cores and 3 busy processes: the proxy was killed
            raise ValueError(f"Ray Serve's HTTP proxy did not start ({type(e).__name__}); is the machine "
                             "overloaded? Ray's session logs say more") from None
        try:
            serve.run(application(scenes, settings, scaling, strict), name=APP_NAME, route_prefix="/",
                      logging_config=QUIET)
        except RuntimeError:
            raise ValueError(f"the Ray Serve replicas did not start: {_startup_error()}") from None
    except BaseException:
        stop(own_ray=address is None)
        raise


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """``ValueError`` when a ``HOST:PORT`` cluster address does not accept a TCP connection within ``timeout_s``
    (Ray itself keeps retrying an unreachable head for minutes); other address forms are left to Ray."""
    host, _, port = address.rpartition(":")
    if not (host and port.isdigit()) or "://" in address:
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout_s).close()
    except OSError as e:
        raise ValueError(f"cannot reach the Ray cluster at {address}: {e.strerror or e}") from None


def _startup_error() -> str:
    """The root cause of a failed deployment: the last line of the replica's traceback that Serve reports."""
    status = serve.status().applications[APP_NAME]
    messages = [d.message for d in status.deployments.values() if d.message] or [status.message]
    return [line for line in messages[0].splitlines() if line.strip()][-1].strip()


def stop(own_ray: bool) -> None:
    """Take the app down: all of Serve and Ray when this process started Ray (``own_ray``), else only this app
    (other Serve apps on the cluster keep running) before disconnecting."""
    if own_ray:
        serve.shutdown()
    else:
        serve.delete(APP_NAME)
    ray.shutdown()
