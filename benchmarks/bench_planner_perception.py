"""Perception planner (detected slot, dead reckoning, no world pose) against the privileged geometric planner.

One scene bundle (surface Gaussians of a synthetic garage, ``tests/sim_fixtures.make_bundle``). The detector
is trained here on the simulator's own BEVs of that bundle (``parksim.planners.slot_data``: random aisle and
slot-entry poses, drawn from their own seed, labelled from the map). Each episode seed is run twice from the
same start: the privileged baseline (``run_episode``: world pose and map, picks the free slot with the
shortest collision-free path), then the perception planner told that same slot in the ego frame (as the
non-privileged env observation gives it). Writes benchmarks/RESULTS_planner_perception.md.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from statistics import median

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import torch  # noqa: E402

from parksim.env import ParkingEnv  # noqa: E402
from parksim.planners import run_episode  # noqa: E402
from parksim.planners.perception import PerceptionParker, run_perception_episode  # noqa: E402
from parksim.planners.slot_data import write_training_bevs  # noqa: E402
from parksim.recon.detectors import load_detector  # noqa: E402
from parksim.recon.detectors.train import TrainOptions, train_detector  # noqa: E402
from sim_fixtures import make_bundle  # noqa: E402


def _cpu() -> str:
    out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    names = [line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name")]
    return names[0] if names else platform.processor() or "unknown CPU"


def _outcome(r: dict) -> str:
    return ("parked" if r["is_success"] else "collision" if r["collision"] else
            "no path found" if not r["planned"] else "not parked in time")


def _summary(name: str, results: list[dict]) -> list[str]:
    parked = [r for r in results if r["is_success"]]
    counts = Counter(_outcome(r) for r in results)
    line = (f"| {name} | {len(parked)}/{len(results)} = {len(parked) / len(results):.0%} | "
            + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) + " | ")
    if parked:
        line += (f"{median(r['steps'] for r in parked):.0f} | {median(r['distance'] for r in parked):.3f} / "
                 f"{max(r['distance'] for r in parked):.3f} | {median(r['heading_error'] for r in parked):.4f} / "
                 f"{max(r['heading_error'] for r in parked):.4f} |")
    else:
        line += "- | - | - |"
    return [line]


def _detector(bundle: Path, work: Path, args: argparse.Namespace) -> tuple[Path, float, float]:
    """Render the training BEVs and train (each reused when ``work`` has it); wall and process-CPU seconds here."""
    wall, cpu = time.perf_counter(), time.process_time()
    bevs = work / "bevs"
    if not bevs.is_dir():
        write_training_bevs(bundle, bevs, args.train_bevs, seed=args.train_seed, scale=args.scale)
    model = work / "dmpr"
    if not (model / "train.json").is_file():
        # one thread: on a loaded 2-core machine a second one mostly spins (3x the CPU time per step)
        train_detector([bevs], model, TrainOptions(steps=args.train_steps, input_size=args.input_size, lr=3e-3,
                                                   seed=args.train_seed, threads=1), progress=False)
    return model, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=30, help="seeds 0 .. episodes-1")
    ap.add_argument("--preset", default="scene1")
    ap.add_argument("--gaussians", type=int, default=150_000)
    ap.add_argument("--scale", type=float, default=0.5, help="fisheye render scale the BEV is made from")
    ap.add_argument("--every", type=int, default=5, help="steps between the planner's BEVs")
    ap.add_argument("--train-bevs", type=int, default=120)
    ap.add_argument("--train-steps", type=int, default=1200)
    ap.add_argument("--input-size", type=int, default=256)
    ap.add_argument("--train-seed", type=int, default=1000, help="training poses and weights (not an episode seed)")
    ap.add_argument("--work", type=Path, default=ROOT / "benchmarks" / "results" / "planner_perception",
                    help="bundle, training BEVs and detector (reused when there)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS_planner_perception.md")
    args = ap.parse_args()
    torch.set_num_threads(2)
    bundle = args.work / args.preset
    if not bundle.is_dir():
        make_bundle(bundle, preset=args.preset, n=args.gaussians)
    model_dir, train_wall, train_cpu = _detector(bundle, args.work, args)
    detector = load_detector(model_dir)
    privileged = ParkingEnv(bundle=bundle, cameras=[], privileged=True)
    env = ParkingEnv(bundle=bundle, cameras=[], bev=True, scale=args.scale)
    spec = env.sim.bundle.rig.bev
    base, perc, rows = [], [], []
    times = {"baseline": [0.0, 0.0], "perception": [0.0, 0.0]}
    for seed in range(args.episodes):
        wall, cpu = time.perf_counter(), time.process_time()
        b = run_episode(privileged, seed)
        times["baseline"][0] += time.perf_counter() - wall
        times["baseline"][1] += time.process_time() - cpu
        wall, cpu = time.perf_counter(), time.process_time()
        p = run_perception_episode(env, seed, PerceptionParker(detector, spec, every=args.every),
                                   options={"slot": b["slot"]})
        times["perception"][0] += time.perf_counter() - wall
        times["perception"][1] += time.process_time() - cpu
        base.append(b)
        perc.append(p)
        rows.append(f"| {seed} | {b['slot']} | {_outcome(b)} | {b['steps']} | {_outcome(p)} | {p['steps']} | "
                    f"{p['distance']:.3f} | {p['heading_error']:.4f} | {'yes' if p['perceived'] else 'no'} | "
                    f"{p['views']} |")
        print(rows[-1], flush=True)
    both = sum(b["is_success"] and p["is_success"] for b, p in zip(base, perc))
    command = "python benchmarks/bench_planner_perception.py " + " ".join(sys.argv[1:])
    lines = [f"# Perception planner vs privileged geometric planner on {args.preset}", "",
             f"- command: `{command.strip()}`",
             f"- machine: {_cpu()}, {os.cpu_count()} cores, torch {torch.__version__} with 2 threads; shared with "
             f"other jobs (load average at the end {os.getloadavg()[0]:.1f}), so compare process-CPU times",
             f"- date: {datetime.datetime.now().isoformat(timespec='minutes')}",
             f"- bundle: `make_bundle(preset={args.preset!r}, n={args.gaussians})`; BEV from fisheye views rendered at "
             f"scale {args.scale}, {spec.width} px = {spec.width * spec.m_per_px:g} m",
             f"- detector: DMPR-style, input {args.input_size} px, trained {args.train_steps} steps on "
             f"{args.train_bevs} BEVs of this bundle (poses from seed {args.train_seed}); rendering + training "
             f"{train_wall:.0f} s wall, {train_cpu:.0f} s process CPU (0 when reused from `{args.work.name}`)",
             f"- episodes: seeds 0..{args.episodes - 1} (fixed before any run), same start and slot for both "
             f"planners; perception planner takes a BEV every {args.every} steps", "",
             "| planner | success | outcomes | median steps (parked) | centre error m, median / max | "
             "heading error rad, median / max |", "| --- | --- | --- | --- | --- | --- |",
             *_summary("privileged geometric (world pose + map)", base),
             *_summary("perception (BEV detector + dead reckoning)", perc), "",
             f"Both parked in {both} episodes. Time over all episodes: baseline {times['baseline'][0]:.0f} s wall / "
             f"{times['baseline'][1]:.0f} s CPU; perception {times['perception'][0]:.0f} s wall / "
             f"{times['perception'][1]:.0f} s CPU (rendering, detection and planning).", "",
             "| seed | slot | baseline | steps | perception | steps | centre error m | heading error rad | "
             "target seen | BEVs |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |", *rows, ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
