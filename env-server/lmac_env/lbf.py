"""Level-Based Foraging (lbforaging==2.0.0) in the paper's variant.

The dynamics are lbforaging's own (`ForagingEnv.step`: moves, collisions, cooperative loading,
normalised rewards). Observations and state are built here from the environment's fields,
because lbforaging 2.0.0's ``grid_observation`` is broken:

- observation (29 per agent): the 3x3 window around the agent (sight 1) of three layers of the
  padded grid: agent levels, food levels, accessible cells (1 = free cell inside the field),
  then the agent's own field row and column scaled to [0, 1] (lbforaging's vector observation
  also starts each agent's own entry with its position; without it a receiver could not place a
  teammate's 3x3 view anywhere on the grid, so no message could say where food or teammates are);
- state (3 x (S+2)^2): the same three layers over the whole padded grid (300 for 8x8, 507 for
  11x11).

Variant choices (the paper's reference code uses MASIA's LBF): every player has level 1, so with
``force_coop`` every food has the sum of the players' levels capped at three, i.e. level 2 with
2 players (both must load together) and level 3 with 6 players. Team reward = sum of the
agents' (normalised) rewards; an episode terminates when all food is eaten and is truncated at
the schema's episode limit (25 steps for 8x8 as in the reference code, 50 for 11x11, lbforaging's
default, because six players on the larger field need longer to gather).
"""
from __future__ import annotations

import numpy as np
from lbforaging.foraging.environment import Action, ForagingEnv

from .core import Batch, Schema, VecEnv, schema_path

SIGHT = 1
VARIANTS = {
    # variant: (field size, players, foods)
    "8x8-2p-2f-s1-coop": (8, 2, 2),
    "11x11-6p-4f-s1-coop": (11, 6, 4),
}


class _Foraging(ForagingEnv):
    """lbforaging's env without its own observation building (we build ours from its fields)."""

    def _make_gym_obs(self):
        return None


class LbfVecEnv(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int):
        if variant not in VARIANTS:
            raise ValueError(f"unknown LBF variant {variant!r}; known: {', '.join(VARIANTS)}")
        self.schema = Schema.load(schema_path(f"lbf:{variant}"))
        self.num_envs = num_envs
        size, players, foods = VARIANTS[variant]
        self.size = size
        self.envs = []
        for _ in range(num_envs):
            env = _Foraging(players=players, min_player_level=1, max_player_level=1,
                            min_food_level=1, max_food_level=None, field_size=(size, size),
                            max_num_food=foods, sight=SIGHT,
                            max_episode_steps=10**9,  # the server loop truncates
                            force_coop=True, normalize_reward=True, grid_observation=False)
            self.envs.append(env)
        self._seeds = np.random.SeedSequence(seed).generate_state(num_envs)
        self._seeded = np.zeros(num_envs, bool)
        p = size + 2 * SIGHT
        self._grid = np.zeros((num_envs, 3, p, p), np.float32)
        self._actions = list(Action)

    # -- observation building from the environment's fields ------------------------------------
    def _write(self, e: int, out: Batch) -> None:
        env = self.envs[e]
        g = self._grid[e]
        s = SIGHT
        g[0].fill(0.0)
        g[1].fill(0.0)
        g[1, s:-s, s:-s] = env.field
        g[2].fill(0.0)
        g[2, s:-s, s:-s] = 1.0
        g[2, s:-s, s:-s][env.field > 0] = 0.0
        for pl in env.players:
            r, c = pl.position
            g[0, r + s, c + s] = pl.level
            g[2, r + s, c + s] = 0.0
        out.state[e] = g.reshape(-1)
        view = 3 * (2 * s + 1) ** 2
        scale = 1.0 / (self.size - 1)
        for i, pl in enumerate(env.players):
            r, c = pl.position
            out.obs[e, i, :view] = g[:, r:r + 2 * s + 1, c:c + 2 * s + 1].reshape(-1)
            out.obs[e, i, view] = r * scale
            out.obs[e, i, view + 1] = c * scale
            av = out.avail[e, i]
            av[:] = 0
            for a in env._valid_actions[pl]:
                av[a.value] = 1

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        for e in env_ids:
            e = int(e)
            env = self.envs[e]
            if not self._seeded[e]:
                env.reset(seed=int(self._seeds[e]))
                self._seeded[e] = True
            else:
                env.reset()
            self._write(e, out)

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        for e, env in enumerate(self.envs):
            if active is not None and not active[e]:
                continue
            _, rewards, _, _, _ = env.step([int(a) for a in actions[e]])
            out.reward[e] = float(sum(rewards))
            out.terminated[e] = 1 if env.field.sum() == 0 else 0
            out.truncated[e] = 0
            self._write(e, out)


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return LbfVecEnv(variant, num_envs, seed)
