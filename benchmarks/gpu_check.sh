#!/bin/bash
# The device check of a lent GPU machine (an H100 or H200 with no network), in ONE call of the device tool:
#
#   run(command="bash benchmarks/gpu_check.sh", carry=[".whl"], timeout_s=600)     (add ".gpu" when it is carried)
#
# One command may run 10 minutes and a session has 15 of device time, start-up included, so every step runs under
# `timeout` (SIGINT first, so servers and workers stop cleanly) and all of them within GPU_CHECK_BUDGET_S (default
# 570 s): a step that would pass the budget gets what is left (the env step leaves 90 s to the training), or is
# skipped below 30 s. One line per step:
#
#   setup   the wheels below into /tmp/site and gsplat's JIT build with 3DGUT (benchmarks/gpu_setup.sh, ~80 s);
#           skipped when /tmp/site/gsplat exists (a warm machine)
#   synth   parksim synth scene1 (640x480, 100 frames) in the background while the tests run: bench gpu's points,
#           rig and poses, and the training data
#   tests   the CUDA tests: pytest tests/test_device_kernels.py tests/test_render_api.py tests/test_rasterize.py
#           tests/test_losses.py tests/test_view_colors.py -k "(cuda or gsplat) and not ptx": the numba-cuda
#           kernels against their CPU target (values and gradients, three lenses), render() and render_batch on CUDA
#           against the CPU path, gsplat's rasterizer, D-SSIM and the SH colour step in float32 on CUDA.
#           The device kernels' CPU-only tests and their PTX compile run in CI; here they would add ~2 minutes of
#           single-threaded numba compiles (3 minutes on the shared 2-core development machine)
#   bench   parksim bench gpu: cases (a), (b) and 1e6 on CUDA beside the CPU path and gsplat's 3DGUT, render_batch
#           of 64 poses x 4 x 320x240 + BEV, image agreement (--bundle .gpu/bundle when carried)
#   server  parksim bench server --device cuda: GET /render p50 (4 views + BEV) and renders/s at 16 clients
#   env     parksim bench env --device cuda --envs 64 (4 x 320x240 each): SyncVectorEnv of 64 LocalSims on the GPU,
#           and one batch POST /render per step against parksim serve --device cuda
#   train   parksim reconstruct DATA --config gpu_fast --device cuda, cut off by `timeout`: its metrics.jsonl is the
#           training curve
#
# Name steps to run some only: `bash benchmarks/gpu_check.sh bench server` (synth runs when bench or train needs it).
# What comes back under $OUT (the tool returns at most 8 files): summary.txt (the step lines and every figure),
# RESULTS.md (the dashboard of this run's records), train_metrics.jsonl, and gpu_check.tgz (logs/ and
# results/SUITE/*.json: copy the records into benchmarks/results/, then `parksim bench report`).
#
# The machine has CUDA 13, torch 2.11+cu130, numba 0.68 with numba-cuda 0.30.4 (parksim.render._numba_cuda works
# around its import failure under numpy 2.5), Triton, httpx, prometheus-client, jinja2, rich, jaxtyping and ninja,
# and none of the packages below. Fetch them once on a connected machine, in the repository root (13 MB; .whl/ is
# git-ignored; versions as tested here):
#
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
#     gsplat==1.5.3 plyfile==1.1.5 pydantic==2.14.4 pydantic-core==2.50.5 annotated-types==0.8.0 \
#     typing-inspection==0.4.5 typing-extensions==4.16.0 fastapi==0.165.0 starlette==1.10.0 uvicorn==0.54.0 \
#     annotated-doc==0.0.7 opentelemetry-api==1.45.2 swagger-ui-bundle-v2==5.31.0 gymnasium==1.4.0 \
#     farama-notifications==0.0.6
#
# (gsplat: the rasterizer and 3DGUT; plyfile: scenes; pydantic: training configs and the server; fastapi,
# starlette, uvicorn, annotated-doc, opentelemetry-api, swagger-ui-bundle-v2: the server; gymnasium,
# farama-notifications: the env.) Optional: a trained bundle in .gpu/bundle (the cpu_fast bundle of scene1 at
# 320x240 is ~7 MB) adds bench gpu's agreement check on trained Gaussians; keep .gpu/ out of git with
# `echo /.gpu/ >> .git/info/exclude`.
set -uo pipefail
export PYTHONUNBUFFERED=1
root=$PWD
out=${OUT:-$root/out/gpu_check}
work=${GPU_CHECK_WORK:-/tmp/gpu_check}
budget=${GPU_CHECK_BUDGET_S:-570}
start=$SECONDS
steps=${*:-setup tests bench server env train}
data=$work/data/scene1
summary=$work/summary.txt
mkdir -p "$out" "$work/logs" "$work/results"
: > "$summary"
export PYTHONPATH=/tmp/site:$root
parksim=(python3 -m parksim.cli)
where=(--quiet --work "$work/bench" --results "$work/results")

wants() { [[ " $steps " == *" $1 "* ]]; }
note() { echo "$*" | tee -a "$summary"; }

pack() {   # everything so far to $OUT, so a kill past the budget still leaves it there
    cp "$summary" "$out/summary.txt"
    [ -f "$work/RESULTS.md" ] && cp "$work/RESULTS.md" "$out/RESULTS.md"
    [ -f "$work/train/metrics.jsonl" ] && cp "$work/train/metrics.jsonl" "$out/train_metrics.jsonl"
    tar -czf "$out/gpu_check.tgz.part" -C "$work" logs results summary.txt &&
        mv "$out/gpu_check.tgz.part" "$out/gpu_check.tgz"
}

step() {   # step NAME LIMIT_S KEEP_S COMMAND...: run it under timeout, leaving KEEP_S of the budget to later steps;
           # log to logs/NAME.log, one line to the summary
    local name=$1 limit=$2 left t0 rc verdict last
    left=$((budget - (SECONDS - start) - 10 - $3))
    shift 3
    ((limit > left)) && limit=$left
    if ((limit < 30)); then
        left=$((budget - (SECONDS - start)))
        note "$(printf '%-7s SKIPPED: %d s of the %d s budget left' "$name" "$left" "$budget")"
        return 1
    fi
    t0=$SECONDS
    timeout -s INT -k 15 "$limit" "$@" > "$work/logs/$name.log" 2>&1
    rc=$?
    case $rc in
        0) verdict=ok ;;
        124 | 137) verdict="TIMEOUT at ${limit} s" ;;
        *) verdict="FAILED (exit $rc)" ;;
    esac
    last=$(tr '\r' '\n' < "$work/logs/$name.log" | grep -v '^\s*$' | tail -1 | cut -c1-150)
    note "$(printf '%-7s %-16s %4d s  %s' "$name" "$verdict" "$((SECONDS - t0))" "$last")"
    pack
    return $rc
}

figures() {   # figures SUITE: every figure of the suite's newest record, one line each, into the summary
    python3 - "$work/results" "$1" << 'EOF' | tee -a "$summary"
import json, sys
from pathlib import Path

records = sorted((Path(sys.argv[1]) / sys.argv[2]).glob("*.json"))
if records:
    r = json.loads(records[-1].read_text())
    m = r["machine"]
    print(f"  {r['suite']}: {m.get('gpu')}, {m['cpu_model']} x {m['cores']}; {r['versions']}")
    for f in r["figures"]:
        line = f"  {f['target']} = {float(f['value']):.4g} {f['unit']}"
        line += f" (cpu {float(f['cpu']):.4g})" if f.get("cpu") is not None else ""
        if f.get("reference") is not None:
            line += f"; ref {float(f['reference']):.4g} ({f['reference_label'][:40]})"
        print(line + (f"; goal {f['goal']}" if f.get("goal") else ""))
else:
    print(f"  {sys.argv[2]}: no record")
EOF
}

card=$(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null | head -1)
commit=$(git rev-parse --short HEAD 2> /dev/null || echo "unknown: no .git here, the records say so too; note it")
note "gpu_check $(date -u +%FT%TZ) on ${card:-no GPU}; commit $commit; steps: $steps; budget $budget s"
if wants setup; then
    if [ -d /tmp/site/gsplat ]; then
        note "setup   skipped: /tmp/site/gsplat is there"
    else
        step setup 240 0 bash benchmarks/gpu_setup.sh
    fi
fi
synth_pid=
if { wants bench || wants train; } && [ ! -f "$data/rig.json" ]; then   # CPU work: overlaps the tests
    limit=$((budget - (SECONDS - start) - 120))
    ((limit > 300)) && limit=300
    timeout -s INT -k 15 "$limit" "${parksim[@]}" synth scene1 -o "$data" --quiet > "$work/logs/synth.log" 2>&1 &
    synth_pid=$!
fi
wants tests && step tests 200 0 python3 -m pytest -q -p no:cacheprovider tests/test_device_kernels.py \
    tests/test_render_api.py tests/test_rasterize.py tests/test_losses.py tests/test_view_colors.py \
    -k "(cuda or gsplat) and not ptx"
if [ -n "$synth_pid" ]; then   # before the timed steps: the CPU path's timings need the cores
    t0=$SECONDS
    wait "$synth_pid"
    rc=$?
    note "$(printf '%-7s %-16s %4d s  %s' synth "exit $rc" "$((SECONDS - t0))" "waited for it after the tests: $data")"
fi
if wants bench; then
    dataset=(); [ -f "$data/rig.json" ] && dataset=(--dataset "$data")
    bundle=(); [ -f .gpu/bundle/bundle.json ] && bundle=(--bundle .gpu/bundle)
    step bench 240 0 "${parksim[@]}" bench gpu "${dataset[@]}" "${bundle[@]}" "${where[@]}"
    figures gpu
fi
if wants server; then
    step server 150 0 "${parksim[@]}" bench server --device cuda --requests 20 --clients 16 --duration 20 "${where[@]}"
    figures server
fi
if wants env; then
    keep=0; wants train && keep=90   # the training curve before the env figures: bench gpu's render_batch has one
    step env 150 "$keep" "${parksim[@]}" bench env --device cuda --envs 64 --backends sync,serve --preset scene1 \
        --gaussians 200000 --scale 0.5 --steps 5 --warmup 1 --repeats 1 "${where[@]}"
    figures env
fi
if wants train; then
    if [ -f "$data/rig.json" ]; then
        rm -rf "$work/train"
        step train 180 0 "${parksim[@]}" reconstruct "$data" -o "$work/train" --config gpu_fast --device cuda
        [ -f "$work/train/metrics.jsonl" ] && python3 - "$work/train/metrics.jsonl" << 'EOF' | tee -a "$summary"
import json, sys

rows = [json.loads(line) for line in open(sys.argv[1]) if line.strip()]
tests = [r for r in rows if r.get("test_psnr") is not None]
last = rows[-1]
print(f"  train: {len(rows)} records, last: iteration {last.get('iteration')} at {last.get('elapsed_s', 0):.0f} s, "
      f"train PSNR {last.get('psnr', float('nan')):.2f} dB, {last.get('gaussians')} Gaussians")
for r in tests:
    print(f"  train: test PSNR {r['test_psnr']:.2f} dB at iteration {r.get('iteration')}, "
          f"{r.get('elapsed_s', 0):.0f} s")
EOF
    else
        note "train   SKIPPED: no dataset at $data (see logs/synth.log)"
    fi
fi
"${parksim[@]}" bench report --results "$work/results" -o "$work/RESULTS.md" > "$work/logs/report.log" 2>&1
note "total   $((SECONDS - start)) s of the $budget s budget; records under results/ in $out/gpu_check.tgz"
pack
