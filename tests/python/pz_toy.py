"""A small PettingZoo ParallelEnv with every feature the `pz:` adapter handles, for the tests:
`pz:pz_toy[,key=value]...` (this folder is on sys.path).

- agents `a`, `b`, `c` with different spaces:
  a: observation Dict{observation: Box(4), action_mask}, actions Discrete(3) masked by the
     observation's action_mask (action 2 is never allowed);
  b: observation Box(2, 3) (6 values), actions MultiDiscrete([2, 3]) (6 joint actions);
  c: observation Discrete(4) (flattened one-hot), actions Discrete(2, start=1) masked by
     info["action_mask"] (only the env's action 2, i.e. lmac's index 1, is allowed);
- rewards 1 (a), 10 (b), 100 (c) per step, b dies (terminates) at step `b_dies` (default 2);
- the episode terminates at step `end` when `end` is set, else it is truncated at `max_cycles`;
- no state(): the adapter's state is the concatenated padded observations;
- `self.received` is the last action dict the env got (the tests check the decoding).
"""
from __future__ import annotations

import functools

import numpy as np
from gymnasium import spaces
from pettingzoo.utils.env import ParallelEnv


class ToyEnv(ParallelEnv):
    metadata = {"name": "pz_toy", "is_parallelizable": True, "render_modes": []}

    def __init__(self, max_cycles: int = 5, b_dies: int = 2, end: int | None = None):
        self.possible_agents = ["a", "b", "c"]
        self.agents = []
        self.max_cycles = max_cycles
        self.b_dies = b_dies
        self.end = end
        self._obs = {
            "a": spaces.Dict({"observation": spaces.Box(-10, 10, (4,), np.float32),
                              "action_mask": spaces.Box(0, 1, (3,), np.int8)}),
            "b": spaces.Box(-10, 10, (2, 3), np.float32),
            "c": spaces.Discrete(4),
        }
        self._act = {"a": spaces.Discrete(3), "b": spaces.MultiDiscrete([2, 3]), "c": spaces.Discrete(2, start=1)}
        self.rng = np.random.default_rng()
        self.t = 0
        self.received = None

    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent):
        return self._obs[agent]

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent):
        return self._act[agent]

    def _observe(self):
        x = self.rng.random(10).astype(np.float32)
        obs = {}
        if "a" in self.agents:
            obs["a"] = {"observation": x[:4] + self.t, "action_mask": np.array([1, 1, 0], np.int8)}
        if "b" in self.agents:
            obs["b"] = x[4:10].reshape(2, 3)
        if "c" in self.agents:
            obs["c"] = self.t % 4
        infos = {a: {} for a in self.agents}
        if "c" in self.agents:
            infos["c"] = {"action_mask": np.array([0, 1], np.int8)}
        return obs, infos

    def reset(self, seed=None, options=None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.agents = list(self.possible_agents)
        self.t = 0
        return self._observe()

    def step(self, actions):
        self.received = dict(actions)
        self.t += 1
        rewards = {a: {"a": 1.0, "b": 10.0, "c": 100.0}[a] for a in self.agents}
        over = self.end is not None and self.t >= self.end
        terms = {a: over or (a == "b" and self.t >= self.b_dies) for a in self.agents}
        truncs = {a: not terms[a] and self.t >= self.max_cycles for a in self.agents}
        obs, infos = self._observe()
        self.agents = [a for a in self.agents if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos


def parallel_env(**kwargs):
    return ToyEnv(**kwargs)
