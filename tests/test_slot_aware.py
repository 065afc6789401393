"""Slot-aware phase: weights and losses against hand-computed values, stop-gradient, gradient flow, skipping."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from parksim.ipm import IPM
from parksim.recon.detectors import DMPRDetector, GCNDetector
from parksim.recon.slot_aware import (
    SlotAwareConfig,
    SlotAwareStep,
    SlotFrame,
    Variant,
    align_loss,
    cam_loss,
    edge_tubes,
    ipm_loss,
    mix,
    shape_confidence,
    spec_of,
    top_edges,
    total_loss,
    upsample,
    weighted_l1,
)
from parksim.synth.rig import avm_rig
from sim_fixtures import garage_scene


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny tensors: one intra-op thread is faster than two fighting over a loaded machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def test_shaping_matches_hand_values() -> None:
    conf = torch.tensor([0.25, 0.75, 0.0])
    expected = torch.tensor([0.5, _sigmoid(1.0), _sigmoid(-0.5)])
    torch.testing.assert_close(shape_confidence(conf), expected)
    torch.testing.assert_close(shape_confidence(conf, gamma=2.0), expected ** 2)


def test_mix_values_and_stop_gradient() -> None:
    teacher = torch.tensor([1.0, 0.0], requires_grad=True)
    student = torch.tensor([0.5, 1.0], requires_grad=True)
    mixed = mix(teacher, student, 0.8)
    torch.testing.assert_close(mixed, torch.tensor([0.9, 0.2]), check_dtype=False)
    mixed.sum().backward()
    assert student.grad is None
    torch.testing.assert_close(teacher.grad, torch.full((2,), 0.8))


def test_upsample_to_bev_resolution() -> None:
    grid = torch.full((1, 1, 2, 2), 0.7)
    up = upsample(grid, (6, 4))
    assert up.shape == (1, 1, 6, 4)
    torch.testing.assert_close(up, torch.full((1, 1, 6, 4), 0.7))


def test_top_edges_skip_the_diagonal() -> None:
    scores = torch.tensor([[0.99, 0.2, 0.7], [0.9, 0.99, 0.1], [0.3, 0.4, 0.99]])
    assert top_edges(scores, 2).tolist() == [[1, 0], [0, 2]]
    assert top_edges(torch.zeros(1, 1), 8).shape == (0, 2)


def test_edge_tube_hand_values() -> None:
    points = torch.tensor([[2.0, 2.0], [6.0, 2.0]])
    tube = edge_tubes(points, torch.tensor([[0, 1]]), (5, 9), sigma=1.5, samples=5)
    assert tube[2, 4] == pytest.approx(1.0)                              # on the segment (a sample point)
    assert tube[3, 4] == pytest.approx(math.exp(-1.0 / 4.5))             # 1 px off it
    assert tube[2, 0] == pytest.approx(math.exp(-4.0 / 4.5))             # 2 px past an end
    assert edge_tubes(points, torch.zeros(0, 2, dtype=torch.long), (5, 9)).abs().sum() == 0


def test_edge_tubes_in_boxes_match_the_whole_grid() -> None:
    points = torch.tensor([[3.0, 4.0], [40.0, 25.0], [12.0, 30.0], [-2.0, 1.0]])
    pairs = torch.tensor([[0, 1], [1, 2], [2, 3]])
    size, sigma = (32, 48), 1.5
    grid = torch.stack(torch.meshgrid(torch.arange(48.0), torch.arange(32.0), indexing="xy"), -1).reshape(-1, 1, 2)
    t = torch.linspace(0.0, 1.0, 32)[:, None]
    full = torch.stack([torch.exp(-((grid - ((1 - t) * points[i] + t * points[j])) ** 2).sum(-1).amin(1)
                                  / (2 * sigma ** 2)) for i, j in pairs.tolist()]).amax(0).reshape(size)
    torch.testing.assert_close(edge_tubes(points, pairs, size, sigma), full, atol=5e-6, rtol=0)
    assert float(edge_tubes(points, pairs, size, sigma).amax()) == pytest.approx(1.0)


def test_align_loss_hand_value() -> None:
    teacher = torch.tensor([[0.9, 0.1], [0.5, 0.2]])
    student = torch.tensor([[0.3, 0.8], [0.6, 0.0]])
    ps = torch.softmax(torch.tensor([0.3, 0.6]), 0)     # teacher's top-2 cells: 0.9 and 0.5
    pt = torch.softmax(torch.tensor([0.9, 0.5]), 0)
    expected = float((ps * (ps / pt).log()).sum())
    assert float(align_loss(student, teacher, k=2)) == pytest.approx(expected, rel=1e-5)
    assert float(align_loss(teacher, teacher, k=3)) == pytest.approx(0.0, abs=1e-7)


def test_weighted_l1_ipm_and_total_hand_values() -> None:
    pred = torch.tensor([[0.5, 1.0], [1.0, 0.25]])[..., None].expand(2, 2, 3)
    gt = torch.zeros(2, 2, 3)
    weights = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    assert float(weighted_l1(pred, gt, weights)) == pytest.approx(0.375)
    assert float(ipm_loss(pred, gt, 2 * weights)) == pytest.approx(0.375)
    total = total_loss(torch.tensor(1.0), torch.tensor(10.0), torch.tensor(2.0), torch.tensor(3.0))
    assert float(total) == pytest.approx(1.0 + 0.01 + 0.2 + 0.3)


def test_cam_loss_uses_back_projected_weights() -> None:
    rig = avm_rig(40, 30, bev_px=32)
    ipm = IPM(rig)
    weights = ipm.to_cameras(torch.ones(32, 32))
    gts = {c: torch.zeros(30, 40, 3) for c in rig.names}
    preds = {c: torch.full((30, 40, 3), 0.2 if c == "front" else 0.6) for c in rig.names}
    sums = {c: float(w.sum()) for c, w in weights.items()}
    expected = sum((0.2 if c == "front" else 0.6) * s for c, s in sums.items()) / sum(sums.values())
    assert float(cam_loss(preds, gts, weights)) == pytest.approx(expected, rel=1e-5)


def test_variants_switch_terms() -> None:
    assert not spec_of(Variant.DIRECT_IPM).uses_detector
    assert spec_of(Variant.FEATURE_ONLY).align and spec_of(Variant.FEATURE_ONLY).weights is None
    assert spec_of(Variant.TEACHER_ONLY).teacher_share == 1.0 and spec_of(Variant.STUDENT_ONLY).teacher_share == 0.0
    full = spec_of(Variant.FULL)
    assert full.align and full.ipm and full.cam and full.teacher_share is None


# --- the step on a tiny rig with random-init detectors ----------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_setup():
    rig = avm_rig(48, 36, bev_px=64)
    scene, _ = garage_scene("tiny", n=400)
    with torch.no_grad():
        from parksim.render import render
        gts = render(scene, rig, (2.5, 0.4, 0.6), backend="torch").images  # the "truth" seen from elsewhere
    return rig, scene, gts


def _detector(kind: type = DMPRDetector) -> DMPRDetector:
    """Random-init detector, fixed seed; variance-preserving conv init so its confidences depend on the input."""
    torch.manual_seed(0)
    detector = kind(width=0.25, input_size=128)
    for module in detector.modules():
        if isinstance(module, nn.Conv2d):
            nn.init.kaiming_normal_(module.weight, nonlinearity="leaky_relu")
    return detector


def _leaf_scene(scene):
    means = scene.means.clone().requires_grad_(True)
    sh = scene.sh.clone().requires_grad_(True)
    return type(scene)(means, scene.quats, scene.log_scales, scene.opacity_logits, sh, scene.sh_degree), means, sh


def _frame(gts, has_slots: bool = True) -> SlotFrame:
    return SlotFrame(gts, {c: torch.ones(img.shape[:2]) for c, img in gts.items()}, has_slots)


def test_align_gradient_reaches_gaussians_through_the_frozen_detector(tiny_setup) -> None:
    rig, scene, gts = tiny_setup
    detector = _detector()
    step = SlotAwareStep(rig, detector, SlotAwareConfig(variant=Variant.FEATURE_ONLY), backend="torch")
    leaf, means, sh = _leaf_scene(scene)
    terms = step(leaf, (1.0, 0.0, 0.0), _frame(gts))
    assert float(terms.align.detach()) > 1e-6
    terms.align.backward()
    assert means.grad is not None and float(means.grad.abs().sum()) > 0
    assert float(sh.grad.abs().sum()) > 0
    assert all(p.grad is None and not p.requires_grad for p in detector.parameters())


@pytest.mark.parametrize("variant", list(Variant))
def test_every_variant_gives_finite_terms(tiny_setup, variant: Variant) -> None:
    rig, scene, gts = tiny_setup
    detector = _detector(GCNDetector if variant == Variant.FULL else DMPRDetector)
    step = SlotAwareStep(rig, detector, SlotAwareConfig(variant=variant), backend="torch")
    leaf, means, _ = _leaf_scene(scene)
    terms = step(leaf, (1.0, 0.0, 0.0), _frame(gts))
    spec = spec_of(variant)
    record = terms.record()
    assert (record["ipm_loss"] > 0) == spec.ipm and (record["cam_loss"] > 0) == spec.cam
    assert spec.align or record["align_loss"] == 0.0
    assert not terms.skipped
    terms.total.backward()
    assert torch.isfinite(means.grad).all()


def test_slotless_frame_skips_detector_and_slot_terms(tiny_setup) -> None:
    rig, scene, gts = tiny_setup

    class Forbidden(DMPRDetector):
        def forward(self, bev):  # noqa: D401 - a detector that must not run
            raise AssertionError("the detector ran on a slot-less frame")

    step = SlotAwareStep(rig, Forbidden(0.25, 64), SlotAwareConfig(), backend="torch")
    leaf, means, _ = _leaf_scene(scene)
    terms = step(leaf, (1.0, 0.0, 0.0), _frame(gts, has_slots=False))
    record = terms.record()
    assert terms.skipped and record["align_loss"] == record["ipm_loss"] == record["cam_loss"] == 0.0
    assert record["loss"] == record["rgb_loss"]
    terms.total.backward()
    assert float(means.grad.abs().sum()) > 0


def test_detector_variants_need_a_detector() -> None:
    with pytest.raises(ValueError, match="needs a detector"):
        SlotAwareStep(avm_rig(48, 36, bev_px=64), None, SlotAwareConfig())
    SlotAwareStep(avm_rig(48, 36, bev_px=64), None, SlotAwareConfig(variant=Variant.DIRECT_IPM))


# --- the trainer hook ---------------------------------------------------------------------------------------------
def test_trainer_runs_photometric_then_slot_aware_iterations(tmp_path) -> None:
    import json

    from parksim.cli import main as cli_main
    from parksim.data import DatasetReader
    from parksim.recon.config import load_config
    from parksim.recon.trainer import METRICS_FILE, Trainer

    data = tmp_path / "tiny"
    assert cli_main(["synth", "tiny", "-o", str(data), "--frames", "4", "--resolution", "96x72", "--bev-px", "96",
                     "--points", "400", "--quiet"]) == 0
    base = load_config("tiny")
    config = base.model_copy(update={
        "photometric": base.photometric.model_copy(update={"iterations": 2}),
        "slot_aware": SlotAwareConfig(iterations=2),
        "run": base.run.model_copy(update={"log_every": 1})})
    trainer = Trainer(DatasetReader(data), config, tmp_path / "run", log=lambda s: None, detector=_detector())
    (tmp_path / "run").mkdir()
    trainer.initialise()
    trainer.train()
    assert trainer.step == trainer.total_iterations == 4
    records = [json.loads(line) for line in (tmp_path / "run" / METRICS_FILE).read_text().splitlines()]
    assert [("ipm_loss" in r) for r in records] == [False, False, True, True]
    assert all(math.isfinite(r["loss"]) and r["ipm_loss"] > 0 and r["cam_loss"] > 0 for r in records[2:])


def test_trainer_without_a_detector_keeps_the_photometric_phase(tiny_data, tmp_path) -> None:
    from parksim.data import DatasetReader
    from parksim.recon.config import TrainConfig
    from parksim.recon.trainer import Trainer

    notes: list[str] = []
    trainer = Trainer(DatasetReader(tiny_data), TrainConfig(), tmp_path, log=notes.append)
    assert trainer.slot_step is None and trainer.total_iterations == 20_000
    assert notes == ["slot-aware phase off: slot_aware.detector is not set"]
