#!/usr/bin/env bash
# Set-up of the PyTorch anchor of `lmac bench learner --against torch` (not part of the main
# set-up: about 3.5 GB, since PyPI's Linux torch wheels bring the CUDA runtime libraries even
# when only the CPU is used). Creates benches/torch/.venv with torch pinned; idempotent.
# Knob: LMAC_TORCH_VENV (where the venv goes).
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
VENV="${LMAC_TORCH_VENV:-$HERE/.venv}"
TORCH_VERSION="2.15.0"
log() { printf '\033[1m[bench-torch]\033[0m %s\n' "$*"; }

if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$TORCH_VERSION')" 2>/dev/null; then
  log "torch $TORCH_VERSION already in $VENV"
  exit 0
fi
PY="${PYTHON:-python3}"
log "creating $VENV with torch $TORCH_VERSION (CPU use; the wheel's CUDA libraries come along)"
"$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q "torch==$TORCH_VERSION" numpy
"$VENV/bin/python" -c "import torch; print('torch', torch.__version__, 'threads', torch.get_num_threads())"
