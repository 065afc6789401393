"""A rendered frame (``Frame``) and its ``.npz`` wire format, shared by the simulator and its HTTP client.

``LocalSim`` (``parksim.sim``) renders ``Frame`` objects; ``parksim serve`` ships them with ``encode_npz``
and ``RemoteSim`` (``parksim.client``) reads them back with ``decode_npz``, bit for bit. The layout
``NPZ_LAYOUT`` is defined here once.
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["Frame", "RequestError", "encode_npz", "decode_npz", "npz_bytes_bound", "pose_text", "NPZ_LAYOUT"]

NPZ_LAYOUT = """\
images/<camera>  uint8 [H, W, 3]     one per camera asked for
depth/<camera>   float32 [H, W]      metres along the ray; only when depth was asked for
bev              uint8 [Hb, Wb, 3]   only when the BEV was asked for
meta             0-d unicode array   JSON: scene, poses, cameras, bev, scale, sizes, timings_ms, batch
batch (POST /render): every array but meta gains a leading pose axis B, e.g. images/<camera> [B, H, W, 3]"""
"""Keys, dtypes and shapes of a render ``.npz`` (uncompressed ``numpy.savez``)."""
_NPZ_ARRAY_OVERHEAD = 512
"""Bytes an array adds to an ``.npz`` beyond its data, at most: zip entry and .npy header."""
_META_CHARS = (2048, 512, 128)
"""Characters of ``meta`` JSON at most: fixed part, per pose, per view (``meta`` is stored as UTF-32)."""


class RequestError(ValueError):
    """A render request names an unknown camera or a scale the scene cannot be rendered at."""


@dataclass
class Frame:
    """One rendered pose: uint8 HxWx3 ``images`` per camera, float32 ``depth`` (m), uint8 ``bev``, ``timings`` (s).

    Attributes:
        images: per camera name, ``[H, W, 3]`` uint8 RGB.
        depth: per camera name, ``[H, W]`` float32 metres along the ray (empty unless asked for).
        bev: ``[Hb, Wb, 3]`` uint8 RGB, or None.
        timings: seconds per stage (``views``, ``bev``).
    """

    images: dict[str, np.ndarray] = field(default_factory=dict)
    depth: dict[str, np.ndarray] = field(default_factory=dict)
    bev: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)


def pose_text(pose: Sequence[float]) -> str:
    """``x,y,yaw`` (or 6 values) with exact float round-trip, as ``GET /render?pose=`` takes it.

    Args:
        pose: the pose's numbers.

    Returns:
        The numbers' ``repr`` joined by commas.

    Example:
        >>> pose_text((12.0, 0.5, 0.1))
        '12.0,0.5,0.1'
    """
    return ",".join(repr(float(v)) for v in pose)


def encode_npz(frames: Sequence[Frame], meta: dict[str, Any], batch: bool) -> bytes:
    """Pack frames (stacked along a leading axis when ``batch``) and ``meta`` into uncompressed ``.npz`` bytes.

    Args:
        frames: one frame or more, all with the same cameras, depth maps and BEV presence.
        meta: JSON values stored under ``meta`` (scene, poses, cameras, ...); ``batch`` is added.
        batch: stack the arrays along a leading pose axis (``POST /render``); False takes ``frames[0]`` alone.

    Returns:
        The ``.npz`` file's bytes in the layout ``NPZ_LAYOUT``.
    """
    first = frames[0]
    arrays: dict[str, np.ndarray] = {}

    def put(key: str, items: list[np.ndarray]) -> None:
        arrays[key] = np.stack(items) if batch else items[0]

    for name in first.images:
        put(f"images/{name}", [f.images[name] for f in frames])
    for name in first.depth:
        put(f"depth/{name}", [f.depth[name] for f in frames])
    bevs = [f.bev for f in frames if f.bev is not None]
    if bevs:   # the frames of one request all have a BEV or none has
        put("bev", bevs)
    arrays["meta"] = np.array(json.dumps({**meta, "batch": len(frames) if batch else None}))
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)   # plain arrays only, as readers load them without pickle
    return buf.getvalue()


def decode_npz(data: bytes) -> tuple[list[Frame], dict[str, Any]]:
    """Inverse of ``encode_npz``: one frame per pose (a single-pose reply gives a list of one) and the metadata.

    Args:
        data: the ``.npz`` bytes.

    Returns:
        ``(frames, meta)``: the frames, ``timings`` converted from ``meta["timings_ms"]`` to seconds, and the
        metadata.

    Example:
        >>> frames, meta = decode_npz(encode_npz([Frame(bev=np.zeros((2, 2, 3), np.uint8))], {"scene": "a"}, False))
        >>> frames[0].bev.shape, meta
        ((2, 2, 3), {'scene': 'a', 'batch': None})
    """
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k: z[k] for k in z.files if k != "meta"}
    n = meta["batch"] or 1
    pick = (lambda a, i: a[i]) if meta["batch"] else (lambda a, i: a)
    frames = []
    for i in range(n):
        f = Frame(timings={k: v / 1000 for k, v in meta.get("timings_ms", {}).items()})
        for key, arr in arrays.items():
            kind, _, name = key.partition("/")
            if kind == "images":
                f.images[name] = pick(arr, i)
            elif kind == "depth":
                f.depth[name] = pick(arr, i)
            else:
                f.bev = pick(arr, i)
        frames.append(f)
    return frames, meta


def npz_bytes_bound(poses: int, data_per_pose: int, views: int) -> int:
    """Upper bound of an ``encode_npz`` reply's size, before rendering it.

    Args:
        poses: frames in the reply.
        data_per_pose: bytes of array data one frame holds (pixels x channels x itemsize over its views).
        views: arrays per frame (images, depth maps and the BEV).

    Returns:
        Bytes: the data, a zip entry and ``.npy`` header per array, and the ``meta`` JSON at its longest.
    """
    fixed, per_pose, per_view = _META_CHARS
    meta = 4 * (fixed + per_pose * poses + per_view * views)
    return poses * data_per_pose + _NPZ_ARRAY_OVERHEAD * (views + 1) + meta
