"""A sparse point cloud from the known poses (``parksim points``): on the true surfaces of a synth scene, exact on
exact correspondences (fisheye rays past 90 deg included), refused over an existing cloud, nothing from blank images."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from parksim.camera import pixel_grid
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.importers import points_sfm
from parksim.importers.points_sfm import MIN_POINTS, SparsePoints, write_sfm_points
from parksim.importers.recording import REPORT_FILE

KEYPOINT_PX = 0.5
"""How well a SIFT keypoint is located, in pixels (the mean reprojection error the runs report is 0.4-0.5 px)."""
TYPICAL_PARALLAX_DEG = 6.0
"""The angle a typical point's rays span: three times the 2 deg kept at least (pairs up to 3 frames of 0.2 m apart
and neighbouring cameras, at 2-6 m)."""
FOOTPRINTS = KEYPOINT_PX / np.sin(np.radians(TYPICAL_PARALLAX_DEG)) + 0.5
"""Median distance from a triangulated point to the true surface, in pixel footprints (depth x pixel angle): the
error along the rays, keypoint error over the parallax (~4.8), plus half a footprint to the nearest true point of
the depth maps' cloud, sampled once per pixel. Random points in the scene's bounding box are ~10 footprints away."""


def _copy(src: Path, dst: Path, blank: bool = False) -> Path:
    """The rig, poses, split and images of dataset ``src`` (no points), as uniform grey images when ``blank``."""
    dst.mkdir()
    for name in ("rig.json", "poses.json", "split.json"):
        shutil.copy(src / name, dst / name)
    shutil.copytree(src / "images", dst / "images")
    if blank:
        import cv2

        for path in (dst / "images").rglob("*.png"):
            cv2.imwrite(str(path), np.full_like(cv2.imread(str(path)), 128))
    return dst


def _true_surface(reader: DatasetReader) -> tuple[np.ndarray, np.ndarray]:
    """The synth scene's surfaces as its depth maps see them: world points ``[N, 3]`` (every pixel with a depth, of
    every image) and their image colours ``[N, 3]`` in [0, 1]."""
    xyz, rgb = [], []
    for frame in reader.frames:
        for camera in reader.rig.names:
            model = reader.rig.cameras[camera].model
            pose = reader.camera_pose(camera, frame).numpy()
            rays = model.unproject(pixel_grid(model.width, model.height)).numpy().reshape(-1, 3)
            depth = reader.depth(camera, frame).numpy().reshape(-1)
            seen = depth > 0
            xyz.append((rays[seen] * depth[seen, None]) @ pose[:3, :3].T + pose[:3, 3])
            rgb.append(reader.image(camera, frame).numpy().reshape(-1, 3)[seen])
    return np.concatenate(xyz), np.concatenate(rgb)


@pytest.fixture(scope="module")
def triangulated(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SparsePoints]:
    """The session's ``synth tiny`` without its points, triangulated from its poses."""
    data = _copy(tiny_data, tmp_path_factory.mktemp("sfm") / "tiny")
    return data, write_sfm_points(data, progress=False)


def test_points_lie_on_the_true_surfaces_in_their_colours(tiny_data: Path, triangulated) -> None:
    data, points = triangulated
    truth = DatasetReader(tiny_data)
    assert len(points.xyz) >= MIN_POINTS and points.images == 40   # 10 train frames x 4 cameras
    assert points.mean_error_px < 1.0
    assert (points.track_length >= 2).all()
    xyz, rgb = DatasetReader(data).points   # what was written is what was returned
    np.testing.assert_array_equal(xyz, points.xyz.astype(np.float32))
    np.testing.assert_array_equal(rgb, points.rgb)

    surface, colour = _true_surface(truth)
    distance, nearest = cKDTree(surface).query(points.xyz)
    depth = cKDTree(truth.camera_centres().numpy()).query(points.xyz)[0]   # at most the distance it was seen from
    pixel = 1.0 / float(truth.rig.cameras["front"].model.fx)   # radians per pixel at the centre of every camera
    assert np.median(distance / (depth * pixel)) < FOOTPRINTS
    # colours from the right pixels: reversed point order or swapped BGR/RGB channels fail these
    assert np.median(np.abs(points.rgb / 255.0 - colour[nearest])) < 0.06
    assert np.median(np.abs(points.rgb[:, ::-1] / 255.0 - colour[nearest])) > np.median(
        np.abs(points.rgb / 255.0 - colour[nearest]))


def test_exact_fisheye_correspondences_triangulate_exactly(tiny_data: Path) -> None:
    """Points 1-5 m around the front camera that it and the left one see at two frames, projected exactly, many
    over 90 deg off a camera's axis (no pinhole image shows them): every track is triangulated back to its point."""
    reader = DatasetReader(tiny_data)
    rig = reader.rig
    views = [(f, c) for f in reader.frames[:2] for c in ("front", "left")]
    poses = np.stack([reader.camera_pose(c, f).numpy() for f, c in views])
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(2000, 3))
    world = poses[0, :3, 3] + rng.uniform(1, 5, (2000, 1)) * directions / np.linalg.norm(directions, axis=1,
                                                                                          keepdims=True)
    local = [torch.from_numpy((world - pose[:3, 3]) @ pose[:3, :3]) for pose in poses]
    seen = np.all([rig.cameras[c].model.project(p)[1].numpy() for (_, c), p in zip(views, local)], axis=0)
    world = world[seen]
    uv, rays, cos_off_axis = [], [], []
    for (_, camera), pose, points in zip(views, poses, local):
        model = rig.cameras[camera].model
        projected = model.project(points[seen])[0]
        uv.append(projected.numpy())
        rays.append(model.unproject(projected).numpy() @ pose[:3, :3].T)
        cos_off_axis.append(points[seen][:, 2].numpy() / points[seen].norm(dim=1).numpy())
    assert len(world) >= 200 and (np.min(cos_off_axis, axis=0) < 0).sum() >= 50
    n = len(world)
    feats = points_sfm._Features(views, poses, np.arange(0, 5 * n, n), [np.zeros((n, 128), np.float32)] * 4,
                                 np.concatenate(uv), np.concatenate(rays), np.zeros((4 * n, 3), np.uint8),
                                 np.repeat(np.arange(4), n))
    chain = np.concatenate([np.column_stack([np.arange(n) + v * n, np.arange(n) + (v + 1) * n]) for v in range(3)])
    assert len(points_sfm._verified(rig, feats, chain)) == len(chain)
    xyz, track, _, error = points_sfm._triangulate_tracks(rig, feats, *points_sfm._tracks(feats, chain))
    assert len(xyz) == n and np.bincount(track).tolist() == [4] * n
    np.testing.assert_allclose(xyz, world, atol=1e-9)
    assert error.max() < 1e-6


def test_command_refuses_existing_points_then_replaces_them(tiny_data: Path, tmp_path: Path, capsys) -> None:
    data = _copy(tiny_data, tmp_path / "tiny")
    shutil.copy(tiny_data / "points3d.ply", data / "points3d.ply")
    before = (data / "points3d.ply").read_bytes()
    assert main(["points", str(data), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "already exists; pass --overwrite" in err
    assert (data / "points3d.ply").read_bytes() == before

    assert main(["points", str(data), "--overwrite", "--quiet", "--max-features", "500"]) == 0
    out = capsys.readouterr().out.strip()
    written = len(DatasetReader(data).points[0])
    assert out.count("\n") == 0 and out.startswith(f"wrote {data / 'points3d.ply'}: {written} points from 40 images")
    assert "mean reprojection error" in out
    assert sorted(p.name for p in data.iterdir()) == ["images", "points3d.ply", "poses.json", "rig.json",
                                                      "split.json"]


def test_too_few_matches_is_one_line_and_writes_nothing(tiny_data: Path, tmp_path: Path, capsys) -> None:
    data = _copy(tiny_data, tmp_path / "blank", blank=True)
    assert main(["points", str(data), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"only 0 points triangulated, {MIN_POINTS} needed" in err
    assert sorted(p.name for p in data.iterdir()) == ["images", "poses.json", "rig.json", "split.json"]
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_import_points_sfm_replaces_the_recordings_points_and_reports_them(tiny_data: Path, tmp_path: Path,
                                                                           capsys) -> None:
    exported, imported = tmp_path / "ns", tmp_path / "imported"
    assert main(["export", "nerfstudio", str(tiny_data), "-o", str(exported)]) == 0
    assert (exported / "sparse_pc.ply").is_file()   # the synth scene's own 3000 points come along
    capsys.readouterr()
    assert main(["import", "nerfstudio", str(exported), "-o", str(imported), "--rig", str(tiny_data),
                 "--points", "sfm", "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads((imported / REPORT_FILE).read_text())
    written = len(DatasetReader(imported).points[0])
    assert printed["points"] == saved["points"] == saved["points_sfm"]["points"] == written != 3000
    assert written >= MIN_POINTS and saved["points_sfm"]["mean_reprojection_px"] < 1.0
