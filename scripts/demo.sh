#!/usr/bin/env bash
# The main job on a fresh machine: install, train 3DGS on the built-in synthetic underwater scene,
# evaluate it. Extra arguments go to uw-train (e.g. --max-num-iterations 500).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
. .venv/bin/activate
# glibc returns big buffers to the OS after every step, which slows PyTorch on CPU 2-4x
export MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000
# idle OpenMP threads must sleep, not spin: spinning steals the cores from the other threads on a busy machine
export OMP_WAIT_POLICY=passive
run=demo-$(date +%Y%m%d-%H%M%S)
uw-train 3dgs --max-num-iterations 2000 --timestamp "$run" "$@"
uw-eval "outputs/synthetic/3dgs/$run/config.yml"
