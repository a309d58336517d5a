#!/usr/bin/env bash
# Set up blurcalib in ./.venv: the CPU build of PyTorch, then the package (with its browser app's
# viser) and its test tools.
# Idempotent: re-running it on a set-up checkout only checks what is there.
# Usage: bash scripts/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip --disable-pip-version-check -q)
# An unpinned torch would pull a multi-GB CUDA build; the CPU build is enough and runs CUDA code
# paths only where a GPU exists. Users with a GPU can install their own torch first.
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  "${PIP[@]}" install "torch==2.13.0"
fi
"${PIP[@]}" install -e ".[dev]"
echo "blurcalib is set up in .venv ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))"
