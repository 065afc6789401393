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
        """Connect and fetch the scene's description (two requests).

        Args:
            base_url: the server's address.
            scene: the scene id to render (default: the server's first scene).
            api_key: sent as ``X-API-Key`` when the server requires one.
            timeout: seconds per request.
            http: an httpx-compatible client to use instead (e.g. FastAPI's ``TestClient``); ``base_url``,
                ``api_key`` and ``timeout`` are then unused.

        Raises:
            RequestError: the server answers an error (unknown scene, wrong key, ...).
        """
        import httpx

        headers = {"X-API-Key": api_key} if api_key else {}
        self.http = http if http is not None else httpx.Client(base_url=base_url, timeout=timeout, headers=headers)
        self.id = scene or self._get("/scenes").json()["scenes"][0]["id"]
        self._info = self._get(f"/scenes/{self.id}").json()

    def _get(self, url: str, **params: Any) -> Any:
        """``GET url?params``, checked (``_check``)."""
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
        """Camera names in rig order."""
        return list(self._info["cameras"])

    @property
    def bounds(self) -> dict[str, list[float]]:
        """Scene extent ``{"x": [lo, hi], "y": ..., "z": ...}`` in metres, as ``LocalSim.bounds``."""
        return self._info["bounds"]

    def info(self) -> dict[str, Any]:
        """The scene's description as the server gave it when the client connected.

        Returns:
            The ``GET /scenes/{id}`` reply, with the keys of ``LocalSim.info``.
        """
        return self._info

    def render(self, pose: Sequence[float], cameras: Sequence[str] | None = None, bev: bool = False,
               scale: float = 1.0, depth: bool = False) -> Frame:
        """``GET /render`` for one pose.

        Args:
            pose: ``(x, y, yaw)`` or ``(x, y, z, roll, pitch, yaw)`` (metres, radians).
            cameras: names of the images to return (default: all).
            bev: also return the BEV.
            scale: image size relative to the rig's cameras.
            depth: also return depth maps.

        Returns:
            The frame, as ``LocalSim.render`` gives it (timings are the server's).

        Raises:
            RequestError: the server refused the request; the message is its reply.
        """
        params: dict[str, Any] = {"pose": pose_text(pose), "scene": self.id, "bev": bev, "scale": repr(float(scale)),
                                  "depth": depth}
        if cameras is not None:
            params["cameras"] = ",".join(cameras)
        return decode_npz(self._get("/render", **params).content)[0][0]

    def render_batch(self, poses: Sequence[Sequence[float]], cameras: Sequence[str] | None = None,
                     bev: bool = False, scale: float = 1.0, depth: bool = False) -> list[Frame]:
        """``POST /render`` for several poses in one request.

        Args:
            poses: ``B`` poses, each ``(x, y, yaw)`` or 6 values.
            cameras: names of the images to return (default: all).
            bev: also return the BEV.
            scale: image size relative to the rig's cameras.
            depth: also return depth maps.

        Returns:
            ``B`` frames in pose order.

        Raises:
            RequestError: the server refused the request; the message is its reply.
        """
        body = {"scene": self.id, "poses": [list(map(float, p)) for p in poses], "cameras": cameras, "bev": bev,
                "scale": float(scale), "depth": depth}
        return decode_npz(self._check(self.http.post("/render", json=body)).content)[0]

    def close(self) -> None:
        """Close the HTTP client (also one passed in as ``http``)."""
        self.http.close()
