#!/bin/bash
# The device check of a lent GPU machine, in one call (see RESULTS_gpu.md): gsplat's JIT build, the CUDA tests,
# bench_gpu.py, and, when a reference package copy sits in .gpu/ab/parksim_prev, the renderer A/B pinned to two
# cores (the "quiet 2-core machine"). Expects .whl/ (gsplat, plyfile wheels) and .gpu/ (scene1_320:
# rig.json, poses.json, points3d.ply; s1_320: a trained bundle) carried; writes its reports under $OUT.
set -uo pipefail
export PYTHONUNBUFFERED=1
root=$PWD out=${OUT:-$PWD/out/gpu}
mkdir -p "$out"
[ -d /tmp/site/gsplat ] || timeout 300 bash benchmarks/gpu_setup.sh > "$out/setup.log" 2>&1 || { tail -20 "$out/setup.log"; exit 1; }
export PYTHONPATH=/tmp/site:$root
timeout 600 python3 -m pytest -v -p no:cacheprovider tests/test_render_api.py tests/test_rasterize.py \
  tests/test_losses.py tests/test_view_colors.py -k "cuda or gsplat" 2>&1 | tee "$out/pytest.log" | tail -8
if [ -d .gpu/ab/parksim_prev ]; then
  PYTHONPATH=/tmp/site:$root:$root/.gpu/ab NUMBA_NUM_THREADS=2 taskset -c 2,3 python3 benchmarks/bench_render.py \
    --dataset .gpu/scene1_320 --reference parksim_prev --cases "(a)" --cases "(b)" --stages --repeats 9 \
    --numba-threads 2 --out "$out/RESULTS_render_2core.md" | tail -25
fi
cd benchmarks && python3 bench_gpu.py --dataset ../.gpu/scene1_320 --bundle ../.gpu/s1_320 --repeats 5 \
  --out "$out/RESULTS_gpu.md" | grep -E "^\| \(|^\| 1e6"
