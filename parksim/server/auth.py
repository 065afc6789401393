"""Access control: loopback needs no key; any other interface requires an API key (``--api-key-file``,
``PARKSIM_API_KEY`` or ``--api-key``), sent as the ``X-API-Key`` header only; a server bound to a named interface
answers only requests whose ``Host`` names it (DNS rebinding)."""

from __future__ import annotations

import hmac
import ipaddress
from typing import Annotated

from fastapi import HTTPException, Request, Security
from fastapi.security import APIKeyHeader

from .deps import SettingsDep

__all__ = ["is_loopback", "check_bind", "allowed_hosts", "host_name", "require_api_key"]

_HEADER = APIKeyHeader(name="X-API-Key", auto_error=False, scheme_name="APIKeyHeader",
                       description="the server's API key; needed only when the server was started with one "
                                   "(--api-key-file, PARKSIM_API_KEY or --api-key)")

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
"""``Host`` names a server bound to a named interface always answers to."""


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and 'localhost'."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, api_key: str | None) -> None:
    """``ValueError`` when asked to listen beyond loopback without an API key."""
    if not is_loopback(host) and not api_key:
        raise ValueError(f"refusing to listen on {host} without an API key: pass --api-key-file or set "
                         f"PARKSIM_API_KEY (loopback addresses such as 127.0.0.1 need none)")


def allowed_hosts(bind_host: str) -> tuple[str, ...] | None:
    """The ``Host`` names a server listening on ``bind_host`` answers to: the loopback names and ``bind_host``;
    None (any) for a wildcard bind (``0.0.0.0``, ``::``, empty), which already requires an API key.

    Args:
        bind_host: the ``--host`` the server listens on.

    Returns:
        Lower-case names, or None for any.
    """
    name = host_name(bind_host)
    if name in ("", "0.0.0.0", "::"):
        return None
    return tuple(dict.fromkeys((*LOOPBACK_NAMES, name)))


def host_name(host: str) -> str:
    """The name part of a ``Host`` header or address, lower case: ``localhost:8000`` -> ``localhost``,
    ``[::1]:8000`` -> ``::1``, ``::1`` -> ``::1``."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else host
    if host.count(":") == 1:
        return host.split(":")[0]
    return host


def require_api_key(request: Request, settings: SettingsDep,
                    header: Annotated[str | None, Security(_HEADER)]) -> None:
    """Route dependency: a key in the query string is refused (400: it would end up in logs); when the server has
    a key, the request must carry it as the X-API-Key header (401 otherwise)."""
    if "api_key" in request.query_params:
        raise HTTPException(400, "the API key is not accepted in the query string (proxies and browsers log URLs): "
                                 "send it as the X-API-Key header")
    expected = settings.api_key
    if not expected:
        return
    if not hmac.compare_digest((header or "").encode(), expected.encode()):
        raise HTTPException(401, "missing or wrong API key: send it as the X-API-Key header",
                            headers={"WWW-Authenticate": "X-API-Key"})
