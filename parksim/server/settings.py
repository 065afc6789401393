"""Server limits and options (pydantic), from ``parksim serve`` flags or ``PARKSIM_*`` environment variables."""

from __future__ import annotations

import os

from pydantic import BaseModel, Field, ValidationError, model_validator

__all__ = ["Settings", "API_KEY_ENV"]

API_KEY_ENV = "PARKSIM_API_KEY"
"""Environment variable holding the API key (the ``--api-key`` flag overrides it)."""


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
    jpeg_quality: int = Field(90, ge=1, le=100, description="JPEG quality of single-view replies")
    api_key: str | None = Field(None, description="required as X-API-Key header or api_key query when set")

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
