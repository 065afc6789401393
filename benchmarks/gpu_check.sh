#!/bin/bash
# The device check of a lent GPU machine, in one call: gsplat's JIT build, the CUDA tests, `parksim bench gpu`, and,
# when a reference package copy sits in .gpu/ab/parksim_prev, `parksim bench render` against it pinned to two cores
# (the "quiet 2-core machine"). Expects .whl/ (gsplat, plyfile wheels) and .gpu/ (scene1_320: rig.json,
# poses.json, points3d.ply; s1_320: a trained bundle) carried. Writes the logs under $OUT, the suites' records under
# $OUT/results (copy them to benchmarks/results/) and their dashboard rows to $OUT/RESULTS.md.
set -uo pipefail
export PYTHONUNBUFFERED=1
root=$PWD out=${OUT:-$PWD/out/gpu}
mkdir -p "$out"
[ -d /tmp/site/gsplat ] || timeout 300 bash benchmarks/gpu_setup.sh > "$out/setup.log" 2>&1 || { tail -20 "$out/setup.log"; exit 1; }
export PYTHONPATH=/tmp/site:$root
bench=(python3 -m parksim.cli bench)
where=(--quiet --work /tmp/parksim-bench --results "$out/results")
timeout 600 python3 -m pytest -v -p no:cacheprovider tests/test_render_api.py tests/test_rasterize.py \
  tests/test_losses.py tests/test_view_colors.py -k "cuda or gsplat" 2>&1 | tee "$out/pytest.log" | tail -8
if [ -d .gpu/ab/parksim_prev ]; then
  PYTHONPATH=/tmp/site:$root:$root/.gpu/ab NUMBA_NUM_THREADS=2 taskset -c 2,3 "${bench[@]}" render \
    --dataset .gpu/scene1_320 --reference parksim_prev --cases a,b,stages --repeats 9 --numba-threads 2 "${where[@]}"
fi
"${bench[@]}" gpu --dataset .gpu/scene1_320 --bundle .gpu/s1_320 --repeats 5 "${where[@]}"
"${bench[@]}" report --results "$out/results" -o "$out/RESULTS.md" && grep -E "^\| (case|large|GPU)" "$out/RESULTS.md"
