#!/usr/bin/env bash
# Idempotent set-up of Google Research Football (gfootball 2.10.2) for the lmac env-server.
#
# 1. Debian build dependencies (only the missing ones; `apt-get update` first).
# 2. Builds the gfootball 2.10.2 wheel (C++ engine; about 8 minutes on 2 cores) into
#    ${LMAC_CACHE:-$HOME/.cache/lmac}/wheels, but only when no cached wheel for this Python
#    version exists, so a second set-up on the same machine skips the build.
# 3. Installs the wheel plus gym==0.25.2 (0.26 changed reset() and breaks gfootball), psutil and six
#    into the project virtual environment (.venv next to this script's parent directory).
#
# Called by scripts/setup.sh when LMAC_WITH_GRF=1; can also be run on its own.
# Knobs: LMAC_CACHE (cache root), GRF_FORCE_BUILD=1 (ignore the cached wheel).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VPY="$ROOT/.venv/bin/python"
PIP=("$VPY" -m pip)
CACHE="${LMAC_CACHE:-$HOME/.cache/lmac}/wheels"
GF_VERSION="2.10.2"
log() { printf '\033[1m[setup-grf]\033[0m %s\n' "$*"; }

if [ ! -x "$VPY" ]; then
  echo "setup-grf: $VPY not found; run scripts/setup.sh first (it creates the venv)" >&2
  exit 1
fi

# Already installed and importable with the right versions: nothing to do.
if "$VPY" - <<'EOF' 2>/dev/null
import importlib.metadata as m, sys
ok = m.version("gfootball") == "2.10.2" and m.version("gym") == "0.25.2"
import gfootball.env, gfootball_engine, psutil  # noqa: F401
sys.exit(0 if ok else 1)
EOF
then
  log "gfootball $GF_VERSION, gym 0.25.2 already installed in .venv"
  exit 0
fi

# --- 1. Debian packages --------------------------------------------------------------------
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
APT_PKGS=(git cmake build-essential libgl1-mesa-dev libsdl2-dev libsdl2-image-dev
          libsdl2-ttf-dev libsdl2-gfx-dev libboost-all-dev libdirectfb-dev libst-dev
          mesa-utils xvfb libsdl-sge-dev)
need_apt=()
for pkg in "${APT_PKGS[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if [ "${#need_apt[@]}" -gt 0 ]; then
  log "installing Debian packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends \
    "${need_apt[@]}" >/dev/null
else
  log "Debian build packages present"
fi

# --- 2. the wheel (cached) -----------------------------------------------------------------
"${PIP[@]}" install -q psutil wheel setuptools
PYTAG="$("$VPY" -c 'import sys; print(f"cp{sys.version_info[0]}{sys.version_info[1]}")')"
mkdir -p "$CACHE"
find_wheel() { ls "$CACHE"/gfootball-"$GF_VERSION"-"$PYTAG"-*.whl 2>/dev/null | head -n 1; }
WHEEL="$(find_wheel || true)"
if [ -n "$WHEEL" ] && [ "${GRF_FORCE_BUILD:-0}" != "1" ]; then
  log "using cached wheel $WHEEL"
else
  log "building the gfootball $GF_VERSION wheel (about 8 minutes on 2 cores) into $CACHE"
  BUILD_LOG="$CACHE/gfootball-build.log"
  start=$(date +%s)
  # --no-build-isolation: the engine build uses the venv's setuptools/wheel/psutil; its build
  # script calls a bare `python3`, so the venv's bin directory goes first on PATH.
  if ! PATH="$ROOT/.venv/bin:$PATH" MAKEFLAGS="-j$(nproc)" "${PIP[@]}" wheel --no-build-isolation --no-deps \
        -w "$CACHE" "gfootball==$GF_VERSION" >"$BUILD_LOG" 2>&1; then
    echo "setup-grf: the gfootball build failed; last lines of $BUILD_LOG:" >&2
    tail -n 40 "$BUILD_LOG" >&2
    exit 1
  fi
  WHEEL="$(find_wheel || true)"
  [ -n "$WHEEL" ] || { echo "setup-grf: build produced no wheel in $CACHE" >&2; exit 1; }
  log "built $WHEEL in $(( $(date +%s) - start )) s"
fi

# --- 3. install ----------------------------------------------------------------------------
# six: imported by gfootball but not among its declared dependencies.
"${PIP[@]}" install -q "$WHEEL" "gym==0.25.2" psutil six
"$VPY" -c 'import gfootball.env, gfootball_engine' \
  || { echo "setup-grf: gfootball installed but does not import" >&2; exit 1; }
log "gfootball $GF_VERSION ready"
