"""Every lmac environment as a PettingZoo ``ParallelEnv``: ``lmac_env.parallel_env(name)``.

This is the other direction of ``lmac_env.pz`` (which serves PettingZoo games to lmac): it lets
EPyMARL, BenchMARL or anyone's own code run lmac's environments (the SMAC-Comm maps without
StarCraft II among them) with the same dynamics, seeds and time limit the lmac pipeline steps.

One lmac ``VecEnv`` with one environment stands behind the adapter. Per PettingZoo's
conventions:

- agents are ``agent_0 .. agent_{n-1}`` in the schema's order (a PettingZoo game's own names
  for ``pz:`` environments) and stay in ``env.agents`` until
  the episode ends (a dead SMAC unit keeps acting with its only available action, no-op, as in
  SMAC); when it ends every agent is terminated or truncated at once and ``env.agents`` empties;
- every agent receives the team reward (``infos[agent]["team_reward"]`` says it is shared, so a
  learner that sums rewards over agents must average them instead);
- an observation is ``{"observation": values, "action_mask": available actions}`` (int8,
  1 = available), PettingZoo's convention for masks that its ``parallel_api_test`` samples
  with; ``infos[agent]["action_mask"]`` holds the same mask;
- ``state()`` is the global state the lmac pipeline writes, ``state_space`` its space;
- an episode that reaches the schema's ``episode_limit`` (or the env's own time limit) is
  truncated, one that the env ends is terminated, as the lmac learner sees them;
  ``infos[agent]["won"]`` says whether a finished episode was won (SMAC's ``battle_won``).

Seeds: ``parallel_env(name, seed=s)`` or ``reset(seed=s)`` rebuild the environment with seed
``s``, so a seed names the same episodes as ``lmac_env.make(name, 1, seed=s)``.
"""
from __future__ import annotations

import functools

import numpy as np

from typing import Callable

from .core import Batch, VecEnv
from .registry import make


def parallel_env(name: str, seed: int = 0, state_last_action: bool = True, render_mode=None,
                 make_vec: Callable[[int], VecEnv] | None = None):
    """A PettingZoo ParallelEnv of the lmac environment ``name`` (``FAMILY:VARIANT``).

    state_last_action  False drops the agents' one-hot last actions from ``state()``, where the
                       environment puts them there (the SMAC-Comm maps; SMAC's own setting of
                       that name, which the LMAC authors run as False); an error elsewhere.
    make_vec           ``make_vec(seed)`` builds the one-env VecEnv, for an environment its name
                       alone does not reach (one on a schema outside the schema directory);
                       default ``lmac_env.make(name, 1, seed)``.
    """
    return LmacParallelEnv(name, seed=seed, state_last_action=state_last_action,
                           render_mode=render_mode, make_vec=make_vec)


def _parallel_base():
    # Imported here so that the env servers, which never use the adapter, do not need PettingZoo.
    from pettingzoo.utils.env import ParallelEnv
    return ParallelEnv


class LmacParallelEnv(_parallel_base()):
    metadata = {"name": "lmac", "render_modes": [], "is_parallelizable": True}

    def __init__(self, name: str, seed: int = 0, state_last_action: bool = True, render_mode=None,
                 make_vec: Callable[[int], VecEnv] | None = None):
        from gymnasium import spaces
        if render_mode is not None:
            raise ValueError(f"{name}: lmac environments do not render (render_mode={render_mode!r})")
        self.render_mode = None
        self.name = name
        self.metadata = dict(self.metadata, name=name)
        self._seed = int(seed)
        self._make = make_vec or (lambda s: make(name, 1, seed=s))
        self._env = self._make(self._seed)
        schema = self.schema = self._env.schema
        self._batch = Batch.allocate(schema, 1)
        self._state_end = schema.state_dim
        if not state_last_action:
            offset = getattr(self._env, "state_last_action_offset", None)
            if offset is None:
                raise ValueError(f"{name}: state_last_action=False, but this environment's state "
                                 "has no last actions to drop")
            self._state_end = int(offset)
        # A PettingZoo game's own agent names (its VecEnv keeps them), else agent_0 .. agent_{n-1}.
        self.possible_agents = list(getattr(self._env, "agents", None) or
                                    [f"agent_{i}" for i in range(schema.n_agents)])
        self.agents: list[str] = []
        self._obs_space = spaces.Dict({
            "observation": spaces.Box(-np.inf, np.inf, (schema.obs_dim,), np.float32),
            "action_mask": spaces.Box(0, 1, (schema.n_actions,), np.int8)})
        self._act_space = spaces.Discrete(schema.n_actions)
        self.state_space = spaces.Box(-np.inf, np.inf, (self._state_end,), np.float32)
        self.episode_limit = schema.episode_limit
        self._t = 0
        self._ended = True

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent):
        return self._obs_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent):
        return self._act_space

    def _out(self, won: bool | None = None):
        b = self._batch
        obs, infos = {}, {}
        for i, a in enumerate(self.possible_agents):
            mask = b.avail[0, i].astype(np.int8)
            obs[a] = {"observation": b.obs[0, i].copy(), "action_mask": mask}
            info = {"action_mask": mask, "team_reward": True}
            if won is not None:
                info["won"] = won
            infos[a] = info
        return obs, infos

    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:  # Gymnasium's convention: a seed given restarts its random stream
            self._env.close()
            self._seed = int(seed)
            self._env = self._make(self._seed)
        self._env.reset(np.array([0]), self._batch)
        self._t = 0
        self._ended = False
        self.agents = list(self.possible_agents)
        return self._out()

    def step(self, actions: dict):
        if self._ended:
            raise RuntimeError(f"{self.name}: step() after the episode ended; call reset() first")
        a = np.zeros((1, self.schema.n_agents), np.int64)
        for i, agent in enumerate(self.possible_agents):
            if agent in actions:
                a[0, i] = int(actions[agent])
            else:  # no action given: the first available one (no-op for a dead SMAC unit)
                a[0, i] = int(np.flatnonzero(self._batch.avail[0, i])[:1].sum())
        b = self._batch
        b.terminated[:] = 0
        b.truncated[:] = 0
        self._env.step(a, b)
        self._t += 1
        term = bool(b.terminated[0])
        trunc = not term and (bool(b.truncated[0]) or self._t >= self.episode_limit)
        won = None
        if term or trunc:
            self._ended = True
            w = getattr(self._env, "won", None)
            won = bool(np.asarray(w, bool)[0]) if w is not None else term
        obs, infos = self._out(won)
        r = float(b.reward[0])
        rewards = {agent: r for agent in self.agents}
        terminations = {agent: term for agent in self.agents}
        truncations = {agent: trunc for agent in self.agents}
        obs = {agent: obs[agent] for agent in self.agents}
        infos = {agent: infos[agent] for agent in self.agents}
        if self._ended:
            self.agents = []
        return obs, rewards, terminations, truncations, infos

    def state(self) -> np.ndarray:
        return self._batch.state[0, :self._state_end].copy()

    def render(self):
        return None

    def close(self):
        self._env.close()
