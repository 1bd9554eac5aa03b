#!/usr/bin/env bash
# Measure the figures the guide (docs/) quotes, on this machine, and keep them as JSON in
# docs/figures/ (one file per measurement, raw output of the lmac commands). Run on a quiet
# machine: every figure is a ratio against a baseline measured in the same run, but absolute
# rates move with the load. Takes about 20 minutes (plus the ndarray build).
#   bash scripts/figures.sh            # everything
#   FIGURES="pipeline grf" bash scripts/figures.sh   # some of: pipeline smaclite grf train criterion
#   FIGURES=lmac bash scripts/figures.sh   # the LMAC comparisons (hours; not in the default set)
#   FIGURES=design bash scripts/figures.sh   # offline designs and what FullComm's messages reveal (minutes)
#   FIGURES=methods bash scripts/figures.sh   # ms per update of the communication baselines against QMIX
#   FIGURES=sweep bash scripts/figures.sh   # a 4-trial sweep through Ray against the same trials one after another
#   FIGURES=learner bash scripts/figures.sh   # one update against pymarl's QLearner in PyTorch (installs torch: benches/torch/setup.sh)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/setup.sh
LMAC="$ROOT/target/release/lmac"
OUT="$ROOT/docs/figures"
mkdir -p "$OUT"
WHAT="${FIGURES:-pipeline smaclite grf train criterion}"
log() { printf '\033[1m[figures]\033[0m %s\n' "$*"; }
want() { [[ " $WHAT " == *" $1 "* ]]; }

if want pipeline; then
  log "pipeline: LBF 8x8, 32 envs in one env server (double-buffered), one sub-batch, two servers"
  # The headline figure five times over: how much it moves from run to run on this machine.
  for i in 1 2 3 4 5; do
    "$LMAC" bench pipeline --env lbf:8x8-2p-2f-s1-coop --envs 32 --steps 128000 --repeat 41 --json >"$OUT/pipeline_lbf8x8_run$i.json"
  done
  "$LMAC" bench pipeline --env lbf:8x8-2p-2f-s1-coop --envs 32 --sub-batches 1 --steps 64000 --repeat 21 --json \
    >"$OUT/pipeline_lbf8x8_one_sub_batch.json"
  "$LMAC" bench pipeline --env lbf:8x8-2p-2f-s1-coop --envs 16 --servers 2 --steps 64000 --repeat 9 --json \
    >"$OUT/pipeline_lbf8x8_two_servers.json"
  "$LMAC" bench pipeline --env lbf:8x8-2p-2f-s1-coop --envs 32 --protocol fullcomm --steps 64000 --repeat 21 --json \
    >"$OUT/pipeline_lbf8x8_fullcomm.json"
  "$LMAC" bench pipeline --env lbf:11x11-6p-4f-s1-coop --envs 32 --steps 32000 --repeat 15 --json >"$OUT/pipeline_lbf11x11.json"
fi

if want smaclite; then
  for map in bane_vs_hM 1o_10b_vs_1r 2o_20b_vs_2r 5z_vs_1ul; do
    log "pipeline: smaclite:$map, 32 envs"
    "$LMAC" bench pipeline --env "smaclite:$map" --envs 32 --steps 64000 --repeat 21 --json >"$OUT/pipeline_smaclite_$map.json"
  done
fi

if want grf; then
  if "$ROOT/.venv/bin/python" -c 'import gfootball' 2>/dev/null; then
    for sc in academy_3_vs_1_with_keeper academy_run_pass_and_shoot_with_keeper; do
      for w in 0 2; do
        log "grf raw: $sc, 4 envs, LMAC_GRF_WORKERS=$w"
        LMAC_GRF_WORKERS=$w PYTHONPATH="$ROOT/env-server" "$ROOT/.venv/bin/python" -m lmac_env.server --raw \
          --env "grf:$sc" --envs 4 --steps 500 >"$OUT/grf_raw_${sc}_workers$w.json"
      done
      log "pipeline: grf:$sc, 4 envs"
      "$LMAC" bench pipeline --env "grf:$sc" --envs 4 --steps 4000 --repeat 9 --json >"$OUT/pipeline_grf_$sc.json"
      LMAC_GRF_WORKERS=2 "$LMAC" bench pipeline --env "grf:$sc" --envs 4 --steps 4000 --repeat 9 --json \
        >"$OUT/pipeline_grf_${sc}_workers2.json"
    done
  else
    log "grf: gfootball is not installed (LMAC_WITH_GRF=1 bash scripts/setup.sh); skipped"
  fi
fi

if want train; then
  log "bench train (flex backend)"
  "$LMAC" bench train --env lbf:8x8-2p-2f-s1-coop --envs 8,32 --steps 40000 --json >"$OUT/train_flex.json"
  log "bench train (ndarray backend: lmac built once more with --features ndarray, kept as lmac-ndarray)"
  cargo build --release -q --bin lmac -p lmac --no-default-features --features ndarray
  cp "$ROOT/target/release/lmac" "$ROOT/target/release/lmac-ndarray"
  cargo build --release -q --bin lmac  # the default (flex) binary again
  "$ROOT/target/release/lmac-ndarray" bench train --env lbf:8x8-2p-2f-s1-coop --envs 8,32 --steps 40000 --json \
    >"$OUT/train_ndarray.json"
fi

if want sweep; then
  log "sweep: 4 LBF 8x8 trials through Ray (cpus_per_trial 2 and 1) against the same runs one after another"
  "$ROOT/.venv/bin/python" scripts/sweep_walltime.py --steps 200k --out "$OUT/sweep_lbf8x8.json"
fi

if want learner; then
  log "bench learner against PyTorch (LBF 8x8 and 1o_10b shapes, 3 alternating rounds)"
  bash "$ROOT/benches/torch/setup.sh"
  "$LMAC" bench learner --shape lbf8x8 --against torch --rounds 3 --updates 10 --profile --out "$OUT/learner_vs_torch_lbf8x8.json"
  "$LMAC" bench learner --shape 1o10b --against torch --rounds 5 --updates 5 --profile --out "$OUT/learner_vs_torch_1o10b.json"
  log "bench learner: LMAC's update against its matmuls' shape ceiling (1o_10b, the authors' design and the offline one)"
  "$LMAC" bench learner --shape 1o10b --algo lmac --input 159 --messages 56 --critical 4 --mixers qmix --no-stepwise \
    --rounds 3 --updates 4 --out "$OUT/lmac_shape_ceiling_1o10b_paper.json"
  "$LMAC" bench learner --shape 1o10b --algo lmac --input 314 --messages 211 --critical 48 --mixers qmix --no-stepwise \
    --rounds 3 --updates 4 --out "$OUT/lmac_shape_ceiling_1o10b_offline.json"
fi

if want methods; then
  # ms per update of every communication baseline next to QMIX: three rounds, each running every
  # method one after another, and the median per method (ratios to QMIX's median are what to
  # compare; absolute speeds move with the load).
  log "bench train per method (qmix and the five communication baselines), 3 alternating rounds"
  T="$(mktemp -d)"
  for r in 1 2 3; do
    for a in qmix ndq maic masia cola t2mac; do
      "$LMAC" bench train --env lbf:8x8-2p-2f-s1-coop --algo "$a" --envs 16 --steps 5000 --updates 20 --json >"$T/${a}_$r.json"
    done
  done
  .venv/bin/python scripts/median_per_method.py "$T" "$OUT/train_methods_lbf8x8.json" qmix ndq maic masia cola t2mac \
    --command "lmac bench train --algo A --envs 16 --steps 5000 --updates 20 --json; 3 rounds, each A in turn (scripts/figures.sh methods)"
  # The same on smaclite:1o_10b_vs_1r's update shape (32 episodes x 50 steps x 11 agents, obs 85,
  # 7 actions, state 148) through `lmac bench learner --algo`: LMAC reads the committed design's
  # 211 message columns and reconstructs its 48 task-critical dims, FullComm's agents read 960.
  log "bench learner per method on 1o_10b's shape, 3 alternating rounds"
  shape=(--shape 1o10b --actions 7 --mixers qmix --no-stepwise --rounds 1 --updates 3 --json)
  for r in 1 2 3; do
    "$LMAC" bench learner "${shape[@]}" --input 103 >"$T/l_qmix_$r.json"
    "$LMAC" bench learner "${shape[@]}" --input 314 --algo lmac --messages 211 --critical 48 >"$T/l_lmac_$r.json"
    "$LMAC" bench learner "${shape[@]}" --input 314 --algo lmac --messages 211 --critical 48 --method encoder='"gru-gate"' \
      >"$T/l_lmac-gru-gate_$r.json"
    "$LMAC" bench learner "${shape[@]}" --input 1063 --algo fullcomm --messages 960 >"$T/l_fullcomm_$r.json"
    "$LMAC" bench learner "${shape[@]}" --input 103 --algo qmix-state >"$T/l_qmix-state_$r.json"
    for a in ndq maic masia cola t2mac; do
      "$LMAC" bench learner "${shape[@]}" --input 103 --algo "$a" >"$T/l_${a}_$r.json"
    done
  done
  .venv/bin/python scripts/median_per_method.py "$T" "$OUT/learner_methods_1o10b.json" --prefix l_ --key figures.0.median_ms \
    qmix lmac lmac-gru-gate fullcomm qmix-state ndq maic masia cola t2mac \
    --command "lmac bench learner --shape 1o10b --actions 7 --mixers qmix --no-stepwise --rounds 1 --updates 3 --algo A ...; 3 rounds, each A in turn (scripts/figures.sh methods)"
fi

if want criterion; then
  log "criterion benches (short measurement windows)"
  cargo bench -q -p lmac-benches --bench data_plane --bench protocol --bench learner -- --warm-up-time 1 --measurement-time 4 2>&1 | grep -v "^Benchmarking" | tee "$OUT/criterion.txt"
fi
if want lmac; then
  # LMAC against the baselines on the committed offline designs, 3 seeds x 1M env steps, seed by
  # seed; rerunning continues an interrupted experiment. Then LMAC's options on seed 0.
  EV="$ROOT/runs-evidence"
  log "lmac experiment on LBF 8x8 (about 2 hours here)"
  "$LMAC" experiment --env lbf:8x8-2p-2f-s1-coop --seeds 0,1,2 --steps 1M --design docs/figures/design_lbf8x8 --out "$EV/lbf8x8"
  "$LMAC" experiment --env lbf:8x8-2p-2f-s1-coop --seeds 0 --steps 1M --design docs/figures/design_lbf8x8 --out "$EV/lbf8x8" \
    --algos lmac --variant lmac-raw=lmac,method.raw_messages=true --variant lmac-td=lmac,method.td_to_encoder=true \
    --variant lmac-gru-gate=lmac,method.encoder='"gru-gate"'
  log "lmac experiment on smaclite:1o_10b_vs_1r with Table 1(a)'s ablations (many hours here)"
  "$LMAC" experiment --env smaclite:1o_10b_vs_1r --seeds 0,1,2 --steps 1M --design docs/figures/design_1o_10b_vs_1r --ablations \
    --out "$EV/1o10b"
  log "LMAC on 1o_10b, seed 0: FullComm's messages as a protocol, the raw designed messages, TD into the encoder"
  "$LMAC" train --env smaclite:1o_10b_vs_1r --algo lmac --steps 1M --seeds 0 --out "$EV/1o10b_fullproto" \
    --protocol docs/figures/lmac_1o10b_diagnosis/fullcomm_1o_10b.protocol.json
  "$LMAC" experiment --env smaclite:1o_10b_vs_1r --seeds 0 --steps 1M --design docs/figures/design_1o_10b_vs_1r --out "$EV/1o10b" \
    --algos lmac --variant lmac-raw=lmac,method.raw_messages=true --variant lmac-td=lmac,method.td_to_encoder=true
  bash scripts/copy_runs.sh "$OUT/lmac_1o10b_diagnosis" "$(ls -d "$EV"/1o10b_fullproto/*/lmac/*/seed0 | tail -n 1)=lmac-fullproto"
  for e in lbf8x8 1o10b; do
    mkdir -p "$OUT/lmac_$e"
    cp "$EV/$e"/comparison.* "$EV/$e"/*.png "$OUT/lmac_$e/"
    bash scripts/copy_runs.sh "$OUT/lmac_$e" $(for r in "$EV/$e"/runs/*/seed*; do echo "$r=$(basename "$(dirname "$r")")"; done)
  done
fi
if want design; then
  # The design loop's fixed-dim trend on three maps (per phase: recovery with messages and
  # without, both definitions, skill over a constant guess, variance across agents), and
  # whether the LBF state gives the discriminator a signal: FullComm written as a protocol,
  # measured on the grid state and on the entity state.
  DS="$ROOT/runs-evidence/designs"
  for e in smaclite:bane_vs_hM smaclite:1o_10b_vs_1r lbf:8x8-2p-2f-s1-coop lbf:8x8-2p-2f-s1-coop-entity; do
    log "offline design of $e"
    /usr/bin/time -v "$LMAC" design --env "$e" --out "$DS" 2>&1 | tee "$DS.${e//:/_}.log" | grep -E "^lmac: phase|Maximum resident|Elapsed"
  done
  S="$OUT/design_signal_lbf"
  for v in grid entity; do
    env=lbf:8x8-2p-2f-s1-coop; [ "$v" = entity ] && env=lbf:8x8-2p-2f-s1-coop-entity
    data="$(ls -d "$DS/${env//:/_}"/*/collect/dataset | tail -n 1)"
    "$LMAC" protocol measure --env "$env" "$S/fullcomm_$v.protocol.json" --dataset "$data" --out "$S/${v}_fullcomm"
  done
  # What the 1o_10b design's messages and FullComm's reveal of the Overseer's and the Roach's
  # positions (state dims 62, 63, 67, 68), on the design's dataset.
  data="$(ls -d "$DS/smaclite_1o_10b_vs_1r"/*/collect/dataset | tail -n 1)"
  D1="$ROOT/docs/figures/design_1o_10b_vs_1r"
  for p in fullcomm design; do
    files="$OUT/lmac_1o10b_diagnosis/fullcomm_1o_10b.protocol.json"
    [ "$p" = design ] && files="$D1/phase0/protocol.json $D1/phase1/protocol.json $D1/phase2/protocol.json"
    # shellcheck disable=SC2086
    "$LMAC" protocol measure --env smaclite:1o_10b_vs_1r --dataset "$data" --dims 62,63,67,68 --out "$DS/measure_1o10b_$p" $files
    cp "$DS/measure_1o10b_$p/summary.json" "$OUT/lmac_1o10b_diagnosis/measure_${p}_positions.json"
  done
fi
log "figures in $OUT"
