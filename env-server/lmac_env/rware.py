"""The Multi-Robot Warehouse (PyPI ``rware`` 2.0.0, EPyMARL's benchmark) as an lmac family.

Variants are rware's own ids without ``rware-`` and ``-v2``: ``rware:tiny-2ag`` is
``rware-tiny-2ag-v2`` (11 x 10 grid, 2 robots, 2 requested shelves at a time), ``rware:small-4ag``
is ``rware-small-4ag-v2``. rware's defaults as registered: sensor range 1 (a 3 x 3 window),
individual rewards (1 to the robot that delivers a requested shelf; the team reward here is
their sum), 500 steps, and no other end: rware reports ``done`` at its step limit, which
``split_done`` makes a truncation, so every episode is truncated and none is won.

Observation (71 values): rware's flattened vector, as it writes it. State: the agents'
observations concatenated (rware has no global state; EPyMARL does the same). Actions: rware's
five, all always available. The family is built in (``registry.FAMILIES``) because a family
named ``rware`` would otherwise import the ``rware`` package itself (SCHEMA.md, "Family names
that shadow packages").
"""
from __future__ import annotations

import numpy as np

from .core import Batch, EnvUnavailable, Schema, VecEnv, schema_path, split_done

VARIANTS = ("tiny-2ag", "small-4ag")


class RwareVecEnv(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int):
        if variant not in VARIANTS:
            raise ValueError(f"unknown rware variant {variant!r}; known: {', '.join(VARIANTS)}")
        try:
            import gymnasium as gym
            import rware  # noqa: F401 - registers the rware-* ids with gymnasium
        except ImportError as e:
            raise EnvUnavailable(f"rware:{variant} needs the rware package (pip install rware==2.0.0): {e}") from None
        self.schema = Schema.load(schema_path(f"rware:{variant}"))
        self.num_envs = num_envs
        # unwrapped: gymnasium's wrappers only check the API, per step, at a cost
        self.envs = [gym.make(f"rware-{variant}-v2").unwrapped for _ in range(num_envs)]
        self.n_agents = self.envs[0].n_agents
        self._seeds = np.random.SeedSequence(seed).generate_state(num_envs)
        self._seeded = np.zeros(num_envs, bool)

    def _write(self, e: int, obs, out: Batch) -> None:
        o = np.stack(obs).astype(np.float32)
        out.obs[e] = o
        out.state[e] = o.reshape(-1)
        out.avail[e] = 1

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        for e in env_ids:
            e = int(e)
            seed = None if self._seeded[e] else int(self._seeds[e])
            self._seeded[e] = True
            obs, _ = self.envs[e].reset(seed=seed)
            self._write(e, obs, out)

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        for e, env in enumerate(self.envs):
            if active is not None and not active[e]:
                continue
            obs, rewards, done, truncated, _ = env.step([int(a) for a in actions[e]])
            out.reward[e] = float(sum(rewards))
            term, trunc = split_done(done, env._cur_steps, env.max_steps)
            out.terminated[e] = term
            out.truncated[e] = trunc or truncated
            self._write(e, obs, out)


def sizes(variant: str) -> dict:
    """What one rware env of ``variant`` writes (`lmac envs --generate rware:<variant>`)."""
    import gymnasium as gym
    import rware  # noqa: F401

    env = gym.make(f"rware-{variant}-v2").unwrapped
    n, obs = env.n_agents, int(gym.spaces.flatdim(env.observation_space[0]))
    return {"n_agents": n, "obs_dim": obs, "state_dim": n * obs, "n_actions": int(env.action_space[0].n),
            "episode_limit": int(env.max_steps)}


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return RwareVecEnv(variant, num_envs, seed)
