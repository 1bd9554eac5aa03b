"""Google Research Football (gfootball 2.10.2) academy scenarios for the LMAC env-server.

Scenarios (variant = gfootball level name):

- ``academy_3_vs_1_with_keeper``: 3 controlled attackers (left-team roster players 1..3, central
  midfielders starting at (0.6, 0), (0.7, 0.2), (0.7, -0.2), the first with the ball) against a
  goalkeeper and a centre back. obs 26, state 26.
- ``academy_run_pass_and_shoot_with_keeper``: 2 controlled attackers (roster players 1..2 at
  (0.7, 0) and (0.7, -0.3); the ball starts at (0.7, -0.28) with the wide one) against a
  goalkeeper and a centre back. obs 22, state 22.

The left team's own goalkeeper (roster 0) is played by the built-in AI and is not featured.
Agent ``i`` always drives roster player ``1 + i``: the scenarios declare our goalkeeper
controllable, so with n agents for n + 1 controllable players gfootball would switch its
controllers between players during play (measured: controller 0 starts on the goalkeeper), and
an agent's "own" features would then describe a different player than the one its actions
move. We mark the goalkeeper non-controllable in each episode's scenario config, which turns
gfootball's dynamic player selection off and fixes controller i to roster player 1 + i
(``fixed_players=False`` restores gfootball's switching, as in the paper's reference wrapper).

Features (the paper's Table C.2 sizes; the same layout as the paper's reference wrapper, built
from gfootball's raw observation; field x in [-1, 1] toward the opponent goal at x = +1,
y in [-0.42, 0.42] with -y = top; directions are displacement per step):

state (absolute), n = controlled players, 2 opponents (keeper, centre back):
  positions of the n players (x, y) | their directions (dx, dy) | opponent positions |
  opponent directions | ball (x, y, z) | ball direction (dx, dy, dz)      -> 4n + 14
obs of agent i (relative to its own player where it says so):
  own position (x, y) | teammates' positions minus own | own direction | teammates' directions |
  opponents' positions minus own | opponents' directions | ball (x, y) minus own | ball z |
  ball direction (dx, dy, dz)                                              -> 4n + 14

Rendering is off. 19 actions (gfootball's default action set), all always available. Reward is
gfootball's scoring reward for the team: +1 when we score, -1 when we concede (not multiplied
by the number of agents). Termination is the academy scenario's own: a goal, the ball going out
of play, or the opponents gaining possession (and the scenario's 400-step game duration, which
the 150-step limit of the schema always reaches first). An episode is won when it ends on our
goal, so the win rate is the share of episodes that score. The server truncates at 150 steps, the
limit used by the paper's reference code.

Backends: ``LMAC_GRF_WORKERS`` = number of worker processes (0 = all environments stepped in
this process). The default (see ``_default_workers``) comes from the measurements in
docs/guide/grf.md. Each environment's episodes are seeded from ``SeedSequence([seed, env_index])``,
so results do not depend on the number of workers.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import sys
import tempfile

import numpy as np

from .core import Batch, Schema, VecEnv, schema_path

VARIANTS = {
    # scenario: number of controlled left-team players
    "academy_3_vs_1_with_keeper": 3,
    "academy_run_pass_and_shoot_with_keeper": 2,
}
N_OPPONENTS = 2  # right team: goalkeeper (roster 0) and centre back (roster 1)
N_ACTIONS = 19

ACTION_NAMES = [
    "idle", "left", "top_left", "top", "top_right", "right", "bottom_right", "bottom",
    "bottom_left", "long_pass", "high_pass", "short_pass", "shot", "sprint",
    "release_direction", "release_sprint", "sliding", "dribble", "release_dribble",
]


def feature_dims(n_agents: int) -> int:
    return 4 * n_agents + 7 * N_OPPONENTS


# -- one gfootball environment ----------------------------------------------------------------

_CONFIG_CLASS = None


def _config_class():
    """gfootball's Config, with our own goalkeeper made non-controllable in every episode's
    scenario (see the module docstring: fixes agent i to roster player 1 + i)."""
    global _CONFIG_CLASS
    if _CONFIG_CLASS is None:
        from gfootball.env import config as gf_config

        class FixedPlayersConfig(gf_config.Config):
            def NewScenario(self, inc=1):
                super().NewScenario(inc)
                if self._values.get("lmac_fixed_players", True):
                    self._scenario_cfg.left_team[0].controllable = False

        _CONFIG_CLASS = FixedPlayersConfig
    return _CONFIG_CLASS


class _Football:
    """One gfootball engine driven through ``FootballEnvCore`` (the layer below the gym env:
    no per-agent deep copies of the observation, no observation wrappers)."""

    def __init__(self, scenario: str, n_agents: int, seed_seq: np.random.SeedSequence,
                 fixed_players: bool = True):
        from gfootball.env import football_env_core

        self.n = n_agents
        self.rng = np.random.default_rng(seed_seq)
        self.config = _config_class()({
            "lmac_fixed_players": fixed_players,
            "level": scenario,
            "players": [f"agent:left_players={n_agents}"],
            "action_set": "default",
            "real_time": False,
            "dump_full_episodes": False,
            "dump_scores": False,
            "write_video": False,
            "tracesdir": os.path.join(tempfile.gettempdir(), "lmac-grf-dumps"),
            # Present from the start so that the engine never draws its own seed (and the
            # team-processing order, fixed from the first seed's parity, is ours too).
            "game_engine_random_seed": self._draw_seed(),
        })
        self.core = football_env_core.FootballEnvCore(self.config)
        self.done = True
        self.obs = None

    def _draw_seed(self) -> int:
        return int(self.rng.integers(0, 2**31 - 1))

    def reset(self):
        self.config["game_engine_random_seed"] = self._draw_seed()
        self.core.reset()
        self.done = False
        self.obs = self.core._observation  # read-only use; core.observation() deep-copies
        return self.obs

    def step(self, actions):
        if self.done:  # never step a finished engine (the server resets it first)
            return self.obs, 0.0, True
        obs, reward, done, _ = self.core.step(list(actions))
        self.obs = obs
        self.done = bool(done)
        return obs, float(reward), self.done

    def close(self):
        self.core.close()


def _write_features(o: dict, n: int, obs_out: np.ndarray, state_out: np.ndarray) -> None:
    """Raw gfootball observation -> the (n, 4n+14) observations and the (4n+14,) state."""
    pos = o["left_team"][1:1 + n]                 # (n, 2) controlled players
    vel = o["left_team_direction"][1:1 + n]
    opp = o["right_team"][:N_OPPONENTS]           # (2, 2) keeper, centre back
    opv = o["right_team_direction"][:N_OPPONENTS]
    ball = o["ball"]
    bvel = o["ball_direction"]

    k = 0
    for part in (pos, vel, opp, opv):
        m = part.size
        state_out[k:k + m] = part.reshape(-1)
        k += m
    state_out[k:k + 3] = ball
    state_out[k + 3:k + 6] = bvel

    for i in range(n):
        row = obs_out[i]
        me = pos[i]
        others = [j for j in range(n) if j != i]
        row[0:2] = me
        k = 2
        m = 2 * (n - 1)
        row[k:k + m] = (pos[others] - me).reshape(-1); k += m
        row[k:k + 2] = vel[i]; k += 2
        row[k:k + m] = vel[others].reshape(-1); k += m
        row[k:k + 4] = (opp - me).reshape(-1); k += 4
        row[k:k + 4] = opv.reshape(-1); k += 4
        row[k:k + 2] = ball[:2] - me; k += 2
        row[k] = ball[2]; k += 1
        row[k:k + 3] = bvel


class _LocalGroup:
    """A group of environments stepped in the calling process."""

    def __init__(self, scenario: str, n_agents: int, seed: int, env_indices: list[int],
                 fixed_players: bool = True):
        self.n = n_agents
        d = feature_dims(n_agents)
        self.envs = [_Football(scenario, n_agents, np.random.SeedSequence([seed, e]),
                               fixed_players) for e in env_indices]
        k = len(env_indices)
        self.obs = np.zeros((k, n_agents, d), np.float32)
        self.state = np.zeros((k, d), np.float32)
        self.reward = np.zeros(k, np.float32)
        self.terminated = np.zeros(k, np.uint8)

    def reset(self, local_ids):
        for j in local_ids:
            o = self.envs[j].reset()
            _write_features(o, self.n, self.obs[j], self.state[j])
        return self.obs[local_ids], self.state[local_ids]

    def step(self, actions, active=None):
        for j, env in enumerate(self.envs):
            if active is not None and not active[j]:
                continue   # its game ended (the server resets it next); stepping it could fail
            o, r, done = env.step(actions[j].tolist())
            self.reward[j] = r
            self.terminated[j] = done
            _write_features(o, self.n, self.obs[j], self.state[j])
        return self.obs, self.state, self.reward, self.terminated

    def close(self):
        for env in self.envs:
            env.close()
        self.envs = []


def _worker_main(conn, scenario, n_agents, seed, env_indices, fixed_players):
    import signal
    # The parent owns shutdown: it closes the pipe (EOF ends this loop). Ctrl-C goes to the
    # whole process group, so ignore it here; SIGTERM keeps its default (exit).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        group = _LocalGroup(scenario, n_agents, seed, env_indices, fixed_players)
        conn.send(("ok", None))
    except BaseException as e:  # report construction failures to the parent
        conn.send(("error", repr(e)))
        return
    while True:
        try:
            cmd, arg = conn.recv()
        except EOFError:
            break
        if cmd == "step":
            conn.send(group.step(*arg))
        elif cmd == "reset":
            conn.send(group.reset(arg))
        elif cmd == "close":
            group.close()
            conn.send(None)
            break


class _RemoteGroup:
    """A group of environments stepped in a worker process (requests are pipelined: all
    groups are sent their actions before any answer is read)."""

    def __init__(self, ctx, scenario, n_agents, seed, env_indices, fixed_players):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, daemon=True,
                                args=(child, scenario, n_agents, seed, env_indices,
                                      fixed_players))
        self.proc.start()
        child.close()

    def wait_ready(self):
        status, msg = self.conn.recv()
        if status != "ok":
            raise RuntimeError(f"GRF worker failed to start: {msg}")

    def send(self, cmd, arg):
        self.conn.send((cmd, arg))

    def recv(self):
        return self.conn.recv()

    def close(self):
        try:
            self.conn.send(("close", None))
            self.conn.recv()
        except (EOFError, OSError, BrokenPipeError):
            pass
        self.proc.join(timeout=5)
        if self.proc.is_alive():
            self.proc.terminate()


def _default_workers(num_envs: int) -> int:
    """In-process by default. Measured (docs/guide/grf.md) on the shared 2-core machine: worker
    processes cost 10-15% more CPU per env-step (pipes, pickling, idle lockstep) and, with the
    cores busy, were slower than stepping all B engines in the server process; the pipeline
    already runs one process per env server, which is the place to add parallelism
    (``--members``). ``LMAC_GRF_WORKERS=2`` opts in where cores are free."""
    return 0


class GrfVecEnv(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int, workers: int | None = None,
                 fixed_players: bool = True):
        if variant not in VARIANTS:
            raise ValueError(f"unknown GRF scenario {variant!r}; known: {', '.join(VARIANTS)}")
        self.schema = Schema.load(schema_path(f"grf:{variant}"))
        self.num_envs = num_envs
        # An episode is won when it ends on our goal (its last step's scoring reward is +1);
        # ending otherwise (the ball out of play, the opponents in possession) is not a win.
        self.won = np.zeros(num_envs, bool)
        self.n = n = VARIANTS[variant]
        if self.schema.n_agents != n or self.schema.obs_dim != feature_dims(n) \
                or self.schema.state_dim != feature_dims(n) or self.schema.n_actions != N_ACTIONS:
            raise ValueError(f"{self.schema.path} does not match the GRF feature layout")
        if workers is None:
            env_w = os.environ.get("LMAC_GRF_WORKERS")
            workers = int(env_w) if env_w not in (None, "") else _default_workers(num_envs)
        workers = max(0, min(int(workers), num_envs))
        self.workers = workers
        # the env indices each group owns (contiguous slices)
        if workers == 0:
            self.slices = [slice(0, num_envs)]
            self.groups = [_LocalGroup(variant, n, seed, list(range(num_envs)), fixed_players)]
            self.remote = False
        else:
            bounds = np.linspace(0, num_envs, workers + 1).astype(int)
            self.slices = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
            # fork is cheap and needs no importable __main__; but once this process holds
            # gfootball engines (an in-process GrfVecEnv), children start clean with spawn.
            method = "spawn" if "gfootball_engine" in sys.modules else "fork"
            ctx = mp.get_context(method)
            self.groups = [_RemoteGroup(ctx, variant, n, seed, list(range(s.start, s.stop)),
                                        fixed_players) for s in self.slices]
            for g in self.groups:
                g.wait_ready()
            self.remote = True

    def _group_of(self, env_ids):
        per = [[] for _ in self.groups]
        for e in env_ids:
            e = int(e)
            for gi, s in enumerate(self.slices):
                if s.start <= e < s.stop:
                    per[gi].append(e - s.start)
                    break
        return per

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        per = self._group_of(env_ids)
        if self.remote:
            for g, ids in zip(self.groups, per):
                if ids:
                    g.send("reset", ids)
            results = [g.recv() if ids else None for g, ids in zip(self.groups, per)]
        else:
            results = [g.reset(ids) if ids else None for g, ids in zip(self.groups, per)]
        for s, ids, res in zip(self.slices, per, results):
            if not ids:
                continue
            obs, state = res
            rows = np.asarray(ids) + s.start
            out.obs[rows] = obs
            out.state[rows] = state
            out.avail[rows] = 1
            # reward/terminated/truncated stay: on auto-reset they belong to the ending step

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        actions = np.asarray(actions, dtype=np.int64)
        act = (lambda s: None) if active is None else (lambda s: np.asarray(active[s], bool))
        if self.remote:
            for g, s in zip(self.groups, self.slices):
                g.send("step", (actions[s], act(s)))
            results = [g.recv() for g in self.groups]
        else:
            results = [g.step(actions[s], act(s)) for g, s in zip(self.groups, self.slices)]
        for s, (obs, state, reward, term) in zip(self.slices, results):
            out.obs[s] = obs
            out.state[s] = state
            out.reward[s] = reward
            out.terminated[s] = term
        out.avail[:] = 1
        out.truncated[:] = 0
        self.won[:] = (out.terminated != 0) & (out.reward > 0)

    def close(self) -> None:
        for g in getattr(self, "groups", []):
            g.close()
        self.groups = []

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


def make(variant: str, num_envs: int, seed: int) -> VecEnv:
    return GrfVecEnv(variant, num_envs, seed)
