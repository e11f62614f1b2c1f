#!/usr/bin/env bash
# The main job on a fresh machine: install, then the demo grid (configs/demo.yaml): 3DGS and UW-3DGS on the
# built-in synthetic underwater scene, 2,000 steps each, side by side, evaluated, and their table. Run it again and
# it shows the table without training (the cells are done); delete outputs/bench/demo to train anew.
# Extra arguments go to uw-bench (e.g. --output-dir outputs/my-demo).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
. .venv/bin/activate
# glibc returns big buffers to the OS after every step, which slows PyTorch on CPU 2-4x
export MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000
# idle OpenMP threads must sleep, not spin: spinning steals the cores from the other threads on a busy machine
export OMP_WAIT_POLICY=passive
# the two runs at once where there are two cores (uw-bench divides the cores among them)
jobs=$(( $(nproc) >= 2 ? 2 : 1 ))
uw-bench configs/demo.yaml --jobs "$jobs" "$@"
