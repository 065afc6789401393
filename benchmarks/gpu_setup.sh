#!/bin/bash
# Install gsplat from wheels in .whl/ (fetched on a connected machine with `pip download --no-deps gsplat plyfile`)
# into /tmp/site and JIT-build its CUDA extension for this GPU's architecture only. The rasterizer is instantiated
# for 1-5 channels only (ParkSim rasterizes RGB + depth = 4): gsplat's full build compiles each rasterizer for
# 19 channel counts, which takes many times longer. Then: export PYTHONPATH=/tmp/site:$PWD
set -euo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
sed -i -E '/^\s*(__INS__|__LAUNCH_KERNEL__)\((8|9|16|17|32|33|64|65|128|129|256|257|512|513)\)\s*$/d' \
    /tmp/site/gsplat/cuda/csrc/*.cu /tmp/site/gsplat/cuda/csrc/*.cpp
arch=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
export PYTHONPATH=/tmp/site:$PWD
TORCH_CUDA_ARCH_LIST=$arch MAX_JOBS=$(nproc) python3 -c "from gsplat.cuda._backend import _C; assert _C is not None"
