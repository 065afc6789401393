"""``parksim bench``: each subcommand's ``--quick`` run end to end on a tiny synthetic garage writes
well-formed JSON, Markdown and PNG; RESULTS.md sections are replaced in place, not duplicated."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from parksim import bundle as bundle_io
from parksim.bench.common import Written, refresh_results_md
from parksim.bench.scenes import garage_scene
from parksim.cli import main
from parksim.rig import Rig

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """``parksim synth tiny`` (160x120, 12 frames)."""
    out = tmp_path_factory.mktemp("bench") / "tiny"
    assert main(["synth", "tiny", "-o", str(out), "--quiet"]) == 0
    return out


def outputs(out: Path, name: str) -> tuple[dict, str]:
    """The JSON and Markdown of one result, after checking all three files are well formed."""
    data = json.loads((out / f"{name}.json").read_text())
    text = (out / f"{name}.md").read_text()
    assert (out / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
    meta = data["meta"]
    for key in ("command", "date", "commit", "machine", "torch_threads", "numba_threads", "load_start", "load_end"):
        assert key in meta, key
    assert meta["command"].startswith(f"parksim bench {name.replace('_', '-')}")
    assert f"![{name}](figures/{name}.png)" in text and "| --- |" in text
    return data, text


def bench(tmp: Path, *args: str) -> Path:
    """Run ``parksim bench ARGS --quick`` writing into ``tmp/results``; returns that folder."""
    out = tmp / "results"
    assert main(["bench", *args, "--quick", "--quiet", "--out", str(out), "--work", str(tmp / "work")]) == 0
    return out


def test_render_compares_bundles_against_full_quality_and_ground_truth(tiny, tmp_path):
    full = garage_scene(tiny, 400, seed=1)
    rig = Rig.load(tiny / "rig.json")
    meta = {"dataset": str(tiny), "gaussians": len(full)}
    a = bundle_io.save(tmp_path / "full", bundle_io.Bundle(full, rig, meta=meta))
    b = bundle_io.save(tmp_path / "half", bundle_io.Bundle(full.subset(torch.arange(len(full)) % 2 == 0), rig,
                                                           meta=meta))
    data, text = outputs(bench(tmp_path, "render", "--bundle", str(a), "--bundle", str(b)), "render")
    points = {(p["knob"], p["label"]): p for p in data["points"]}
    assert points[("full", "full quality")]["psnr_vs_full"] == "inf"
    assert points[("full", "full quality")]["pareto"]
    assert math.isfinite(points[("input", "input 1")]["psnr_vs_full"])       # half the Gaussians: not identical
    assert {k for k, _ in points} == {"full", "input", "scale", "sh", "method", "cameras", "backend"}
    assert all(isinstance(p["psnr_vs_gt"], float) for p in data["points"])
    assert all(p["wall_ms"] > 0 and p["max_abs_vs_full"] >= 0 for p in data["points"])
    assert "input 1" in text


def test_scaling_fits_growth_exponents(tiny, tmp_path):
    data, text = outputs(bench(tmp_path, "scaling", "--dataset", str(tiny)), "scaling")
    for key in ("gaussians", "pixels"):
        assert len(data[key]["timings"]) == len(data[key]["x"]) == 3
        assert all(math.isfinite(v) for v in data[key]["exponent"].values())
    assert "time ~ N^" in text and "time ~ pixels^" in text


def test_train_records_psnr_against_time_and_off_the_path(tiny, tmp_path):
    data, text = outputs(bench(tmp_path, "train", "--data-root", str(tiny.parent)), "train")
    (run,) = data["runs"]
    assert run["config"] == "tiny" and run["iterations"] == 20
    assert len(run["curve"]) >= 2 and all(math.isfinite(c["test_psnr"]) for c in run["curve"])
    assert (tiny / "offpath" / "offpath.json").is_file()   # written for the benchmark when missing
    groups = {g["group"]: g for g in run["offpath"]["groups"]}
    assert {"lateral ±0.25 m", "yaw ±20 deg"} <= set(groups) and all(g["views"] for g in groups.values())
    assert "| tiny | tiny | " in text and "| on path | lateral ±0.25 m |" in text
    assert "| tiny PSNR | tiny SSIM |" in text
    # --reuse takes the finished run and its evaluation as they are; --only-finished lists the pair never run
    bundle_file = tmp_path / "work" / "tiny_tiny" / "gaussians.ply"
    stamp = bundle_file.stat().st_mtime_ns
    again, text = outputs(bench(tmp_path, "train", "--data-root", str(tiny.parent), "--configs", "tiny,demo",
                                "--only-finished"), "train")
    assert bundle_file.stat().st_mtime_ns == stamp and not (tmp_path / "work" / "tiny_demo").exists()
    assert [r["config"] for r in again["runs"]] == ["tiny"] and again["runs"][0]["psnr"] == run["psnr"]
    assert "Not run (no finished run in the work folder): tiny / demo" in text


def test_stress_counts_cases_and_failures(tmp_path):
    # A child process: the stress module reads its example count at import, and this session imported it already.
    out = tmp_path / "results"
    subprocess.run([sys.executable, "-m", "parksim.cli", "bench", "stress", "--quick", "--quiet", "--out", str(out)],
                   check=True, capture_output=True)
    data, text = outputs(out, "stress")
    props = {p["property"]: p for p in data["properties"]}
    assert "test_losses_are_finite_with_finite_gradients_and_float32_agrees" in props
    assert all(p["outcome"] == "passed" and p["cases"] >= 1 for p in props.values())
    assert data["total"]["cases"] == sum(p["cases"] for p in props.values())
    assert data["total"]["failing_properties"] == 0


def test_soak_train_logs_count_memory_and_finiteness(tiny, tmp_path):
    data, _ = outputs(bench(tmp_path, "soak-train", "--dataset", str(tiny)), "soak_train")
    s = data["summary"]
    assert s["steps"] == 30 and s["nan_steps"] == [] and s["gaussians_max"] <= s["cap_max"]
    assert [r["step"] for r in data["log"]] == [10, 20, 30] and all(r["rss_mib"] > 0 for r in data["log"])


def test_soak_server_counts_statuses_and_memory(tiny, tmp_path):
    data, _ = outputs(bench(tmp_path, "soak-server", "--dataset", str(tiny)), "soak_server")
    s = data["summary"]
    assert s["requests"] == 5 and s["statuses"] == {"200": 5}
    assert len(data["log"]) == 5 and s["rss_after_warmup_mib"] > 0


def test_results_md_section_is_replaced_not_duplicated(tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    (out / "x.md").write_text("first\n")
    (out / "x.png").write_bytes(PNG_MAGIC)
    md = tmp_path / "RESULTS.md"
    md.write_text("# Results\n\nkept\n")
    written = Written(out / "x.json", out / "x.md", out / "x.png")
    refresh_results_md(written, "X", md)
    (out / "x.md").write_text("second\n")
    refresh_results_md(written, "X", md)
    text = md.read_text()
    assert text.startswith("# Results\n\nkept\n") and "second" in text and "first" not in text
    assert text.count("## X") == 1
    assert (tmp_path / "figures" / "x.png").read_bytes() == PNG_MAGIC
