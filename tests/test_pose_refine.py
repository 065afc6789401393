"""Pose refinement: identity start, exact gradients, resume, the bundle and test-time alignment in evaluation."""

from __future__ import annotations

import json
import math
import shutil
import statistics
from pathlib import Path

import pytest
import torch
import yaml

from parksim.bundle import load
from parksim.cli import main as cli_main
from parksim.data import DatasetReader
from parksim.data.writer import DatasetWriter
from parksim.gaussians import GaussianScene
from parksim.recon.checkpoint import checkpoint_path, load_checkpoint
from parksim.recon.config import PRESETS_DIR, PoseRefineConfig
from parksim.recon.evaluate import evaluate_bundle
from parksim.recon.losses import photometric_loss
from parksim.recon.masks import scene_mask
from parksim.recon.pose_refine import POSES_KEY, PoseCorrections, align_poses, pose_error, refinement_enabled, so3xr3
from parksim.recon.reconstruct import reconstruct
from parksim.render import render
from parksim.rig import Rig, RigCamera
from parksim.synth.layout import build_garage
from parksim.synth.presets import get_preset
from parksim.synth.rig import avm_rig
from parksim.synth.trajectory import drive
from sim_fixtures import garage_scene

PERTURBED = "front"
PERTURBATION = torch.tensor([0.0, 0.0, 0.017, 0.08, -0.06, 0.0], dtype=torch.float64)
"""1 deg of yaw and 10 cm in the camera frame on the front camera's extrinsics (a mounting error)."""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pose") / "tiny"
    assert cli_main(["synth", "tiny", "-o", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def perturbed(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny dataset with the front camera's calibrated extrinsics off by ``PERTURBATION``."""
    out = tmp_path_factory.mktemp("pose") / "perturbed"
    shutil.copytree(tiny, out)
    rig = json.loads((out / "rig.json").read_text())
    T = torch.tensor(rig["cameras"][PERTURBED]["T_vehicle_camera"], dtype=torch.float64)
    rig["cameras"][PERTURBED]["T_vehicle_camera"] = (T @ so3xr3(PERTURBATION)).tolist()
    (out / "rig.json").write_text(json.dumps(rig))
    return out


def _config(tmp: Path, **pose_opt: object) -> Path:
    data = yaml.safe_load((PRESETS_DIR / "tiny.yaml").read_text())
    data["photometric"]["iterations"] = 30
    data["pose_opt"] = {"enabled": True, "lr": 5e-3, "test_steps": 3, **pose_opt}
    path = tmp / "pose.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def refined_run(perturbed: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("runs")
    return reconstruct(perturbed, tmp / "refined", _config(tmp), log=lambda s: None)


EGO_CM, EGO_DEG, EXT_CM, EXT_DEG = 5.0, 0.5, 2.0, 0.3
"""Issue [10]'s perturbations: every ego pose, and the front camera's extrinsics."""


def _delta(g: torch.Generator, cm: float, deg: float) -> torch.Tensor:
    """A correction ``(omega, v)`` of exactly ``cm`` and ``deg`` in random directions."""
    axis, move = (v / v.norm() for v in torch.randn(2, 3, generator=g, dtype=torch.float64))
    return torch.cat([axis * math.radians(deg), move * cm / 100])


@pytest.fixture(scope="module")
def garage(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, GaussianScene, torch.Tensor, Rig]:
    """Self-consistent data: a fixed Gaussian garage rendered at the true poses of six frames (160x120), stored with
    every ego pose off by 5 cm and 0.5 deg and the front camera's extrinsics off by 2 cm and 0.3 deg.

    The corrections that undo the ego errors come in +-pairs (zero mean, the gauge ``PoseCorrections`` fixes), so
    the truth is exactly the optimum. Returns the dataset, the scene, the true ego poses and the true rig."""
    preset = get_preset("tiny")
    scene, _ = garage_scene("tiny", n=20000)
    rig = avm_rig(160, 120, preset.bev_px)
    poses, stamps = drive(build_garage(preset.layout), preset.trajectory, 6)
    truth = torch.from_numpy(poses)
    g = torch.Generator().manual_seed(0)
    fixes = [d for _ in range(3) for d in [_delta(g, EGO_CM, EGO_DEG)] for d in (d, -d)]
    front = rig.cameras["front"]
    wrong = {**rig.cameras, "front": RigCamera("front", front.model,
                                               front.T_vehicle_camera @ so3xr3(_delta(g, EXT_CM, EXT_DEG)))}
    out = tmp_path_factory.mktemp("pose") / "garage"
    writer = DatasetWriter(out)
    writer.rig(Rig(wrong, rig.bev))
    writer.poses(torch.stack([T @ torch.linalg.inv(so3xr3(d)) for T, d in zip(truth, fixes)]).numpy(), stamps)
    for frame, pose in enumerate(truth):
        for camera in rig.names:
            writer.image(camera, frame, render(scene, rig, pose, cameras=[camera]).images[camera].clamp(0, 1).numpy())
    writer.split(range(6), [])
    return out, scene, truth, rig


def _view_loss(scene: GaussianScene, rig: Rig, pose: torch.Tensor, camera: str, target: torch.Tensor) -> torch.Tensor:
    """The training loss (L1 + 0.2 D-SSIM over the scene mask) of one view rendered at ``pose``."""
    image = render(scene, rig, pose, cameras=[camera]).images[camera]
    mask = scene_mask(rig.cameras[camera], rig.bev).to(torch.float32)[None, None]
    return photometric_loss(image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], mask, 0.2)


def test_training_corrections_recover_known_pose_errors(garage: tuple) -> None:
    """Gaussians frozen, one random view per step as the trainer draws them, 200 steps of ``lr`` 5e-3: the ego
    poses come within 15 % of their errors, each camera's world pose too, the front extrinsics within 50 %."""
    data, scene, truth, rig = garage
    reader = DatasetReader(data)
    corr = PoseCorrections(reader, reader.rig, PoseRefineConfig(enabled=True, lr=5e-3), 200)
    views = [(f, c) for f in reader.frames for c in rig.names]
    targets = {(f, c): reader.image(c, f) for f, c in views}
    g = torch.Generator().manual_seed(0)
    for step in range(200):
        frame, camera = views[int(torch.randint(len(views), (1,), generator=g))]
        _view_loss(scene, reader.rig, corr.view_pose(camera, frame), camera, targets[(frame, camera)]).backward()
        corr.step(step)
    with torch.no_grad():
        ego = [pose_error(corr.ego_pose(f), truth[f]) for f in reader.frames]
        cams = [pose_error(corr.view_pose(c, f) @ reader.rig.cameras[c].T_vehicle_camera,
                           truth[f] @ rig.cameras[c].T_vehicle_camera) for f, c in views]
        front = pose_error(corr.refined_rig().cameras["front"].T_vehicle_camera, rig.cameras["front"].T_vehicle_camera)
    for errors in (ego, cams):
        assert statistics.median(e[0] for e in errors) < 0.15 * EGO_CM
        assert statistics.median(e[1] for e in errors) < 0.15 * EGO_DEG
    assert front[0] < 0.5 * EXT_CM and front[1] < 0.5 * EXT_DEG


def test_test_time_alignment_recovers_a_perturbed_pose(garage: tuple) -> None:
    """The default alignment (``test_lr``) of one frame's front and rear views, rig and Gaussians frozen, 60 steps:
    its ego pose comes within 10 % of its 5 cm and 0.5 deg error."""
    data, scene, truth, rig = garage
    reader = DatasetReader(data)
    frame = 1
    before = pose_error(reader.pose(frame), truth[frame])
    views = [(frame, "front"), (frame, "rear")]
    corr = align_poses(scene, reader, rig, views, None, PoseRefineConfig(enabled=True), 60)
    after = pose_error(corr.ego_pose(frame).detach(), truth[frame])
    assert before == pytest.approx((EGO_CM, EGO_DEG))
    assert after[0] < 0.1 * EGO_CM and after[1] < 0.1 * EGO_DEG


def _per_image_copy(data: Path, out: Path) -> Path:
    """``data`` with every image's own T_world_camera instead of ego poses (as COLMAP or nerfstudio give)."""
    shutil.copytree(data, out)
    reader = DatasetReader(data)
    frames = [{"frame": f, "timestamp": t, "T_world_camera": {c: reader.camera_pose(c, f).tolist()
                                                             for c in reader.rig.names}}
              for f, t in zip(reader.frames, reader.timestamps)]
    (out / "poses.json").write_text(json.dumps({"frames": frames}))
    return out


def _scene(reader: DatasetReader, n: int, dtype: torch.dtype) -> GaussianScene:
    g = torch.Generator().manual_seed(0)
    xyz = torch.from_numpy(reader.points[0])[torch.randperm(len(reader.points[0]), generator=g)[:n]]
    return GaussianScene(xyz.to(dtype), torch.randn(n, 4, generator=g, dtype=dtype),
                         torch.full((n, 3), -1.5, dtype=dtype), torch.zeros(n, dtype=dtype),
                         torch.rand(n, 4, 3, generator=g, dtype=dtype), 1)


def test_auto_is_on_exactly_for_imports() -> None:
    auto, on, off = (PoseRefineConfig(enabled=e) for e in ("auto", True, False))
    imported, synth = {"source": "import", "importer": "colmap"}, {"generator": "parksim synth"}
    assert refinement_enabled(auto, imported) and not refinement_enabled(auto, synth)
    assert refinement_enabled(on, synth) and not refinement_enabled(off, imported)


@pytest.mark.parametrize("per_image", [False, True])
def test_zero_corrections_render_bit_identically(tiny: Path, tmp_path: Path, per_image: bool) -> None:
    data = _per_image_copy(tiny, tmp_path / "images") if per_image else tiny
    reader = DatasetReader(data)
    corr = PoseCorrections(reader, reader.rig, PoseRefineConfig(enabled=True), 10)
    assert corr.per_image == per_image and corr.extrinsics_on == (not per_image)
    scene = _scene(reader, 200, torch.float32)
    scene.means.requires_grad_(True)   # as in training: both renders take the differentiable path
    for frame in reader.frames[:3]:
        for camera in reader.rig.names:
            assert torch.equal(corr.view_pose(camera, frame), reader.view_pose(camera, frame))
    frame, camera = reader.frames[1], reader.rig.names[2]
    ours = render(scene, reader.rig, corr.view_pose(camera, frame), cameras=[camera]).images[camera]
    theirs = render(scene, reader.rig, reader.view_pose(camera, frame), cameras=[camera]).images[camera]
    assert torch.equal(ours, theirs)


def test_gradient_matches_finite_differences(tiny: Path) -> None:
    """d(weighted image sum)/d(correction) through render, float64, against central differences."""
    reader = DatasetReader(tiny)
    corr = PoseCorrections(reader, reader.rig, PoseRefineConfig(enabled=True), 10)
    scene = _scene(reader, 40, torch.float64)
    frame, camera = reader.frames[0], reader.rig.names[0]
    weights = torch.rand(120, 160, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    with torch.no_grad():
        corr.poses[corr.rows[frame]] = torch.tensor([0.002, -0.003, 0.004, 0.02, -0.01, 0.005])
        corr.extrinsics[0] = torch.tensor([-0.001, 0.002, 0.001, 0.01, 0.005, -0.01])

    def loss() -> torch.Tensor:
        pose = corr.view_pose(camera, frame)
        return (render(scene, reader.rig, pose, cameras=[camera], backend="torch").images[camera] * weights).sum()

    loss().backward()
    eps = 1e-7
    for tensor, row in ((corr.poses, corr.rows[frame]), (corr.extrinsics, 0)):
        assert tensor.grad is not None and tensor.grad[row].abs().max() > 1.0
        for k in range(6):
            with torch.no_grad():
                tensor[row, k] += eps
                plus = float(loss())
                tensor[row, k] -= 2 * eps
                minus = float(loss())
                tensor[row, k] += eps
            fd = (plus - minus) / (2 * eps)
            assert fd == pytest.approx(float(tensor.grad[row, k]), rel=1e-4, abs=1e-3), (row, k)


def test_bundle_carries_refined_rig_and_poses(refined_run: Path, perturbed: Path) -> None:
    bundle, reader = load(refined_run), DatasetReader(perturbed)
    assert bundle.poses is not None and bundle.poses["refined"] == reader.split["train"]
    refined = {e["frame"]: torch.tensor(e["T_world_vehicle"], dtype=torch.float64) for e in bundle.poses["frames"]}
    assert sorted(refined) == reader.frames
    for frame in reader.split["test"]:
        assert torch.equal(refined[frame], reader.pose(frame))
    assert any(not torch.equal(refined[f], reader.pose(f)) for f in reader.split["train"])
    assert not torch.equal(bundle.rig.cameras[PERTURBED].T_vehicle_camera,
                           reader.rig.cameras[PERTURBED].T_vehicle_camera)
    assert bundle.meta[POSES_KEY]["mode"] == "ego" and bundle.meta[POSES_KEY]["config"]["test_steps"] == 3
    path = bundle.meta["recorded_path"]
    assert path[1][:2] == pytest.approx(refined[reader.frames[1]][:2, 3].tolist())


def test_resume_continues_the_corrections_exactly(refined_run: Path, perturbed: Path, tmp_path: Path) -> None:
    out = tmp_path / "killed"
    config = _config(tmp_path)
    reconstruct(perturbed, out, config, stop_after=10, log=lambda s: None)
    assert load_checkpoint(checkpoint_path(out))["iteration"] == 10
    reconstruct(perturbed, out, None, resume=True, log=lambda s: None)
    full, resumed = (load_checkpoint(checkpoint_path(p))["pose_opt"] for p in (refined_run, out))
    assert torch.equal(full["poses"], resumed["poses"]) and torch.equal(full["extrinsics"], resumed["extrinsics"])
    assert full["poses"].abs().max() > 0


def test_evaluation_aligns_test_poses_only_when_refined(refined_run: Path, perturbed: Path, tmp_path: Path) -> None:
    aligned = evaluate_bundle(refined_run, perturbed, tmp_path / "aligned")
    note = aligned["pose_alignment"]
    assert note.startswith("test-time pose alignment") and "3 Adam steps" in note
    assert "test-time pose alignment" in (tmp_path / "aligned" / "eval.md").read_text()
    plain = evaluate_bundle(refined_run, perturbed, tmp_path / "plain", align_steps=0)
    assert plain["pose_alignment"].startswith("off")
    assert aligned["overall"]["psnr"] != plain["overall"]["psnr"]
