"""The paper's experiment tables: slot-aware runs started from a photometric run, detection on rendered vs
ground-truth BEVs against a hand count, the Markdown tables, and clear errors for missing detectors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from parksim.cli import main as cli_main
from parksim.data import DatasetReader
from parksim.ipm import IPM
from parksim.recon.config import dump_config, load_config
from parksim.recon.detectors import DecodeOptions, SlotLabels, load_detector
from parksim.recon.detectors.evaluate import MatchOptions, match_points, match_slots, summarize
from parksim.recon.detectors.train import TrainOptions, train_detector
from parksim.recon.paper_eval import evaluate_runs
from parksim.recon.paper_tables import tables_markdown
from parksim.recon.plots import read_metrics
from parksim.recon.reconstruct import reconstruct
from parksim.recon.slot_aware import DetectorError, DetectorRef, SlotAwareConfig

ROOT = Path(__file__).resolve().parents[1]
PHOTOMETRIC, SLOT_AWARE = 4, 2
THRESHOLD = 0.3  # an operating point at which the few-step detector below detects something on these BEVs


def _write_config(path: Path, **sections) -> Path:
    base = load_config("tiny")
    config = base.model_copy(update={"photometric": base.photometric.model_copy(update={"iterations": PHOTOMETRIC}),
                                     "run": base.run.model_copy(update={"log_every": 1}), **sections})
    path.write_text(dump_config(config))
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Tiny data, a photometric run, a detector trained for a few steps, a slot-aware run from the photometric one."""
    tmp = tmp_path_factory.mktemp("tables")
    data = tmp / "tiny"
    assert cli_main(["synth", "tiny", "-o", str(data), "--resolution", "96x72", "--bev-px", "96", "--quiet"]) == 0
    photo = reconstruct(data, tmp / "photo", _write_config(tmp / "photo.yaml"), log=lambda s: None)
    detector = train_detector([data], tmp / "dmpr", TrainOptions(steps=3, batch_size=2, input_size=64, threads=1),
                              progress=False).parent
    slot = SlotAwareConfig(iterations=SLOT_AWARE, detector=DetectorRef(kind="dmpr", path=str(detector)))
    config = _write_config(tmp / "slot.yaml", slot_aware=slot)
    sa = reconstruct(data, tmp / "sa", config, start_from=photo, log=lambda s: None)
    return {"data": data, "photo": photo, "sa": sa, "detector": detector, "slot_config": config, "tmp": tmp}


@pytest.fixture(scope="module")
def result(runs: dict[str, Path]) -> dict:
    model = load_detector(runs["detector"])
    return evaluate_runs([(runs["photo"], None), (runs["sa"], None)], runs["data"], {"dmpr": model},
                         runs["tmp"] / "eval", backend="numba", decode=DecodeOptions(threshold=THRESHOLD))


def test_slot_aware_run_continues_the_photometric_run(runs: dict[str, Path]) -> None:
    meta = json.loads((runs["sa"] / "bundle.json").read_text())
    assert meta["phase"] == "slot_aware" and meta["iterations"] == PHOTOMETRIC + SLOT_AWARE
    records = [r for r in read_metrics(runs["sa"] / "metrics.jsonl") if "loss" in r]
    assert [r["iteration"] for r in records] == list(range(PHOTOMETRIC + 1, PHOTOMETRIC + SLOT_AWARE + 1))
    assert all(r["ipm_loss"] > 0 for r in records)


def test_start_from_needs_the_same_photometric_phase(runs: dict[str, Path], tmp_path: Path) -> None:
    other = load_config(runs["slot_config"])
    other = other.model_copy(update={"photometric": other.photometric.model_copy(update={"iterations": 3})})
    (tmp_path / "other.yaml").write_text(dump_config(other))
    with pytest.raises(ValueError, match="photometric settings"):
        reconstruct(runs["data"], tmp_path / "x", tmp_path / "other.yaml", start_from=runs["photo"], log=lambda s: None)
    with pytest.raises(ValueError, match="needs a slot-aware phase"):
        reconstruct(runs["data"], tmp_path / "y", _write_config(tmp_path / "p.yaml"), start_from=runs["photo"],
                    log=lambda s: None)
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_missing_or_wrong_detector_is_a_clear_error(runs: dict[str, Path], tmp_path: Path, capsys) -> None:
    with pytest.raises(DetectorError, match=r"missing.*checkpoint not found"):
        DetectorRef(kind="gcn", path=str(tmp_path / "missing")).load()
    with pytest.raises(DetectorError, match="holds a 'dmpr' detector"):
        DetectorRef(kind="gcn", path=str(runs["detector"])).load()
    slot = SlotAwareConfig(iterations=1, detector=DetectorRef(kind="dmpr", path=str(tmp_path / "gone" / "model.pt")))
    with pytest.raises(DetectorError, match="checkpoint not found"):
        reconstruct(runs["data"], tmp_path / "run", _write_config(tmp_path / "c.yaml", slot_aware=slot),
                    log=lambda s: None)
    assert not (tmp_path / "run").exists()
    code = cli_main(["eval", str(runs["photo"]), str(runs["data"]), "-o", str(tmp_path / "ev"),
                     "--detector", f"gcn={tmp_path / 'nowhere'}"])
    err = capsys.readouterr().err
    assert code == 2 and "checkpoint not found" in err and len(err.strip().splitlines()) == 1


def _hand_count(data: Path, model: torch.nn.Module) -> dict[str, list[int]]:
    """Detect on IPM(ground-truth images) frame by frame and count matches: [TP, detections, labelled]."""
    reader = DatasetReader(data)
    ipm, bev = IPM(reader.rig), reader.rig.bev
    counts = {"points": [0, 0, 0], "slots": [0, 0, 0]}
    for frame in reader.split["test"]:
        image = ipm({c: reader.image(c, frame) for c in reader.rig.names})
        raw = reader.labels(frame)
        labels = SlotLabels.from_parksim(raw, bev.width, bev.height, bev.m_per_px)
        det = model.detect(image.permute(2, 0, 1)[None], bev.m_per_px, DecodeOptions(threshold=THRESHOLD))[0]
        for name, flags, labelled in (("points", match_points(det, labels, MatchOptions()), len(raw["marks"])),
                                      ("slots", match_slots(det, labels, MatchOptions()), len(raw["slots"]))):
            counts[name] = [counts[name][0] + sum(flags), counts[name][1] + len(flags), counts[name][2] + labelled]
    return counts


def test_gt_row_matches_a_hand_count(runs: dict[str, Path], result: dict) -> None:
    counts = _hand_count(runs["data"], load_detector(runs["detector"]))
    assert counts["points"][1] > 0, "the test needs detections to check precision"
    for name, (tp, detected, labelled) in counts.items():
        gt = result["gt"]["dmpr"][name]
        assert (gt["tp"], gt["tp"] + gt["fp"], gt["labelled"]) == (tp, detected, labelled)
        assert gt["precision"] == pytest.approx(tp / detected if detected else 0.0)
        assert gt["recall"] == pytest.approx(tp / labelled)


def test_tables_have_the_paper_rows_and_columns(runs: dict[str, Path], result: dict) -> None:
    text = (runs["tmp"] / "eval" / "tables.md").read_text()
    assert text == tables_markdown([result])
    lines = text.splitlines()
    assert "| Scene | Reconstruction | iterations | PSNR | SSIM | slot PSNR | slot SSIM |" in lines
    assert "| Variant | tiny point P | tiny point R | tiny slot P | tiny slot R |" in lines
    rows = {line.split(" | ")[0].lstrip("| ") for line in lines if line.startswith("| ")}
    assert {"GT-DMPR-PS", "Photometric only", "Full slot-aware w/ DMPR-PS"} <= rows
    photo, sa = result["runs"]
    assert (photo["iterations"], sa["iterations"]) == (PHOTOMETRIC, PHOTOMETRIC + SLOT_AWARE)
    for run in (photo, sa):
        assert run["psnr"] > 10 and run["slot_psnr"] is not None
        assert f"| tiny | {run['label']} | {run['iterations']} | {run['psnr']:.2f} | {run['ssim']:.3f} |" in text
    assert (runs["tmp"] / "eval" / "panel_dmpr.png").stat().st_size > 0


def _scores(point_flags: list[bool], slot_flags: list[bool], points: int, slots: int) -> dict:
    from dataclasses import asdict

    return {"points": asdict(summarize(point_flags, [], [], points)),
            "slots": asdict(summarize(slot_flags, [], [], slots))}


def test_markdown_cells_from_hand_counts() -> None:
    run = {"label": "Photometric only", "variant": None, "iterations": 10, "psnr": 30.123, "ssim": 0.9,
           "slot_psnr": 28.0, "slot_ssim": 0.8,
           "detection": {"gcn": _scores([True, True, True, False], [True, False], 6, 4)}}
    one = {"scene": "s1", "test_frames": [0, 10], "runs": [run],
           "gt": {"gcn": _scores([True] * 5, [True, True, True], 6, 4)}}
    two = {"scene": "s3", "test_frames": [0], "runs": [], "gt": {"gcn": _scores([], [], 2, 1)}}
    lines = tables_markdown([one, two]).splitlines()
    # points 3 TP of 4 detections, 6 labelled -> P 0.75, R 0.5; slots 1 of 2, 4 labelled -> 0.5, 0.25
    assert "| Photometric only | 0.750 | 0.500 | 0.500 | 0.250 | n/a | n/a | n/a | n/a |" in lines
    # GT: 5 of 5 of 6 points, 3 of 3 of 4 slots; scene s3 detects nothing of 2 points and 1 slot
    assert "| GT-GCN | 1.000 | 0.833 | 1.000 | 0.750 | 0.000 | 0.000 | 0.000 | 0.000 |" in lines
    assert "| s1 | Photometric only | 10 | 30.12 | 0.900 | 28.00 | 0.800 |" in lines
    assert "Labelled: s1: 6 points, 4 slots in 2 test frames; s3: 2 points, 1 slots in 1 test frames." in lines


def test_cpu_slot_aware_config_shares_the_cpu_fast_photometric_phase() -> None:
    slot_aware = load_config("cpu_slot_aware")
    photometric = load_config("cpu_fast")
    assert all(getattr(slot_aware, k) == getattr(photometric, k) for k in ("init", "lr", "photometric", "densify"))
    assert slot_aware.slot_aware.iterations > 0 and slot_aware.slot_aware.detector is not None
