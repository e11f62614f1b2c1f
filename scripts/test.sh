#!/usr/bin/env bash
# Install (if needed) and run the whole test suite, then the linter. Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
. .venv/bin/activate
export MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=100000000000 OMP_WAIT_POLICY=passive
ruff check .
# the unit suite first, then the end-to-end tests (tests/conftest.py marks them slow): each phase prints its own time.
# -rs: every skipped test is listed with its reason (e.g. no CUDA); --durations: the slowest tests of each phase
# (exit status 5, "no test selected", is fine for a phase: e.g. a file without slow tests)
for phase in "not slow" "slow"; do
  status=0
  python -m pytest -q -rs --durations=15 -m "$phase" "$@" || status=$?
  [ "$status" -eq 0 ] || [ "$status" -eq 5 ] || exit "$status"
done
