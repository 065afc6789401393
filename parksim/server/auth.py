"""Access control: loopback needs no key; any other interface requires an API key (flag or PARKSIM_API_KEY)."""

from __future__ import annotations

import hmac
import ipaddress
from typing import Annotated

from fastapi import HTTPException, Security
from fastapi.security import APIKeyHeader, APIKeyQuery

from .deps import SettingsDep

__all__ = ["is_loopback", "check_bind", "require_api_key"]

_HEADER = APIKeyHeader(name="X-API-Key", auto_error=False, scheme_name="APIKeyHeader",
                       description="the server's API key; needed only when the server was started with one "
                                   "(--api-key or PARKSIM_API_KEY)")
_QUERY = APIKeyQuery(name="api_key", auto_error=False, scheme_name="APIKeyQuery",
                     description="the same key as a query parameter, where a header cannot be sent (an <img> tag)")


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
        raise ValueError(f"refusing to listen on {host} without an API key: pass --api-key or set PARKSIM_API_KEY "
                         f"(loopback addresses such as 127.0.0.1 need none)")


def require_api_key(settings: SettingsDep, header: Annotated[str | None, Security(_HEADER)],
                    query: Annotated[str | None, Security(_QUERY)]) -> None:
    """Route dependency: when the server has a key, the request must carry it (X-API-Key header or api_key query)."""
    expected = settings.api_key
    if not expected:
        return
    given = header or query or ""
    if not hmac.compare_digest(given.encode(), expected.encode()):
        raise HTTPException(401, "missing or wrong API key: send it as the X-API-Key header or the api_key "
                                 "query parameter", headers={"WWW-Authenticate": "X-API-Key"})
