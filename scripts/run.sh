#!/usr/bin/env bash
# Set up everything (idempotent) and run the main job on embedded defaults (no API key, no game
# binary): the pipeline benchmark on Level-Based Foraging and a short verified run with FullComm.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/setup.sh
LMAC="$ROOT/target/release/lmac"
"$LMAC" envs
echo
"$LMAC" bench pipeline --env lbf:8x8-2p-2f-s1-coop --envs 32 --steps 128000 --repeat 41
"$LMAC" run --env lbf:8x8-2p-2f-s1-coop --envs 16 --servers 2 --protocol fullcomm --steps 32000 --verify
