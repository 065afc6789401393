"""The two detection scoring protocols on hand-made cases whose DMPR-PS results follow from DMPR-PS' own rules
(``config.py``, ``data/struct.py``, ``util/precision_recall.py``), and ps2.0 ``.mat`` labels.

All cases use a 600x600 BEV of 10 m (DMPR-PS' scale), where ParkSim's 10 px and DMPR-PS' squared image fraction
0.000277778 are the same 10 px tolerance.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import scipy.io
import torch

from parksim.recon.detectors import (
    DecodeOptions,
    Detections,
    LabelError,
    MarkingPoint,
    Slot,
    SlotLabels,
    read_ps2_labels,
)
from parksim.recon.detectors.backbone import PointMaps
from parksim.recon.detectors.decode import decode_points
from parksim.recon.detectors.evaluate import Evaluator, Metrics
from parksim.recon.detectors.protocols import DMPRPSProtocol, MatchOptions, ParkSimProtocol, Protocol, get_protocol
from parksim.recon.paper_tables import tables_markdown

M_PER_PX = 10.0 / 600
PARKSIM, DMPR = ParkSimProtocol(), DMPRPSProtocol()


def _labels(marks: list[tuple[float, float, float, float]], slots: tuple[tuple[int, int], ...] | list = (),
            angles: tuple[float, ...] | list = ()) -> SlotLabels:
    return SlotLabels(np.array(marks, dtype=np.float64).reshape(-1, 4), np.array(slots, dtype=np.int64).reshape(-1, 2),
                      np.array(angles, dtype=np.float64), 600, 600, M_PER_PX)


def _score(protocol: Protocol, det: Detections, labels: SlotLabels, sweep: Detections | None = None) -> dict:
    ev = Evaluator(protocol)
    ev.add(det, det if sweep is None else sweep, labels)
    return ev.result()


def _counts(m: Metrics) -> tuple[int, int, int]:
    return m.tp, m.fp, m.labelled


def test_shape_mismatch_rejected_by_dmpr_ps_only():
    """A T label and an L detection at the same place and direction.

    DMPR-PS' ``match_marking_points`` returns False when one shape is > 0.5 and the other < 0.5 (T = 0, L = 1),
    before looking at distance: the label is missed and the detection is a false positive (TP 0, FP 1). ParkSim
    ignores the shape: TP 1, FP 0.
    """
    labels = _labels([(300.0, 300.0, 0.0, 0.0)])
    det = Detections([MarkingPoint(300.0, 300.0, 0.0, "L", 0.9)])
    assert _counts(_score(PARKSIM, det, labels)["points"]) == (1, 0, 1)
    assert _counts(_score(DMPR, det, labels)["points"]) == (0, 1, 1)
    same = Detections([MarkingPoint(300.0, 300.0, 0.0, "T", 0.9)])
    assert _counts(_score(DMPR, same, labels)["points"]) == (1, 0, 1)


def test_label_first_most_confident_vs_detection_first_first_free():
    """Labels A (100, 100) then B (108, 100); detection d1 (104, 100) at 0.9 is 4 px from both, d2 (96, 100) at 0.8
    is 4 px from A and 12 px from B (all directions 0, shapes T).

    ParkSim, detection-first: d1 takes the first free label it matches, A; d2 then finds A taken and B too far:
    TP 1, FP 1, precision 1/2, recall 1/2. DMPR-PS, label-first (``match_gt_with_preds``): A takes its most
    confident matching prediction d1, B also takes d1 (a prediction may serve several labels); d2 serves no label:
    TP 2, FP 1, precision 2/3, recall 1.
    """
    labels = _labels([(100.0, 100.0, 0.0, 0.0), (108.0, 100.0, 0.0, 0.0)])
    det = Detections([MarkingPoint(104.0, 100.0, 0.0, "T", 0.9), MarkingPoint(96.0, 100.0, 0.0, "T", 0.8)])
    parksim, dmpr = _score(PARKSIM, det, labels)["points"], _score(DMPR, det, labels)["points"]
    assert _counts(parksim) == (1, 1, 2) and (parksim.precision, parksim.recall) == (0.5, 0.5)
    assert _counts(dmpr) == (2, 1, 2) and (dmpr.precision, dmpr.recall) == (2 / 3, 1.0)


def _border_maps(offset_x: float) -> PointMaps:
    """A 16x16 grid (DMPR-PS' feature map) with one confident T point in cell (8, 0) at ``offset_x``, direction 0."""
    logits = torch.full((1, 6, 16, 16), -10.0)
    logits[0, :, 8, 0] = torch.tensor([5.0, -5.0, math.log(offset_x / (1 - offset_x)), 0.0, 5.0, 0.0])
    return PointMaps(logits)


def test_border_prediction_between_1_and_5_percent():
    """A prediction at u = 0.48 / 16 = 0.03 of the width (v = 8.5 / 16): DMPR-PS' ``get_predicted_points`` keeps
    only ``BOUNDARY_THRESH <= u <= 1 - BOUNDARY_THRESH`` with 0.05, so it is dropped and its label (at the same
    place) is missed: TP 0, FP 0, recall 0. ParkSim's 1 % margin keeps it: TP 1."""
    maps = _border_maps(0.48)
    u, v = 0.48 / 16 * 600 - 0.5, 8.5 / 16 * 600 - 0.5
    labels = _labels([(u, v, 0.0, 0.0)])
    results = {}
    for protocol in (PARKSIM, DMPR):
        det = Detections(decode_points(maps, 0, 600, 600, protocol.decode_options(DecodeOptions())))
        results[protocol.name] = _score(protocol, det, labels)["points"]
    assert _counts(results["parksim"]) == (1, 0, 1)
    assert _counts(results["dmpr-ps"]) == (0, 0, 1) and results["dmpr-ps"].recall == 0.0
    assert DMPR.sweep_options(DecodeOptions()).threshold == 0.01
    assert PARKSIM.sweep_options(DecodeOptions()).margin == 0.01


def _maps(cells: list[tuple[int, int, float, float]]) -> PointMaps:
    """A 16x16 grid with a T point of direction 0 per ``(row, col, offset_x, confidence)``, offset_y 0.5."""
    logits = torch.full((1, 6, 16, 16), -10.0)
    for row, col, offset_x, confidence in cells:
        logits[0, :, row, col] = torch.tensor([math.log(confidence / (1 - confidence)), -5.0,
                                               math.log(offset_x / (1 - offset_x)), 0.0, 5.0, 0.0])
    return PointMaps(logits)


def _decode_and_score(protocol: Protocol, maps: PointMaps, labels: SlotLabels, decode: DecodeOptions) -> Metrics:
    """Decode at the operating point and for the sweep as ``evaluate_folder`` does, and score the points."""
    det = Detections(decode_points(maps, 0, 600, 600, protocol.decode_options(decode)))
    sweep = Detections(decode_points(maps, 0, 600, 600, protocol.sweep_options(decode)))
    return _score(protocol, det, labels, sweep)["points"]


def test_dmpr_nms_lets_a_suppressed_point_suppress():
    """Three points in a row 30 px apart (u = 0.30, 0.35, 0.40 of 600 px), A 0.9, B 0.5, C 0.3, each labelled;
    NMS suppresses within 1/16 = 37.5 px on both axes, so A-B and B-C are close, A-C (60 px) not.

    ParkSim's greedy NMS: A is kept, B is suppressed by A, C is close only to the suppressed B and is kept: A and C.
    Scored by ParkSim: TP 2 of 3 labels, recall 2/3; ranked A, C both TP at recall 1/3, 2/3 with precision 1:
    all-point AP 1/3 + 1/3 = 2/3. DMPR-PS' ``non_maximum_suppression`` compares every pair: A suppresses B and B,
    though suppressed, suppresses C: A alone. Scored by DMPR-PS: recall 1/3; TP confidences [0, 0, 0.9] -> curve
    recall 1/3 at precision 1, then the missed labels' 0 adds recall 1, precision 0; 11-point AP: recall 0 .. 0.3
    (4 points) -> 1, 0.4 .. 1 -> 0: 4/11 = 0.364. (DMPR-PS' scoring of the greedy A, C, the old ``dmpr-ps``:
    recall 2/3, curve 1/3 and 2/3 at precision 1, 11-point 0 .. 0.6 (7 points) -> 1: 7/11 = 0.636.)
    """
    maps = _maps([(8, 4, 0.8, 0.9), (8, 5, 0.6, 0.5), (8, 6, 0.4, 0.3)])
    y = 8.5 / 16 * 600 - 0.5
    labels = _labels([(u * 600 - 0.5, y, 0.0, 0.0) for u in (0.30, 0.35, 0.40)])
    decode = DecodeOptions(threshold=0.1)
    greedy = decode_points(maps, 0, 600, 600, PARKSIM.decode_options(decode))
    assert [round(p.score, 3) for p in greedy] == [0.9, 0.3]
    assert [round(p.score, 3) for p in decode_points(maps, 0, 600, 600, DMPR.decode_options(decode))] == [0.9]
    parksim, dmpr = _decode_and_score(PARKSIM, maps, labels, decode), _decode_and_score(DMPR, maps, labels, decode)
    assert _counts(parksim) == (2, 0, 3) and parksim.recall == pytest.approx(2 / 3)
    assert parksim.ap == pytest.approx(2 / 3)
    assert _counts(dmpr) == (1, 0, 3) and dmpr.recall == pytest.approx(1 / 3) and dmpr.ap == pytest.approx(4 / 11)
    old = _score(DMPR, Detections(greedy), labels)["points"]
    assert old.recall == pytest.approx(2 / 3) and old.ap == pytest.approx(7 / 11)


def test_dmpr_border_test_in_float32():
    """A point in the last column whose offset is float32(0.2): DMPR-PS (under NumPy 2) computes (15 + offset) / 16
    in float32, which rounds to float32(0.95), and compares it with 1 - 0.05 taken to float32 as well: on the
    border, kept (its label found, recall 1). In float64 the same position is 0.95000000019 > 0.95: dropped."""
    maps = _maps([(8, 15, 0.2, 0.9)])
    offset = float(maps.offset[0, 0, 8, 15])
    assert (np.float32(15) + np.float32(offset)) / np.float32(16) == np.float32(0.95)
    assert (15 + offset) / 16 > 0.95
    assert decode_points(maps, 0, 600, 600, DecodeOptions(margin=0.05)) == []
    labels = _labels([(float(np.float32(0.95)) * 600 - 0.5, 8.5 / 16 * 600 - 0.5, 0.0, 0.0)])
    dmpr = _decode_and_score(DMPR, maps, labels, DecodeOptions())
    assert _counts(dmpr) == (1, 0, 1) and dmpr.recall == 1.0


def test_eleven_point_voc_ap_differs_from_all_point():
    """Two labels far apart; sweep detections d1 on label 0 (0.9), d2 on nothing (0.8), d3 on label 1 (0.7).

    All-point (ParkSim): ranked TP, FP, TP -> precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1; made monotone
    1, 2/3, 2/3; area 1/2 * 1 + 1/2 * 2/3 = 5/6.
    DMPR-PS (``calc_precision_recall``): TP confidences [0.7, 0.9], FP [0.8]; thresholds 0.9 -> recall 1/2,
    precision 1; 0.7 -> recall 1, precision 2/3; curve recall [0, 1/2, 1], precision [0, 1, 2/3]. 11-point AP:
    recall >= 0, 0.1 .. 0.5 (6 points) -> max precision from there on 1; 0.6 .. 1.0 (5 points) -> 2/3;
    (6 + 5 * 2/3) / 11 = 28/33.
    """
    labels = _labels([(100.0, 100.0, 0.0, 0.0), (400.0, 400.0, 0.0, 0.0)])
    sweep = Detections([MarkingPoint(100.0, 100.0, 0.0, "T", 0.9), MarkingPoint(250.0, 250.0, 0.0, "T", 0.8),
                        MarkingPoint(400.0, 400.0, 0.0, "T", 0.7)])
    parksim = _score(PARKSIM, sweep, labels)["points"].ap
    dmpr = _score(DMPR, sweep, labels)["points"].ap
    assert abs(parksim - 5 / 6) <= 4 * np.spacing(5 / 6)
    assert abs(dmpr - 28 / 33) <= 4 * np.spacing(28 / 33)


def test_missed_label_enters_dmpr_curve_at_recall_one_precision_zero():
    """One of two labels found (0.9), one FP (0.5): TP confidences [0, 0.9], FP [0.5]. Thresholds 0.9 -> recall
    1/2, precision 1; then 0 -> DMPR-PS appends recall 1, precision 0 and stops. 11-point: recall >= 0 .. 0.5
    (6 points) -> 1; 0.6 .. 1 -> 0; AP 6/11."""
    labels = _labels([(100.0, 100.0, 0.0, 0.0), (400.0, 400.0, 0.0, 0.0)])
    sweep = Detections([MarkingPoint(100.0, 100.0, 0.0, "T", 0.9), MarkingPoint(250.0, 250.0, 0.0, "T", 0.5)])
    assert abs(_score(DMPR, sweep, labels)["points"].ap - 6 / 11) <= 4 * np.spacing(6 / 11)


def test_slot_angle_check_only_in_parksim():
    """A slot whose entrance points sit exactly on the labelled ones (angle 90) but whose decoded angle is 105:
    ParkSim's 10 deg slot-angle check rejects it (TP 0, FP 1); DMPR-PS' ``match_slots`` compares the two ordered
    entrance points only (TP 1). DMPR-PS scores the slot by its weaker point (0.6), and its slot AP comes from the
    operating detections: one TP at 0.6 -> recall 1, precision 1 -> AP 1."""
    labels = _labels([(150.0, 300.0, -math.pi / 2, 0.0), (300.0, 300.0, -math.pi / 2, 0.0)], [(1, 0)], [90.0])
    points = [MarkingPoint(150.0, 300.0, -math.pi / 2, "T", 0.9), MarkingPoint(300.0, 300.0, -math.pi / 2, "T", 0.6)]
    det = Detections(points, [Slot(1, 0, 0.8, 105.0)])
    assert _counts(_score(PARKSIM, det, labels)["slots"]) == (0, 1, 1)
    dmpr = _score(DMPR, det, labels, sweep=Detections(points))["slots"]
    assert _counts(dmpr) == (1, 0, 1) and dmpr.ap == 1.0
    assert _counts(_score(ParkSimProtocol(MatchOptions(slot_angle_deg=20.0)), det, labels)["slots"]) == (1, 0, 1)


def test_protocol_by_name_and_dmpr_thresholds_fixed():
    assert get_protocol("parksim", MatchOptions(distance_px=5.0)) == ParkSimProtocol(MatchOptions(distance_px=5.0))
    assert get_protocol("dmpr-ps") == DMPR
    with pytest.raises(ValueError, match="fixed thresholds"):
        get_protocol("dmpr-ps", MatchOptions(distance_px=5.0))
    with pytest.raises(ValueError, match="unknown protocol 'voc'"):
        get_protocol("voc")


def test_tables_name_their_protocol():
    scores = {"points": vars(Metrics(1.0, 1.0, 1.0, 1, 0, 1)), "slots": vars(Metrics(1.0, 1.0, 1.0, 1, 0, 1))}
    result = {"scene": "s1", "test_frames": [0], "runs": [], "gt": {"dmpr": scores}, "protocol": DMPR.describe()}
    text = tables_markdown([result])
    assert text.count("Detection scored with the dmpr-ps protocol") == 2   # detection and ablation tables
    assert DMPR.describe()["name"] == "dmpr-ps" and PARKSIM.describe()["slot_angle_deg"] == 10.0


PS2 = {"marks": [[101.0, 201.0, 101.0, 251.0, 0.0], [251.0, 201.0, 251.0, 251.0, 1.0]],
       "slots": [[1.0, 2.0, 1.0, 90.0]]}


def _same(a: SlotLabels, b: SlotLabels) -> bool:
    return (np.array_equal(a.marks, b.marks, equal_nan=True) and np.array_equal(a.slots, b.slots)
            and np.array_equal(a.slot_angles, b.slot_angles) and (a.width, a.height, a.m_per_px)
            == (b.width, b.height, b.m_per_px))


def test_mat_labels_read_like_json(tmp_path):
    """ps2.0's ``.mat`` layout (``marks`` N x 5 or N x 2, ``slots`` M x 4, 1-based) as MATLAB's ``save`` writes it,
    here through ``scipy.io.savemat``, reads to the same labels as the JSON form (a single row and an empty
    slot table included)."""
    for name, data in (("two", PS2), ("one", {"marks": [PS2["marks"][0]], "slots": np.zeros((0, 0))}),
                       ("original", {"marks": [[101.0, 201.0], [251.0, 201.0]], "slots": PS2["slots"]})):
        scipy.io.savemat(tmp_path / f"{name}.mat", {k: np.asarray(v, dtype=np.float64) for k, v in data.items()})
        as_json = {k: np.asarray(v).tolist() for k, v in data.items()}
        (tmp_path / f"{name}.json").write_text(json.dumps(as_json))
        mat, js = read_ps2_labels(tmp_path / f"{name}.mat"), read_ps2_labels(tmp_path / f"{name}.json")
        assert _same(mat, js), name
    two = read_ps2_labels(tmp_path / "two.mat")
    assert two.marks[:, :2].tolist() == [[100.0, 200.0], [250.0, 200.0]] and two.slots.tolist() == [[0, 1]]
    assert two.directional and two.marks[1, 3] == 1.0
    original = read_ps2_labels(tmp_path / "original.mat")
    assert not original.directional and original.slot_angles.tolist() == [90.0]


def test_original_ps2_labels_give_slot_scores_only(tmp_path):
    """Position-only labels (ps2.0's originals) cannot score marking points: the evaluator counts their slots and
    leaves their points out (0 labelled), under either protocol."""
    scipy.io.savemat(tmp_path / "o.mat", {"marks": np.array([[151.0, 301.0], [301.0, 301.0]]),
                                          "slots": np.array([[2.0, 1.0, 1.0, 90.0]])})
    labels = read_ps2_labels(tmp_path / "o.mat")
    det = Detections([MarkingPoint(150.0, 300.0, -math.pi / 2, "T", 0.9),
                      MarkingPoint(300.0, 300.0, -math.pi / 2, "T", 0.9)], [Slot(1, 0, 0.9, 90.0)])
    for protocol in (PARKSIM, DMPR):
        result = _score(protocol, det, labels)
        assert _counts(result["points"]) == (0, 0, 0) and _counts(result["slots"]) == (1, 0, 1)


@pytest.mark.parametrize("content, message", [(b"MATLAB 5.0 MAT-file garbage", "not a readable MATLAB file"),
                                              (None, "missing 'slots'")])
def test_bad_mat_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "bad.mat"
    if content is None:
        scipy.io.savemat(path, {"marks": np.array(PS2["marks"])})
    else:
        path.write_bytes(content)
    with pytest.raises(LabelError, match=f"bad.mat: .*{message}"):
        read_ps2_labels(path)



def test_ps2_folder_of_mat_labels_is_read_and_plain_labels_cannot_train(tmp_path):
    """A ps2.0 folder whose labels are .mat files yields its items; the original position-only labels are refused
    for training (a detector learns directions and shapes from them) with a line naming the item."""
    import cv2

    from parksim.recon.detectors.dataset import TrainingSet, iter_items

    cv2.imwrite(str(tmp_path / "a.jpg"), np.full((600, 600, 3), 90, np.uint8))
    scipy.io.savemat(tmp_path / "a.mat", {"marks": np.array([[151.0, 301.0], [301.0, 301.0]]),
                                          "slots": np.array([[2.0, 1.0, 1.0, 90.0]])})
    items = list(iter_items(tmp_path))
    assert [i.name for i in items] == [f"{tmp_path.name}/a"] and len(items[0].labels.marks) == 2
    with pytest.raises(ValueError, match="a: labels without marking-point directions"):
        TrainingSet([tmp_path], 64)
