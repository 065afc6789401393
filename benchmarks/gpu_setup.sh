#!/bin/bash
# Install the wheels carried in .whl/ (benchmarks/gpu_check.sh's header lists them) into /tmp/site and JIT-build
# gsplat's CUDA extension for this GPU's architecture only. Then: export PYTHONPATH=/tmp/site:$PWD
#
# The build keeps gsplat's rasterizers for 1-5 channels only (sed below): its full build instantiates each of its six
# rasterizers (3DGS, 2DGS, and 3DGUT's "from world" one, forward and backward) for 19 channel counts, which takes many
# times longer. ParkSim rasterizes RGB + depth (4 channels) and gsplat's 3DGUT RGB (3): the sed deletes the same
# counts (8 and up) from the kernels' explicit instantiations (*.cu: __INS__(N)) and from the dispatch switches
# (Rasterization.cpp: __LAUNCH_KERNEL__(N)), so every kept case still links; the UT projection
# (ProjectionUT3DGSFused.cu) has no channel template and is built whole. Checked on gsplat 1.5.3's sources: 6 x 19
# instantiations and 114 dispatch cases before, 6 x 5 and 30 after. A full build (no sed) is the fallback if a later
# gsplat changes that layout: it compiles about four times the rasterizer instances (its time not measured here;
# the reduced build took 75-83 s on the lent machines' 16 cores).
set -euo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
sed -i -E '/^\s*(__INS__|__LAUNCH_KERNEL__)\((8|9|16|17|32|33|64|65|128|129|256|257|512|513)\)\s*$/d' \
    /tmp/site/gsplat/cuda/csrc/*.cu /tmp/site/gsplat/cuda/csrc/*.cpp
arch=$(python3 -c "import torch; print('%d.%d' % torch.cuda.get_device_capability())")
export PYTHONPATH=/tmp/site:$PWD
TORCH_CUDA_ARCH_LIST=$arch MAX_JOBS=$(nproc) python3 -c "
from gsplat.cuda._backend import _C
assert _C is not None, 'gsplat built no CUDA extension'
assert hasattr(_C, 'projection_ut_3dgs_fused'), 'gsplat built without 3DGUT (projection_ut_3dgs_fused)'
print('gsplat built for compute capability $arch, 3DGUT included')"
