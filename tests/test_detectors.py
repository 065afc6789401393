"""Slot detectors: decoding, slot inference, metrics on hand-made labels, gradients, label validation, augmentation."""

from __future__ import annotations

import ast
import graphlib
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import parksim.recon.detectors
from parksim.recon.detectors import (
    DecodeOptions,
    Detections,
    DMPRDetector,
    GCNDetector,
    LabelError,
    MarkingPoint,
    PointMaps,
    Slot,
    SlotLabels,
    load_detector,
    read_ps2_labels,
)
from parksim.recon.detectors.dataset import hflip, photometric, rotate
from parksim.recon.detectors.decode import decode_points, infer_slots
from parksim.recon.detectors.evaluate import MatchOptions, average_precision, match_points, match_slots, summarize
from parksim.recon.detectors.targets import point_targets

M_PER_PX = 10.0 / 600
UP = -math.pi / 2  # direction pointing up in the image


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def _maps(cells: dict[tuple[int, int], tuple[float, float, float, float]], grid: int = 8) -> PointMaps:
    """Point maps with the given cells set to (confidence, offset x, offset y, direction) and everything else off."""
    logits = torch.full((1, 6, grid, grid), -10.0)
    for (r, c), (conf, ox, oy, d) in cells.items():
        logits[0, :, r, c] = torch.tensor([_logit(conf), -5.0, _logit(ox), _logit(oy),
                                           math.atanh(0.9 * math.cos(d)), math.atanh(0.9 * math.sin(d))])
    return PointMaps(logits)


def test_decode_points_threshold_margin_nms():
    # 8x8 grid over a 600 px BEV: cell (2, 3) at offset (0.9, 0.5) -> x = 3.9 / 8 * 600 - 0.5
    maps = _maps({(2, 3): (0.9, 0.9, 0.5, UP), (2, 4): (0.8, 0.1, 0.5, 0.0),  # 0.2 cell apart: NMS drops the weaker
                  (5, 5): (0.3, 0.5, 0.5, 0.0),                                 # below threshold
                  (7, 7): (0.95, 0.99, 0.5, 0.0)})                              # inside the border margin
    points = decode_points(maps, 0, 600, 600, DecodeOptions(threshold=0.5, margin=0.01))
    assert len(points) == 1
    p = points[0]
    assert p.x == pytest.approx(3.9 / 8 * 600 - 0.5, abs=1e-3) and p.y == pytest.approx(2.5 / 8 * 600 - 0.5, abs=1e-3)
    assert p.direction == pytest.approx(UP, abs=1e-4) and p.shape == "T" and p.score == pytest.approx(0.9, abs=1e-4)


def _row(xs: list[float], y: float = 300.0, direction: float = UP, shapes: str = "") -> list[MarkingPoint]:
    shapes = shapes or "T" * len(xs)
    return [MarkingPoint(x, y, direction, s, 0.9) for x, s in zip(xs, shapes)]


def test_infer_slots_pairs_neighbours_in_order_only():
    # A row of points 2.5 m apart, separators pointing up: slots lie right of p1 -> p2 (viewed, v down) = up,
    # so p1 is the right-hand point. The 0-2 pair (5 m) is not a parallel slot: point 1 lies on its entrance.
    points = _row([150.0, 300.0, 450.0])
    slots = infer_slots(points, M_PER_PX, DecodeOptions())
    assert sorted((s.p1, s.p2) for s in slots) == [(1, 0), (2, 1)]
    assert all(s.angle == pytest.approx(90.0) for s in slots)


def test_infer_slots_rejects_wrong_direction_and_length():
    down = _row([150.0, 300.0], direction=-UP)                  # separators pointing down: slots right of 0 -> 1
    assert [(s.p1, s.p2) for s in infer_slots(down, M_PER_PX, DecodeOptions())] == [(0, 1)]
    crossed = [MarkingPoint(150.0, 300.0, UP, "T", 0.9), MarkingPoint(300.0, 300.0, -UP, "T", 0.9)]
    assert infer_slots(crossed, M_PER_PX, DecodeOptions()) == []  # directions disagree
    far = _row([100.0, 370.0])                                  # 4.5 m: between the short and the long window
    assert infer_slots(far, M_PER_PX, DecodeOptions()) == []
    parallel = _row([100.0, 460.0])                             # 6 m: a parallel slot
    assert [(s.p1, s.p2) for s in infer_slots(parallel, M_PER_PX, DecodeOptions())] == [(1, 0)]


def test_slanted_slot_width_is_measured_across_the_separators():
    # Separators at 60 deg to the entrance 1 -> 0: a 2.6 m wide slot has a 3.0 m entrance; two slanted bays leave
    # 3.7 m of floor between their end points (3.2 m across the separators), which is no slot.
    lean = math.atan2(-math.sin(math.radians(60)), -math.cos(math.radians(60)))
    slot = _row([100.0, 100.0 + 3.0 / M_PER_PX], direction=lean)
    assert [(s.p1, s.p2, round(s.angle)) for s in infer_slots(slot, M_PER_PX, DecodeOptions())] == [(1, 0, 60)]
    assert infer_slots(_row([100.0, 100.0 + 3.7 / M_PER_PX], direction=lean), M_PER_PX, DecodeOptions()) == []


def test_l_point_bounds_one_slot():
    points = _row([150.0, 300.0, 450.0], shapes="TLT")
    assert len(infer_slots(points, M_PER_PX, DecodeOptions())) == 1


def _labels() -> SlotLabels:
    marks = np.array([[150.0, 300.0, UP, 0.0], [300.0, 300.0, UP, 0.0], [450.0, 300.0, UP, 1.0]])
    return SlotLabels(marks, np.array([[1, 0], [2, 1]]), np.array([90.0, 90.0]), 600, 600, M_PER_PX)


def test_point_metrics_threshold_and_direction():
    labels = _labels()
    det = Detections([MarkingPoint(159.9, 300.0, UP, "T", 0.9),               # 9.9 px: match
                      MarkingPoint(310.1, 300.0, UP, "T", 0.8),               # 10.1 px: off by threshold
                      MarkingPoint(450.0, 300.0, UP + math.radians(31), "L", 0.7)])  # direction 31 deg off
    assert match_points(det, labels, MatchOptions()) == [True, False, False]
    assert match_points(det, labels, MatchOptions(distance_px=11.0, direction_deg=32.0)) == [True, True, True]
    # On a BEV at 2x DMPR-PS' resolution the same 10 px tolerance is 20 of its pixels.
    fine = SlotLabels(labels.marks, labels.slots, labels.slot_angles, 1200, 1200, M_PER_PX / 2)
    assert match_points(det, fine, MatchOptions()) == [True, True, False]
    m = summarize([True, False, False], [0.9, 0.8, 0.7], [True, False, False], 3)
    assert (m.precision, m.recall, m.tp, m.fp) == (pytest.approx(1 / 3), pytest.approx(1 / 3), 1, 2)


def test_slot_metrics_swapped_and_angle():
    labels = _labels()
    points = [MarkingPoint(x, 300.0, UP, "T", 0.9) for x in (150.0, 300.0, 450.0)]
    det = Detections(points, [Slot(1, 0, 0.9, 90.0), Slot(1, 2, 0.8, 90.0)])  # second one swapped
    assert match_slots(det, labels, MatchOptions()) == [True, False]
    bent = Detections(points, [Slot(2, 1, 0.9, 75.0)])                     # angle 15 deg off
    assert match_slots(bent, labels, MatchOptions()) == [False]
    assert match_slots(bent, labels, MatchOptions(slot_angle_deg=20.0)) == [True]


def test_average_precision_known_curve():
    # ranked TP, FP, TP with 2 labelled: precision 1 at recall 0.5, 2/3 at recall 1 -> AP = 0.5 + 0.5 * 2/3
    assert average_precision([0.9, 0.8, 0.7], [True, False, True], 2) == pytest.approx(0.5 + 1 / 3)
    assert average_precision([], [], 2) == 0.0


def test_confidence_map_has_gradient_wrt_input():
    torch.manual_seed(0)
    model = DMPRDetector(width=0.125, input_size=64).eval()
    bev = torch.rand(1, 3, 90, 90, requires_grad=True)
    conf = model.confidence(bev)
    assert conf.shape == (1, 1, 2, 2)
    conf.sum().backward()
    assert bev.grad is not None and torch.isfinite(bev.grad).all() and bev.grad.abs().sum() > 0


def test_gcn_edge_scores_have_gradient_and_checkpoint_roundtrip(tmp_path):
    torch.manual_seed(0)
    model = GCNDetector(width=0.125, input_size=64, descriptor_dim=16, graph_layers=1, heads=2).eval()
    bev = torch.rand(1, 3, 64, 64, requires_grad=True)
    (locations, scores), = model.edges(bev, DecodeOptions(threshold=0.0, margin=0.0))
    assert locations.shape == (scores.shape[0], 2) and scores.shape[0] >= 2
    scores.sum().backward()
    assert bev.grad.abs().sum() > 0
    model.save(tmp_path / "model.pt")
    loaded = load_detector(tmp_path)
    x = torch.rand(1, 3, 64, 64)
    assert torch.equal(loaded.confidence(x), model.confidence(x))


def test_point_targets_cell_and_offset():
    t = point_targets(np.array([[100.0, 40.0, 0.0, 1.0]]), 256, 8)  # 32 px cells
    assert t[0].sum() == 1 and t[0, 1, 3] == 1 and t[1, 1, 3] == 1
    assert t[2, 1, 3] == pytest.approx(100.5 / 32 - 3) and t[3, 1, 3] == pytest.approx(40.5 / 32 - 1)


def test_rotation_and_mirror_move_labels_with_the_image():
    image = np.zeros((101, 101, 3), np.uint8)
    image[20, 70] = 255
    labels = SlotLabels(np.array([[70.0, 20.0, 0.0, 0.0], [30.0, 20.0, 0.0, 0.0]]), np.array([[0, 1]]),
                        np.array([60.0]), 101, 101, 0.1)
    rot, rl = rotate(image, labels, 90.0)  # counter-clockwise as viewed
    assert rl.marks[0, :2] == pytest.approx([20.0, 30.0], abs=1e-6)
    assert rl.marks[0, 2] == pytest.approx(-math.pi / 2, abs=1e-6)
    assert np.unravel_index(rot[..., 0].argmax(), rot.shape[:2]) == (30, 20)
    flipped, fl = hflip(image, labels)
    assert fl.marks[0, :2] == pytest.approx([30.0, 20.0]) and fl.marks[0, 2] == pytest.approx(math.pi)
    assert fl.slots.tolist() == [[1, 0]] and fl.slot_angles[0] == pytest.approx(120.0)
    assert flipped[20, 30, 0] == 255


def test_photometric_augmentation_is_seeded_and_in_range():
    image = np.full((32, 32, 3), 128, np.uint8)
    image[8:16] = 250
    a, b = (photometric(image, np.random.default_rng(1)) for _ in range(2))
    assert a.dtype == np.float32 and a.shape == image.shape and np.array_equal(a, b)
    assert a.min() >= 0.0 and a.max() <= 1.0 and np.abs(a - image / 255.0).mean() > 0.01
    assert a[8:16].mean() > a[16:].mean() + 0.2  # the bright band stays bright


def _write(tmp_path, data) -> str:
    path = tmp_path / "img.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def test_ps2_labels_good_file(tmp_path):
    path = _write(tmp_path, {"marks": [[101, 201, 101, 251, 0], [251, 201, 251, 251, 1]], "slots": [[1, 2, 1, 90]]})
    labels = read_ps2_labels(path)
    assert labels.marks[0, :2].tolist() == [100.0, 200.0]
    assert labels.marks[0, 2] == pytest.approx(math.pi / 2) and labels.marks[1, 3] == 1.0
    assert labels.slots.tolist() == [[0, 1]] and labels.m_per_px == pytest.approx(10 / 600)
    single = read_ps2_labels(_write(tmp_path, {"marks": [101, 201, 101, 251, 0], "slots": []}))
    assert len(single.marks) == 1 and len(single.slots) == 0


@pytest.mark.parametrize("data, message", [
    ("{not json", "not valid JSON"),
    ({"slots": []}, "missing 'marks'"),
    ({"marks": [[900, 10, 900, 20, 0]], "slots": []}, "outside the 600x600"),
    ({"marks": [[10, 10, 10, 20, 2]], "slots": []}, "expected 0 (T) or 1 (L)"),
    ({"marks": [[10, 10, 10, 10, 0]], "slots": []}, "no direction"),
    ({"marks": [[10, 10, 10, 20, 0], [200, 10, 200, 20, 0]], "slots": [[1, 3, 1, 90]]}, "marks are numbered 1..2"),
    ({"marks": [[10, 10, 10, 20, 0], [200, 10, 200, 20, 0]], "slots": [[1, 2, 1, 270]]}, "angle 270"),
    ({"marks": [[10, 10, "x", 20, 0]], "slots": []}, "list of number rows"),
    ({"marks": [[10, 10, 20]], "slots": []}, "at least 5 numbers"),
])
def test_ps2_labels_bad_values_give_clear_errors(tmp_path, data, message):
    path = _write(tmp_path, data)
    with pytest.raises(LabelError, match=re.escape(path) + ".*" + re.escape(message)):
        read_ps2_labels(path)


def test_parksim_slot_angle_must_agree_with_its_points():
    # Entrance 1 -> 0 runs left, separators lean up-right: the slot angle is 135 deg, not the slant's 45.
    marks = [{"x": x, "y": 300.0, "direction": -math.pi / 4, "shape": "T"} for x in (150.0, 300.0)]

    def labels(angle: float | None) -> SlotLabels:
        slot = {"p1": 1, "p2": 0} if angle is None else {"p1": 1, "p2": 0, "angle": angle}
        return SlotLabels.from_parksim({"marks": marks, "slots": [slot]}, 600, 600, M_PER_PX, "f/000001.json")

    assert labels(135.0).slot_angles[0] == 135.0 and labels(None).slot_angles[0] == pytest.approx(135.0)
    with pytest.raises(LabelError, match=r"f/000001.json: slot 0 has angle 45 deg but .* make 135 deg"):
        labels(45.0)


def test_gcn_graph_without_nodes_stays_finite():
    torch.manual_seed(0)
    model = GCNDetector(width=0.125, input_size=64, descriptor_dim=16, graph_layers=1, heads=2)
    _, descriptors = model.run(torch.rand(2, 3, 64, 64))
    mask = torch.tensor([[True, True, False], [False, False, False]])
    assert torch.isfinite(model.edge_logits(descriptors, torch.rand(2, 3, 5), mask)).all()


def test_ps2_folder_feeds_training_batches(tmp_path):
    import cv2

    from parksim.recon.detectors.dataset import TrainingSet, iter_items

    cv2.imwrite(str(tmp_path / "a.png"), np.full((600, 600, 3), 90, np.uint8))
    _write(tmp_path, {"marks": [[101, 201, 101, 251, 0], [251, 201, 251, 251, 1]], "slots": [[1, 2, 1, 90]]})
    (tmp_path / "img.json").rename(tmp_path / "a.json")
    item, = iter_items(tmp_path)
    assert item.image.shape == (600, 600, 3) and item.labels.slots.tolist() == [[0, 1]]
    batch = TrainingSet([tmp_path], 64).batch(2, np.random.default_rng(0), 2)
    assert batch["images"].shape == (2, 3, 64, 64) and batch["points"].shape == (2, 6, 2, 2)
    (tmp_path / "a.png").unlink()
    with pytest.raises(FileNotFoundError, match="no image a.jpg or .png"):
        list(iter_items(tmp_path))


def _sibling_imports(path: Path) -> set[str]:
    """Modules of ``parksim.recon.detectors`` that ``path`` imports anywhere in it, inside functions too."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            names |= {node.module.split(".")[0]} if node.module else {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("parksim.recon.detectors."):
            names.add(node.module.split(".")[3])
        elif isinstance(node, ast.Import):
            names |= {a.name.split(".")[3] for a in node.names if a.name.startswith("parksim.recon.detectors.")}
    return names


def test_detector_modules_import_no_cycle():
    """dmpr.load_detector imported gcn (inside the function) while gcn imports dmpr: a cycle hidden until called."""
    package = Path(parksim.recon.detectors.__file__).parent
    graph = {f.stem: _sibling_imports(f) for f in package.glob("*.py") if f.stem != "__init__"}
    assert "base" in graph["gcn"]   # the parser sees the imports
    try:
        list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as e:
        pytest.fail(f"import cycle in parksim.recon.detectors: {' -> '.join(e.args[1])}")


@pytest.mark.parametrize("module", ["dmpr", "gcn", "registry"])
def test_detector_module_imports_alone_in_a_fresh_interpreter(module):
    code = f"import parksim.recon.detectors.{module} as m; print(sorted(m.__all__))"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0, run.stderr


def test_training_device_is_checked_before_training() -> None:
    """A device other than cpu / cuda[:N] fails at once with its name; the default trains on the CPU."""
    import pytest

    from parksim.recon.detectors.train import TrainOptions

    assert TrainOptions().device == "cpu" and TrainOptions(device="cuda:1").device == "cuda:1"
    with pytest.raises(ValueError, match="'tpu'"):
        TrainOptions(device="tpu")
