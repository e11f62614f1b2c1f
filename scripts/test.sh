#!/usr/bin/env bash
# Install (if needed) and run the whole test suite, then the linter. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
. .venv/bin/activate
export MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 OMP_WAIT_POLICY=passive
ruff check .
python -m pytest -q -rs "$@"  # -rs: every skipped test is listed with its reason (e.g. no CUDA)
