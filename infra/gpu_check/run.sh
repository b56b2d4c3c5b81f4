#!/bin/bash
# The checks that need a CUDA GPU and gsplat (skipped on CPU machines), run from the repository root on a GPU
# machine where `pip install gsplat` works (gsplat compiles its kernels on first use: about a minute on 16 cores).
#   1. gsplat parity: tests/render/test_render_gsplat.py (images, depths and gradients against the CPU backend);
#   2. render timing: both backends on one random scene at 640x360 (20k Gaussians) and 1600x900 (200k);
#   3. a CUDA fit: the checks of tests/nsg/test_nsg_device.py's CUDA test on a tiny scene, then one fast-preset fit
#      of a small two-camera scene on CUDA and on the CPU (seconds, held-out PSNR);
#   4. behaviour variants on CUDA: tests/scs/test_behavior_adversarial.py's CUDA test, then three variants of one
#      procedural scene on each device (seconds);
#   5. relit agent nodes on CUDA: tests/nsg/test_relight.py's CUDA case on the tiny scene (relit colours through
#      gsplat, the light fitted back through it, and the dual strategy's colour correction and refinement there).
# Steps can be picked: GPU_CHECK_STEPS="1 5" (default: all).
# Scenes are written first with the test fixtures (GPU_CHECK_SCENES, default .gpu_check; pre-made copies are used
# as they are, for a machine without the world's packages).
set -u
export MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
SCENES=${GPU_CHECK_SCENES:-.gpu_check}
PY=${PYTHON:-python3}
if [ ! -d "$SCENES/scene_small" ]; then
  $PY -c "from pathlib import Path; from tests.nsg_fixtures import nsg_world, write_nsg_scene; \
write_nsg_scene(Path('$SCENES/scene_small'), nsg_world(n_frames=4)); \
write_nsg_scene(Path('$SCENES/scene_big'), nsg_world(n_frames=10, n_cameras=2, width=480, height=270), scene_id='nsg-big')" || exit 1
fi
if [ ! -f "$SCENES/traffic.pkl" ]; then
  $PY -c "import pickle; from omniscs.pipeline.procedural import traffic_from_world, procedural_traffic; \
from tests.behavior_fixtures import straight_world; \
pickle.dump({'straight': traffic_from_world(straight_world([{'x': 8.0, 'y': 3.3, 'speed': 8.0}])), \
't_junction': procedural_traffic('t_junction', 330001, 100, scene_id='syn-t_junction-s330001')}, \
open('$SCENES/traffic.pkl', 'wb'))" || exit 1
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
t0=$(date +%s)
$PY -c "from gsplat.cuda._backend import _C; print('gsplat kernels ready:', _C is not None)" || exit 1
echo "gsplat build/load seconds: $(( $(date +%s) - t0 ))"
STEPS=" ${GPU_CHECK_STEPS:-1 2 3 4 5} "
step() { [[ "$STEPS" == *" $1 "* ]]; }
step 1 && $PY -m pytest -q --noconftest -o addopts="" -p no:cacheprovider tests/render/test_render_gsplat.py
step 2 && $PY infra/gpu_check/render_timing.py
step 3 && GPU_CHECK_SCENES=$SCENES $PY infra/gpu_check/fit_cuda.py 300
step 4 && GPU_CHECK_SCENES=$SCENES $PY infra/gpu_check/variants_cuda.py
step 5 && GPU_CHECK_SCENES=$SCENES $PY infra/gpu_check/relight_cuda.py
