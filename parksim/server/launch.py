"""Starting the simulator service: in this process under uvicorn (:func:`serve`) or from Ray Serve replicas
(:func:`serve_ray`), each serving until Ctrl-C or SIGTERM.

What ``parksim serve`` runs, callable from Python with typed arguments. Both refuse a non-loopback interface
without an API key, answer only requests whose ``Host`` is a loopback name or ``host`` (unless bound to every
interface; see :func:`parksim.server.auth.allowed_hosts`), and take the port before the scenes load, so a busy port
fails at once.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import time
from collections.abc import Callable
from pathlib import Path

import uvicorn

from ..device import describe_device, resolve_device
from .app import create_app
from .auth import allowed_hosts, check_bind
from .settings import Settings

__all__ = ["serve", "serve_ray", "bind", "wait_for_interrupt"]


def _say(line: str) -> None:
    print(line, flush=True)


def _guarded(host: str, settings: Settings) -> Settings:
    """``settings`` checked for listening on ``host``, answering only the ``Host`` names it allows (unless the
    caller set ``allowed_hosts`` itself)."""
    check_bind(host, settings.api_key)
    if settings.allowed_hosts is not None:
        return settings
    return settings.model_copy(update={"allowed_hosts": allowed_hosts(host)})


def bind(host: str, port: int) -> list[socket.socket]:
    """Bind ``host:port`` as uvicorn would (every address ``host`` resolves to, SO_REUSEADDR, IPv6 only on IPv6
    sockets), so a busy port fails before the scenes load; uvicorn then serves on these sockets (no race).

    Args:
        host: interface name or address.
        port: TCP port.

    Returns:
        The bound (not yet listening) sockets; the caller closes them.

    Raises:
        ValueError: ``host`` does not resolve.
        OSError: the port is taken or not allowed (the message names ``host:port``).
    """
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


def serve(scenes: str | Path, settings: Settings, host: str = "127.0.0.1", port: int = 8000,
          log: Callable[[str], None] = _say, strict: bool = False) -> None:
    """Serve every scene bundle under ``scenes`` from this process until Ctrl-C; a bundle that does not load is
    refused (a warning on the ``parksim.server.scenes`` logger, listed in ``/scenes`` and ``/healthz``) and the
    others are served.

    Args:
        scenes: a folder of bundle folders, or one bundle folder.
        settings: the server's limits, API key and device (``settings.device``, resolved here).
        host: interface to listen on; other than loopback it needs ``settings.api_key``. Requests whose ``Host``
            is neither a loopback name nor ``host`` are refused (421), unless ``host`` is 0.0.0.0 or ::.
        port: TCP port.
        log: receives the one line saying what is served where, on which device (and which bundles were refused),
            once the scenes are loaded.
        strict: fail on the first bundle that does not load instead of refusing it.

    Raises:
        ValueError: a non-loopback ``host`` without an API key, or an unresolvable ``host``.
        DeviceError: ``settings.device`` is a bad name or a GPU this machine lacks (before the port is taken).
        OSError: the port is taken (before any scene loads).
        parksim.bundle.BundleError: no loadable scene under ``scenes``, or with ``strict`` a bundle that does not
            load.
    """
    settings = _guarded(host, settings)
    device = resolve_device(settings.device)
    sockets = bind(host, port)
    try:
        app = create_app(scenes, settings, strict)
        registry = app.state.registry
        refused = f"; refused {', '.join(registry.refused)} (see /scenes)" if registry.refused else ""
        log(f"serving {', '.join(registry.ids)} on http://{host}:{port} (rendering on {describe_device(device)}; "
            f"viewer at /, docs at /docs){refused}")
        server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
        with contextlib.suppress(KeyboardInterrupt):   # Ctrl-C is the way to stop it, as with uvicorn.run
            server.run(sockets=sockets)
    finally:
        for sock in sockets:
            sock.close()


def serve_ray(scenes: str | Path, settings: Settings, host: str = "127.0.0.1", port: int = 8000,
              replicas: int = 1, autoscale: tuple[int, int] | None = None, replica_cpus: int = 1,
              address: str | None = None, log: Callable[[str], None] = _say, strict: bool = False,
              replica_gpus: float = 0.0) -> None:
    """Serve the scenes from Ray Serve replicas until Ctrl-C or SIGTERM, then take the deployment (and a Ray this
    call started) down. Each replica loads the scenes itself, so ``scenes`` must be readable at the same path on
    every node; ``settings``' limits hold per replica. Each replica refuses a bundle that does not load as
    :func:`serve` does (the warning goes to Ray's session logs; ``/scenes`` and ``/healthz`` list it).

    Args:
        scenes: a folder of bundle folders, or one bundle folder.
        settings: the server's limits, API key and device; each replica resolves ``settings.device`` on its node
            (``auto`` takes the GPU it reserved, if any).
        host: interface Serve's HTTP proxy listens on; other than loopback it needs ``settings.api_key``; the
            ``Host`` check is as for :func:`serve`.
        port: TCP port of the proxy.
        replicas: fixed number of replicas (ignored with ``autoscale``).
        autoscale: (min, max) replicas, scaled on each replica's ongoing requests.
        replica_cpus: CPUs each replica reserves and renders with.
        address: ``HEAD:PORT`` of a Ray cluster to join; None starts a local Ray on this machine's cores.
        log: receives the one line saying where it serves, once every replica has loaded the scenes.
        strict: a replica fails to start on the first bundle that does not load instead of refusing it.
        replica_gpus: GPUs each replica reserves (fractions share one GPU among replicas); 0: none, and Ray then
            shows a replica no GPU.

    Raises:
        ValueError: Ray Serve is not installed, the scenes folder is missing, the cluster cannot be reached or a
            replica fails to start (one line each; no loadable scene, or with ``strict`` a bad bundle), a
            non-loopback ``host`` without an API key, or a ``cuda`` device with no ``replica_gpus``.
        DeviceError: ``settings.device`` is neither ``cuda[:N]`` nor a name this machine resolves.
        OSError: the port is taken (before Ray starts).
    """
    settings = _guarded(host, settings)
    _check_replica_device(settings.device, replica_gpus)
    try:
        from . import ray_serve  # optional dependency (parksim[ray]): imported only when asked for
    except ModuleNotFoundError as e:
        if e.name != "ray" and not str(e.name).startswith("ray."):
            raise
        raise ValueError("--ray needs Ray Serve, which is not installed: install parksim[ray] "
                         "(pip install 'parksim[ray]')") from None
    if not Path(scenes).is_dir():
        raise ValueError(f"scenes folder not found: {scenes}")
    for sock in bind(host, port):   # a busy port fails before Ray starts; Serve's proxy binds it next
        sock.close()
    scaling = ray_serve.Scaling(replicas, autoscale, replica_cpus, replica_gpus)
    ray_serve.start(scenes, settings, scaling, host, port, address, strict)
    try:
        size = f"{autoscale[0]} to {autoscale[1]}" if autoscale else str(replicas)
        gpus = f" and {replica_gpus:g} GPU(s)" if replica_gpus else ""
        log(f"serving on http://{host}:{port} from {size} Ray Serve replica(s) of {replica_cpus} CPU(s){gpus} "
            f"(rendering on {settings.device} on each replica's node; viewer at /, docs at /docs)")
        wait_for_interrupt()
    finally:
        ray_serve.stop(own_ray=address is None)


def _check_replica_device(device: str, replica_gpus: float) -> None:
    """Check on the driver what it can of a replica's device: ``cuda[:N]`` needs reserved GPUs (Ray hides the others
    from a replica), and any other name must resolve here (auto, cpu; a bad name fails now, not in every replica)."""
    if device.strip().lower().startswith("cuda"):
        if not replica_gpus:
            raise ValueError(f"--device {device} with --ray needs --replica-gpus > 0: a Ray Serve replica sees only "
                             "the GPUs it reserves")
    else:
        resolve_device(device)


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
