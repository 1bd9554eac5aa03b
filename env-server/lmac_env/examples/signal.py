"""A communication game with a known answer and agents that differ: an observer that sees the
goal but cannot act, actors that act on the goal but cannot see it, and a bystander.

Family ``lmac_env.examples.signal``; variant ``observer-2actors`` (4 agents). Each step the goal
is one of three cells (it moves now and then); each actor is rewarded when its action names the
goal. Only agent 0 (the observer) sees the goal, and it has one action (stay); agents 1 and 2
(the actors) see their own last reward and a bit all agents share; agent 3 (the bystander) sees
the bit only and has one action. Without messages an actor can only guess (a third of the
reward); with the goal sent from the observer to the actors it can earn all of it. The right
protocol: agent 0 sends the goal to agents 1 and 2, and nobody needs to send the bystander or
the observer anything. The schema describes each kind of agent's observation on its own
(``[[agent_obs]]``). Vectorized over the batch with numpy.
"""
import numpy as np

from lmac_env.core import Batch, Schema, VecEnv, schema_path

VARIANTS = {"observer-2actors": 12}  # variant: episode length
N_AGENTS, OBS_DIM, STATE_DIM, N_ACTIONS = 4, 2, 2, 3
ACTORS = [1, 2]
MOVE = 0.2  # chance per step that the goal moves to another cell


class SignalVecEnv(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int):
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant {variant!r} of {__name__}; known: {', '.join(VARIANTS)}")
        self.schema = Schema.load(schema_path(f"{__name__}:{variant}"))
        self.num_envs, self.limit = num_envs, VARIANTS[variant]
        self.rng = np.random.default_rng(np.random.SeedSequence(seed))
        self.goal = np.zeros(num_envs, np.int64)
        self.bit = np.zeros(num_envs, np.float32)
        self.t = np.zeros(num_envs, np.int64)
        self.won = np.zeros(num_envs, bool)

    def write(self, ids: np.ndarray, out: Batch) -> None:
        obs = np.zeros((len(ids), N_AGENTS, OBS_DIM), np.float32)
        obs[:, 0, 0] = self.goal[ids]
        obs[:, :, 1] = self.bit[ids, None]
        out.obs[ids] = obs
        out.state[ids] = np.stack([self.goal[ids], self.bit[ids]], 1)
        avail = np.zeros((len(ids), N_AGENTS, N_ACTIONS), np.uint8)
        avail[:, ACTORS, :] = 1
        avail[:, [0, 3], 0] = 1  # the observer and the bystander cannot act: one action, stay
        out.avail[ids] = avail

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        ids = np.asarray(env_ids, np.int64)
        self.goal[ids] = self.rng.integers(0, 3, len(ids))
        self.bit[ids] = self.rng.integers(0, 2, len(ids))
        self.t[ids] = 0
        self.write(ids, out)

    def step(self, actions: np.ndarray, out: Batch, active=None) -> None:
        ids = np.arange(self.num_envs) if active is None else np.flatnonzero(active)
        hit = (np.asarray(actions)[ids][:, ACTORS] == self.goal[ids, None]).astype(np.float32)
        out.reward[ids] = hit.sum(1) / len(ACTORS)
        self.t[ids] += 1
        moves = self.rng.random(len(ids)) < MOVE
        self.goal[ids[moves]] = (self.goal[ids[moves]] + self.rng.integers(1, 3, moves.sum())) % 3
        self.bit[ids] = self.rng.integers(0, 2, len(ids))
        out.terminated[ids] = False
        out.truncated[ids] = self.t[ids] >= self.limit
        self.won[ids] = False
        self.write(ids, out)


def sizes(variant: str) -> dict:
    return {"n_agents": N_AGENTS, "obs_dim": OBS_DIM, "state_dim": STATE_DIM, "n_actions": N_ACTIONS,
            "episode_limit": VARIANTS[variant]}


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return SignalVecEnv(variant, num_envs, seed)
