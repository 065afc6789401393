"""Rigid-body helpers on 4x4 homogeneous transforms (torch, batched, differentiable).

Naming follows ``T_a_b``: the transform that maps points in frame ``b`` into frame ``a``.
An ego pose is ``T_world_vehicle``; a planner pose ``(x, y, yaw)`` lies on the ground
(z = 0, roll = pitch = 0) with yaw in radians about the world z axis.

``nearest_rotation`` (numpy) is the one check of a rotation read from a file: what every input that carries one
(importers, rig files, ``bundle from-ply --transform``) passes its matrices through.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "make_transform",
    "invert_transform",
    "compose",
    "transform_points",
    "pose_from_xy_yaw",
    "xy_yaw_from_pose",
    "pose_from_xyz_rpy",
    "rotation_from_quaternion",
    "quaternion_from_rotation",
    "as_pose",
    "nearest_rotation",
    "ROTATION_TOLERANCE",
    "ROTATION_ROUNDOFF",
]

ROTATION_TOLERANCE = 1e-3
"""Largest ``max(|R^T R - I|, |det R - 1|)`` (largest entry) of a matrix read as a rotation; see
``nearest_rotation`` for how it is derived and why it is safe."""
ROTATION_ROUNDOFF = 1e-12
"""Float64 round-off, not a tolerance: a matrix off orthonormal by at most this much is a rotation as computed in
float64 (a few products leave ~1e-15) and is kept bit for bit; a float32 or printed one is off by far more."""


def make_transform(rotation: Tensor, translation: Tensor) -> Tensor:
    """Stack ``R[...,3,3]`` and ``t[...,3]`` into ``T[...,4,4]``.

    Args:
        rotation: ``[..., 3, 3]`` rotations.
        translation: ``[..., 3]`` translations, same batch shape and dtype.

    Returns:
        ``[..., 4, 4]`` homogeneous transforms with bottom row ``(0, 0, 0, 1)``.

    Example:
        >>> make_transform(torch.eye(3), torch.tensor([1.0, 2.0, 3.0]))[:, 3].tolist()
        [1.0, 2.0, 3.0, 1.0]
    """
    batch = rotation.shape[:-2]
    bottom = torch.zeros(*batch, 1, 4, dtype=rotation.dtype, device=rotation.device)
    bottom[..., 0, 3] = 1.0
    top = torch.cat([rotation, translation.unsqueeze(-1)], dim=-1)
    return torch.cat([top, bottom], dim=-2)


def invert_transform(T: Tensor) -> Tensor:
    """Inverse of a rigid transform, using R^T rather than a general matrix inverse.

    Args:
        T: ``[..., 4, 4]`` rigid transforms ``T_a_b``.

    Returns:
        ``[..., 4, 4]`` the inverses ``T_b_a``.
    """
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = R.transpose(-1, -2)
    return make_transform(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def compose(*transforms: Tensor) -> Tensor:
    """``compose(A, B, C) = A @ B @ C`` (apply C first).

    Args:
        *transforms: one or more ``[..., 4, 4]`` transforms (batch dimensions broadcast).

    Returns:
        ``[..., 4, 4]`` their product, left to right.
    """
    out = transforms[0]
    for T in transforms[1:]:
        out = out @ T
    return out


def transform_points(T: Tensor, points: Tensor) -> Tensor:
    """Apply ``T[...,4,4]`` to ``points[...,3]`` (broadcasting over batch dims).

    Args:
        T: ``[4, 4]`` transform ``T_a_b``, or ``[..., 4, 4]`` with one transform per point.
        points: ``[..., 3]`` points in frame ``b`` (any batch shape for a single ``[4, 4]``).

    Returns:
        ``[..., 3]`` the points in frame ``a``.
    """
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., :3, 3]


def _rot_z(yaw: Tensor) -> Tensor:
    c, s = torch.cos(yaw), torch.sin(yaw)
    z, o = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack([c, -s, z, s, c, z, z, z, o], dim=-1).reshape(*yaw.shape, 3, 3)


def pose_from_xy_yaw(x: float | Tensor, y: float | Tensor, yaw: float | Tensor,
                     dtype: torch.dtype = torch.float64) -> Tensor:
    """Planner pose ``(x, y, yaw)`` -> ``T_world_vehicle`` on the ground plane.

    Args:
        x: position in metres (a float or a tensor; the three broadcast together).
        y: position in metres.
        yaw: heading in radians about the world z axis.
        dtype: dtype of the result.

    Returns:
        ``[..., 4, 4]`` transforms, ``[4, 4]`` for scalars.

    Example:
        >>> import math
        >>> pose_from_xy_yaw(1.0, 2.0, math.pi / 2)[:2, 3].tolist()
        [1.0, 2.0]
    """
    xs, ys, yaws = torch.broadcast_tensors(*(torch.as_tensor(v, dtype=dtype) for v in (x, y, yaw)))
    t = torch.stack([xs, ys, torch.zeros_like(xs)], dim=-1)
    return make_transform(_rot_z(yaws), t)


def xy_yaw_from_pose(T: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``T_world_vehicle`` -> ``(x, y, yaw)``; roll, pitch and z are dropped.

    Args:
        T: ``[..., 4, 4]`` poses.

    Returns:
        ``(x, y, yaw)``, each ``[...]``: metres, metres, radians in (-pi, pi].
    """
    return T[..., 0, 3], T[..., 1, 3], torch.atan2(T[..., 1, 0], T[..., 0, 0])


def pose_from_xyz_rpy(x: float, y: float, z: float, roll: float, pitch: float, yaw: float,
                      dtype: torch.dtype = torch.float64) -> Tensor:
    """Full 6-DoF pose, rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (ISO 8855 / aerospace order).

    Args:
        x: position in metres.
        y: position in metres.
        z: position in metres.
        roll: rotation about x in radians.
        pitch: rotation about y in radians.
        yaw: rotation about z in radians.
        dtype: dtype of the result.

    Returns:
        ``[4, 4]`` ``T_world_vehicle``.
    """
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    R = torch.tensor([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ], dtype=dtype)
    return make_transform(R, torch.tensor([x, y, z], dtype=dtype))


def rotation_from_quaternion(q: Tensor) -> Tensor:
    """Unit quaternion ``q[...,4]`` in (w, x, y, z) order -> rotation matrix ``[...,3,3]``.

    The quaternion is normalised first; a zero quaternion maps to the identity (never NaN).

    Args:
        q: ``[..., 4]`` quaternions (w, x, y, z), any norm.

    Returns:
        ``[..., 3, 3]`` rotation matrices, ``q``'s dtype.
    """
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    safe = torch.where(norm > 0, q, identity)
    w, x, y, z = (safe / safe.norm(dim=-1, keepdim=True)).unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1)
    return R.reshape(*q.shape[:-1], 3, 3)


def quaternion_from_rotation(R: Tensor) -> Tensor:
    """Rotation matrix ``[...,3,3]`` -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method).

    Args:
        R: ``[..., 3, 3]`` rotation matrices.

    Returns:
        ``[..., 4]`` unit quaternions (w, x, y, z), the inverse of ``rotation_from_quaternion``.
    """
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.flatten(-2).unbind(-1)
    trace = m00 + m11 + m22
    cands = torch.stack([
        torch.stack([1 + trace, m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
        torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
        torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
    ], dim=-2)
    diag = torch.stack([trace, m00, m11, m22], dim=-1)
    best = diag.argmax(dim=-1)
    q = torch.gather(cands, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def as_pose(pose: Tensor | Sequence[float], dtype: torch.dtype = torch.float64) -> Tensor:
    """Accept a 4x4 ``T_world_vehicle``, an ``(x, y, yaw)`` or an ``(x, y, z, roll, pitch, yaw)``.

    Args:
        pose: a ``[..., 4, 4]`` tensor (kept, cast to ``dtype``), or 3 or 6 numbers (a sequence or tensor).
        dtype: dtype of the result.

    Returns:
        ``[4, 4]`` ``T_world_vehicle`` (or the given batch of 4x4 transforms).

    Raises:
        ValueError: a non-finite value, or a number of values other than 3 or 6.

    Example:
        >>> as_pose((1.0, 2.0, 0.0))[:3, 3].tolist()
        [1.0, 2.0, 0.0]
    """
    if isinstance(pose, Tensor) and pose.shape[-2:] == (4, 4):
        return pose.to(dtype)
    values = [float(v) for v in (pose.tolist() if isinstance(pose, Tensor) else pose)]
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"pose has non-finite values: {values}")
    if len(values) == 3:
        x, y, yaw = values
        return pose_from_xy_yaw(x, y, yaw, dtype=dtype)
    if len(values) == 6:
        x, y, z, roll, pitch, yaw = values
        return pose_from_xyz_rpy(x, y, z, roll, pitch, yaw, dtype=dtype)
    raise ValueError(f"pose must be a 4x4 matrix, (x, y, yaw) or (x, y, z, roll, pitch, yaw); got {len(values)} values")


def nearest_rotation(R: np.ndarray, tol: float = ROTATION_TOLERANCE) -> tuple[np.ndarray, float]:
    """The proper rotation nearest ``R`` (Frobenius norm, by SVD: ``U V^T``) when ``R`` is one within ``tol``.

    Real files hold rotations rounded: a float32 matrix is off by up to half the float32 spacing at 1
    (``2^-24`` ~ 6e-8 per entry, spacing 1.2e-7), so ``|R^T R - I| <= 2 sqrt(3) 6e-8`` ~ 2e-7 from the cast alone,
    a few times more when the writer computed the matrix in float32 (1.1e-6 in a real nerfstudio
    ``transforms.json``); a matrix printed with 6 decimals is off by up to 5e-7 per entry, which the 3-term dot
    products of ``R^T R`` accumulate to ``2 sqrt(3) 5e-7`` ~ 1.7e-6 (3e-6 by the cruder ``6 * 5e-7``), and
    ``det R`` alike. ``ROTATION_TOLERANCE`` = 1e-3 accepts all of these with a margin of ~300 for longer float32
    chains, and is still safe: a matrix 1e-3 off orthonormal is a rotation with a skew or scale of at most 1e-3
    (0.06 deg, 1 mm per metre), below what a calibration is good to, while what is not a rotation (a scale of 1 %,
    a shear, a transposed or mixed-up axis, a reflection with ``|det R - 1| = 2``) is off by 1e-2 or more and
    stays an error. A reflection is never "fixed": it fails ``|det R - 1|``; an ``R`` that passes (``tol < 1``)
    has ``det R > 0``, so ``U V^T`` is a proper rotation.

    Args:
        R: ``[3, 3]`` matrix (any float dtype; computed in float64).
        tol: largest ``max(|R^T R - I|, |det R - 1|)`` accepted (largest entry), below 1.

    Returns:
        ``(rotation, correction)``: the ``[3, 3]`` float64 proper rotation and the largest entry of
        ``|rotation - R|``; ``R`` itself (as float64, bit for bit) and 0.0 when it is a rotation to float64
        round-off (``ROTATION_ROUNDOFF``).

    Raises:
        ValueError: ``R`` is not a finite 3x3, or is off by more than ``tol`` (one line with the value).

    Example:
        >>> c, s = math.cos(0.3), math.sin(0.3)
        >>> printed = np.round([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], 6)   # as a file holds it
        >>> R, correction = nearest_rotation(printed)
        >>> 0 < correction < 1e-6, bool(np.abs(R.T @ R - np.eye(3)).max() < 1e-15)
        (True, True)
        >>> nearest_rotation(np.diag([1.0, 1.0, -1.0]))
        Traceback (most recent call last):
        ValueError: not a proper rotation (|R^T R - I| or |det R - 1| = 2 > 0.001)
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise ValueError(f"not a proper rotation (expected a finite 3x3 matrix, got shape {R.shape})")
    error = max(float(np.abs(R.T @ R - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))
    if error > tol:
        raise ValueError(f"not a proper rotation (|R^T R - I| or |det R - 1| = {error:.2g} > {tol:g})")
    if error <= ROTATION_ROUNDOFF:
        return R, 0.0
    u, _, vt = np.linalg.svd(R)
    rotation = u @ vt
    return rotation, float(np.abs(rotation - R).max())
