"""HTTP client of ``parksim serve`` (``RemoteSim``) with the interface of the in-process ``parksim.sim.LocalSim``.

Both return the same ``Frame`` for the same request, bit for bit (``parksim.frames`` holds the wire format).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .frames import Frame, RequestError, decode_npz, pose_text

__all__ = ["RemoteSim"]


class RemoteSim:
    """HTTP client of ``parksim serve`` with the ``LocalSim`` interface (``info``, ``render``, and ``render_batch``)."""

    def __init__(self, base_url: str = "http://127.0.0.1:8000", scene: str | None = None,
                 api_key: str | None = None, timeout: float = 60.0, http: Any = None) -> None:
        import httpx

        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = http if http is not None else httpx.Client(base_url=base_url, timeout=timeout, headers=headers)
        self.id = scene or self._get("/scenes").json()["scenes"][0]["id"]
        self._info = self._get(f"/scenes/{self.id}").json()

    def _get(self, url: str, **params: Any) -> Any:
        return self._check(self.http.get(url, params=params))

    @staticmethod
    def _check(response: Any) -> Any:
        """Raise ``RequestError`` with the server's message on a 4xx/5xx reply."""
        if response.status_code >= 400:
            try:
                detail = response.json().get("detail", response.text)
            except ValueError:
                detail = response.text
            raise RequestError(f"server answered {response.status_code}: {detail}")
        return response

    @property
    def cameras(self) -> list[str]:
        return list(self._info["cameras"])

    @property
    def bounds(self) -> dict[str, list[float]]:
        return self._info["bounds"]

    def info(self) -> dict[str, Any]:
        """The scene's description as the server gives it (same keys as ``LocalSim.info``)."""
        return self._info

    def render(self, pose: Sequence[float], cameras: Sequence[str] | None = None, bev: bool = False,
               scale: float = 1.0, depth: bool = False) -> Frame:
        """``GET /render`` for one pose."""
        params: dict[str, Any] = {"pose": pose_text(pose), "scene": self.id, "bev": bev, "scale": repr(float(scale)),
                                  "depth": depth}
        if cameras is not None:
            params["cameras"] = ",".join(cameras)
        return decode_npz(self._get("/render", **params).content)[0][0]

    def render_batch(self, poses: Sequence[Sequence[float]], cameras: Sequence[str] | None = None,
                     bev: bool = False, scale: float = 1.0, depth: bool = False) -> list[Frame]:
        """``POST /render`` for several poses in one request."""
        body = {"scene": self.id, "poses": [list(map(float, p)) for p in poses], "cameras": cameras, "bev": bev,
                "scale": float(scale), "depth": depth}
        return decode_npz(self._check(self.http.post("/render", json=body)).content)[0]

    def close(self) -> None:
        self.http.close()
