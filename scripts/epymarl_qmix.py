"""An independent learner on lmac's environments: EPyMARL's QMIX (PyPI's PyMARLzoo+, unmodified)
trained on any lmac environment through its PettingZoo adapter (`lmac_env.parallel_env`).

Set up once with `bash scripts/setup-epymarl.sh` (a virtual environment outside the project),
then run with that environment's Python, from the repository root:

    ~/.cache/lmac/epymarl-venv/bin/python scripts/epymarl_qmix.py \
        --env smaclite:1o_10b_vs_1r --seed 0 --steps 300000 --out runs/epymarl/seed_0

The defaults are the LMAC authors' QMIX settings (their `src/config/algs/qmix.yaml`,
`default.yaml` and `envs/sc2.yaml`): EPyMARL's episode runner (one env, one update of 32
episodes per episode once 32 are buffered), double Q, epsilon 1 -> 0.05 over 50k steps, a
5000-episode buffer, a target copy every 200 episodes, last action and agent id in the agents'
input, raw rewards, SMAC's `state_last_action: False` and its time limit reported as a
termination (SMAC's `continuing_episode: False` leaves `episode_limit` out of the info, so
EPyMARL does not bootstrap there). Tests: 32 greedy episodes every 10k steps, as lmac's.

Writes into --out: `metrics.csv` (t_env, test return, test win rate, train return, epsilon),
`config.json` (every setting EPyMARL ran with), `summary.json` and EPyMARL's own sacred files.
Not part of the tests: this is a measurement beside lmac, one core per run.
"""
from __future__ import annotations

import argparse
import csv
import json
import pathlib
import shutil
import sys
import time
from functools import partial

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "env-server"))

import numpy as np  # noqa: E402

import lmac_env  # noqa: E402


def _epymarl():
    try:
        import pymarlzooplus.envs as envs
        import pymarlzooplus.main as main
        from pymarlzooplus.envs.multiagentenv import MultiAgentEnv
    except ImportError as e:
        sys.exit(f"epymarl_qmix: {e}; run `bash scripts/setup-epymarl.sh` and use its Python "
                 "(~/.cache/lmac/epymarl-venv/bin/python)")
    return envs, main, MultiAgentEnv


ENVS, MAIN, MultiAgentEnv = _epymarl()


class LmacEpymarlEnv(MultiAgentEnv):
    """EPyMARL's MultiAgentEnv over lmac's PettingZoo adapter: the team reward once (not summed
    over agents), lmac's state and action masks, `battle_won` at an episode's end."""

    def __init__(self, key: str, seed: int = 0, state_last_action: bool = False,
                 limit_terminal: bool = True, **_gymma_args):
        super().__init__()
        self._env = lmac_env.parallel_env(key, seed=int(seed), state_last_action=state_last_action)
        self.agents = list(self._env.possible_agents)
        self.n_agents = len(self.agents)
        self.episode_limit = self._env.episode_limit
        self.limit_terminal = limit_terminal
        self._obs = self._masks = None

    def _keep(self, obs, infos):
        self._obs = [np.asarray(obs[a]["observation"], np.float32) for a in self.agents]
        self._masks = [infos[a]["action_mask"].astype(int).tolist() for a in self.agents]

    def reset(self, seed=None):
        self._keep(*self._env.reset(seed=seed))
        return self.get_obs(), self.get_state()

    def step(self, actions):
        acts = {a: int(x) for a, x in zip(self.agents, actions)}
        obs, rew, term, trunc, infos = self._env.step(acts)
        self._keep(obs, infos)
        first = self.agents[0]
        info = {}
        done = term[first] or trunc[first]
        if done:
            info["battle_won"] = bool(infos[first]["won"])
            if trunc[first] and not self.limit_terminal:
                info["episode_limit"] = True
        return float(rew[first]), bool(done), info

    def get_obs(self):
        return self._obs

    def get_obs_agent(self, agent_id):
        return self._obs[agent_id]

    def get_obs_size(self):
        return int(self._env.schema.obs_dim)

    def get_state(self):
        return self._env.state()

    def get_state_size(self):
        return int(self._env.state_space.shape[0])

    def get_avail_actions(self):
        return self._masks

    def get_avail_agent_actions(self, agent_id):
        return self._masks[agent_id]

    def get_total_actions(self):
        return int(self._env.schema.n_actions)

    def get_print_info(self):
        return None

    def get_stats(self):
        return {}

    def render(self):
        pass

    def close(self):
        self._env.close()

    def seed(self):
        return None

    def save_replay(self):
        pass


def _bool(text: str) -> bool:
    if text.lower() in ("true", "1", "yes"):
        return True
    if text.lower() in ("false", "0", "no"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="smaclite:1o_10b_vs_1r", help="an lmac environment name")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=300_000, help="env steps (EPyMARL's t_max)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="output directory (must not exist)")
    p.add_argument("--state-last-action", type=_bool, default=False,
                   help="keep the agents' last actions in the state (lmac's default: true; "
                        "the LMAC authors' SMAC setting: false)")
    p.add_argument("--limit-terminal", type=_bool, default=True,
                   help="an episode that reaches the time limit ends as a termination, with no "
                        "bootstrap (SMAC as the authors run it); false reports `episode_limit` "
                        "so EPyMARL bootstraps there, as lmac does")
    p.add_argument("--test-interval", type=int, default=10_000)
    p.add_argument("--test-episodes", type=int, default=32)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other EPyMARL setting (a JSON value or a string), e.g. standardise_rewards=true")
    a = p.parse_args(argv)
    out = a.out.resolve()
    if out.exists():
        p.error(f"--out {out} exists; choose a new directory")
    out.mkdir(parents=True)

    ENVS.REGISTRY["lmac"] = partial(ENVS.env_fn, env=LmacEpymarlEnv)
    MAIN.get_caller_path = lambda: str(out)   # sacred's files go under --out, not next to this file
    settings = {
        # the authors' qmix.yaml / default.yaml where PyMARLzoo+'s differ or are silent
        "standardise_rewards": False, "standardise_returns": False,
        "epsilon_anneal_time": 50_000, "buffer_size": 5000, "target_update_interval_or_tau": 200,
        "obs_agent_id": True, "obs_last_action": True, "double_q": True, "batch_size": 32,
        "lr": 0.0005, "gamma": 0.99, "grad_norm_clip": 10, "runner": "episode", "batch_size_run": 1,
        "t_max": a.steps, "test_interval": a.test_interval, "test_nepisode": a.test_episodes,
        "log_interval": a.test_interval, "runner_log_interval": a.test_interval,
        "learner_log_interval": a.test_interval, "save_model": False, "use_tensorboard": False,
        "use_cuda": False, "seed": a.seed,
        "env": "lmac",
        "env_args": {"key": a.env, "seed": a.seed, "state_last_action": a.state_last_action,
                     "limit_terminal": a.limit_terminal},
    }
    for kv in a.set:
        k, sep, v = kv.partition("=")
        if not sep:
            p.error(f"--set {kv!r}: expected KEY=VALUE")
        settings[k] = _value(v)
    t0 = time.time()
    MAIN.pymarlzooplus({"config": "qmix", "env-config": "gymma", "algo_args": settings})
    wall = time.time() - t0

    runs = sorted(out.glob("results/sacred/*/*/*/info.json"), key=lambda f: f.stat().st_mtime)
    if not runs:
        sys.exit(f"epymarl_qmix: EPyMARL wrote no info.json under {out}/results (see its log above)")
    run_dir = runs[-1].parent
    info = json.loads((run_dir / "info.json").read_text())
    shutil.copy(run_dir / "config.json", out / "config.json")

    def number(v):  # sacred stores numpy scalars as jsonpickle objects
        return float(v["value"]) if isinstance(v, dict) else float(v)

    def series(key):
        return {t: number(v) for t, v in zip(info.get(f"{key}_T", []), info.get(key, []))}

    test_ret, test_won = series("test_return_mean"), series("test_battle_won_mean")
    ret, eps = series("return_mean"), series("epsilon")
    rows = sorted(set(test_ret) | set(ret))
    with open(out / "metrics.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_env", "test_return_mean", "test_win_rate", "train_return_mean", "epsilon"])
        for t in rows:
            w.writerow([t, test_ret.get(t, ""), test_won.get(t, ""), ret.get(t, ""), eps.get(t, "")])
    tests = sorted(test_ret)
    last = tests[-5:]
    best = max(tests, key=lambda t: (test_won.get(t, 0.0), test_ret[t])) if tests else None
    summary = {
        "learner": "EPyMARL QMIX (pymarlzooplus 1.1.0, unmodified)", "env": a.env, "seed": a.seed,
        "steps": a.steps, "state_last_action": a.state_last_action, "limit_terminal": a.limit_terminal,
        "test_interval": a.test_interval, "test_episodes": a.test_episodes, "sets": a.set,
        "wall_seconds": round(wall, 1), "tests": len(tests),
        "final_test_return": float(np.mean([test_ret[t] for t in last])) if last else None,
        "final_win_rate": float(np.mean([test_won.get(t, 0.0) for t in last])) if last else None,
        "best_test_phase": {"t_env": best, "return": test_ret[best], "win_rate": test_won.get(best)} if best is not None else None,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
