"""One render request as a job: validate against the scene and limits, render on the pool, encode the reply.

Everything slow (rendering and encoding) runs inside the pool's worker thread; the event loop only
validates and hands bytes back.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from parksim.frames import Frame, RequestError, encode_npz
from parksim.sim import LocalSim

from .budget import ReplyTooLarge
from .pool import RenderPool
from .scenes import SceneRegistry, check_pose
from .schemas import PlacedActor, Pose, RenderMeta
from .settings import Settings

if TYPE_CHECKING:
    from parksim.render.actors import Actor

__all__ = ["RenderJob", "Reply", "MEDIA_TYPES", "render_together"]

MEDIA_TYPES = {"npz": "application/x-npz", "png": "image/png", "jpeg": "image/jpeg"}


@dataclass
class Reply:
    """Encoded body, its media type and the job's metadata."""

    body: bytes
    media_type: str
    meta: RenderMeta


def encode_image(image: np.ndarray, fmt: Literal["png", "jpeg"], jpeg_quality: int) -> bytes:
    """uint8 RGB -> PNG or JPEG bytes."""
    import cv2

    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if fmt == "jpeg" else []
    ok, buf = cv2.imencode(f".{'jpg' if fmt == 'jpeg' else 'png'}", np.ascontiguousarray(image[..., ::-1]), params)
    if not ok:
        raise RuntimeError(f"{fmt} encoding failed for an image of shape {image.shape}")
    return buf.tobytes()


@dataclass
class RenderJob:
    """A validated request: which scene, poses, views, actors and encoding, and its reply size (bytes, upper bound)."""

    sim: LocalSim
    poses: list[Pose]
    cameras: list[str]
    bev: bool
    scale: float
    depth: bool
    fmt: Literal["npz", "png", "jpeg"]
    batch: bool
    reply_bytes: int
    actors: Sequence[PlacedActor] = ()

    @classmethod
    def build(cls, registry: SceneRegistry, settings: Settings, scene: str | None, poses: list[Pose],
              cameras: list[str] | None, bev: bool, scale: float, depth: bool,
              fmt: Literal["npz", "png", "jpeg"] = "npz", batch: bool = False,
              actors: Sequence[PlacedActor] = ()) -> RenderJob:
        """Check everything that can be checked before rendering; ``RequestError`` says what is wrong,
        ``ReplyTooLarge`` when the reply would exceed ``settings.max_reply_bytes``.

        A PNG/JPEG of one view is counted as its raw pixels: the encodings are no larger but for a few bytes per row.
        """
        sim = registry.get(scene)
        if not settings.min_scale <= scale <= settings.max_scale:
            raise RequestError(f"scale={scale:g} is out of range: it must be in [{settings.min_scale:g}, "
                               f"{settings.max_scale:g}]")
        if len(poses) > settings.max_batch:
            raise RequestError(f"{len(poses)} poses in one request; at most {settings.max_batch} are allowed")
        names = sim.check(cameras, scale)
        if not names and not bev:
            raise RequestError("nothing to render: ask for at least one camera, or bev=on")
        if fmt != "npz" and len(names) + int(bev) != 1:
            raise RequestError(f"format={fmt} returns one image: ask for exactly one view (cameras=NAME with bev=off, "
                               f"or cameras= (empty) with bev=on), or use format=npz")
        if fmt != "npz" and depth:
            raise RequestError(f"depth is only returned in format=npz, not {fmt}")
        for pose in poses:
            check_pose(sim, pose, settings)
        size = sim.reply_bytes(len(poses), names, bev, scale, depth)
        if size > settings.max_reply_bytes:
            raise ReplyTooLarge(f"the reply would be {size} bytes ({size / 2**20:.1f} MiB: {len(poses)} pose(s) x "
                                f"{len(names)} camera(s){' + BEV' if bev else ''}{' with depth' if depth else ''} at "
                                f"scale {scale:g}), over this server's limit of {settings.max_reply_bytes} bytes "
                                f"({settings.max_reply_bytes / 2**20:.1f} MiB) per request: ask for fewer poses or "
                                f"views, a smaller scale, or no depth")
        return cls(sim, poses, names, bev, scale, depth, fmt, batch, size, actors)

    def _placed(self) -> list[Actor] | None:
        """The actors with their built-in assets (baked on first use, so on a pool thread), or None."""
        if not self.actors:
            return None
        from parksim.render.actors import Actor
        from parksim.scenarios.episode import load_actor_asset

        return [Actor(load_actor_asset(a.asset), _pose_values(a.pose)) for a in self.actors]

    def _run(self, jpeg_quality: int) -> tuple[bytes, dict[str, float], list[Frame]]:
        """Render every pose (together: ``LocalSim.render_batch``) and encode (runs on a pool thread)."""
        frames = self.sim.render_batch([_pose_values(p) for p in self.poses], self.cameras, self.bev, self.scale,
                                       self.depth, self._placed())
        body, timings = self.encode(frames, jpeg_quality)
        return body, timings, frames

    def encode(self, frames: list[Frame], jpeg_quality: int, gathered: int = 1) -> tuple[bytes, dict[str, float]]:
        """This job's reply body from its rendered ``frames`` (one per pose), and its stage timings (s);
        ``gathered`` requests shared the render."""
        timings = {k: sum(f.timings.get(k, 0.0) for f in frames) for k in ("views", "bev")}
        start = time.perf_counter()
        if self.fmt == "npz":
            body = encode_npz(frames, self._meta(frames[0], timings, gathered).model_dump(), self.batch)
        else:
            f = frames[0]
            image = f.bev if self.bev else f.images[self.cameras[0]]
            if image is None:
                raise RuntimeError(f"scene {self.sim.id}: a BEV was asked for but the render holds none")
            body = encode_image(image, self.fmt, jpeg_quality)
        timings["encode"] = time.perf_counter() - start
        return body, timings

    def _meta(self, frame: Frame, timings: dict[str, float], gathered: int = 1) -> RenderMeta:
        sizes = {n: [int(a.shape[1]), int(a.shape[0])] for n, a in frame.images.items()}
        if frame.bev is not None:
            sizes["bev"] = [int(frame.bev.shape[1]), int(frame.bev.shape[0])]
        return RenderMeta(scene=self.sim.id, poses=self.poses, cameras=self.cameras, bev=self.bev, scale=self.scale,
                          sizes=sizes, timings_ms={k: round(v * 1000, 3) for k, v in timings.items()},
                          gathered=gathered)

    async def run(self, pool: RenderPool, jpeg_quality: int) -> Reply:
        """Render and encode on ``pool``; the reply's metadata carries queue, views, bev and encode times."""
        (body, timings, frames), queued = await pool.run(lambda: self._run(jpeg_quality))
        timings["queue"] = queued
        return Reply(body, MEDIA_TYPES[self.fmt], self._meta(frames[0], timings))


def _pose_values(pose: Pose) -> list[float]:
    """``[x, y, yaw]`` for a ground pose (the exact path the in-process env takes), else all six values."""
    if pose.z == 0 and pose.roll == 0 and pose.pitch == 0:
        return [pose.x, pose.y, pose.yaw]
    return pose.values()


def render_together(jobs: list[RenderJob], jpeg_quality: int) -> list[Reply]:
    """Single-pose jobs of one scene and view set rendered in one ``LocalSim.render_batch``, each encoded as its own
    reply (runs on a pool thread; ``parksim.server.gather``).

    Args:
        jobs: jobs with one pose each and the same scene, cameras, BEV, scale and depth.
        jpeg_quality: of single-view JPEG replies.

    Returns:
        One reply per job, in order; each job's timings are its share of the render, ``gathered`` the group's size.
    """
    first = jobs[0]
    frames = first.sim.render_batch([_pose_values(job.poses[0]) for job in jobs], first.cameras, first.bev,
                                    first.scale, first.depth)
    replies = []
    for job, frame in zip(jobs, frames):
        body, timings = job.encode([frame], jpeg_quality, len(jobs))
        replies.append(Reply(body, MEDIA_TYPES[job.fmt], job._meta(frame, timings, len(jobs))))
    return replies
