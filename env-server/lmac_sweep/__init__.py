"""lmac-sweep: hyperparameter sweeps of `lmac train` (or `lmac experiment`) as Ray Tune trials.

Each trial launches the `lmac` binary as a subprocess with the CPUs it asked Ray for, streams the
run's `metrics.jsonl` back to Tune as results and hands Tune each checkpoint the run writes, so a
failed trial restarts from its last checkpoint (`lmac train --resume`) and `lmac-sweep --resume`
continues an interrupted sweep (`Tuner.restore`). See `sweep.py` and docs/guide/sweeps.md.
"""

from .sweep import load_sweep, main, run_trial  # noqa: F401
