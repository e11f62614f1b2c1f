#!/usr/bin/env bash
# A GPU check in one go, for a CUDA machine with PyTorch but no network: build gsplat, run the CUDA parity tests,
# time the rasterizer backends and 500 training steps of each Gaussian method (docs/gsplat.md, "Measured on an H100").
#   bash benchmarks/speed/gpu_check.sh [WHEEL_DIR]
# WHEEL_DIR (optional) holds wheels to install offline first: gsplat==1.5.3, this project's (`pip wheel --no-deps .`)
# and any of its dependencies the machine lacks (tyro, kornia, pycolmap, ...). Results go to $OUT (default
# ./gpu-check), one file per step.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-$PWD/gpu-check}; mkdir -p "$OUT"; L=$OUT/log.txt; t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 ))s] $*" | tee -a "$L"; }
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-$(nproc)}
if [ -n "${1:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --upgrade --target /tmp/uw3dgs-site "$1"/*.whl
  export PYTHONPATH=/tmp/uw3dgs-site   # installed (not this checkout): the methods' entry points must resolve
fi
stamp "$(python3 -c 'import torch; print(torch.__version__, torch.cuda.get_device_name())')"
stamp "gsplat build"; python3 -c "from gsplat.cuda._backend import _C" >"$OUT/gsplat_build.txt" 2>&1; stamp "built"
(cd tests && timeout 300 python3 -m pytest -p no:cacheprovider -q -rf --tb=short test_gsplat_backend.py) \
  >"$OUT/parity.txt" 2>&1; tail -3 "$OUT/parity.txt" | tee -a "$L"
timeout 300 python3 benchmarks/speed/rasterizer.py --device cuda --repeats 10 >"$OUT/rasterizer.txt" 2>&1
for m in 3dgs uw3dgs seasplat watersplatting; do
  (cd /tmp && timeout 300 python3 -m uw3dgs.cli.train "$m" --device cuda --max-num-iterations 500 --seed 0 \
    --output-dir /tmp/uw3dgs-gpu-check synthetic) >"$OUT/train_$m.txt" 2>&1
  stamp "$m: $(grep -rho '"train_seconds": *[0-9.]*' "/tmp/uw3dgs-gpu-check/synthetic/$m" | tail -1)"
done
