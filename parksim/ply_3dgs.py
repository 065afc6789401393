"""Third-party INRIA 3DGS PLY files in their own world frame, brought into ParkSim's (z up, floor at z = 0).

The file layout is ParkSim's own (``GaussianScene.load_ply`` / ``save_ply``); what differs is the world frame.
``FRAMES`` names the conventions a foreign scene's axes follow; ``T_parksim_ply`` composes one with a
similarity (rotation or reflection, uniform scale, translation) applied after it, and with the inverse of the
transform nerfstudio's dataparser applied before training (``dataparser_transform``); ``transform_scene`` moves
every Gaussian by such a transform: means, rotations, log-scales and the degree 1-3 SH coefficients together.
``bundle_from_ply`` does all of it for one file and writes a servable scene bundle (``parksim bundle from-ply``).
"""

from __future__ import annotations

import datetime
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .bundle import Bundle, drop_absurd
from .bundle import save as save_bundle
from .data import DatasetLayout
from .fileio import atomic_directory
from .gaussians import GaussianScene, PLYFormatError
from .geometry import nearest_rotation, quaternion_from_rotation
from .rig import Rig
from .sh_rotation import rotate_sh

__all__ = ["FRAMES", "T_parksim_ply", "dataparser_transform", "similarity_parts", "proper_similarity",
           "transform_scene", "read_ply", "write_ply", "bundle_from_ply"]

FRAMES: dict[str, np.ndarray] = {
    "parksim": np.eye(3),
    "opencv": np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    "colmap": np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),
    "opengl": np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
}
"""``R_parksim_ply`` per convention: the PLY's forward axis becomes ParkSim x, its left y and its up z.

parksim: x forward, y left, z up (no change). opencv and colmap: x right, y down, z forward (COLMAP's world
is that of its upright cameras). opengl (nerfstudio, Blender cameras): x right, y up, z backward.
"""

def similarity_parts(T: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, Q, t)`` with ``T = [[s Q, t], [0, 0, 0, 1]]``, ``s > 0`` and ``Q`` orthogonal: ``sign Q`` is the
    proper rotation nearest ``sign A / s`` (``parksim.geometry.nearest_rotation``, ``sign`` that of ``det A``,
    ``A`` the 3x3 part), ``Q = A / s`` itself when that is exact.

    ``ValueError`` (one line) unless ``T`` is a finite 4x4 similarity within ``parksim.geometry.ROTATION_TOLERANCE``
    (a transform printed with 6 decimals, or cast to float32, is one).
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"a transform must be a 4x4 matrix, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"a transform must be finite, got {T.tolist()}")
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"a transform's last row must be 0 0 0 1, got {T[3].tolist()}")
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    s = abs(det) ** (1.0 / 3.0)
    sign = 1.0 if det > 0 else -1.0
    try:
        if not s > 0:
            raise ValueError("not a proper rotation (its determinant is 0)")
        R, _ = nearest_rotation(sign * A / s)
    except ValueError as e:
        raise ValueError(f"a transform must be a similarity (uniform scale times a rotation or reflection): its 3x3 "
                         f"part over its scale (and the sign of its determinant) is {e}") from None
    return s, sign * R, T[:3, 3].copy()


def proper_similarity(T: np.ndarray) -> tuple[np.ndarray, float]:
    """``T`` (a similarity, ``similarity_parts``) with its rotation projected: ``[[s Q, t], [0, 0, 0, 1]]``, and
    the largest entry of ``Q`` that moved, ``|Q - A / s|`` (``T`` itself, as float64, and 0.0 when it was exact)."""
    s, Q, t = similarity_parts(T)
    correction = float(np.abs(Q - np.asarray(T, dtype=np.float64)[:3, :3] / s).max())
    if not correction:
        return np.asarray(T, dtype=np.float64), 0.0
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = s * Q, t
    return out, correction


def dataparser_transform(data: Mapping[str, Any], source: str = "dataparser transforms") -> np.ndarray:
    """The 4x4 ``D`` of a nerfstudio ``dataparser_transforms.json`` (``{"transform": 3x4, "scale": s}``).

    nerfstudio trains in ``p_ns = s (A p + b)`` of the world its dataparser read (``[A | b]`` = ``transform``,
    ``applied_transform`` included), and ``ns-export gaussian-splat`` writes that world: ``D`` maps into it.
    """
    try:
        Ab = np.asarray(data["transform"], dtype=np.float64)
        scale = float(data["scale"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{source}: not a nerfstudio dataparser_transforms.json (needs 'transform' 3x4 and "
                         f"'scale'; {type(e).__name__}: {e})") from None
    if Ab.shape != (3, 4) or not np.isfinite(Ab).all() or not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"{source}: 'transform' must be a finite 3x4 and 'scale' a positive number, got shape "
                         f"{Ab.shape} and scale {scale}")
    D = np.eye(4)
    D[:3] = scale * Ab
    return D


def T_parksim_ply(frame: str = "parksim", transform: np.ndarray | None = None,
                  dataparser: np.ndarray | None = None) -> np.ndarray:
    """The 4x4 from PLY world coordinates to ParkSim's: undo ``dataparser`` (a nerfstudio ``D``), change the
    axes of ``frame``, then apply ``transform``: ``transform @ F @ inv(dataparser)`` (None: identity)."""
    if frame not in FRAMES:
        raise ValueError(f"unknown frame {frame!r}; one of {sorted(FRAMES)}")
    F = np.eye(4)
    F[:3, :3] = FRAMES[frame]
    T = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    return T @ F @ (np.eye(4) if dataparser is None else np.linalg.inv(dataparser))


def transform_scene(scene: GaussianScene, T: np.ndarray) -> GaussianScene:
    """``scene`` moved by the similarity ``T`` (float64 maths, ``scene``'s dtype): what was seen from a camera is
    seen, unchanged in colour, from the transformed camera.

    A reflection ``Q`` turns each Gaussian like the rotation ``-Q`` (a Gaussian is symmetric about its centre)
    and its SH by ``Q`` itself.
    """
    s, Q, t = similarity_parts(T)
    f64 = scene.to(torch.float64)
    Qt, t_ = (torch.from_numpy(v).to(f64.means.device) for v in (Q, t))
    turn = quaternion_from_rotation(Qt * float(np.sign(np.linalg.det(Q))))
    w0, v0 = turn[0], turn[1:]
    w, v = f64.quats[:, 0], f64.quats[:, 1:]
    quats = torch.cat([(w0 * w - v @ v0)[:, None],
                       w0 * v + w[:, None] * v0 + torch.linalg.cross(v0.expand_as(v), v)], dim=1)
    out = GaussianScene(s * f64.means @ Qt.T + t_, quats, f64.log_scales + math.log(s),
                        f64.opacity_logits, rotate_sh(f64.sh, Q), scene.sh_degree)
    return out.to(scene.means.dtype)


def read_ply(path: str | Path, T: np.ndarray | None = None, dtype: torch.dtype = torch.float32) -> GaussianScene:
    """A third-party INRIA 3DGS PLY (SH degree 0-3) as a ParkSim scene, moved by ``T`` (``T_parksim_ply(...)``;
    None: as stored) in float64. ``PLYFormatError`` names a missing property or a non-finite value."""
    scene = GaussianScene.load_ply(path, dtype=torch.float64)
    if len(scene) == 0:
        raise PLYFormatError(f"{path}: holds no Gaussians")
    return (scene if T is None else transform_scene(scene, T)).to(dtype)


def write_ply(scene: GaussianScene, path: str | Path, T: np.ndarray | None = None) -> None:
    """Write ``scene`` as an INRIA 3DGS PLY in a foreign world frame: the inverse of ``read_ply`` with the same
    ``T``."""
    (scene if T is None else transform_scene(scene, np.linalg.inv(T))).save_ply(path)


def _read_object(path: Path) -> dict[str, Any]:
    """The JSON object in the file ``path``; ``ValueError`` (one line, naming it) for anything else."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable JSON ({' '.join(str(e).split())})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def bundle_from_ply(ply: str | Path, rig: str | Path, output: str | Path, frame: str = "parksim",
                    transform: np.ndarray | None = None, dataparser_transforms: str | Path | None = None,
                    world_map: str | Path | None = None, overwrite: bool = False) -> Bundle:
    """A servable scene bundle from a third-party INRIA 3DGS PLY and a ParkSim rig, written to ``output`` whole
    or not at all. Every input is checked before the PLY is read.

    Args:
        ply: the 3DGS PLY (graphdeco ``point_cloud.ply``, a gsplat or splatfacto export), SH degree 0-3.
        rig: ``rig.json``/``.yaml``, or a dataset folder (its ``rig.json``).
        output: the bundle folder to write.
        frame: the PLY world's axis convention, a key of ``FRAMES``.
        transform: 4x4 similarity applied after ``frame`` (None: identity).
        dataparser_transforms: nerfstudio's ``dataparser_transforms.json`` of the run that trained the PLY,
            undone first, so ``frame`` describes the world nerfstudio was given.
        world_map: ``map.json`` (or a dataset folder's) in the same world frame; None: a bundle without a map
            (render, serve and the viewer work; the gym env and compaction need one).
        overwrite: replace an existing ``output``.

    Returns:
        The bundle as written: Gaussians in Morton order without the absurd ones (``parksim.bundle.drop_absurd``,
        in ParkSim's frame), ``meta["ply_import"]`` recording the inputs, ``T_parksim_ply``, ``dropped`` (count
        per reason) and ``transform_correction`` (how far ``transform``'s rotation was from a proper one, projected
        by ``proper_similarity``; 0.0 when exact).

    Raises:
        ValueError: a transform that is not a similarity, an unknown frame, unreadable JSON.
        parksim.bundle.BundleError: every Gaussian, or more than ``MAX_DROPPED_FRACTION`` of them, is absurd.
        parksim.gaussians.PLYFormatError: a missing property, a non-finite value, no Gaussians.
        parksim.rig.CalibrationError: no or a bad rig.
        FileExistsError: ``output`` exists and ``overwrite`` is False.
    """
    ply, rig, output = Path(ply), Path(rig), Path(output)
    correction = 0.0
    if transform is not None:
        transform, correction = proper_similarity(transform)
    dataparser = (None if dataparser_transforms is None else
                  dataparser_transform(_read_object(Path(dataparser_transforms)), str(dataparser_transforms)))
    T = T_parksim_ply(frame, transform, dataparser)
    similarity_parts(T)
    rig_model = Rig.load(DatasetLayout(rig).rig if rig.is_dir() else rig)
    map_data = None
    if world_map is not None:
        world_map = Path(world_map)
        map_data = _read_object(DatasetLayout(world_map).map if world_map.is_dir() else world_map)
    scene, _, dropped = drop_absurd(read_ply(ply, T), map_data, str(ply))
    meta = {"source": f"third-party 3DGS PLY {ply.resolve()}", "gaussians": len(scene), "sh_degree": scene.sh_degree,
            "ply_import": {"ply": str(ply.resolve()), "frame": frame,
                           "transform": None if transform is None else np.asarray(transform).tolist(),
                           "dataparser_transform": None if dataparser is None else dataparser.tolist(),
                           "T_parksim_ply": T.tolist(), "dropped": dropped, "transform_correction": correction},
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    bundle = Bundle(scene.spatially_sorted(), rig_model, map_data, meta)
    with atomic_directory(output, overwrite=overwrite) as tmp:
        save_bundle(tmp, bundle)
    return bundle
