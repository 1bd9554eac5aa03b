"""Speed of the SMAC-Comm re-implementation: env-steps per second (B envs x steps / time) with
random available actions and auto-reset, one process, one core.

    python -m lmac_env.smaclite.bench [--steps 2000] [--envs 1 32] [--maps ...]
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from ..core import Batch
from .env import SmacliteVecEnv
from .maps import MAPS
from .policies import random_actions


def measure(variant: str, num_envs: int, steps: int, seed: int = 0) -> tuple[float, float]:
    """(env-steps per wall-clock second, env-steps per CPU second of this process). The second
    figure does not depend on how busy the machine is."""
    env = SmacliteVecEnv(variant, num_envs, seed)
    out = Batch.allocate(env.schema, num_envs)
    env.reset(np.arange(num_envs), out)
    rng = np.random.default_rng(seed)
    # the random policy's cost is part of the loop, as in the raw server baseline
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        env.step(random_actions(env, out, rng), out)
        done = (out.terminated | out.truncated) > 0
        if done.any():
            env.reset(np.flatnonzero(done), out)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    return num_envs * steps / dt, num_envs * steps / max(dc, 1e-9)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lmac_env.smaclite.bench")
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--envs", type=int, nargs="*", default=[1, 32])
    ap.add_argument("--maps", nargs="*", default=list(MAPS))
    args = ap.parse_args(argv)
    print("env-steps/s with random available actions, one process; wall clock (and per CPU "
          "second of this process)")
    print(f"{'map':14s} " + " ".join(f"{'B=' + str(b):>20s}" for b in args.envs))
    for m in args.maps:
        row = [measure(m, b, args.steps) for b in args.envs]
        print(f"{m:14s} " + " ".join(f"{w:10.0f} ({c:7.0f})" for w, c in row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
