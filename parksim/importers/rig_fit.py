"""Recover a fixed rig and ego poses from per-image camera poses (COLMAP, nerfstudio), and the metric scale.

A multi-camera recording fits a rig when every camera's pose relative to a reference camera is the same in
every frame, within a tolerance. Then the ego poses follow, and the scene can be served at ego poses; otherwise
the dataset keeps per-image poses only and renders at camera poses. SfM has no metric scale: it comes from a
``--scale`` flag, else from a known rig's camera baselines, else the poses are taken as metric.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np
import torch

from ..rig import BEVSpec, Rig, RigCamera
from .recording import Recording, RecordingError

__all__ = ["RigFit", "fit_rig", "mean_pose", "TOLERANCE_M", "TOLERANCE_DEG"]

TOLERANCE_M = 0.02
"""Default largest spread of a camera's position relative to the reference camera across frames (metres)."""
TOLERANCE_DEG = 0.5
"""Default largest spread of a camera's rotation relative to the reference camera across frames (degrees)."""


def _project_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` in the Frobenius norm (the chordal mean of the rotations summed in M)."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return U @ D @ Vt


def mean_pose(poses: Sequence[np.ndarray]) -> np.ndarray:
    """Mean of rigid transforms: chordal mean rotation, mean translation."""
    T = np.eye(4)
    T[:3, :3] = _project_rotation(np.sum([p[:3, :3] for p in poses], axis=0))
    T[:3, 3] = np.mean([p[:3, 3] for p in poses], axis=0)
    return T


def _angle_deg(R: np.ndarray) -> float:
    """Rotation angle of ``R`` in degrees."""
    return math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(R)) - 1.0) / 2.0))))


@dataclass
class RigFit:
    """The outcome: whether a fixed rig explains the poses, the rig and ego poses if so, and the scale used."""

    consistent: bool
    scale: float
    scale_source: str
    spread_m: float
    spread_deg: float
    T_vehicle_camera: dict[str, np.ndarray]
    poses: np.ndarray | None
    vehicle_frame: str
    message: str
    bev: BEVSpec | None = None

    def apply(self, rec: Recording) -> Recording:
        """``rec`` at metric scale, with the recovered rig (and the known rig's BEV) and ego poses when consistent
        (camera poses kept)."""
        assert rec.camera_poses is not None
        s = self.scale
        camera_poses = [{c: _scaled(T, s) for c, T in p.items()} for p in rec.camera_poses]
        points = None if rec.points is None else (np.asarray(rec.points[0]) * s, rec.points[1])
        rig, poses = rec.rig, None
        if self.consistent:
            rig = Rig({c: RigCamera(c, cam.model, torch.from_numpy(self.T_vehicle_camera[c]))
                       for c, cam in rec.rig.cameras.items()}, self.bev or rec.rig.bev)
            poses = self.poses
        notes = {**rec.notes, "scale": s, "scale_source": self.scale_source, "rig_consistent": self.consistent,
                 "rig_spread_m": self.spread_m, "rig_spread_deg": self.spread_deg,
                 "vehicle_frame": self.vehicle_frame, "rig_fit": self.message}
        return dataclasses.replace(rec, rig=rig, poses=poses, camera_poses=camera_poses, points=points, notes=notes)


def _scaled(T: np.ndarray, s: float) -> np.ndarray:
    out = np.array(T, np.float64)
    out[:3, 3] *= s
    return out


def _scale(camera_poses: list[dict[str, np.ndarray]], known: Rig | None, scale: float | None) -> tuple[float, str]:
    """The metric scale and where it came from: the flag, the known rig's baselines, or none (1)."""
    if scale is not None:
        if not (math.isfinite(scale) and scale > 0):
            raise RecordingError(f"--scale must be a positive number, got {scale}")
        return float(scale), "--scale"
    if known is None:
        return 1.0, "as given (no --scale and no known rig: poses taken as metric)"
    names = [c for c in known.names if c in camera_poses[0]]
    pairs = list(combinations(names, 2))
    if not pairs:
        return 1.0, "as given (the known rig has fewer than two of the recording's cameras)"
    ratios = []
    for a, b in pairs:
        D = float(torch.linalg.vector_norm(known.cameras[a].T_vehicle_camera[:3, 3]
                                           - known.cameras[b].T_vehicle_camera[:3, 3]))
        for p in camera_poses:
            d = float(np.linalg.norm(p[a][:3, 3] - p[b][:3, 3]))
            if d > 0:
                ratios.append(D / d)
    if not ratios:
        raise RecordingError("cannot take the scale from the rig: the cameras' centres coincide in every frame")
    return float(np.median(ratios)), (f"known rig baselines (median of {len(ratios)} camera-pair distance "
                                      f"ratios over {len(pairs)} pairs)")


def _vehicle_from_cameras(rel: dict[str, np.ndarray], reference: str, camera_height: float | None) -> np.ndarray:
    """T_reference_vehicle from the cameras alone: origin at their centroid (lowered by ``camera_height``), z up
    as the mean of the cameras' up (-y) axes, x along the ``front`` camera's (else the reference's) view."""
    up = np.mean([T[:3, :3] @ [0.0, -1.0, 0.0] for T in rel.values()], axis=0)
    up /= np.linalg.norm(up)
    look = rel.get("front", rel[reference])[:3, :3] @ [0.0, 0.0, 1.0]
    x = look - up * float(look @ up)
    if np.linalg.norm(x) < 1e-6:
        x = rel[reference][:3, :3] @ [1.0, 0.0, 0.0]
        x = x - up * float(x @ up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(up, x), up], axis=1)
    T[:3, 3] = np.mean([p[:3, 3] for p in rel.values()], axis=0) - (camera_height or 0.0) * up
    return T


def fit_rig(camera_poses: list[dict[str, np.ndarray]], names: Sequence[str], known: Rig | None = None,
            scale: float | None = None, tol_m: float = TOLERANCE_M, tol_deg: float = TOLERANCE_DEG,
            camera_height: float | None = None) -> RigFit:
    """Fit a fixed rig to per-image poses ``camera_poses[frame][camera] = T_world_camera``.

    Args:
        names: the cameras, the first being the reference.
        known: a calibrated rig (T_vehicle_camera) naming the vehicle frame and, by its baselines, the scale.
        scale: metric scale applied to the poses' translations (overrides the rig's baselines).
        tol_m, tol_deg: largest spread of a camera's pose relative to the reference across frames.
        camera_height: without a known rig, how far the vehicle origin (ground) lies below the cameras' centroid.
    """
    s, source = _scale(camera_poses, known, scale)
    poses = [{c: _scaled(p[c], s) for c in names} for p in camera_poses]
    ref = names[0]
    rel_frames = {c: [np.linalg.inv(p[ref]) @ p[c] for p in poses] for c in names}
    rel = {c: mean_pose(r) for c, r in rel_frames.items()}
    spread_m = max(float(np.linalg.norm(r[:3, 3] - rel[c][:3, 3])) for c in names for r in rel_frames[c])
    spread_deg = max(_angle_deg(rel[c][:3, :3].T @ r[:3, :3]) for c in names for r in rel_frames[c])
    if known is not None:
        T_vehicle_ref = known.cameras[ref].T_vehicle_camera.numpy()
        T_vc = {c: known.cameras[c].T_vehicle_camera.numpy() for c in names}
        off_m = max(float(np.linalg.norm((T_vehicle_ref @ rel[c] - T_vc[c])[:3, 3])) for c in names)
        off_deg = max(_angle_deg(T_vc[c][:3, :3].T @ (T_vehicle_ref @ rel[c])[:3, :3]) for c in names)
        frame = (f"the known rig's (its extrinsics differ from the recording's by up to {off_m:.3g} m, "
                 f"{off_deg:.3g} deg)")
        spread_m, spread_deg = max(spread_m, off_m), max(spread_deg, off_deg)
    else:
        T_vehicle_ref = np.linalg.inv(_vehicle_from_cameras(rel, ref, camera_height))
        T_vc = {c: T_vehicle_ref @ rel[c] for c in names}
        frame = ("from the cameras: origin at their centroid" +
                 (f" lowered by {camera_height} m" if camera_height else " (ground height unknown: give --rig or "
                                                                          "--camera-height for a correct BEV)") +
                 ", z up = mean camera up, x = front camera's view")
    consistent = spread_m <= tol_m and spread_deg <= tol_deg
    ego = None
    if consistent:
        ego = np.stack([mean_pose([p[c] @ np.linalg.inv(T_vc[c]) for c in names]) for p in poses])
        message = (f"consistent with a fixed rig (spread {spread_m:.3g} m, {spread_deg:.3g} deg within "
                   f"{tol_m} m, {tol_deg} deg): ego poses recovered, the scene serves at ego poses")
    else:
        message = (f"not consistent with a fixed rig (spread {spread_m:.3g} m, {spread_deg:.3g} deg beyond "
                   f"{tol_m} m, {tol_deg} deg): per-image poses only, the scene renders at camera poses")
    return RigFit(consistent, s, source, spread_m, spread_deg, T_vc, ego, frame, message,
                  None if known is None else known.bev)
