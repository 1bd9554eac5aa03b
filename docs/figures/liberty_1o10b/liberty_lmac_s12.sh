#!/bin/bash
# LMAC with the authors' 1o_10b design on the Liberty unit data, at --preset paper, seeds 1-2.
export LMAC_ROOT=/work/main
cd /work/main
/work/bin/lmac train --env smaclite:1o_10b_vs_1r-liberty --algo lmac --protocol paper:1o_10b_vs_1r --preset paper \
  --seeds 1,2 --steps 300k --out /work/runs/liberty
