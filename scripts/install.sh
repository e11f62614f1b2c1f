#!/usr/bin/env bash
# Create .venv (if missing) and install uw3dgs with its test tools, with torch pinned by constraints.txt.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -c constraints.txt torch==2.13.0
.venv/bin/python -m pip install --quiet -c constraints.txt -e ".[dev]"
# gsplat (the kernels of the 'gsplat' CUDA backend, the `cuda` extra): a pure-Python wheel, installed here too so
# that the CPU glue tests of tests/test_gsplat_backend.py run; it compiles CUDA only when used on a GPU.
.venv/bin/python -m pip install --quiet -c constraints.txt "gsplat==1.5.3"
