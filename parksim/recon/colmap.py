"""COLMAP SfM on a dataset's fisheye images (pycolmap), and aligning the poses it recovers.

Models are read by ``parksim.importers.colmap.read_model`` (our reader of COLMAP's files), so only SfM needs
pycolmap. ``run_sfm`` extracts SIFT features per camera (OPENCV_FISHEYE with the rig's intrinsics, held fixed),
matches all pairs and runs incremental mapping. ``vehicle_poses`` turns the registered images back into
per-frame ego poses through the rig; ``align_similarity`` (Umeyama) compares them with known poses,
since SfM recovers poses only up to a similarity transform.
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from parksim.data import DatasetReader
from parksim.data.layout import frame_name
from parksim.importers.colmap import ColmapError, ColmapModel, read_model

__all__ = ["ColmapError", "require_pycolmap", "read_colmap_points", "run_sfm", "import_model", "vehicle_poses",
           "align_similarity", "pose_errors"]


def require_pycolmap() -> ModuleType:
    """Import pycolmap or explain how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise ColmapError("pycolmap is not installed; install it with "
                          "`python -m pip install -c constraints.txt pycolmap`") from None
    return pycolmap


def read_colmap_points(model: str | Path | ColmapModel) -> tuple[np.ndarray, np.ndarray]:
    """Sparse points of a COLMAP model (or its folder): positions ``[N, 3]`` float32 and colours ``[N, 3]`` uint8."""
    model = model if isinstance(model, ColmapModel) else read_model(model)
    return model.xyz.astype(np.float32), model.rgb


def run_sfm(data_dir: str | Path, work_dir: str | Path, cameras: list[str] | None = None,
            frame_stride: int = 1, seed: int = 0) -> ColmapModel:
    """Incremental SfM on the dataset's images; returns the largest model, saved in ``work_dir/sparse``."""
    pycolmap = require_pycolmap()
    reader = DatasetReader(data_dir)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    database.unlink(missing_ok=True)
    image_root = reader.layout.root / "images"
    frames = reader.frames[::frame_stride]
    for name in cameras or reader.rig.names:
        m = reader.rig.cameras[name].model
        # COLMAP's first pixel centre is (0.5, 0.5), ParkSim's (0, 0) (parksim.importers.colmap reads it back).
        params = [float(m.fx), float(m.fy), float(m.cx) + 0.5, float(m.cy) + 0.5, *[float(k) for k in m.to_dict()["k"]]]
        options = pycolmap.ImageReaderOptions()
        options.camera_model = "OPENCV_FISHEYE"
        options.camera_params = ",".join(f"{p:.10g}" for p in params)
        pycolmap.extract_features(database, image_root, image_names=[f"{name}/{frame_name(f)}.png" for f in frames],
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=options)
    pycolmap.match_exhaustive(database)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.random_seed = seed
    models = pycolmap.incremental_mapping(database, image_root, work / "sparse", options)
    if not models:
        raise ColmapError(f"{data_dir}: COLMAP registered no images (too little texture or overlap)")
    best = max(models.values(), key=lambda r: r.num_reg_images())
    best.write(str(work / "sparse"))
    return read_model(work / "sparse")


def vehicle_poses(model: ColmapModel, reader: DatasetReader) -> dict[int, np.ndarray]:
    """Per-frame ``T_world_vehicle`` in COLMAP's world, from the first registered camera image of each frame."""
    out: dict[int, list[np.ndarray]] = {}
    for image in model.images.values():
        camera, stem = Path(image.name).parent.name, Path(image.name).stem
        T_vc = reader.rig.cameras[camera].T_vehicle_camera.numpy()
        out.setdefault(int(stem), []).append(image.T_world_camera @ np.linalg.inv(T_vc))
    return {f: ts[0] for f, ts in out.items()}


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: ``s, R, t`` minimising ``|dst - (s R src + t)|`` for point sets ``[N, 3]``."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a * a).sum(1).mean())
    return s, R, mu_d - s * R @ mu_s


def pose_errors(estimated: dict[int, np.ndarray], reader: DatasetReader) -> dict[str, float]:
    """Position RMSE (m) and mean rotation error (deg) of recovered ego poses after similarity alignment."""
    frames = sorted(estimated)
    if len(frames) < 3:
        raise ColmapError(f"only {len(frames)} frames registered; need 3 to align")
    est = np.stack([estimated[f] for f in frames])
    gt = np.stack([reader.pose(f).numpy() for f in frames])
    s, R, t = align_similarity(est[:, :3, 3], gt[:, :3, 3])
    pos = (s * est[:, :3, 3] @ R.T + t) - gt[:, :3, 3]
    rel = np.einsum("nji,njk->nik", R @ est[:, :3, :3], gt[:, :3, :3])
    angles = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"frames": len(frames), "position_rmse_m": float(np.sqrt((pos ** 2).sum(1).mean())),
            "rotation_mean_deg": float(angles.mean()), "scale": s,
            "trajectory_length_m": float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())}


def import_model(model_dir: str | Path, data_dir: str | Path, overwrite: bool = False) -> dict[str, Any]:
    """Bring a COLMAP model of the dataset's images into the dataset: ``points3d.ply`` (and poses when it has none).

    With poses in the dataset the model is aligned to them (similarity from the registered frames) and its
    points are written in the dataset's world frame; without, the recovered ego poses are written too.
    """
    from parksim.data import DatasetWriter

    model, data_dir = read_model(model_dir), Path(data_dir)
    writer = DatasetWriter(data_dir)
    if writer.layout.points.exists() and not overwrite:
        raise ColmapError(f"{writer.layout.points} exists (pass overwrite to replace it)")
    xyz, rgb = read_colmap_points(model)
    reader = DatasetReader(data_dir, validate=False)
    if writer.layout.poses.is_file():
        poses = vehicle_poses(model, reader)
        report: dict[str, Any] = pose_errors(poses, reader)
        s, R, t = align_similarity(np.stack([poses[f][:3, 3] for f in sorted(poses)]),
                                   np.stack([reader.pose(f).numpy()[:3, 3] for f in sorted(poses)]))
        xyz = (s * xyz.astype(np.float64) @ R.T + t).astype(np.float32)
    else:
        poses = vehicle_poses(model, reader)
        frames = sorted(poses)
        writer.poses(np.stack([poses[f] for f in frames]), [0.1 * f for f in frames], frames)
        report = {"frames": len(frames), "poses": "written from COLMAP (COLMAP's world frame and scale)"}
    writer.points(xyz, rgb, np.zeros_like(xyz))
    return {"points": len(xyz), **report}
