"""The perception suites (``parksim bench detectors``, ``planner``, ``slot-aware``) run ``--quick`` through the CLI on
the tiny garage and record what the library measures; ``docs/make_figures.py`` draws its figures."""

from __future__ import annotations

import importlib.util
import math
import shutil
from pathlib import Path

import pytest

from parksim.bench.record import Record, read_record
from parksim.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory, tiny_data: Path) -> Path:
    """A work folder holding a copy of the tiny garage where the suites look for it (shared by this module's runs,
    so the detectors trained by one are reused by the next)."""
    work = tmp_path_factory.mktemp("perception")
    shutil.copytree(tiny_data, work / "data" / "tiny")
    return work


def bench(work: Path, *args: str) -> Record:
    """Run ``parksim bench ARGS --quick`` in ``work``; its (only new) record."""
    results = work / "results"
    before = set(results.glob("*/*.json"))
    assert main(["bench", *args, "--quick", "--quiet", "--work", str(work), "--results", str(results)]) == 0
    (path,) = set(results.glob("*/*.json")) - before
    return read_record(path)


def by_target(record: Record) -> dict:
    return {f.target: f for f in record.figures}


def test_detectors_record_what_the_evaluator_measures_and_reuse_their_models(work):
    from parksim.recon.detectors import load_detector
    from parksim.recon.detectors.evaluate import evaluate_folder

    record = bench(work, "detectors")
    figures = by_target(record)
    for title in ("DMPR-PS-style", "GCN-style"):
        for what in ("point precision", "point recall", "slot precision", "slot recall"):
            f = figures[f"{title}: {what} on GT BEVs of the test frames of tiny"]
            assert f.unit == "fraction" and f.better == "higher" and f.goal and 0.0 <= f.value <= 1.0
        (timing,) = [f for t, f in figures.items() if t.startswith(f"{title}: detection on one 300x300 BEV")]
        assert timing.unit == "ms" and timing.value > 0 and timing.cpu is not None and timing.cpu > 0
    assert len(figures) == 10
    for arch in ("dmpr", "gcn"):
        recorded = record.data["detectors"][arch]
        (folder,) = recorded["folders"]
        fresh = evaluate_folder(load_detector(recorded["model"]), Path(folder["folder"]), "test")
        for key in ("points", "slots"):   # the evaluator's counts, not a re-derivation of them
            assert {k: fresh[key][k] for k in ("tp", "fp", "labelled")} == \
                   {k: folder[key][k] for k in ("tp", "fp", "labelled")}
            assert recorded["all"][key]["labelled"] == fresh[key]["labelled"] > 0
    assert record.data["detectors"]["gcn"]["steps"] == [4, 2]
    model = Path(record.data["detectors"]["gcn"]["model"]) / "model.pt"
    stamp = model.stat().st_mtime_ns
    again = bench(work, "detectors")
    assert model.stat().st_mtime_ns == stamp   # reused, not retrained
    assert again.data["detectors"]["gcn"]["train_seconds"] == record.data["detectors"]["gcn"]["train_seconds"]
    # a stage trained with other steps is refused, not silently reused
    assert main(["bench", "detectors", "--quick", "--quiet", "--work", str(work), "--dmpr-steps", "5"]) == 2


def test_planner_runs_both_planners_from_the_same_starts(work):
    record = bench(work, "planner")
    figures = by_target(record)
    geometric = figures["privileged geometric planner (world pose + map) on tiny: parked, 2 random starts"]
    perception = figures["perception planner (BEV detector + dead reckoning) on tiny: parked, 2 random starts"]
    assert geometric.unit == perception.unit == "%" and perception.better == "higher"
    assert geometric.reference is None
    assert perception.reference == geometric.value and perception.reference_label.startswith("privileged geometric")
    episodes = record.data["episodes"]
    assert record.data["seeds"] == [0, 1] and len(episodes["geometric"]) == len(episodes["perception"]) == 2
    for planner, f in (("geometric", geometric), ("perception", perception)):
        runs = episodes[planner]
        parked = [e for e in runs if e["outcome"] == "parked"]
        assert f.value == 100.0 * len(parked) / len(runs) == 100.0 * record.data["summaries"][planner]["parked"] / 2
        assert all(e["distance"] <= 0.35 and 0 < e["steps"] <= 500 for e in parked)   # the env's tolerance
        timing = figures[f"{f.target.split(': parked')[0]}: one episode (median of 2)"]
        assert timing.value > 0 and timing.cpu > 0
    for g, p in zip(episodes["geometric"], episodes["perception"]):
        assert p["slot"] == g["slot"]   # told the slot the geometric planner chose at the same start
        assert p["views"] >= 1
    assert record.data["detector"]["train_seconds"] > 0


def test_slot_aware_checks_each_full_run_against_photometric_only_the_control_and_gt(work):
    record = bench(work, "slot-aware")
    (result,) = record.data["results"]
    rows = {r["label"]: r for r in result["runs"]}
    assert set(rows) == {"Photometric only", "Full slot-aware w/ DMPR-PS", "Full slot-aware w/ GCN",
                         "Photometric only, continued"}
    assert len(record.figures) == 12
    for f in record.figures:
        assert f.reference is not None and f.goal and math.isfinite(f.value) and math.isfinite(f.reference)
        label = f.target.split(": ")[0].split(", ")[-1]
        assert f.target.startswith("tiny, 20 + 2 it., ") and label in rows
        if f.unit == "dB":
            reference = rows[f.reference_label]["slot_psnr"]
            assert f.value == rows[label]["slot_psnr"] and 10.0 < f.value < 60.0
        else:
            kind = rows[label]["detector"]
            source = (result["gt"][kind] if f.reference_label.startswith("GT")
                      else rows[f.reference_label]["detection"][kind])
            reference = source["slots"]["recall" if "recall" in f.target else "precision"]
        assert f.reference == reference
    for check in record.data["targets"]:
        met = (abs(check["value"] - check["reference"]) <= 0.05 if check["goal"].startswith("within")
               else check["value"] > check["reference"])
        assert check["met"] == met
    assert all(t["slot_aware_seconds"] > 0 for t in record.data["timings"] if "slot_aware_seconds" in t)
    assert (work / "results" / "slot-aware" / record.plot).read_bytes()[:8] == PNG_MAGIC
    # a finished run is reused only under the config it was trained with: other guide detectors are refused
    copies = shutil.copytree(Path(record.data["detectors"]["gcn"]).parent, work / "other_detectors")
    assert main(["bench", "slot-aware", "--quick", "--quiet", "--work", str(work), "--detector",
                 f"dmpr={copies / 'dmpr'}", "--detector", f"gcn={copies / 'gcn'}"]) == 2


def test_make_figures_draws_the_synth_and_detector_figures(work, tmp_path):
    from parksim.bench.suite import Context
    from parksim.bench.suites.detectors import default_models

    spec = importlib.util.spec_from_file_location("make_figures", Path(__file__).parents[1] / "docs/make_figures.py")
    assert spec is not None and spec.loader is not None
    figures = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(figures)
    synth = figures.draw_synth_frame(work / "data" / "tiny", 5, tmp_path / "synth.png")
    assert synth.read_bytes()[:8] == PNG_MAGIC
    root = tmp_path / "data"
    root.mkdir()
    (root / "scene1").symlink_to(work / "data" / "tiny")   # stands in for scene1: same layout, seconds to read
    models = default_models(Context(work=work, quick=True, quiet=True))   # the suites' (trained if run alone)
    (detector,) = figures.draw_detector(tmp_path, models, root)
    assert detector.name == "detector_bev.png" and detector.read_bytes()[:8] == PNG_MAGIC
