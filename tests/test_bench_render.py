"""The renderer's suites (``parksim bench render``, ``projection``, ``rasterize``, ``ipm``, ``ut-accuracy``) run
``--quick`` through the CLI and record what they measure; ``gpu`` has its own file (test_bench_gpu.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from parksim.bench.record import Figure, Record, read_record
from parksim.cli import main


def bench(tmp: Path, *args: str) -> Record:
    """Run ``parksim bench ARGS --quick``; its record."""
    results = tmp / "results"
    assert main(["bench", *args, "--quick", "--quiet", "--work", str(tmp / "work"), "--results", str(results)]) == 0
    (path,) = results.glob("*/*.json")
    return read_record(path)


def by_target(record: Record) -> dict[str, Figure]:
    return {f.target: f for f in record.figures}


def timed(f: Figure) -> bool:
    """A wall-time figure with its process CPU time beside it."""
    return f.unit == "ms" and math.isfinite(f.value) and f.value > 0 and f.cpu is not None and f.cpu > 0


def test_render_times_every_part_against_the_reference_copy(tiny_data, tmp_path):
    record = bench(tmp_path, "render", "--dataset", str(tiny_data), "--cases", "a,b,c,stages,serve",
                   "--reference", "parksim")
    figures = by_target(record)
    b = "case (b) fwd, 4 cameras 160x120 + BEV 64, 4e3 Gaussians"
    cases = ["case (a) fwd, 1 camera 80x60, 2e3 Gaussians", "case (a) fwd+bwd, 1 camera 80x60, 2e3 Gaussians", b,
             "case (c) fwd, 1 camera 160x120 + BEV 64, 4e3 Gaussians", "case (c) fwd, 4 cameras 160x120, 4e3 Gaussians",
             *(f"case (c) fwd, 4 cameras 160x120 + BEV 64, 4e3 Gaussians, {off} off"
               for off in ("culling", "early stop"))]
    stages = [f"{b}: {s}, 1 numba thread" for s in
              ("projection", "binning", "compositing", "epilogue", "BEV", "whole render")]
    serve = "serve 4 cameras 160x120 (LocalSim.render, no BEV) through EWA, garage 4,000 Gaussians"
    pairs = f"{b}: compositor pairs evaluated per pair blended"
    assert list(figures) == [*cases, *stages, pairs, serve]
    for target in cases + stages:   # this tree against the same package imported as the reference, alternately
        f = figures[target]
        assert timed(f) and f.reference_label == "package copy parksim, same process"
        assert f.reference is not None and f.reference > 0 and f.reference_cpu is not None
        assert f.goal is None   # the targets hold at the issue's sizes, not the quick ones
    counts = record.data["stages"]["pairs"]
    assert counts["evaluated"] >= counts["blended"] > 0 and counts["intersections"] > 0
    assert figures[pairs].value == pytest.approx(counts["evaluated"] / counts["blended"])
    assert timed(figures[serve]) and figures[serve].reference_label.endswith("through UT, same run")
    test_frames = json.loads((tiny_data / "split.json").read_text())["test"]
    assert record.data["serve"]["test_frames"] == test_frames
    assert record.options["reference"] == "parksim" and record.options["repeats"] == 1


def test_render_goals_belong_to_the_issue_sizes_and_parts_are_checked(tiny_data, tmp_path, capsys):
    from parksim.bench.cases import bev_rig
    from parksim.bench.suites.render import RenderOptions, _cases
    from parksim.rig import Rig

    rig = bev_rig(Rig.load(tiny_data / "rig.json"), 512)
    goals = {c.target: c.goal for c in _cases(RenderOptions(), rig) if c.goal}
    assert goals == {"case (a) fwd+bwd, 1 camera 320x240, 1e5 Gaussians": "<= 150 ms",
                     "case (b) fwd, 4 cameras 640x480 + BEV 512, 2e5 Gaussians": "<= 200 ms"}
    assert not any(c.goal for c in _cases(RenderOptions(gaussians_b=100_000), rig) if c.group == "b")
    assert main(["bench", "render", "--quick", "--cases", "a,x", "--work", str(tmp_path)]) == 2
    assert "--cases takes a, b, c, stages, serve; got a,x" in capsys.readouterr().err


def test_projection_times_the_fused_path_against_the_torch_path(tmp_path):
    record = bench(tmp_path, "projection")
    figures = by_target(record)
    assert list(figures) == [f"projection {p}, {c}, 2e3 Gaussians" for c in
                             ("1 fisheye 640x480 190 deg", "4 fisheyes 640x480 190 deg") for p in ("fwd", "fwd+bwd")]
    for f in figures.values():
        assert timed(f) and f.reference_label == "torch path, same run" and f.reference > 0
    assert [(r["cameras"], r["backward"]) for r in record.data["rows"]] == [(1, False), (1, True), (4, False),
                                                                            (4, True)]


def test_rasterize_counts_pairs_and_runs_the_torch_reference_on_the_small_case(tmp_path):
    record = bench(tmp_path, "rasterize")
    figures = by_target(record)
    small = [f for t, f in figures.items() if "32x24, 200 Gaussians" in t]
    assert small and all(timed(f) and f.reference_label == "dense torch reference, same run" for f in small)
    per_pair = [f for t, f in figures.items() if "per Gaussian-pixel pair" in t]
    assert {t.split(", ")[1] for t in figures if "per Gaussian-pixel pair" in t} == {"80x60", "160x120"}
    assert all(f.unit == "ns" and f.value > 0 for f in per_pair)
    assert "rasterize fwd+bwd, 80x60, 4e3 Gaussians, numba 1 thread" in figures
    assert not any(t.startswith("rasterize fwd+bwd, 160x120") for t in figures)   # the large case: forward only
    rows = record.data["rows"]
    assert [r["backend"] for r in rows].count("torch") == 1
    for r in rows:
        assert r["evaluated"] >= r["blended"] > 0 and r["intersections"] > 0


def test_ipm_matches_cv2_remap_of_the_same_grids(tmp_path):
    record = bench(tmp_path, "ipm")
    bev = "4 x 960x640 sample -> 240x320 BEV (5 cm/px)"
    figures = by_target(record)
    assert list(figures) == [f"IPM call, {bev}", f"IPM call + backward, {bev}", f"IPM build, {bev}",
                             f"IPM max |difference| to the cv2.remap blend, {bev}"]
    call = figures[f"IPM call, {bev}"]
    assert timed(call) and call.reference_label.startswith("cv2.remap") and call.reference > 0
    assert timed(figures[f"IPM call + backward, {bev}"])
    assert figures[f"IPM build, {bev}"].unit == "s" and figures[f"IPM build, {bev}"].value > 0
    diff = figures[f"IPM max |difference| to the cv2.remap blend, {bev}"]
    assert diff.goal == "<= 0.002" and 0 <= diff.value <= 2e-3


def test_ut_accuracy_ranks_the_projections_against_monte_carlo(tmp_path):
    record = bench(tmp_path, "ut-accuracy")
    figures = by_target(record)
    for angle in (80, 85, 90, 95):
        f = figures[f"UT covariance error, {angle} deg off-axis, sigma = 0.3 d: ParkSim default"]
        assert f.unit == "%" and f.goal == "<= half of 3DGUT's" and 0 < f.value < f.reference
    rows = {(r["angle_deg"], r["sigma_over_d"]): r["methods"] for r in record.data["accuracy"]}
    assert len(rows) == 21 and all(len(m) == 5 for m in rows.values())
    wide = rows[(95, 0.3)]   # linearisation far off-axis on a large Gaussian: an order of magnitude worse
    assert wide["EWA"]["cov_rel"] > 3 * wide["19-pt deg-5"]["cov_rel"]
    assert wide["EWA"]["mean_px"] > 3 * wide["ParkSim default"]["mean_px"]
    scene = "2e3 Gaussians x 4 fisheyes 640x640"
    adaptive = figures[f"projection (cull + project, fwd), {scene}: ParkSim default (adaptive)"]
    assert timed(adaptive) and adaptive.reference_label == "7-point UT, same run"
    assert adaptive.goal == "<= 1.5x the 7-point UT"
    assert 0 < figures[f"visible Gaussians on the 19-point set, {scene}"].value < 100

