"""Success rate of the baseline geometric planner (parksim.planners) in ParkingEnv on scene1, random starts.

Each episode: a seeded random start on the aisle (either direction), the planner picks the free
slot with the shortest collision-free forward path, then drives it in closed loop through the env
API (privileged state only: world pose, no images are rendered, so the scene's Gaussians do not matter here).
Writes benchmarks/RESULTS_planner.md.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import gymnasium as gym  # noqa: E402

import parksim.env  # noqa: E402, F401  (registers ParkSim-v0)
from parksim.planners import run_episode  # noqa: E402
from sim_fixtures import make_bundle  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--preset", default="scene1")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "RESULTS_planner.md")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        env = gym.make("ParkSim-v0", bundle=make_bundle(Path(tmp) / args.preset, preset=args.preset, n=500),
                       cameras=[], privileged=True, max_episode_steps=500)
        start = time.perf_counter()
        results = [run_episode(env, seed) for seed in range(args.episodes)]
        elapsed = time.perf_counter() - start
    outcome = Counter("parked" if r["is_success"] else "collision" if r["collision"] else
                      "no path found" if not r["planned"] else "not parked in time" for r in results)
    parked = [r for r in results if r["is_success"]]
    lines = [f"# Baseline geometric planner on {args.preset}", "",
             f"- command: `python benchmarks/bench_planner.py --episodes {args.episodes} --preset {args.preset}`",
             f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
             f"- success rate: {len(parked)}/{len(results)} = {len(parked) / len(results):.0%}",
             "- outcomes: " + ", ".join(f"{k} {v}" for k, v in sorted(outcome.items())),
             f"- parked episodes: mean {sum(r['steps'] for r in parked) / max(len(parked), 1):.0f} steps "
             f"({0.1 * sum(r['steps'] for r in parked) / max(len(parked), 1):.1f} s simulated), final centre error "
             f"max {max((r['distance'] for r in parked), default=0):.2f} m, heading error max "
             f"{max((r['heading_error'] for r in parked), default=0):.3f} rad",
             f"- wall time {elapsed:.0f} s for all episodes (planning dominates)", "",
             "Forward moves only: starts that face away from every reachable free slot find no path "
             "(a U-turn does not fit in the 6 m aisle).", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
