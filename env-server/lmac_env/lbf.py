"""Level-Based Foraging (lbforaging==2.0.0) in the paper's variant.

The dynamics are lbforaging's own (`ForagingEnv.step`: moves, collisions, cooperative loading,
normalised rewards). Observations and state are built here from the environment's fields,
because lbforaging 2.0.0's ``grid_observation`` is broken:

- observation (29 per agent): the 3x3 window around the agent (sight 1) of three layers of the
  padded grid: agent levels, food levels, accessible cells (1 = free cell inside the field),
  then the agent's own field row and column scaled to [0, 1] (lbforaging's vector observation
  also starts each agent's own entry with its position; without it a receiver could not place a
  teammate's 3x3 view anywhere on the grid, so no message could say where food or teammates are);
- state, one of two kinds chosen by the variant's name (dynamics, observation, actions, rewards
  and episode limit are the same for both):
  - ``grid`` (``lbf:8x8-2p-2f-s1-coop``): the same three layers over the whole padded grid,
    3 x (S+2)^2 values (300 for 8x8, 507 for 11x11);
  - ``entity`` (``lbf:8x8-2p-2f-s1-coop-entity``): the entities themselves, in raw field cells
    and levels: per agent (lbforaging's player order = agent id) row, col, level; then per food
    row, col, level, on-field flag. Foods are numbered in row-major order of the cells they
    spawned on (foods never move, so the numbering holds for the whole episode). An eaten food
    keeps its row and col, its level becomes 0 and its flag 0 (so its position dims stay a
    fact of the episode instead of jumping to an arbitrary value). A food slot lbforaging
    failed to spawn (it gives up after 1000 attempts; never seen on these fields) is all zeros.
    3 x players + 4 x foods values (14 for 8x8, 34 for 11x11).

  The grid state is a few sparse cells among hundreds, which a small state reconstructor (the
  protocol designer's discriminator) recovers no better than a constant guess; the entity state
  says the same thing in dims that each carry one fact.

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
from .sizes import SizeMismatch

SIGHT = 1
VARIANTS = {
    # variant: (field size, players, foods)
    "8x8-2p-2f-s1-coop": (8, 2, 2),
    "11x11-6p-4f-s1-coop": (11, 6, 4),
}
# state kind: variant-name suffix ("" for the grid state, the original variants' names)
STATE_KINDS = {"grid": "", "entity": "-entity"}
AGENT_FIELDS = 3  # row, col, level
FOOD_FIELDS = 4   # row, col, level, on-field flag
OBS_DIM = 3 * (2 * SIGHT + 1) ** 2 + 2


def split_variant(variant: str) -> tuple[str, str]:
    """`8x8-2p-2f-s1-coop-entity` -> (`8x8-2p-2f-s1-coop`, `entity`); no suffix -> grid."""
    for kind, suffix in STATE_KINDS.items():
        if suffix and variant.endswith(suffix) and variant[:-len(suffix)] in VARIANTS:
            return variant[:-len(suffix)], kind
    if variant in VARIANTS:
        return variant, "grid"
    known = [base + suffix for base in VARIANTS for suffix in STATE_KINDS.values()]
    raise ValueError(f"unknown LBF variant {variant!r}; known: {', '.join(known)}")


def state_dim(size: int, players: int, foods: int, kind: str) -> int:
    if kind == "grid":
        return 3 * (size + 2 * SIGHT) ** 2
    return AGENT_FIELDS * players + FOOD_FIELDS * foods


def sizes(variant: str) -> dict:
    """What an env of ``variant`` writes (the schema must say the same; `lmac envs --generate`)."""
    base, kind = split_variant(variant)
    size, players, foods = VARIANTS[base]
    return {"n_agents": players, "obs_dim": OBS_DIM, "state_dim": state_dim(size, players, foods, kind),
            "n_actions": len(Action)}


class _Foraging(ForagingEnv):
    """lbforaging's env without its own observation building (we build ours from its fields)."""

    def _make_gym_obs(self):
        return None


class LbfVecEnv(VecEnv):
    """B lbforaging envs. ``variant`` names the field, the team and the state kind
    (see the module doc): `8x8-2p-2f-s1-coop` (grid state) or `8x8-2p-2f-s1-coop-entity`."""

    def __init__(self, variant: str, num_envs: int, seed: int):
        base, self.state_kind = split_variant(variant)
        size, players, foods = VARIANTS[base]
        self.schema = Schema.load(schema_path(f"lbf:{variant}"))
        self._check_schema(variant)
        self.num_envs = num_envs
        self.size = size
        self.n_foods = foods
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
        # entity state: each env's food cells (row, col), row-major, fixed at reset
        self._food_cells = [np.zeros((0, 2), np.int64)] * num_envs
        self._actions = list(Action)

    def _check_schema(self, variant: str) -> None:
        """The schema file must describe what this env writes (the shared-memory layout is
        computed from it): a mismatch would misplace every row, so it fails here, by name."""
        s = self.schema
        for field, want in sizes(variant).items():
            got = getattr(s, field)
            if got != want:
                raise SizeMismatch(f"{s.path}: {field} = {got}, but lbf:{variant} ({self.state_kind} "
                                 f"state) writes {want}; fix the schema file")

    # -- observation and state building from the environment's fields --------------------------
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
        if self.state_kind == "grid":
            out.state[e] = g.reshape(-1)
        else:
            self._write_entities(e, out.state[e])
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

    def _write_entities(self, e: int, st: np.ndarray) -> None:
        env = self.envs[e]
        players = env.players
        agents = st[:AGENT_FIELDS * len(players)].reshape(len(players), AGENT_FIELDS)
        for i, pl in enumerate(players):
            agents[i] = (pl.position[0], pl.position[1], pl.level)
        foods = st[AGENT_FIELDS * len(players):].reshape(self.n_foods, FOOD_FIELDS)
        foods[:] = 0.0
        for j, (r, c) in enumerate(self._food_cells[e]):
            level = env.field[r, c]
            foods[j] = (r, c, level, 1.0 if level > 0 else 0.0)

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        for e in env_ids:
            e = int(e)
            env = self.envs[e]
            if not self._seeded[e]:
                env.reset(seed=int(self._seeds[e]))
                self._seeded[e] = True
            else:
                env.reset()
            self._food_cells[e] = np.argwhere(env.field > 0)[:self.n_foods]  # row-major
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
