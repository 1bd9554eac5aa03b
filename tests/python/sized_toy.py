"""A family module for the size-check tests (`sized_toy:a2-o5-s7-n4` on PYTHONPATH): an env whose
real sizes come from its variant name (2 agents, 5 observation values, 7 state values, 4 actions)
while its schema file may say otherwise, so a test can write a wrong schema and see it refused.
It writes the way a newcomer's env does: whole rows (`out.obs[e, i] = vector`). `-notrunc` in
the variant leaves `truncated` unwritten in step (a broken contract)."""
import numpy as np

from lmac_env.core import Batch, Schema, VecEnv, schema_path


class SizedToy(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int):
        parts = variant.split("-")
        self.writes_truncated = "notrunc" not in parts
        sizes = {p[0]: int(p[1:]) for p in parts if p[:1] in "aosn" and p[1:].isdigit()}
        self.n_agents, self.obs_dim, self.state_dim, self.n_actions = (sizes[k] for k in "aosn")
        self.schema = Schema.load(schema_path(f"sized_toy:{variant}"))
        self.num_envs = num_envs
        self.t = np.zeros(num_envs, np.int64)

    def _write(self, e: int, out: Batch) -> None:
        for i in range(self.n_agents):
            out.obs[e, i] = np.full(self.obs_dim, self.t[e] + i, np.float32)
            out.avail[e, i] = np.ones(self.n_actions, np.uint8)
        out.state[e] = np.full(self.state_dim, self.t[e], np.float32)

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        for e in env_ids:
            self.t[e] = 0
            self._write(e, out)

    def step(self, actions: np.ndarray, out: Batch, active=None) -> None:
        for e in range(self.num_envs):
            self.t[e] += 1
            self._write(e, out)
            out.reward[e] = 1.0
            out.terminated[e] = 0
            if self.writes_truncated:
                out.truncated[e] = 0


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return SizedToy(variant, num_envs, seed)
