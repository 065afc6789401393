"""Gaussian actors in a scene: each asset moved to its pose and rendered with the scene's Gaussians in one pass.

``render(..., actors=[Actor(asset, pose), ...])`` rasterizes the scene's Gaussians and every actor's together, so
who hides whom is the rasterizer's ordinary depth order in every view, the BEV and depth, on every backend.

Joining them naively copies the whole scene every frame (2e5 Gaussians of SH degree 3 are 47 MB: ~30 ms on two
cores, and a full upload on a GPU). ``joined`` instead keeps, per scene, staging tensors on the scene's device that
hold the scene's rows once, followed by room for actor rows; a frame rewrites only the rows of the actors whose
asset or pose differs from what that staging buffer last held (a parked car costs nothing after its first frame).
A render takes a buffer from a small pool and gives it back, so threads rendering at once never share one; a
scene changed in place (its tensors' version counters move) is copied again. At most ``_SCENES_KEPT`` x
``_IDLE_PER_SCENE`` idle buffers are kept, each the size of its scene plus ``_SPARE_ROWS``: a second copy of the
scene's memory per thread rendering it with actors at once. When a gradient is needed the join is a plain
``torch.cat``, through which autograd flows. An asset is taken as unchanging once placed (staged rows are matched
to it by identity and pose): to change one, make a new ``ActorAsset``.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..actor_asset import ActorAsset
from ..gaussians import GaussianScene
from ..geometry import as_pose, quaternion_from_rotation

__all__ = ["Actor", "posed_gaussians", "joined", "RIGID_TOLERANCE"]

RIGID_TOLERANCE = 1e-6
"""Largest ``|R^T R - I|`` entry of an actor pose's rotation (float32-rounded poses pass, scalings do not)."""
_SCENES_KEPT = 2
"""Scenes whose staging buffers are kept (a planner crossing between two visibility cells keeps both)."""
_IDLE_PER_SCENE = 2
"""Idle staging buffers kept per scene (one per thread that rendered it at the same time, up to this many)."""
_SPARE_ROWS = 4096
"""Rows of room beyond the actors of the frame that made a buffer, so a few more actors need no new buffer."""
_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def _rigid(pose: Tensor | Sequence[float]) -> Tensor:
    """``pose`` as a float64 CPU ``(4, 4)``; ``ValueError`` (one line) unless it is a proper rigid transform."""
    T = as_pose(pose).detach().to("cpu", torch.float64)
    if T.shape != (4, 4):
        raise ValueError(f"actor pose must be one 4x4 transform, got shape {tuple(T.shape)}")
    M = T.numpy()
    R = M[:3, :3]
    if not (np.isfinite(M).all() and np.abs(R.T @ R - np.eye(3)).max() <= RIGID_TOLERANCE
            and np.linalg.det(R) > 0 and np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0])):
        raise ValueError(f"actor pose must be a finite rigid transform (rotation within {RIGID_TOLERANCE:g} of "
                         f"orthonormal, determinant +1), got {M.tolist()}")
    return T


@dataclass(frozen=True, eq=False)
class Actor:
    """An asset placed in the world: ``T_world_actor`` moves its Gaussians from the asset frame to the world.

    Attributes:
        asset: the actor's Gaussians, footprint box and name.
        pose: ``T_world_actor`` as ``parksim.geometry.as_pose`` takes it: a 4x4, ``(x, y, yaw)`` on the floor or
            ``(x, y, z, roll, pitch, yaw)`` (metres, radians).
        T_world_actor: ``pose`` as a float64 ``(4, 4)``, set on construction.

    Raises:
        ValueError: ``pose`` is not a finite rigid transform.
    """

    asset: ActorAsset
    pose: Tensor | Sequence[float]
    T_world_actor: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        """Convert and check the pose once."""
        object.__setattr__(self, "T_world_actor", _rigid(self.pose))

    def footprint(self) -> np.ndarray:
        """The asset box's floor rectangle in the world (``ActorAsset.footprint`` at this pose).

        Returns:
            ``(4, 2)`` float64 world ``(x, y)`` corners, counter-clockwise.
        """
        return self.asset.footprint(self.T_world_actor)


def _left_product(q: Tensor) -> Tensor:
    """``(4, 4)`` ``L`` with ``q * p == L @ p`` for wxyz quaternions (the Hamilton product, ``q`` on the left)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([torch.stack([w, -x, -y, -z]), torch.stack([x, w, -z, y]),
                        torch.stack([y, z, w, -x]), torch.stack([z, -y, x, w])])


def posed_gaussians(asset: ActorAsset, pose: Tensor | Sequence[float], sh_degree: int | None = None
                    ) -> GaussianScene:
    """The asset's Gaussians moved to ``pose``: means, rotations and SH colours turned together (float64 maths).

    Args:
        asset: the actor's asset.
        pose: ``T_world_actor`` (a proper rigid transform) as ``Actor`` takes it.
        sh_degree: SH degree of the result (None: the asset's): higher bands are dropped, missing ones are zero.

    Returns:
        ``N`` Gaussians in the world, the asset's dtype and device; seen from a camera moved by the same pose
        they look as the asset does from the unmoved camera.

    Raises:
        ValueError: ``pose`` is not a finite rigid transform.
    """
    T = _rigid(pose)
    s = asset.scene
    degree = s.sh_degree if sh_degree is None else sh_degree
    out = [t.new_empty((len(s), *t.shape[1:])) for t in _tensors(s)[:4]]
    out.append(s.sh.new_empty((len(s), (degree + 1) ** 2, 3)))
    _write_posed(asset, T, quaternion_from_rotation(T[:3, :3]), out)
    return GaussianScene(**dict(zip(_FIELDS, out)), sh_degree=degree)


def _write_posed(asset: ActorAsset, T: Tensor, q: Tensor, out: Sequence[Tensor]) -> None:
    """Write the asset moved by ``T`` (float64 ``(4, 4)``, its rotation's quaternion ``q``) into ``out``: one tensor
    per field of ``_FIELDS`` with the asset's rows, any dtype and device; SH bands ``out`` lacks are dropped, those the
    asset lacks written zero."""
    from ..sh_rotation import rotate_sh  # here: sh_rotation imports the render package, which imports this module

    s = asset.scene
    T = T.to(s.means.device)
    R = T[:3, :3]
    means, quats, log_scales, opacity_logits, sh = out
    means.copy_(torch.addmm(T[:3, 3], s.means.to(torch.float64), R.T))
    quats.copy_(s.quats.to(torch.float64) @ _left_product(q.to(s.quats.device)).T)
    log_scales.copy_(s.log_scales)
    opacity_logits.copy_(s.opacity_logits)
    k = min(sh.shape[1], s.sh.shape[1])
    sh[:, :k].copy_(rotate_sh(s.sh[:, :k], R) if k > 1 else s.sh[:, :k])
    sh[:, k:].zero_()


def _tensors(scene: GaussianScene) -> list[Tensor]:
    return [getattr(scene, name) for name in _FIELDS]


def _stamp(scene: GaussianScene) -> tuple[tuple[int, int], ...]:
    """Where the scene's tensors live and their in-place version counters: equal stamps, equal contents."""
    return tuple((t.data_ptr(), t._version) for t in _tensors(scene))


@dataclass(eq=False)
class _Stage:
    """A scene's rows then actor rows, in tensors with room for more; which actor at which pose holds which rows.

    Attributes:
        scene: the scene copied (weakly: a dropped scene frees its buffers).
        stamp: the scene's ``_stamp`` when copied.
        tensors: per field of ``_FIELDS``, ``capacity`` rows; rows below ``len(scene)`` are the scene's.
        held: per actor block, ``(asset, pose bytes, first row)`` as last written.
    """

    scene: weakref.ref[GaussianScene]
    stamp: tuple[tuple[int, int], ...]
    tensors: list[Tensor]
    held: list[tuple[ActorAsset, bytes, int]] = field(default_factory=list)

    @classmethod
    def of(cls, scene: GaussianScene, capacity: int) -> _Stage:
        """A buffer of ``capacity`` rows holding a copy of ``scene`` in its first rows."""
        tensors = []
        for t in _tensors(scene):
            buf = t.new_empty((capacity, *t.shape[1:]))
            buf[:len(t)].copy_(t.detach())
            tensors.append(buf)
        return cls(weakref.ref(scene), _stamp(scene), tensors)

    def place(self, scene: GaussianScene, actors: Sequence[Actor]) -> GaussianScene:
        """Write the actors that changed after the scene's rows; the scene and actors as views of the buffer."""
        row, held, before, stale = len(scene), [], self.held, []
        self.held = []   # until every row is written: a failed write leaves nothing to trust
        for k, actor in enumerate(actors):
            key = actor.T_world_actor.numpy().tobytes()
            old = before[k] if k < len(before) else None
            if old is None or old[0] is not actor.asset or old[1] != key or old[2] != row:
                stale.append((actor, row))
            held.append((actor.asset, key, row))
            row += len(actor.asset.scene)
        if stale:   # one quaternion call for all the rotations: per actor it costs more than the rest of the move
            quats = quaternion_from_rotation(torch.stack([a.T_world_actor[:3, :3] for a, _ in stale]))
            for (actor, first), q in zip(stale, quats):
                rows = slice(first, first + len(actor.asset.scene))
                _write_posed(actor.asset, actor.T_world_actor, q, [buf[rows] for buf in self.tensors])
        self.held = held
        return GaussianScene(**{name: t[:row] for name, t in zip(_FIELDS, self.tensors)}, sh_degree=scene.sh_degree)


_IDLE: OrderedDict[int, list[_Stage]] = OrderedDict()
"""Idle staging buffers by ``id(scene)``, least recently used first."""
_IDLE_LOCK = threading.Lock()


def _take(scene: GaussianScene, rows: int) -> _Stage:
    """An idle buffer of ``scene`` (unchanged since copied) with room for ``rows`` actor rows, or a new one."""
    stamp = _stamp(scene)
    with _IDLE_LOCK:
        idle = _IDLE.get(id(scene), [])
        while idle:
            stage = idle.pop()
            if stage.scene() is scene and stage.stamp == stamp and len(stage.tensors[0]) >= len(scene) + rows:
                return stage
    return _Stage.of(scene, len(scene) + rows + _SPARE_ROWS)


def _give_back(scene: GaussianScene, stage: _Stage) -> None:
    """Keep ``stage`` for the next render of ``scene``, within ``_IDLE_PER_SCENE`` and ``_SCENES_KEPT``."""
    with _IDLE_LOCK:
        idle = _IDLE.setdefault(id(scene), [])
        idle.append(stage)
        del idle[:-_IDLE_PER_SCENE]
        _IDLE.move_to_end(id(scene))
        while len(_IDLE) > _SCENES_KEPT:
            _IDLE.popitem(last=False)


@contextmanager
def joined(scene: GaussianScene, actors: Sequence[Actor]) -> Iterator[GaussianScene]:
    """The scene's Gaussians followed by every actor's, posed, for one render inside the block.

    Args:
        scene: the scene's Gaussians (world frame).
        actors: the actors, in the order their rows follow the scene's.

    Yields:
        ``len(scene) + sum(len(actor.asset.scene))`` Gaussians in the scene's dtype, device and SH degree (actor
        SH bands above it dropped, missing ones zero). Without a gradient they are views of a staging buffer,
        valid inside the block only; with one (``torch.is_grad_enabled()`` and a scene tensor that requires it)
        a ``torch.cat`` that autograd flows through.
    """
    rows = sum(len(a.asset.scene) for a in actors)
    if torch.is_grad_enabled() and any(t.requires_grad for t in _tensors(scene)):
        moved = [_tensors(posed_gaussians(a.asset, a.T_world_actor, scene.sh_degree)) for a in actors]
        yield GaussianScene(**{name: torch.cat([t, *(m[i].to(t) for m in moved)])
                               for i, (name, t) in enumerate(zip(_FIELDS, _tensors(scene)))}, sh_degree=scene.sh_degree)
        return
    stage = _take(scene, rows)
    try:
        yield stage.place(scene, actors)
    finally:
        _give_back(scene, stage)
