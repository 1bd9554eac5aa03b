"""A worked example: a small gymnasium-style cooperative game plugged into lmac.

Its family is this module's dotted path, so nothing is registered anywhere: the name
``lmac_env.examples.meet:line5-2ag`` imports this module and reads the schema
``env-server/schemas/lmac_env.examples.meet/line5-2ag.toml``. To plug in your own env, copy this
file into your package (``mypkg/myenv.py`` -> family ``mypkg.myenv``), replace ``Meet`` with your
game and write ``schemas/mypkg.myenv/<variant>.toml``; ``lmac envs --check`` then builds it and
compares what it writes with the schema. The numbered rules are the ``VecEnv`` contract
(lmac_env/core.py).
"""
import numpy as np

from lmac_env.core import Batch, Schema, VecEnv, schema_path, split_done

VARIANTS = {"line5-2ag": (5, 2, 20)}  # variant: cells, agents, the game's own step limit
LEFT, STAY, RIGHT = 0, 1, 2


class Meet:
    """The game, one copy, gym style: agents on a line of cells; each sees only its own cell and
    whether a teammate stands on it. The team earns 1 and the game ends when all stand on one
    cell. Like many gym envs it also reports ``done`` at its own step limit."""

    def __init__(self, cells: int, agents: int, max_steps: int):
        self.cells, self.agents, self.max_steps = cells, agents, max_steps
        self.rng = np.random.default_rng()

    def reset(self, seed=None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.pos, self.t = self.rng.integers(0, self.cells, self.agents), 0
        return self.observe()

    def observe(self) -> np.ndarray:
        obs = np.zeros((self.agents, self.cells + 1), np.float32)
        obs[np.arange(self.agents), self.pos] = 1.0
        obs[:, -1] = [np.count_nonzero(self.pos == p) > 1 for p in self.pos]
        return obs

    def step(self, actions):
        self.pos = np.clip(self.pos + np.asarray(actions) - 1, 0, self.cells - 1)
        self.t += 1
        met = bool(np.all(self.pos == self.pos[0]))
        return self.observe(), float(met), met or self.t >= self.max_steps, {"met": met}


class MeetVecEnv(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int):
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant {variant!r} of {__name__}; known: {', '.join(VARIANTS)}")
        # Rule 1: the env loads its own schema by its name, FAMILY:VARIANT. The shared memory is
        # laid out from that file, so reset and step must write exactly its sizes (the env
        # server checks them on its first reset and step and stops naming the file and field).
        self.schema = Schema.load(schema_path(f"{__name__}:{variant}"))
        self.num_envs = num_envs
        self.games = [Meet(*VARIANTS[variant]) for _ in range(num_envs)]
        # Rule 2, seeding: deterministic for `seed`. Copy k takes seed k of SeedSequence(seed) on
        # its first reset and continues its own generator on later resets.
        self.seeds = np.random.SeedSequence(seed).generate_state(num_envs)
        self.seeded = np.zeros(num_envs, bool)
        # Optional: which episodes that just ended were won (default: the terminated ones).
        self.won = np.zeros(num_envs, bool)

    def write(self, e: int, obs: np.ndarray, out: Batch) -> None:
        game = self.games[e]
        out.obs[e] = obs              # (n_agents, obs_dim): whole rows, so sizes are checked
        out.state[e] = game.pos       # the state the protocol designer reconstructs: every cell
        avail = np.ones((game.agents, 3), np.uint8)
        avail[game.pos == 0, LEFT] = 0  # the ends of the line cannot be left
        avail[game.pos == game.cells - 1, RIGHT] = 0
        out.avail[e] = avail          # Rule 3: available actions with every observation

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        # Rule 4: reset writes obs, state and available actions of the listed envs only; the
        # other rows belong to episodes still running.
        for e in env_ids:
            seed = None if self.seeded[e] else int(self.seeds[e])
            self.seeded[e] = True
            self.write(e, self.games[e].reset(seed), out)

    def step(self, actions: np.ndarray, out: Batch, active=None) -> None:
        for e, game in enumerate(self.games):
            # Rule 5: an inactive env's episode ended at a time limit; the server resets it right
            # after this call, so it is not stepped.
            if active is not None and not active[e]:
                continue
            obs, reward, done, info = game.step(actions[e])
            # Rule 6: reward, terminated and truncated for every env stepped (the slot would keep
            # the previous step's values). A `done` at the game's own step limit is a truncation,
            # not a termination: the learner bootstraps from the observation written below
            # (split_done; `terminal` is the game's own word for a real end, where it has one).
            out.reward[e] = reward
            out.terminated[e], out.truncated[e] = split_done(done, game.t, game.max_steps, terminal=info["met"])
            self.won[e] = info["met"]
            self.write(e, obs, out)


def sizes(variant: str) -> dict:
    """Optional: what an env of ``variant`` writes, so `lmac envs --generate` can write the
    schema's numbers (you then describe its texts)."""
    cells, agents, max_steps = VARIANTS[variant]
    return {"n_agents": agents, "obs_dim": cells + 1, "state_dim": agents, "n_actions": 3,
            "episode_limit": max_steps}


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return MeetVecEnv(variant, num_envs, seed)
