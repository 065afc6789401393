"""Dataset layout: the reader round-trips what the writer wrote, and bad inputs give named errors."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from parksim.data import DatasetError, DatasetLayout, DatasetReader, DatasetWriter
from parksim.fileio import atomic_directory
from parksim.synth.rig import avm_rig
from tolerances import f32_tol

W, H, N = 64, 48, 3


def _labels() -> dict:
    return {"bev": {"width": 100, "height": 100, "m_per_px": 0.1},
            "marks": [{"x": 10.0, "y": 20.0, "direction": 1.0, "shape": "T", "id": 0},
                      {"x": 40.0, "y": 20.5, "direction": 1.0, "shape": "L", "id": 1}],
            "slots": [{"p1": 0, "p2": 1, "type": "perpendicular", "angle": 90.0, "occupied": False, "id": 0}]}


@pytest.fixture()
def dataset(tmp_path: Path) -> tuple[Path, dict]:
    """A small dataset written by DatasetWriter, and what was written."""
    rng = np.random.default_rng(0)
    rig = avm_rig(W, H, bev_px=100)
    root = tmp_path / "ds"
    w = DatasetWriter(root)
    poses = np.tile(np.eye(4), (N, 1, 1))
    poses[:, 0, 3] = np.arange(N) * 0.2
    w.rig(rig)
    w.poses(poses, np.arange(N) / 10)
    images = {(c, f): rng.random((H, W, 3), dtype=np.float32) for c in rig.names for f in range(N)}
    depths = {(c, f): rng.uniform(0, 30, (H, W)) for c in rig.names for f in range(N)}
    for (c, f), img in images.items():
        w.image(c, f, img)
        w.depth(c, f, depths[(c, f)])
    for f in range(N):
        w.ipm(f, rng.random((100, 100, 3)))
        w.labels(f, _labels())
    w.split([1, 2], [0])
    w.map({"slots": [], "obstacles": []})
    xyz = rng.normal(size=(50, 3))
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    w.points(xyz, rgb, np.tile([0.0, 0.0, 1.0], (50, 1)))
    w.meta({"preset": "test"})
    return root, {"poses": poses, "images": images, "depths": depths, "xyz": xyz, "rgb": rgb, "rig": rig}


def test_round_trip(dataset):
    root, src = dataset
    r = DatasetReader(root)
    r.validate(deep=True)
    assert r.frames == list(range(N))
    assert torch.equal(r.poses, torch.from_numpy(src["poses"]))
    assert r.split == {"train": [1, 2], "test": [0]}
    assert r.rig.names == src["rig"].names and r.rig.bev == src["rig"].bev
    for (c, f), img in src["images"].items():
        got = r.image(c, f).numpy()
        assert got.shape == (H, W, 3)
        # Quantisation to 1/255 and to 1 mm, plus float32 rounding in ulps: the writer's x * 255 and the reader's
        # u8 / 255 (a quarter ulp of 1 each); the reader's mm / 1000 (half an ulp of the deepest pixel: at 30 m
        # the fixed 1e-6 this replaces was 0.52 ulp, and 0.49 of it was used).
        assert np.abs(got - img).max() <= 0.5 / 255 + f32_tol(1.0, ulps=1)
        depth = src["depths"][(c, f)]
        assert np.abs(r.depth(c, f).numpy() - depth).max() <= 0.0005 + f32_tol(depth, ulps=1)
    assert r.labels(1)["slots"][0]["type"] == "perpendicular"
    assert r.ipm(2).shape == (100, 100, 3)
    xyz, rgb = r.points
    assert np.allclose(xyz, src["xyz"], atol=1e-6) and np.array_equal(rgb, src["rgb"])
    assert r.meta == {"preset": "test"} and r.map == {"slots": [], "obstacles": []}


def test_missing_frame_names_the_file(dataset):
    root, _ = dataset
    missing = DatasetLayout(root).image("left", 1)
    missing.unlink()
    with pytest.raises(DatasetError, match="missing image for frame 1") as e:
        DatasetReader(root)
    assert e.value.path == missing


def test_corrupt_png_names_the_file(dataset):
    root, _ = dataset
    path = DatasetLayout(root).image("front", 2)
    path.write_bytes(path.read_bytes()[:40])
    r = DatasetReader(root)  # existence checks pass: decoding is lazy
    with pytest.raises(DatasetError, match="corrupt or truncated") as e:
        r.image("front", 2)
    assert e.value.path == path
    with pytest.raises(DatasetError):
        r.validate(deep=True)


def test_pose_count_mismatch(dataset):
    root, _ = dataset
    layout = DatasetLayout(root)
    data = json.loads(layout.poses.read_text())
    data["frames"] = data["frames"][:-1]
    layout.poses.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"2 poses but 3 images") as e:
        DatasetReader(root)
    assert e.value.path == layout.poses


def test_labels_outside_bev(dataset):
    root, _ = dataset
    layout = DatasetLayout(root)
    bad = _labels()
    bad["marks"][1]["x"] = 130.0
    layout.labels(0).write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match="marking point 1 .* outside the 100x100 BEV") as e:
        DatasetReader(root).labels(0)
    assert e.value.path == layout.labels(0)


def test_bad_poses_and_rig(dataset, tmp_path):
    root, _ = dataset
    layout = DatasetLayout(root)
    layout.poses.write_text("{not json")
    with pytest.raises(DatasetError, match="not valid JSON") as e:
        DatasetReader(root)
    assert e.value.path == layout.poses
    other = tmp_path / "norig"
    shutil.copytree(root, other)
    DatasetLayout(other).rig.unlink()
    with pytest.raises(DatasetError, match="rig.json") as e:
        DatasetReader(other)
    assert str(e.value).count(str(DatasetLayout(other).rig)) == 1
    DatasetLayout(other).rig.write_text("{not a rig")
    with pytest.raises(DatasetError, match="rig.json") as e:
        DatasetReader(other)
    assert str(e.value).count(str(DatasetLayout(other).rig)) == 1
    with pytest.raises(DatasetError, match="dataset directory not found"):
        DatasetReader(tmp_path / "nothing")


def test_atomic_directory_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "scene"
    with pytest.raises(RuntimeError):
        with atomic_directory(target, overwrite=False) as tmp:
            (tmp / "poses.json").write_text("{}")
            raise RuntimeError("killed")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    with atomic_directory(target, overwrite=False) as tmp:
        (tmp / "a").write_text("1")
    assert (target / "a").read_text() == "1"
    umask = os.umask(0)
    os.umask(umask)
    assert target.stat().st_mode & 0o777 == 0o777 & ~umask   # a folder like any other, not mkdtemp's 0700
    with pytest.raises(FileExistsError):
        with atomic_directory(target, overwrite=False) as tmp:
            (tmp / "c").write_text("3")  # never runs: an existing scene is not touched
    assert sorted(p.name for p in target.iterdir()) == ["a"]
    with atomic_directory(target) as tmp:
        (tmp / "b").write_text("2")
    assert sorted(p.name for p in target.iterdir()) == ["b"] and len(list(tmp_path.iterdir())) == 1


def test_per_image_poses_replace_or_join_the_ego_poses(dataset):
    """A pose per image (COLMAP, nerfstudio) is read back exactly, and view_pose puts the camera there."""
    root, src = dataset
    rig, rng = src["rig"], np.random.default_rng(1)
    rot = torch.linalg.qr(torch.from_numpy(rng.normal(size=(N, 4, 3, 3))))[0]
    per_image = []
    for f in range(N):
        poses = {}
        for i, c in enumerate(rig.names):
            T = np.eye(4)
            T[:3, :3] = rot[f, i].numpy() * np.sign(np.linalg.det(rot[f, i].numpy()))
            T[:3, 3] = rng.normal(size=3)
            poses[c] = T
        per_image.append(poses)
    layout = DatasetLayout(root)
    for ego in (None, src["poses"]):
        DatasetWriter(root).poses(ego, np.arange(N) / 10, camera_poses=per_image)
        r = DatasetReader(root)
        assert r.has_camera_poses and r.has_vehicle_poses == (ego is not None)
        for f in range(N):
            for c in rig.names:
                T = r.camera_pose(c, f).numpy()
                assert np.array_equal(T, per_image[f][c])
                through_rig = (r.view_pose(c, f) @ rig.cameras[c].T_vehicle_camera).numpy()
                np.testing.assert_allclose(through_rig, T, rtol=0, atol=8 * np.spacing(np.abs(T).max() + 1))
        assert r.camera_centres().shape == (N * len(rig.names), 3)
    with pytest.raises(DatasetError, match="per-image camera poses only") as e:
        DatasetWriter(root).poses(None, np.arange(N) / 10, camera_poses=per_image)
        DatasetReader(root).pose(0)
    assert e.value.path == layout.poses
    # Without per-image poses, camera_pose is the ego pose through the rig.
    DatasetWriter(root).poses(src["poses"], np.arange(N) / 10)
    r = DatasetReader(root)
    assert not r.has_camera_poses
    c = rig.names[0]
    assert torch.equal(r.camera_pose(c, 1), r.pose(1) @ rig.cameras[c].T_vehicle_camera)


@pytest.mark.parametrize("bad, message", [
    ({"frames": [{"frame": 0, "timestamp": 0.0}]}, "T_world_vehicle, T_world_camera, or both"),
    ({"frames": [{"frame": 0, "timestamp": 0.0, "T_world_vehicle": np.eye(4).tolist()},
                 {"frame": 1, "timestamp": 0.1}]}, "T_world_vehicle must be given for every frame or for none"),
    ({"frames": [{"frame": 0, "timestamp": 0.0, "T_world_camera": {"front": np.eye(4).tolist()}}]},
     "T_world_camera names cameras"),
    ({"frames": [{"frame": 0, "timestamp": 0.0, "T_world_camera": {c: np.eye(4).tolist() for c in
                                                                   ("front", "left", "rear", "right")}},
                 {"frame": 1, "timestamp": 0.1, "T_world_camera": {"front": np.eye(4).tolist()}}]},
     "same cameras"),
])
def test_bad_per_image_poses_are_named(dataset, bad, message):
    root, _ = dataset
    layout = DatasetLayout(root)
    layout.poses.write_text(json.dumps(bad))
    for f in range(N):
        for c in ("front", "left", "rear", "right"):
            if f >= len(bad["frames"]):
                layout.image(c, f).unlink()
    with pytest.raises(DatasetError, match=message) as e:
        DatasetReader(root)
    assert e.value.path == layout.poses
