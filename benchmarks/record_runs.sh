#!/usr/bin/env bash
# The full-preset suite runs whose records were committed on 2026-11-27 (issue [14]), one at a time on a quiet
# machine, then the dashboard. Run from the repository root after `make setup`; each suite writes
# benchmarks/results/SUITE/STAMP-COMMIT.json. The render suite's reference is the package as it was before that
# session (commit 1c52457), imported from a copy under another name and timed alternately in the same process.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=.venv/bin
REF=${REF:-1c52457}
AB=$(mktemp -d)
trap 'rm -rf "$AB"' EXIT
git archive "$REF" parksim | tar -x -C "$AB" && mv "$AB/parksim" "$AB/parksim_prev"

PYTHONPATH="$AB" $BIN/parksim bench render --reference parksim_prev --quiet
for suite in ipm ut-accuracy projection rasterize server scaling synth knobs env soak-server import ray stress \
             server-memory batch pose-refine; do
  $BIN/parksim bench "$suite" --quiet
done
$BIN/parksim bench report

# Issue [18] (2026-11-27, second session): the reliability figures re-measured after the hardening (schemathesis
# comes with the dev extra; 3000 examples per operation is about as many requests as the probe's 19,022).
$BIN/parksim bench hardening --quiet
$BIN/parksim bench hardening --schemathesis-examples 3000 --quiet
for suite in server-memory soak-server; do
  $BIN/parksim bench "$suite" --quiet
done
$BIN/parksim bench report

# 2026-11-28 (issues [16] and [17]): the real-recording experiment (fixed schedule, see the suite's docstring), the
# actors' render overhead on 2e5 Gaussians, and the planner suite with the Hybrid A* planner beside the geometric one.
$BIN/parksim bench real --quiet
$BIN/parksim bench actors --quiet
$BIN/parksim bench planner --planners geometric,hybrid --quiet
$BIN/parksim bench report

# 2026-11-28 (issue [17]): the scenario scorecards: a graded set of 30 per scene (scene1, worn, busy), every planner.
$BIN/parksim bench scenarios --quiet
$BIN/parksim bench report
