#!/bin/bash
# QMIX on the authors' 71-value state (no last actions), at the runner and settings of the lmac
# arm of the independent-learner comparison (docs/figures/epymarl_qmix_1o10b/lmac): only the state differs.
export LMAC_ROOT=/work/main
cd /work/main
/work/bin/lmac train --env smaclite:1o_10b_vs_1r-no-last-action --algo qmix --preset paper --set run.envs=1 \
  --set run.servers=1 --set 'learn.time_limit="terminal"' --seeds 0,1,2 --steps 300k --out /work/runs/nla
