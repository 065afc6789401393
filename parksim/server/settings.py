"""Server limits and options (pydantic), from ``parksim serve`` flags or ``PARKSIM_*`` environment variables."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

__all__ = ["Settings", "API_KEY_ENV", "read_key_file"]

API_KEY_ENV = "PARKSIM_API_KEY"
"""Environment variable holding the API key (``--api-key-file`` and ``--api-key`` override it)."""


def read_key_file(path: str | Path) -> str:
    """The API key in ``path``: its text less one trailing newline (LF or CRLF).

    Args:
        path: a file holding the key, e.g. written by ``openssl rand -hex 32 > key``.

    Returns:
        The key.

    Raises:
        ValueError: the file cannot be read, is not UTF-8, or holds no key (one line naming the file).
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        reason = e.strerror if isinstance(e, OSError) else "not UTF-8 text"
        raise ValueError(f"--api-key-file {path}: {reason}") from None
    key = text.removesuffix("\n")   # read_text turns \r\n into \n
    if not key.strip():
        raise ValueError(f"--api-key-file {path}: the file holds no key (it is empty or whitespace only)")
    return key


class Settings(BaseModel):
    """Request limits, render pool size and access control of one server.

    Each field's ``description`` says what it limits and in which unit.

    Raises:
        ValidationError: a value out of its range, or ``reply_budget_bytes < max_reply_bytes``.
    """

    max_scale: float = Field(2.0, gt=0, description="largest resolution factor a request may ask for")
    min_scale: float = Field(0.05, gt=0, description="smallest resolution factor a request may ask for")
    max_batch: int = Field(16, ge=1, description="most poses in one POST /render")
    pose_margin_m: float = Field(5.0, ge=0, description="how far (m) outside the scene bounds a pose may lie")
    max_tilt_rad: float = Field(0.5, ge=0, description="largest |roll| and |pitch| of a pose (rad)")
    workers: int = Field(1, ge=1, description="render threads (each render already uses every core)")
    queue_size: int = Field(8, ge=0, description="requests that may wait for a render thread before 503")
    retry_after_s: int = Field(1, ge=1, description="Retry-After (s) sent with 503 when the queue is full")
    render_timeout_s: float = Field(60.0, gt=0, description="a render taking longer answers 503")
    max_body_bytes: int = Field(1 << 20, ge=1024, description="largest POST body")
    max_reply_bytes: int = Field(64 << 20, ge=1 << 16, description="largest reply one render request may ask for "
                                 "(views x pixels x channels x poses, counted before rendering); larger: 413")
    reply_budget_bytes: int = Field(256 << 20, ge=1 << 16, description="reply bytes rendered or being sent at once, "
                                    "over all clients; a request that would exceed it: 503")
    jpeg_quality: int = Field(90, ge=1, le=100, description="JPEG quality of single-view replies and of episode "
                              "observations sent as JPEG")
    max_episodes: int = Field(16, ge=1, description="episodes (POST /episodes) held at once; one more: 503")
    episode_ttl_s: float = Field(300.0, gt=0, description="an episode no request has touched for this long (s) is "
                                 "dropped")
    api_key: str | None = Field(None, description="required as the X-API-Key header when set; not empty, no "
                                "whitespace at either end (HTTP trims header values, so such a key could never match)")
    allowed_hosts: tuple[str, ...] | None = Field(None, description="Host header names (port ignored) the server "
                                                  "answers to, others get 421; None: any. parksim serve sets the "
                                                  "loopback names and --host unless bound to 0.0.0.0 or ::")
    gather: Literal["auto", "on", "off"] = Field("auto", description="render concurrent single-pose requests for "
                                                 "the same views of a scene together (one batch): auto = for scenes "
                                                 "on a GPU, where a batch costs little more than one render")
    gather_window_ms: float = Field(2.0, ge=0, description="how long a request waits for others to render with")
    device: str = Field("auto", description="where the scenes render: auto, cpu or cuda[:N] "
                        "(parksim.device.resolve_device), resolved where the scenes load: by the server process, "
                        "or by each Ray Serve replica on its node")

    @field_validator("api_key")
    @classmethod
    def _usable_key(cls, key: str | None) -> str | None:
        if key is not None and (not key.strip() or key != key.strip()):
            raise ValueError("the API key is empty or whitespace only" if not key.strip() else
                             "the API key starts or ends with whitespace, which HTTP trims from headers")
        return key

    @field_validator("allowed_hosts")
    @classmethod
    def _lower_case(cls, hosts: tuple[str, ...] | None) -> tuple[str, ...] | None:
        return None if hosts is None else tuple(h.strip("[]").lower() for h in hosts)

    @model_validator(mode="after")
    def _budget_holds_a_reply(self) -> Settings:
        if self.reply_budget_bytes < self.max_reply_bytes:
            raise ValueError(f"reply_budget_bytes ({self.reply_budget_bytes}) must be at least max_reply_bytes "
                             f"({self.max_reply_bytes}), or the largest allowed request could never be served")
        return self

    @classmethod
    def from_env(cls, **overrides: object) -> Settings:
        """Defaults, then the API key from ``PARKSIM_API_KEY``, then explicit ``overrides`` (None ones ignored).

        Args:
            **overrides: field values, e.g. from ``parksim serve`` flags; None means "not given".

        Returns:
            The settings.

        Raises:
            ValueError: one line naming each bad value.
        """
        values: dict[str, object] = {}
        if os.environ.get(API_KEY_ENV):
            values["api_key"] = os.environ[API_KEY_ENV]
        values.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls(**values)
        except ValidationError as e:
            raise ValueError("server settings: " + "; ".join(
                f"{'.'.join(map(str, err['loc'])) or 'settings'}: {str(err['msg']).removeprefix('Value error, ')}"
                for err in e.errors())) from None
