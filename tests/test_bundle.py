"""Scene bundles round-trip through save/load and fail with clear errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

import parksim.bundle as bundle_io
from parksim.bundle import Bundle, BundleError
from parksim.gaussians import GaussianScene
from parksim.render import render
from parksim.synth.rig import avm_rig
from parksim.visibility import VisibilityGrid


@pytest.fixture()
def sample() -> Bundle:
    scene = GaussianScene.random(200, bounds=((0, -3, 0), (6, 3, 2)), sh_degree=1, seed=3)
    world_map = {"frame": "world", "slots": [{"id": 0, "corners": [[0, 0], [2, 0], [2, 5], [0, 5]]}], "obstacles": []}
    meta = {"iterations": 7, "camera_response": {"front": {"gain": [1, 1, 1]}}}
    return Bundle(scene, avm_rig(64, 48, 100), world_map, meta)


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


def _grid(n_gaussians: int) -> VisibilityGrid:
    """A 1x1 grid whose one measured cell sees every Gaussian."""
    return VisibilityGrid(0.0, 0.0, 1.0, 1, 1, np.array([0, n_gaussians]), np.arange(n_gaussians, dtype=np.int32),
                          np.array([True]))


def test_bundle_paths_stay_inside_the_folder(sample: Bundle, tmp_path: Path) -> None:
    """bundle.json's visibility entry, and the files themselves, must not lead outside the bundle folder."""
    folder = bundle_io.save(tmp_path / "b", sample)
    _grid(len(sample.scene)).save(tmp_path / "outside.npz")   # a valid grid: only its place is wrong
    meta = json.loads((folder / "bundle.json").read_text())
    for escape in ("../outside.npz", str(tmp_path / "outside.npz")):
        (folder / "bundle.json").write_text(json.dumps({**meta, "visibility": escape}))
        with pytest.raises(BundleError, match=r"bundle.json key 'visibility' .* points outside the bundle folder"):
            bundle_io.load(folder)
    (folder / "bundle.json").write_text(json.dumps(meta))
    (folder / "rig.json").rename(tmp_path / "rig.json")
    (folder / "rig.json").symlink_to(tmp_path / "rig.json")
    with pytest.raises(BundleError, match="'rig.json' points outside the bundle folder"):
        bundle_io.load(folder)


def test_visibility_inside_the_folder_loads(sample: Bundle, tmp_path: Path) -> None:
    sample.visibility = _grid(len(sample.scene))
    back = bundle_io.load(bundle_io.save(tmp_path / "b", sample))
    assert back.visibility is not None and back.meta["visibility"] == "visibility.npz"


@pytest.mark.parametrize("field, index, value, words", [
    ("sh", (17, 2, 1), float("nan"), "sh is not finite for 1 Gaussian(s), first at Gaussian 17"),
    ("means", (3, 0), float("inf"), "means is not finite for 1 Gaussian(s), first at Gaussian 3"),
    ("log_scales", (9, 2), float("-inf"), "log_scales is not finite"),
    ("opacity_logits", (5,), float("nan"), "opacity_logits is not finite"),
    ("quats", (11,), 0.0, "quats is all zero (no rotation) for 1 Gaussian(s), first at Gaussian 11"),
])
def test_a_bad_scene_is_refused_once_when_the_bundle_is_built(sample: Bundle, field: str, index: tuple, value: float,
                                                             words: str) -> None:
    """One non-finite value (or a zero quaternion) would turn every view it touches NaN: refused up front."""
    getattr(sample.scene, field)[index] = value
    with pytest.raises(BundleError, match=re.escape(words)):
        Bundle(sample.scene, sample.rig, sample.map, sample.meta)


def test_a_reshaped_tensor_is_refused(sample: Bundle) -> None:
    sample.scene.sh = sample.scene.sh[:, :1]
    with pytest.raises(BundleError, match=r"sh must have shape \(200, 4, 3\), got \(200, 1, 3\)"):
        Bundle(sample.scene, sample.rig)
