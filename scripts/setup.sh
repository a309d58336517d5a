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
# PyPI's torch is a multi-GB CUDA build; the CPU build (the "+cpu" release of PyTorch's own CPU
# index) is enough: blurcalib runs its CUDA paths only where a GPU and a CUDA torch exist. Users with
# a GPU install their own torch into .venv first, and this step keeps it. Where the CPU index cannot
# be reached (an offline mirror), the "+cpu" release is taken from pip's configured sources.
TORCH=${TORCH:-torch==2.13.0+cpu}
TORCH_CPU_INDEX=${TORCH_CPU_INDEX:-https://download.pytorch.org/whl/cpu}
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
  if .venv/bin/python -c "import sys, urllib.request; urllib.request.urlopen(sys.argv[1] + '/torch/', timeout=10)" \
      "$TORCH_CPU_INDEX" 2>/dev/null; then
    "${PIP[@]}" install "$TORCH" --extra-index-url "$TORCH_CPU_INDEX"
  elif ! "${PIP[@]}" install "$TORCH"; then
    echo "setup: $TORCH is neither on $TORCH_CPU_INDEX (not reachable) nor in pip's sources;" \
         "install a torch build into .venv yourself (https://pytorch.org) and run this again" >&2
    exit 2
  fi
fi
"${PIP[@]}" install -e ".[dev]"
echo "blurcalib is set up in .venv ($(.venv/bin/python -c 'import torch; print("torch", torch.__version__)'))"
