"""``parksim scenarios make`` and ``run`` end to end on a small real scene1 bundle: a graded set with thumbnails,
the same set from the same seed, a run's results, table and plots, the same results.json from a second run and from
Ray tasks, a planner class of one's own, and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from parksim.cli import main
from parksim.imageio import read_image
from parksim.planners.scenario_runs import run_set
from parksim.scenarios import load_set
from sim_fixtures import make_bundle

COUNT = 6


class StandStill:
    """A planner of one's own (``--planner test_scenario_runs:StandStill``): no throttle, no steering: it stays."""

    privileged, bev, status, wants_view = True, False, "", False

    def start(self, world, obs):
        self.status = ""

    def act(self, world, obs):
        return np.zeros(2, np.float32)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    return make_bundle(tmp_path_factory.mktemp("runs") / "scene1", preset="scene1", n=300, bev_px=64)


@pytest.fixture(scope="module")
def made(bundle):
    out = bundle.parent / "graded"
    assert main(["scenarios", "make", str(bundle), "-o", str(out), "--count", str(COUNT), "--seed", "3"]) == 0
    return out


def test_make_writes_a_graded_set_with_a_thumbnail_each(made, bundle, tmp_path):
    graded = load_set(made)
    assert [s.difficulty for s in graded.scenarios] == ["easy"] * 2 + ["medium"] * 2 + ["hard"] * 2
    assert all((made / s.scene / "bundle.json").is_file() for s in graded.scenarios), "scene: the bundle, relative"
    for s in graded.scenarios:
        image = read_image(made / "thumbnails" / f"{s.name}.png")
        assert image.shape[2] == 3 and image.std() > 0.02, s.name
    again = tmp_path / "again"
    assert main(["scenarios", "make", str(bundle), "-o", str(again), "--count", str(COUNT), "--seed", "3",
                 "--no-thumbnails"]) == 0
    assert not (again / "thumbnails").exists()
    for path in sorted(made.glob("*.yaml")):
        assert (again / path.name).read_text() == path.read_text().replace(
            graded.scenarios[0].scene, load_set(again).scenarios[0].scene), path.name


def test_run_writes_results_a_table_and_plots_and_repeats_exactly(made, tmp_path, capsys):
    first, second = tmp_path / "first", tmp_path / "second"
    assert main(["scenarios", "run", str(made), "--planner", "hybrid", "-o", str(first), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert main(["scenarios", "run", str(made), "--planner", "hybrid", "-o", str(second), "--quiet",
                 "--no-plots"]) == 0
    assert (first / "results.json").read_bytes() == (second / "results.json").read_bytes()
    results = json.loads((first / "results.json").read_text())
    assert results["planner"] == "hybrid" and len(results["episodes"]) == COUNT
    assert results["summary"]["all"]["episodes"] == COUNT
    assert sum(results["summary"]["all"]["outcomes"].values()) == COUNT
    easy_medium = [e for e in results["episodes"] if e["difficulty"] != "hard"]
    assert all(e["outcome"] == "parked" for e in easy_medium), easy_medium
    assert all(e["scorecard"]["success"] == (e["outcome"] == "parked") for e in results["episodes"])
    table = (first / "results.md").read_text()
    assert "| all | 6 |" in table and "| easy | 2 |" in table and "plots/easy_000.png" in table
    assert "| all | 6 |" in printed
    for e in results["episodes"]:
        image = read_image(first / "plots" / f"{e['scenario']}.png")
        assert image.shape[2] == 3 and image.shape[1] > 100
    assert not (second / "plots").exists()
    timings = json.loads((first / "timings.json").read_text())["episodes"]
    assert [t["scenario"] for t in timings] == [e["scenario"] for e in results["episodes"]]


def test_ray_tasks_give_the_same_results(made):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, object_store_memory=100 * 1024**2, include_dashboard=False, logging_level="ERROR",
             log_to_driver=False)
    try:
        spread = run_set(made, "geometric", ray=True)
    finally:
        ray.shutdown()
    assert spread.results_json() == run_set(made, "geometric").results_json()


def test_a_planner_of_ones_own_runs_by_module_and_class(made, tmp_path):
    out = tmp_path / "own"
    assert main(["scenarios", "run", str(made / "easy_000.yaml"), "--planner", "test_scenario_runs:StandStill",
                 "-o", str(out), "--quiet", "--no-plots"]) == 0
    (episode,) = json.loads((out / "results.json").read_text())["episodes"]
    assert episode["outcome"] == "not parked in time" and episode["scorecard"]["path_length"] < 0.01


@pytest.mark.parametrize("argv, message", [
    (["--planner", "teleport"], "unknown planner 'teleport'"),
    (["--planner", "no_such_module:Planner"], "cannot be loaded"),
    (["--planner", "test_scenario_runs:COUNT"], "is not a class"),
    (["--planner", "json:JSONDecoder"], "lacks a ScenarioPlanner member"),
    (["--planner", "perception"], "needs a slot detector checkpoint"),
    (["--scenes", "/nowhere", "--bundle", "/nowhere/at/all"], "no scene bundle"),
])
def test_bad_runs_are_one_line(made, tmp_path, capsys, argv, message):
    assert main(["scenarios", "run", str(made), "-o", str(tmp_path / "out"), "--quiet", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


def test_bench_scenarios_quick_records_the_scorecards(tmp_path):
    """``parksim bench scenarios --quick``: a figure per scene, planner and difficulty against Hybrid A*, Hybrid A*'s
    easy and medium against the 90 % goal, the full tables as the record's details, the trajectory grid."""
    from parksim.bench.record import records_in

    results = tmp_path / "results"
    assert main(["bench", "scenarios", "--quick", "--quiet", "--work", str(tmp_path / "work"),
                 "--results", str(results)]) == 0
    ((path, record),) = records_in(results)
    targets = {f.target: f for f in record.figures}
    hybrid_easy = targets["tiny, hybrid: parked, easy (1 of 3 scenarios)"]
    assert hybrid_easy.goal == ">= 90 %" and hybrid_easy.reference is None
    geometric_hard = targets["tiny, geometric: parked, hard (1 of 3 scenarios)"]
    assert geometric_hard.reference_label == "Hybrid A* on the same scenarios" and geometric_hard.goal is None
    assert "## tiny" in record.details and "| hybrid: all | 3 |" in record.details
    assert "Hybrid A* on easy and medium:" in record.details
    assert (path.parent / record.plot).is_file()
    episodes = record.data["scenes"]["tiny"]["planners"]["hybrid"]["episodes"]
    assert [e["difficulty"] for e in episodes] == ["easy", "medium", "hard"]
