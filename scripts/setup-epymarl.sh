#!/usr/bin/env bash
# One-time (idempotent) set-up of an independent learner beside lmac: EPyMARL's QMIX as PyPI's
# PyMARLzoo+ (`pymarlzooplus`) ships it, unmodified, in a virtual environment outside the project
# (default ~/.cache/lmac/epymarl-venv; LMAC_EPYMARL_VENV overrides). Not part of the tests.
# torch from PyPI brings its CUDA libraries: about 5 GB on disk, a few minutes.
# Then: scripts/epymarl_qmix.py runs it on any lmac environment (see that file).
set -euo pipefail
VENV="${LMAC_EPYMARL_VENV:-$HOME/.cache/lmac/epymarl-venv}"
log() { printf '\033[1m[setup-epymarl]\033[0m %s\n' "$*"; }
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c 'import pymarlzooplus, torch, pettingzoo' 2>/dev/null; then
  log "already set up in $VENV"; exit 0
fi
log "creating $VENV"
python3 -m venv "$VENV"
PIP="$VENV/bin/pip"
"$PIP" install -q "torch==2.15.0"
"$PIP" install -q "numpy<2" gymnasium pyyaml sacred pandas scipy tqdm rich dill "lbforaging>1.1.1" \
  tensorboard-logger matplotlib six networkx opencv-python-headless "pettingzoo==1.24.3" seaborn scikit-learn
# sacred imports pkg_resources, which setuptools 70 removed; pip warns that torch wants a newer one,
# which it does not need to run (installed on its own: one resolve with torch refuses it).
"$PIP" install -q "setuptools<70"
"$PIP" install -q --no-deps "pymarlzooplus==1.1.0"
"$VENV/bin/python" -c 'import pymarlzooplus, torch; print("pymarlzooplus", torch.__version__)'
log "done: $VENV"
