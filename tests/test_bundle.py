"""Scene bundles round-trip through save/load and fail with clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import parksim.bundle as bundle_io
from parksim.bundle import Bundle, BundleError
from parksim.gaussians import GaussianScene
from parksim.render import render
from parksim.synth.rig import avm_rig


@pytest.fixture()
def sample() -> Bundle:
    scene = GaussianScene.random(200, bounds=((0, -3, 0), (6, 3, 2)), sh_degree=1, seed=3)
    world_map = {"frame": "world", "slots": [{"id": 0, "corners": [[0, 0], [2, 0], [2, 5], [0, 5]]}], "obstacles": []}
    return Bundle(scene, avm_rig(64, 48, 100), world_map, {"iterations": 7, "camera_response": {"front": {"gain": [1, 1, 1]}}})


def test_round_trip(sample: Bundle, tmp_path: Path) -> None:
    bundle_io.save(tmp_path / "b", sample)
    back = bundle_io.load(tmp_path / "b")
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        torch.testing.assert_close(getattr(back.scene, name), getattr(sample.scene, name))
    assert back.scene.sh_degree == 1
    assert back.rig.to_dict() == sample.rig.to_dict() and back.bev == sample.rig.bev
    assert back.map == sample.map and back.meta == sample.meta
    image = render(back.scene, back.rig, (0.0, 0.0, 0.0), cameras=["front"]).images["front"]
    assert image.shape == (48, 64, 3) and torch.isfinite(image).all()


def test_missing_or_bad_files_are_named(sample: Bundle, tmp_path: Path) -> None:
    with pytest.raises(BundleError, match="not found"):
        bundle_io.load(tmp_path / "nothing")
    folder = bundle_io.save(tmp_path / "b", sample)
    (folder / "rig.json").unlink()
    with pytest.raises(BundleError, match="rig.json is missing"):
        bundle_io.load(folder)
    bundle_io.save(folder, sample)
    (folder / "bundle.json").write_text(json.dumps({"version": 99}))
    with pytest.raises(BundleError, match="version 99"):
        bundle_io.load(folder)
    bundle_io.save(folder, sample)
    (folder / "gaussians.ply").write_bytes(b"ply\nbroken")
    with pytest.raises(BundleError, match="gaussians.ply"):
        bundle_io.load(folder)
