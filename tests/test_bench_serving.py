"""``parksim bench`` serving suites (server, server-memory, batch, ray, env): each ``--quick`` run through the real
CLI, against real ``parksim serve`` subprocesses and a real local Ray, writes a record with the expected targets,
finite values, units and the references measured in the same run, and leaves no server or Ray instance behind.

The suites share one work folder (the tiny garage bundle is made once); the Ray suites share one Ray instance
started here (2 CPUs, small object store) and shut down at the end of the module.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

from parksim.bench.procs import descendants, local_ray, process_name
from parksim.bench.record import Figure, Record, read_record
from parksim.cli import main

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("bench-serving")


def bench(work: Path, name: str, *args: str) -> Record:
    """Run ``parksim bench NAME --quick`` into ``work/results``; its one record."""
    results = work / "results"
    assert main(["bench", name, "--quick", "--quiet", "--work", str(work), "--results", str(results), *args]) == 0
    (path,) = (results / name).glob("*.json")
    return read_record(path)


def figures(record: Record) -> dict[str, Figure]:
    """Target -> figure, after checking every value is finite and the targets are distinct."""
    found = {f.target: f for f in record.figures}
    assert len(found) == len(record.figures)
    for f in record.figures:
        assert all(v is None or math.isfinite(v) for v in (f.value, f.cpu, f.reference, f.reference_cpu)), f
    return found


def no_ray_left() -> None:
    """No Ray daemon among this process's descendants (the module's own instance aside)."""
    assert not ray.is_initialized()
    assert not [p for p in descendants(os.getpid()) if process_name(p) in ("raylet", "gcs_server")]


def test_server_latency_load_and_memory(work):
    record = bench(work, "server")
    found = figures(record)
    scene = record.data["scene"]
    assert scene.startswith("2,000 Gaussians, 4 x 160x120 views")
    main_case = found[f"GET /render 4 views + BEV, {scene}: p50 latency"]
    assert main_case.unit == "ms" and main_case.goal == "<= 250 ms" and main_case.value > 0
    assert main_case.cpu is not None and main_case.cpu >= 0
    for case in ("4 views + BEV", "one view (front)", "BEV only"):
        p50, p95 = (found[f"GET /render {case}, {scene}: p{q} latency"] for q in (50, 95))
        assert 0 < p50.value <= p95.value
        assert record.data["latency"][case]["n"] == 3 == len(record.data["latency"][case]["ms"])
    load = record.data["load"]
    assert load["ok"] > 0 and load["errors"] == 0
    assert found[f"GET /render 4 views + BEV, {scene}: renders/s at 4 clients"].value == pytest.approx(
        load["ok"] / load["seconds"])
    stages = record.data["stages"]
    assert {"queue", "views", "bev", "encode"} <= set(stages)
    assert stages["views"]["jobs"] >= 3 * 2 + load["ok"]   # the cases with views, and every render of the load
    assert found[f"parksim serve RSS after the load test, {scene}"].value > 100


def test_server_memory_stays_within_the_reply_budget(work):
    record = bench(work, "server-memory")
    found = figures(record)
    data = record.data
    reply, budget = data["request"]["reply_mib"], data["budget_mib"]
    assert 4 < reply <= 8   # the quick preset's largest reply: above the kernel's socket buffers
    bounded, control = data["bounded"], data["control"]
    assert bounded["held_clients"] == budget // reply and bounded["held_mib"] <= budget
    assert bounded["held_clients"] + bounded["refused_503"] == 4
    assert control["held_clients"] == 4 and control["refused_503"] == 0
    assert bounded["released"] == control["released"] == 1.0
    peak = next(f for t, f in found.items() if t.startswith("parksim serve peak RSS"))
    assert peak.unit == "MiB" and peak.value == bounded["peak_with_clients"]
    assert peak.reference == control["peak_with_clients"] and peak.reference_label.startswith("control")
    headroom = next(f for t, f in found.items() if t.startswith("headroom"))
    assert headroom.goal == ">= 0 MiB" and headroom.value == pytest.approx(data["bound_mib"] - peak.value)


def test_batch_times_every_process_of_each_command(work):
    record = bench(work, "batch")
    sequential, batch = record.figures
    assert sequential.target.startswith("sequential") and sequential.reference is None
    assert batch.target.startswith("Ray tasks") and batch.reference == sequential.value
    assert batch.reference_cpu == sequential.cpu
    for f in (sequential, batch):
        assert f.unit == "s" and f.value > 0 and f.cpu > 0
    for variant in record.data["variants"].values():
        (run,) = variant["runs"]
        assert run["train_wall_s"] > 0 and 0 < run["train_cpu_s"] < run["cpu_s"]
    no_ray_left()


@pytest.fixture(scope="module")
def ray_instance():
    """One local Ray instance for the Ray suites of this module (2 CPUs, small object store)."""
    with local_ray(2):
        yield
    no_ray_left()


def test_ray_serve_against_the_single_process_server(work, ray_instance):
    record = bench(work, "ray")
    found = figures(record)
    label = "Ray Serve, 1 replica x 2 CPUs"
    assert list(record.data["ray"]) == [label]
    run, single = record.data["ray"][label], record.data["single"]
    for r in (run, single):
        assert r["ok"] > 0 and r["errors"] == 0
    assert run["cpu"]["replicas"] > 0 and run["rss_replicas"] > 0 and run["rss_ray"] > 0
    load = f"4 clients on GET /render every view + BEV, {record.data['scene']}"
    rate, p99, cpu = (found[f"{label}: {what}, {load}"] for what in ("renders/s", "p99 latency",
                                                                      "server-side CPU per render"))
    assert (rate.value, rate.reference, rate.better) == (run["throughput"], single["throughput"], "higher")
    assert (p99.value, p99.reference, p99.unit) == (run["p99"], single["p99"], "ms")
    assert cpu.value > 0 and cpu.reference > 0 and cpu.unit == "ms"
    assert {f.reference_label for f in (rate, p99, cpu)} == {"parksim serve, single process"}
    idle = record.data["idle"]
    assert {"raylet", "gcs_server", "ray::ServeController"} <= set(idle["rss"])
    assert found["idle Ray + Serve (no app deployed): RSS of its processes"].value == pytest.approx(
        sum(idle["rss"].values()))
    assert ray.is_initialized()   # the module's instance is used and left running, Serve (the suite's) is down
    assert not [p for p in descendants(os.getpid()) if process_name(p).startswith(("ray::ServeController",
                                                                                    "ray::ProxyActor"))]


def test_env_vectorisations_against_sync_vector_env(work, ray_instance):
    record = bench(work, "env")
    found = figures(record)
    assert set(record.data["rows"]) == {"sync", "ray", "serve-ray"}
    for label in ("in-process SyncVectorEnv", "Ray actors (RayVectorEnv)", "batch POST /render, serve --ray"):
        (f,) = (f for t, f in found.items() if t.startswith(f"{label}, 2 envs: ms per env step"))
        assert f.unit == "ms" and f.value > 0 and f.cpu > 0
        if label.startswith("in-process"):
            assert f.reference is None
            sync = f
        else:
            assert f.reference == sync.value and f.reference_cpu == sync.cpu
            assert f.reference_label == "in-process SyncVectorEnv"


@pytest.mark.parametrize("args", [["ray", "--configs", "3x3"], ["batch", "--variants", "ray-nothing"],
                                  ["env", "--backends", "dask"],
                                  ["server-memory", "--max-reply-mib", "32", "--reply-budget-mib", "16"]])
def test_bad_options_are_refused_before_anything_runs(args, tmp_path, capsys):
    assert main(["bench", *args, "--quick", "--work", str(tmp_path)]) == 2
    assert args[-1] in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
