#!/usr/bin/env bash
# Set up everything (idempotent) and run the main job on embedded defaults (no API key, no game
# binary): a short LMAC experiment on Level-Based Foraging (offline protocol design, then LMAC,
# QMIX, FullComm and QMIX+State over three seeds, then the comparison table), and the pipeline
# benchmark.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/setup.sh
LMAC="$ROOT/target/release/lmac"
"$LMAC" envs
echo
# Rerunning continues where an interrupted run stopped (the design and finished seeds are kept).
"$LMAC" experiment --env lbf:8x8-2p-2f-s1-coop --seeds 0,1,2 --steps 150k \
  --algos lmac,qmix,fullcomm,qmix-state --design-steps 50k --dataset-episodes 500 \
  --out experiments/main-lbf8x8
"$LMAC" bench pipeline --env lbf:8x8-2p-2f-s1-coop --envs 32 --steps 128000 --repeat 41
