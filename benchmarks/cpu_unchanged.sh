#!/usr/bin/env bash
# Whether the CPU render path still gives the bits it gave at commit REF (default: the commit before the 2026-11-27
# kernel changes): one render of a garage scene (four fisheye views, alpha, depth, BEV) by the package at REF and by
# the working tree's, each in its own process (run from the REF copy's folder, the editable install's finder set aside), compared with torch.equal. Needs a
# synth dataset (DATA, default out/bench/data/tiny; `parksim synth tiny -o DATA` makes one).
set -euo pipefail
cd "$(dirname "$0")/.."
REF=${REF:-b3eff7d}
DATA=$(realpath "${DATA:-out/bench/data/tiny}")
PY="$PWD/.venv/bin/python"
N=${N:-30000}
AB=$(mktemp -d)
trap 'rm -rf "$AB"' EXIT
git archive "$REF" parksim | tar -x -C "$AB"
RENDER='import sys
sys.meta_path[:] = [f for f in sys.meta_path if "Editable" not in getattr(f, "__name__", "")]  # the cwd decides
import torch
from pathlib import Path
import parksim.bench.scenes as scenes, parksim.render.api as api
from parksim.data import DatasetReader
data = Path(sys.argv[1]); rig = DatasetReader(data).rig
r = api.render(scenes.garage_scene(data, int(sys.argv[2])), rig, (2.0, 0.5, 0.1), bev=True)
torch.save({"images": r.images, "alpha": r.alpha, "depth": r.depth, "bev": r.bev, "at": api.__file__}, sys.argv[3])'
(cd "$AB" && "$PY" -c "$RENDER" "$DATA" "$N" "$AB/ref.pt")
.venv/bin/python -c "$RENDER" "$DATA" "$N" "$AB/now.pt"
.venv/bin/python - "$AB/ref.pt" "$AB/now.pt" "$REF" "$N" <<'PY'
import sys

import torch

ref, now = torch.load(sys.argv[1]), torch.load(sys.argv[2])
assert ref["at"] != now["at"], "both renders came from one package"
for kind in ("images", "alpha", "depth"):
    worst = max(float((ref[kind][k] - now[kind][k]).abs().max()) for k in ref[kind])
    print(f"{kind}: {'bit-identical' if worst == 0 else f'DIFFERENT (max {worst:.3g})'} to {sys.argv[3]} "
          f"({sys.argv[4]} Gaussians, {len(ref[kind])} views)")
worst = float((ref["bev"] - now["bev"]).abs().max())
print(f"bev: {'bit-identical' if worst == 0 else f'DIFFERENT (max {worst:.3g})'} to {sys.argv[3]}")
PY
