"""Appearance: per-image exposure learned in training, and the served renders through the bundle's camera response.

The exposure tests train on a copy of ``synth tiny`` whose training images are scaled by 2^EV, EV drawn uniformly
in [-1, 1] per (frame, camera) (clipped to [0, 1], as a real sensor clips), and score the test frames against the
unperturbed images.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from parksim.bundle import load
from parksim.data import DatasetReader
from parksim.geometry import as_pose
from parksim.imageio import to_uint8, write_image
from parksim.recon.checkpoint import checkpoint_path, load_checkpoint
from parksim.recon.config import TrainConfig, load_config
from parksim.recon.evaluate import evaluate_views, render_view
from parksim.recon.response import CameraResponse
from parksim.recon.trainer import Trainer
from parksim.render import bev_ipm, render
from parksim.sim import LocalSim
from sim_fixtures import make_bundle

ITERATIONS = 300
"""Photometric iterations of the perturbed runs (40 training views: each drawn about 7 times)."""
EXPOSURE_LR = 3e-3


def _config(exposure: float, iterations: int | None = None) -> TrainConfig:
    """The ``tiny`` preset with ``lr.exposure`` (and the photometric iterations) replaced."""
    base = load_config("tiny")
    photometric = base.photometric.model_copy(update={"iterations": iterations or base.photometric.iterations})
    return base.model_copy(update={"lr": base.lr.model_copy(update={"exposure": exposure}),
                                   "photometric": photometric})


@pytest.fixture(scope="module")
def exposed(tiny_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[tuple[int, str], float]]:
    """A copy of ``tiny`` with every training image exposed by its own EV; returns the folder and the EVs."""
    out = tmp_path_factory.mktemp("exposed") / "tiny"
    shutil.copytree(tiny_data, out)
    reader = DatasetReader(tiny_data)
    rng = np.random.default_rng(0)
    evs = {(f, c): float(rng.uniform(-1.0, 1.0)) for f in reader.split["train"] for c in reader.rig.names}
    layout = DatasetReader(out).layout
    for (frame, camera), ev in evs.items():
        write_image(layout.image(camera, frame), (reader.image(camera, frame) * 2.0 ** ev).clamp(0.0, 1.0))
    return out, evs


def _train(data: Path, config: TrainConfig, out: Path, stop_after: int | None = None) -> Trainer:
    out.mkdir(parents=True, exist_ok=True)
    trainer = Trainer(DatasetReader(data), config, out, log=lambda s: None)
    trainer.initialise()
    trainer.train(stop_after)
    return trainer


def _clean_psnr(trainer: Trainer, clean: Path) -> float:
    """Mean PSNR of the test views (recorded, never perturbed) through the per-camera response only."""
    reader = DatasetReader(clean)
    views = [(f, c) for f in reader.split["test"] for c in reader.rig.names]
    assert trainer.params is not None
    value = evaluate_views(trainer.params.snapshot(), reader, views, trainer.response, slots=False).mean("psnr")
    assert value is not None
    return value


@pytest.fixture(scope="module")
def runs(exposed: tuple[Path, dict[tuple[int, str], float]],
         tmp_path_factory: pytest.TempPathFactory) -> dict[str, Trainer]:
    """The perturbed dataset trained for ``ITERATIONS`` without and with the per-image correction."""
    data, _ = exposed
    root = tmp_path_factory.mktemp("exposure-runs")
    return {"off": _train(data, _config(0.0, ITERATIONS), root / "off"),
            "on": _train(data, _config(EXPOSURE_LR, ITERATIONS), root / "on")}


def test_learned_gains_follow_the_applied_exposure(runs: dict[str, Trainer], tiny_data: Path,
                                                   exposed: tuple[Path, dict[tuple[int, str], float]]) -> None:
    """Each view's correction brightens it by about the EV it was given relative to its camera's mean EV.

    Measured at 300 iterations, lr 3e-3: correlation 0.97, slope 0.86, signs agree for 37 of 40 views. The
    correction is affine, so its EV is read at the view's mean (valid-pixel) intensity: log2((g mu + b) / mu).
    """
    _, evs = exposed
    exposure = runs["on"].exposure
    assert exposure is not None
    reader = DatasetReader(tiny_data)
    learned, applied = [], []
    for camera in reader.rig.names:
        mean_ev = float(np.mean([ev for (_, c), ev in evs.items() if c == camera]))
        for frame in reader.split["train"]:
            image = reader.image(camera, frame)
            mu = float(image[image.sum(-1) > 0].mean())
            gain, bias = (float(t.detach().mean()) for t in exposure.correction(frame, camera))
            learned.append(math.log2((gain * mu + bias) / mu))
            applied.append(evs[(frame, camera)] - mean_ev)
    learned_a, applied_a = np.array(learned), np.array(applied)
    assert np.corrcoef(learned_a, applied_a)[0, 1] > 0.9
    assert 0.5 < np.polyfit(applied_a, learned_a, 1)[0] < 1.5
    assert np.mean(np.sign(learned_a) == np.sign(applied_a)) >= 0.8


def test_the_correction_does_not_make_the_clean_test_views_worse(runs: dict[str, Trainer], tiny_data: Path) -> None:
    """Measured on this machine: 20.67 dB without the correction, 21.95 dB with it (test views never perturbed)."""
    off, on = _clean_psnr(runs["off"], tiny_data), _clean_psnr(runs["on"], tiny_data)
    assert on >= off, (on, off)


def test_off_keeps_no_correction_and_writes_none(runs: dict[str, Trainer]) -> None:
    """``lr.exposure: 0`` (every preset) builds no correction: the step and checkpoint are today's."""
    assert runs["off"].exposure is None
    state = load_checkpoint(checkpoint_path(runs["off"].out))
    assert "exposure" not in state and state["config"]["lr"]["exposure"] == 0.0
    assert all(load_config(name).lr.exposure == 0.0 for name in ("tiny", "cpu_fast", "parkgaussian"))


def test_kill_and_resume_with_the_correction_matches_uninterrupted(
        exposed: tuple[Path, dict[tuple[int, str], float]], tmp_path: Path) -> None:
    data, _ = exposed
    config = _config(EXPOSURE_LR)
    full = _train(data, config, tmp_path / "full")
    _train(data, config, tmp_path / "resumed", stop_after=10)
    resumed = Trainer.from_checkpoint(DatasetReader(data), config, tmp_path / "resumed", log=lambda s: None)
    resumed.train()
    assert full.exposure is not None and resumed.exposure is not None and resumed.params is not None
    assert torch.equal(full.exposure.log_gain, resumed.exposure.log_gain)
    assert torch.equal(full.exposure.bias, resumed.exposure.bias)
    assert full.params is not None
    assert all(torch.equal(full.params.tensors[k], resumed.params.tensors[k]) for k in full.params.tensors)
    assert not torch.equal(full.exposure.log_gain, torch.zeros_like(full.exposure.log_gain))


RESPONSE = {"front": {"gain": [1.3, 0.9, 1.1], "vignetting": [-0.4, 0.1]},
            "left": {"gain": [0.8, 1.0, 1.2], "vignetting": [0.2, -0.3]},
            "rear": {"gain": [1.0, 1.1, 0.9], "vignetting": [-0.1, 0.0]}}
"""A non-identity response (the rig's fourth camera keeps the identity, as a bundle missing it would)."""
POSE = [1.0, 0.5, 0.3]


@pytest.fixture(scope="module")
def bundles(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The tiny garage bundle without a response and with ``RESPONSE``."""
    plain = load(make_bundle(tmp_path_factory.mktemp("bundle") / "b", "tiny", n=2000))
    return {"plain": plain, "response": dataclasses.replace(plain, meta={**plain.meta, "camera_response": RESPONSE})}


def test_served_views_and_bev_equal_eval_s_render_through_the_response(bundles: dict[str, Any],
                                                                        tiny_data: Path) -> None:
    bundle = bundles["response"]
    frame = LocalSim(bundle, device="cpu").render(POSE, bev=True)
    response = CameraResponse(bundle.rig, 0.0)
    response.load_dict(RESPONSE)
    reader = DatasetReader(tiny_data)
    expected = {c: render_view(bundle.scene, reader, 0, c, response, "auto", bundle.rig,
                               lambda cam, f: as_pose(POSE), bundle.projection) for c in bundle.rig.names}
    for camera, image in expected.items():
        diff = np.abs(frame.images[camera].astype(int) - to_uint8(image).astype(int))
        assert diff.max() <= 1, camera
    assert np.abs(frame.bev.astype(int) - to_uint8(bev_ipm(bundle.rig)(expected)).astype(int)).max() <= 1
    plain = render(bundle.scene, bundle.rig, as_pose(POSE), method=bundle.projection).images
    assert any(not np.array_equal(frame.images[c], to_uint8(plain[c])) for c in RESPONSE)


def test_the_served_response_is_built_for_the_rendered_scale(bundles: dict[str, Any]) -> None:
    """At half size the vignetting radius map is the full-size one at the scaled camera (2x2 means agree)."""
    sim = LocalSim(bundles["response"], device="cpu")
    full, half = sim.response(1.0), sim.response(0.5)
    assert sim.response(0.5) is half
    for camera in RESPONSE:
        model = bundles["response"].rig.cameras[camera].model
        ones = torch.ones(model.height, model.width, 3)
        pooled = torch.nn.functional.avg_pool2d(full(ones, camera).permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
        small = half(torch.ones(model.height // 2, model.width // 2, 3), camera)
        assert (small - pooled).abs().max() < 0.02, camera
    frame = sim.render(POSE, scale=0.5)
    assert frame.images["front"].shape == (model.height // 2, model.width // 2, 3)


def test_a_bundle_without_a_response_serves_exactly_the_plain_render(bundles: dict[str, Any]) -> None:
    bundle = bundles["plain"]
    sim = LocalSim(bundle, device="cpu")
    assert sim.response(1.0) is None
    frame = sim.render(POSE, bev=True, scale=0.5)
    plain = render(bundle.scene, bundle.rig, as_pose(POSE), scale=0.5, bev=True, method=bundle.projection)
    assert all(np.array_equal(frame.images[c], to_uint8(plain.images[c])) for c in bundle.rig.names)
    assert np.array_equal(frame.bev, to_uint8(plain.bev))
