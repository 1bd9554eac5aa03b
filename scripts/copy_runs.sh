#!/usr/bin/env bash
# Flat copies of finished runs into docs/figures (the guide's figures in docs/ read these):
# metrics.csv -> <label>_seed<k>.csv, config.toml -> .config.toml, marl_eval.json -> .marl_eval.json.
#   bash scripts/copy_runs.sh DEST RUN_DIR=LABEL...   (RUN_DIR: a seed directory, seed<k>)
set -euo pipefail
dest=$1; shift
mkdir -p "$dest"
for pair in "$@"; do
  run=${pair%=*}; label=${pair##*=}
  seed=$(basename "$run")
  [ -f "$run/marl_eval.json" ] || { echo "copy_runs: $run has not finished (no marl_eval.json); skipped" >&2; continue; }
  cp "$run/metrics.csv" "$dest/${label}_${seed}.csv"
  cp "$run/config.toml" "$dest/${label}_${seed}.config.toml"
  cp "$run/marl_eval.json" "$dest/${label}_${seed}.marl_eval.json"
  echo "copy_runs: $run -> $dest/${label}_${seed}.*"
done
