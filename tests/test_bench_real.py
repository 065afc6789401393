"""``parksim bench real --quick``: the messy recording of the tiny garage really imported (mp4v videos, 6-decimal
calibration, exposure drift, ``--points sfm``) and every run of the matrix really trained and scored; the record holds
one test PSNR per run beside its clean reference, the target gap computed from them, and the import report's numbers,
which match what was done to the recording."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from parksim.bench.record import Record, read_record
from parksim.bench.suites.real import DECIMALS, GOAL_DB, RUNS, RealOptions, exposure_evs
from parksim.cli import main
from parksim.data import DatasetReader
from parksim.recon.config import load_config

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SIX_DECIMALS_BOUND = 3 * 0.5e-6
"""Largest correction of a 6-decimal rotation matrix (``test_messy_recording.SIX_DECIMALS_BOUND``)."""
CODEC_REL = 0.05
"""A darkened view's mean intensity through mp4v against ``2^EV`` times the clean one's: the codec's error averages
out over a view (its PSNR to the PNGs is ~35 dB, an RMS error of ~2 %, and unbiased)."""
SCHEDULE_KEYS = {("init", "source"), ("lr", "exposure"), ("data", "image_scale")}
"""The only config entries the runs may differ in."""


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """One ``parksim bench real --quick`` run: its record, work folder and the clean dataset."""
    work, results = tmp_path_factory.mktemp("bench_real"), tmp_path_factory.mktemp("bench_real_results")
    assert main(["bench", "real", "--quick", "--quiet", "--work", str(work), "--results", str(results)]) == 0
    (path,) = sorted((results / "real").glob("*.json"))
    return {"record": read_record(path), "path": path, "work": work / "real",
            "clean": DatasetReader(read_record(path).data["dataset"])}


def _figures(record: Record) -> dict[str, Any]:
    by_target = {f.target: f for f in record.figures}
    assert len(by_target) == len(record.figures), "targets must be distinct"
    return by_target


def test_one_psnr_per_run_beside_its_clean_reference_and_the_gap_from_the_numbers(bench: dict[str, Any]) -> None:
    record = bench["record"]
    assert record.suite == "real" and record.options["quick"] is True
    assert record.command.startswith("parksim bench real ")
    for f in record.figures:
        assert math.isfinite(f.value) and f.unit, f
    runs = record.data["runs"]
    assert list(runs) == [r.name for r in RUNS]
    psnr_figures = [f for f in record.figures if f.target.startswith("test PSNR, ")]
    assert len(psnr_figures) == len(RUNS)
    for run, figure in zip(RUNS, psnr_figures):
        assert run.label in figure.target and figure.value == runs[run.name]["psnr"] and figure.unit == "dB"
        clean = "clean_half" if run.half else "clean"
        assert figure.reference == (runs[clean]["psnr"] if run.recording else None)
        assert runs[run.name]["image_scale"] == (0.5 if run.half else 1.0)
        assert 5.0 < runs[run.name]["psnr"] < 60.0 and 0.0 < runs[run.name]["ssim"] <= 1.0
    (gap,) = [f for f in record.figures if f.goal is not None]
    assert gap.goal == f"<= {GOAL_DB:g} dB" and "every remedy" in gap.target
    assert gap.value == runs["clean"]["psnr"] - runs["remedies"]["psnr"]
    assert record.data["target"] == {"gap_db": gap.value, "goal_db": GOAL_DB, "met": gap.value <= GOAL_DB}
    assert bench["path"].with_suffix(".png").read_bytes()[:8] == PNG_MAGIC


def test_every_run_trained_on_one_schedule_as_the_matrix_says(bench: dict[str, Any]) -> None:
    record, work = bench["record"], bench["work"]
    options = RealOptions(**{k: v for k, v in record.options.items() if k not in ("seed", "quick")})
    configs = {r.name: load_config(str(work / f"{r.name}.yaml")).model_dump(mode="json") for r in RUNS}
    for run in RUNS:
        cfg = configs[run.name]
        assert cfg["init"]["source"] == ("points" if run.points else "random")
        assert cfg["lr"]["exposure"] == (options.exposure_lr if run.exposure else 0.0)
        assert cfg["data"]["image_scale"] == (0.5 if run.half else 1.0)
        assert cfg["photometric"]["iterations"] == options.iterations and not cfg["pose_opt"]["enabled"]
        assert 0 < record.data["runs"][run.name]["gaussians"] <= options.cap
        data = bench["work"] / "recording" if run.recording else Path(record.data["dataset"])
        assert Path(json.loads((work / f"run_{run.name}" / "bundle.json").read_text())["dataset"]) == data.resolve()
    for cfg in configs.values():
        for section, key in SCHEDULE_KEYS:
            cfg[section].pop(key)
    assert all(cfg == configs["clean"] for cfg in configs.values())
    assert record.data["config"] == json.loads(json.dumps(load_config(str(work / "remedies.yaml")).model_dump(
        mode="json")))


def _svd_correction(R: np.ndarray) -> float:
    u, _, vt = np.linalg.svd(np.asarray(R, np.float64))
    return float(np.abs(u @ vt - R).max())


def _numbers(value: Any) -> list[float]:
    if isinstance(value, float):
        return [value]
    if isinstance(value, (list, dict)):
        return [x for v in (value.values() if isinstance(value, dict) else value) for x in _numbers(v)]
    return []


def test_the_import_report_numbers_are_what_the_recording_was_given(bench: dict[str, Any]) -> None:
    numbers, calib, clean = bench["record"].data["import"], bench["work"] / "log" / "calib", bench["clean"]
    # nothing was dropped from the videos: every frame came through
    assert numbers["dropped"] == 0 and numbers["dropped_by_reason"] == {} and numbers["frames"] == len(clean.frames)
    # the calibration really is printed with 6 decimals, and the corrections are those of what it says
    cameras = json.loads((calib / "extrinsics.json").read_text())["cameras"]
    assert all(round(v, DECIMALS) == v for v in _numbers(cameras))
    for name in clean.rig.names:
        fs = cv2.FileStorage(str(calib / f"{name}.yaml"), cv2.FILE_STORAGE_READ)
        K = fs.getNode("camera_matrix").mat()
        fs.release()
        assert np.array_equal(np.round(K, DECIMALS), K)
    matrices = [np.array(e["T_vehicle_camera"])[:3, :3] for e in cameras.values() if "T_vehicle_camera" in e]
    norms = [abs(float(np.linalg.norm([e[k] for k in ("qw", "qx", "qy", "qz")])) - 1.0)
             for e in cameras.values() if "qw" in e]
    assert matrices and norms
    assert numbers["largest_rotation_correction"] == max(map(_svd_correction, matrices))
    assert 0 < numbers["largest_rotation_correction"] <= SIX_DECIMALS_BOUND
    assert numbers["largest_quaternion_norm_error"] == max(norms) > 0
    # SfM points: the report's count is the points written
    xyz, _ = DatasetReader(bench["work"] / "recording").points
    assert numbers["sfm"]["points"] == len(xyz) > 0
    assert math.isfinite(numbers["sfm"]["mean_reprojection_px"]) and numbers["sfm"]["mean_reprojection_px"] < 1.0
    figures = _figures(bench["record"])
    assert [f.value for t, f in figures.items() if "SfM points" in t] == [numbers["sfm"]["points"]]


def test_the_recording_carries_the_exposure_drift(bench: dict[str, Any]) -> None:
    """The imported (decoded) training images against the clean ones: darkened views by 2^EV (darkening never
    clips), and the EVs are those the suite's seed gives."""
    clean, record = bench["clean"], bench["record"]
    evs = exposure_evs(clean.frames, clean.split["train"], clean.rig.names, record.options["seed"],
                       record.options["max_ev"])
    imported = DatasetReader(bench["work"] / "recording")
    darker = [(f, c) for (f, c), ev in evs.items() if ev < -0.2]
    assert darker
    for f, c in darker:
        ratio = float(imported.image(c, f).mean() / clean.image(c, f).mean())
        assert ratio == pytest.approx(2.0 ** evs[(f, c)], rel=CODEC_REL), (f, c)
    ranges = record.data["exposure"]["range_ev"]
    assert max(max(abs(lo), abs(hi)) for lo, hi in ranges.values()) == pytest.approx(record.options["max_ev"])


def test_exposure_evs_are_centred_per_camera_and_reach_the_largest_ev() -> None:
    frames, train, cameras = list(range(40)), [f for f in range(40) if f % 10], ["front", "rear", "left", "right"]
    evs = exposure_evs(frames, train, cameras, seed=3, max_ev=0.75)
    assert set(evs) == {(f, c) for f in frames for c in cameras}
    assert max(abs(v) for v in evs.values()) == pytest.approx(0.75, abs=1e-15)
    for c in cameras:
        assert abs(np.mean([evs[(f, c)] for f in train])) < 1e-15 * len(train)
        assert np.ptp([evs[(f, c)] for f in frames]) > 0.2   # each camera drifts
    assert evs == exposure_evs(frames, train, cameras, seed=3, max_ev=0.75)
    assert evs != exposure_evs(frames, train, cameras, seed=4, max_ev=0.75)
