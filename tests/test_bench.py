"""``parksim bench``: the --quick run of scaling, knobs, train, stress, soak-train and soak-server, end to end on a
tiny synthetic garage through the real CLI, each writing one well-formed record (and its PNG) whose figures and
data hold what the suite measures."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from parksim import bundle as bundle_io
from parksim.bench.record import Record, read_record
from parksim.bench.scenes import garage_scene
from parksim.cli import main
from parksim.rig import Rig

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """``parksim synth tiny`` (160x120, 12 frames)."""
    out = tmp_path_factory.mktemp("bench") / "tiny"
    assert main(["synth", "tiny", "-o", str(out), "--quiet"]) == 0
    return out


def checked(results: Path, name: str) -> Record:
    """The one record of suite ``name`` under ``results``, after checking it is well formed and its plot a PNG."""
    (path,) = sorted((results / name).glob("*.json"))
    record = read_record(path)
    assert record.suite == name and record.command.startswith(f"parksim bench {name} ")
    assert record.options["quick"] is True and record.machine.cores >= 1
    assert record.plot is not None and (path.parent / record.plot).read_bytes()[:8] == PNG_MAGIC
    for f in record.figures:
        assert f.unit and not math.isnan(f.value), f
    return record


def bench(tmp: Path, name: str, *args: str, results: str = "results") -> Record:
    """Run ``parksim bench NAME ARGS --quick`` (work folder ``tmp/work``) and read its record."""
    out = tmp / results
    assert main(["bench", name, *args, "--quick", "--quiet", "--work", str(tmp / "work"), "--results", str(out)]) == 0
    return checked(out, name)


def figures(record: Record) -> dict:
    return {f.target: f for f in record.figures}


def test_scaling_fits_growth_exponents(tiny, tmp_path):
    record = bench(tmp_path, "scaling", "--dataset", str(tiny))
    for key in ("gaussians", "pixels"):
        assert len(record.data[key]["timings"]) == len(record.data[key]["x"]) == 3
        assert all(math.isfinite(v) for v in record.data[key]["exponent"].values())
    exponents = [f for f in record.figures if f.unit == "exponent"]
    assert [f.value for f in exponents] == [record.data["gaussians"]["exponent"]["upper"],
                                            record.data["pixels"]["exponent"]["upper"]]


def test_knobs_compares_bundles_against_full_quality_and_ground_truth(tiny, tmp_path):
    full = garage_scene(tiny, 400, seed=1)
    rig = Rig.load(tiny / "rig.json")
    meta = {"dataset": str(tiny), "gaussians": len(full)}
    a = bundle_io.save(tmp_path / "full", bundle_io.Bundle(full, rig, meta=meta))
    b = bundle_io.save(tmp_path / "half", bundle_io.Bundle(full.subset(torch.arange(len(full)) % 2 == 0), rig,
                                                           meta=meta))
    record = bench(tmp_path, "knobs", "--bundle", f"{a},{b}")
    points = {p["label"]: p for p in record.data["points"]}
    reference = points["full quality, all cameras"]
    assert reference["psnr_vs_full"] == "inf" and reference["pareto"]
    assert math.isfinite(points["input 1"]["psnr_vs_full"])       # half the Gaussians: not identical
    assert {p["knob"] for p in points.values()} == {"full", "input", "scale", "sh", "method", "cameras", "backend"}
    assert all(isinstance(p["psnr_vs_gt"], float) for p in points.values())
    assert all(p["wall_ms"] > 0 and p["max_abs_vs_full"] >= 0 for p in points.values())
    # figures: full quality's latency and PSNR vs ground truth, then per knob its fastest point against full quality
    by = figures(record)
    assert by["full quality, all cameras: latency"].value == reference["wall_ms"]
    assert by["full quality, all cameras: PSNR vs ground truth"].value == reference["psnr_vs_gt"]
    latencies = [f for f in record.figures if f.target.endswith(": latency") and f.reference is not None]
    assert len(latencies) == 6 and {"input 1: latency", "scale 0.5: latency", "SH <= 0: latency",
                                    "EWA projection: latency", "torch backend: latency"} <= set(by)
    for f in latencies:
        label = f.target.removesuffix(": latency")
        knob = points[label]["knob"]
        assert f.value == min(p["wall_ms"] for p in points.values() if p["knob"] == knob)
        assert (f.reference, f.reference_label, f.unit) == (reference["wall_ms"], "full quality", "ms")
        assert f.cpu is not None and f.cpu > 0
        psnr = by[f"{label}: PSNR vs full quality"]
        assert psnr.better == "higher" and psnr.unit == "dB"
        assert psnr.value == (math.inf if points[label]["psnr_vs_full"] == "inf" else points[label]["psnr_vs_full"])


def test_train_records_psnr_against_time_and_off_the_path(tiny, tmp_path):
    record = bench(tmp_path, "train", "--data-root", str(tiny.parent))
    (run,) = record.data["runs"]
    assert run["config"] == "tiny" and run["iterations"] == 20
    assert len(run["curve"]) >= 2 and all(math.isfinite(c["test_psnr"]) for c in run["curve"])
    assert (tiny / "offpath" / "offpath.json").is_file()   # written for the benchmark when missing
    groups = {g["group"]: g for g in run["offpath"]["groups"]}
    assert {"lateral ±0.25 m", "yaw ±20 deg"} <= set(groups) and all(g["views"] for g in groups.values())
    by = figures(record)
    psnr, cpu = by["tiny (native), tiny: final test PSNR"], by["tiny (native), tiny: training CPU time"]
    assert (psnr.value, psnr.unit, psnr.goal, psnr.better) == (run["psnr"], "dB", ">= 28 dB", "higher")
    assert (cpu.value, cpu.unit) == (run["cpu_s"] / 60, "min") and cpu.value > 0
    # --reuse takes the finished run and its evaluation as they are; --only-finished lists the pair never run
    bundle_file = tmp_path / "work" / "tiny_tiny" / "gaussians.ply"
    stamp = bundle_file.stat().st_mtime_ns
    again = bench(tmp_path, "train", "--data-root", str(tiny.parent), "--configs", "tiny,demo", "--only-finished",
                  results="again")
    assert bundle_file.stat().st_mtime_ns == stamp and not (tmp_path / "work" / "tiny_demo").exists()
    assert [r["config"] for r in again.data["runs"]] == ["tiny"] and again.data["runs"][0]["psnr"] == run["psnr"]
    assert again.data["not_run"] == [{"scene": "tiny", "config": "demo"}]
    assert set(figures(again)) == set(by)


def test_stress_counts_cases_and_failures(tmp_path):
    # A child process run from the repository root (the default --tests): the stress tests read their example
    # count when imported, and this session imported them already.
    out = tmp_path / "results"
    subprocess.run([sys.executable, "-m", "parksim.cli", "bench", "stress", "--quick", "--quiet",
                    "--work", str(tmp_path / "work"), "--results", str(out)], check=True, capture_output=True, cwd=REPO)
    record = checked(out, "stress")
    props = {p["property"]: p for p in record.data["properties"]}
    assert "test_losses_are_finite_with_finite_gradients_and_float32_agrees" in props
    assert all(p["outcome"] == "passed" and p["cases"] >= 1 for p in props.values())
    total = record.data["total"]
    assert total["cases"] == sum(p["cases"] for p in props.values()) and total["failing_properties"] == 0
    by = figures(record)
    cases = by["test_stress.py at 3 examples per property: cases tried"]
    failing = by["test_stress.py at 3 examples per property: failing properties"]
    assert cases.value == total["cases"] and (failing.value, failing.goal) == (0, "0")


def test_stress_without_its_test_file_says_where_to_run_it(tmp_path, capsys):
    missing = tmp_path / "test_stress.py"
    assert main(["bench", "stress", "--quick", "--quiet", "--tests", str(missing), "--work", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(missing) in err and "run from the repository root or pass --tests" in err


def test_soak_train_logs_count_memory_and_finiteness(tiny, tmp_path):
    record = bench(tmp_path, "soak-train", "--dataset", str(tiny))
    s = record.data["summary"]
    assert s["steps"] == 30 and s["nan_steps"] == [] and s["gaussians_max"] <= s["cap_max"]
    log = record.data["log"]
    assert [r["step"] for r in log] == [10, 20, 30] and all(r["rss_mib"] > 0 and r["finite"] for r in log)
    where = "tiny stretched to 30 steps on tiny"
    by = figures(record)
    assert by[f"{where}: steps done"].value == 30 and by[f"{where}: non-finite checks failed"].value == 0
    assert by[f"{where}: RSS growth over the second half"].value == s["rss_growth_second_half_mib"]


def test_soak_server_counts_statuses_and_memory(tiny, tmp_path):
    record = bench(tmp_path, "soak-server", "--dataset", str(tiny))
    s = record.data["summary"]
    assert s["requests"] == 5 and s["statuses"] == {"200": 5}
    assert len(record.data["log"]) == 5 and s["rss_after_warmup_mib"] > 0
    where = "5 renders of 500 Gaussians, all cameras + BEV"
    by = figures(record)
    assert by[f"{where}: requests sent"].value == 5 and by[f"{where}: non-200 replies"].value == 0
    assert by[f"{where}: server RSS growth after warm-up"].value == s["rss_end_mib"] - s["rss_after_warmup_mib"]
