"""``parksim bench`` training-side suites: train-step, compact, import, pose-refine and synth, each run with --quick
through the real CLI on the tiny garage, writing one well-formed record whose figures and data hold what the suite
measures. train-step and compact share one tiny bundle, trained once for the module under the shared work folder."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

import parksim
from parksim.bench.bundles import ensure_bundle
from parksim.bench.record import Figure, Record, read_record
from parksim.bench.suite import Context
from parksim.cli import main
from parksim.compact import budget_count

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A work folder holding the tiny garage trained with the tiny config (what --quick suites default to)."""
    folder = tmp_path_factory.mktemp("bench_training")
    run, _ = ensure_bundle(Context(folder, quick=True, quiet=True), "scene1", None, "cpu_30min")
    assert (run / "bundle.json").is_file() and (run / "checkpoints" / "last.pt").is_file()
    return folder


def bench(work: Path, results: Path, name: str, *args: str) -> Record:
    """Run ``parksim bench NAME ARGS --quick`` and return its one record, checked well formed."""
    assert main(["bench", name, *args, "--quick", "--quiet", "--work", str(work), "--results", str(results)]) == 0
    (path,) = sorted((results / name).glob("*.json"))
    record = read_record(path)
    assert record.suite == name and record.command.startswith(f"parksim bench {name} ")
    assert record.options["quick"] is True
    for f in record.figures:
        assert math.isfinite(f.value) and f.unit, f
        assert f.cpu is None or f.cpu > 0, f
    return record


def by_target(record: Record) -> dict[str, Figure]:
    targets = {f.target: f for f in record.figures}
    assert len(targets) == len(record.figures), "targets must be distinct"
    return targets


def test_train_step_times_this_package_and_a_reference_in_their_own_processes(work: Path, tmp_path: Path):
    # the reference is this package reached through a link: a copy elsewhere would recompile every numba kernel
    # (numba keys its cache by the source's path), a minute and more
    reference = tmp_path / "reference"
    reference.symlink_to(Path(parksim.__file__).resolve().parent.parent, target_is_directory=True)
    record = bench(work, tmp_path / "results", "train-step", "--reference", str(reference), "--reference-label",
                   "the same package, linked", "--profile", "1")
    gaussians = json.loads((work / "bundles" / "tiny_tiny" / "bundle.json").read_text())["gaussians"]
    rows = record.data["rounds"]
    assert [(r["round"], r["package"]) for r in rows] == [(1, "this"), (1, "reference")]
    assert rows[0]["folder"] == rows[1]["folder"] == str(Path(parksim.__file__).resolve().parent.parent)
    assert all(r["gaussians"] == gaussians and r["faults"] >= 0 for r in rows)
    step, faults = record.figures
    assert step.target.startswith(f"training step, {gaussians:,} Gaussians, SH degree 1, 160x120")
    assert step.unit == "ms" and step.value > 0 and step.value == rows[0]["wall_ms"] and step.cpu == rows[0]["cpu_ms"]
    assert step.reference == rows[1]["wall_ms"] and step.reference_cpu == rows[1]["cpu_ms"]
    assert step.reference_label == "the same package, linked" and step.goal
    assert faults.unit == "count" and faults.reference == rows[1]["faults"] and faults.cpu is None
    ops = record.data["profile"]
    assert 0 < len(ops) <= 20 and all(op["self_cpu_ms"] >= 0 for op in ops)
    assert [op["self_cpu_ms"] for op in ops] == sorted((op["self_cpu_ms"] for op in ops), reverse=True)


def test_train_step_refuses_a_reference_without_a_package(work: Path, tmp_path: Path, capsys):
    assert main(["bench", "train-step", "--reference", str(tmp_path), "--quick", "--quiet", "--work", str(work),
                 "--results", str(tmp_path / "results")]) == 2
    assert "no parksim package" in capsys.readouterr().err
    assert not (tmp_path / "results").exists()


def test_compact_scores_and_times_every_series_against_the_full_scene(work: Path, tmp_path: Path):
    results = tmp_path / "results"
    record = bench(work, results, "compact")
    rows = {r["name"]: r for r in record.data["variants"]}
    full = rows.pop("full scene")
    control = rows.pop("full scene + fine-tune (control)")
    n = record.data["scene"]["gaussians"]
    assert full["gaussians"] == control["gaussians"] == n and full["speedup"] == 1.0
    assert sorted(rows) == sorted(f"{ranking}{' + fine-tune' if tuned else ''}, budget 0.5"
                                  for ranking in ("weight", "benefit-cost") for tuned in (False, True))
    assert all(r["gaussians"] == budget_count(0.5, n) for r in rows.values())
    assert control["psnr"] != full["psnr"]   # the two fine-tuning steps ran
    assert record.data["offpath_frames"] is None and record.data["measurement"]["poses"] > 0
    figures = by_target(record)
    for name, r in rows.items():
        render, psnr = figures[f"{name}: 4-camera serving render"], figures[f"{name}: test PSNR"]
        assert render.value == r["wall_ms"] and render.reference == full["wall_ms"] and render.unit == "ms"
        assert psnr.value == r["psnr"] and psnr.reference == full["psnr"] and psnr.better == "higher"
        assert math.isclose(full["psnr"] - r["psnr"], r["loss_db"])
    best = figures["best speed-up at <= 0.3 dB test PSNR loss against the full scene"]
    assert best.goal == ">= 2.5x" and best.value == max(r["speedup"] for r in [full, control, *rows.values()]
                                                        if r["loss_db"] <= 0.3)
    (png,) = (results / "compact").glob("*.png")
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_import_scores_the_mp4_round_trip_and_times_both_sources(work: Path, tmp_path: Path):
    record = bench(work, tmp_path / "results", "import")
    quality, timing = record.data["quality"], record.data["timing"]
    mp4, decoded, imports = record.figures
    assert mp4.value == quality["mp4"]["psnr"] and mp4.reference == quality["original"]["psnr"]
    assert mp4.better == "higher" and "1 dB" in (mp4.goal or "")
    assert all(10 < q["psnr"] < 60 and 0 < q["ssim"] <= 1 for q in quality.values())
    assert decoded.value > 30   # mp4v at the backend's default quality: ~35 dB on the tiny garage
    assert imports.target == "rig-log import, 12 frames x 4 cameras at 160x120, mp4v videos"
    assert imports.value == timing["videos (mp4v)"]["wall_ms"]
    assert imports.reference == timing["image folders (PNG)"]["wall_ms"] and imports.reference_label
    assert record.data["config"]["pose_opt"]["enabled"] is False
    assert record.data["config"]["init"]["source"] == "random"
    assert not (work / "import" / "imported").exists()   # the timed imports' outputs are removed


def test_pose_refine_measures_the_errors_it_put_in(work: Path, tmp_path: Path):
    record = bench(work, tmp_path / "results", "pose-refine")
    figures = by_target(record)
    at = "(tiny garage 160x120, 20 iterations)"
    clean = figures[f"test PSNR, clean poses {at}"]
    refined = figures[f"test PSNR, perturbed poses, refined, test poses aligned {at}"]
    assert refined.reference == clean.value and refined.goal == "within 0.5 dB of clean poses"
    errors = record.data["pose_error"]
    # every ego pose was moved by exactly 5 cm and 0.5 deg, the front camera by 2 cm and 0.3 deg
    assert math.isclose(errors["train_before"]["median_cm"], 5.0, rel_tol=1e-9)
    assert math.isclose(errors["train_before"]["max_deg"], 0.5, rel_tol=1e-6)
    assert math.isclose(errors["extrinsics_before"]["front"][0], 2.0, rel_tol=1e-9)
    assert all(max(errors["extrinsics_before"][c]) < 1e-4 for c in ("rear", "left", "right"))
    assert 0 <= errors["gauge_floor"]["cm"] < 5.0
    ego = figures[f"train ego poses: median error in cm after refinement {at}"]
    assert ego.value == errors["train_after"]["median_cm"] and ego.reference == errors["train_before"]["median_cm"]
    runs = record.data["runs"]
    assert "psnr_unaligned" in runs["refined"] and record.data["config"]["pose_opt"]["test_steps"] == 2
    assert record.data["train_frames"] + record.data["test_frames"] == 12


def test_synth_times_each_worker_count_against_the_first(work: Path, tmp_path: Path):
    record = bench(work, tmp_path / "results", "synth")
    serial, pool = record.figures
    runs = record.data["runs"]
    assert set(runs) == {"1", "2"} and all(len(v) == 1 for v in runs.values())
    assert serial.target == "synth tiny, 4 frames at 160x120: time per frame, 1 worker" and serial.reference is None
    assert math.isclose(serial.value, 1e3 * runs["1"][0]["wall_s"] / 4)
    assert pool.reference == serial.value and pool.reference_cpu == serial.cpu and pool.reference_label == "1 worker"
    assert serial.goal is None   # the goal is stated at 640x480
    assert not [p for p in work.iterdir() if p.name.startswith("tmp")]   # the generated datasets are removed
