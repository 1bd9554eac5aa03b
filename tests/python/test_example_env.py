"""The worked example environment (lmac_env/examples/meet.py): its contract rules on their own,
then end to end through the real pipeline (`lmac run --verify` and a short `lmac train`) with the
repository's venv, found by its module path alone (no registry entry)."""
import csv

import numpy as np

from lmac_env.core import Batch
from lmac_env.examples import meet
from lmac_env.registry import make
from lmac_env.sizes import check
from test_pz_cli import run

NAME = "lmac_env.examples.meet:line5-2ag"


def test_the_schema_fits_and_the_family_is_found_by_its_module_path():
    s = check(NAME)
    assert (s.n_agents, s.obs_dim, s.state_dim, s.n_actions) == (2, 6, 2, 3)
    assert isinstance(make(NAME, 1, 0), meet.MeetVecEnv)


def rollout(seed, steps=30):
    env = make(NAME, 3, seed)
    out = Batch.allocate(env.schema, 3)
    env.reset(np.arange(3), out)
    rows = []
    for t in range(steps):
        env.step(np.full((3, 2), t % 3), out)
        rows.append(np.concatenate([out.obs.ravel(), out.state.ravel(), out.reward]))
        ended = np.nonzero(out.terminated | out.truncated)[0]
        env.reset(ended, out)
    return np.stack(rows)


def test_a_seed_gives_the_same_episodes_and_another_seed_others():
    assert np.array_equal(rollout(3), rollout(3))
    assert not np.array_equal(rollout(3), rollout(4))


def test_the_games_own_step_limit_is_a_truncation_and_meeting_a_termination():
    env = make(NAME, 1, 0)
    out = Batch.allocate(env.schema, 1)
    env.reset(np.arange(1), out)
    apart = np.array([[meet.LEFT, meet.RIGHT]])  # never on one cell after the first step
    for t in range(env.schema.episode_limit):
        out.truncated[:] = 7  # step must overwrite it on every step
        env.step(apart, out)
        last = t == env.schema.episode_limit - 1
        assert (out.terminated[0], out.truncated[0]) == (0, int(last))
    assert out.avail[0, 0, meet.LEFT] == 0 and out.avail[0, 1, meet.RIGHT] == 0, "the line's ends"
    env.reset(np.arange(1), out)
    game = env.games[0]
    toward = np.where(game.pos > game.pos.mean(), meet.LEFT, meet.RIGHT)
    for _ in range(5):
        env.step(np.where(game.pos == game.pos[0], meet.STAY, toward)[None], out)
        if out.terminated[0]:
            break
    assert out.terminated[0] == 1 and out.truncated[0] == 0 and out.reward[0] == 1.0 and env.won[0]


def test_end_to_end_through_the_pipeline(tmp_path):
    r = run(["run", "--env", NAME, "--envs", "4", "--steps", "2000", "--verify"])
    assert r.returncode == 0, r.stderr[-3000:]
    assert "0 invariant violations" in r.stdout, r.stdout
    r = run(["train", "--env", NAME, "--algo", "qmix", "--steps", "3000", "--out", str(tmp_path),
             "--set", "run.envs=4", "--set", "run.log_interval=500", "--set", "run.test_interval=1000",
             "--set", "run.test_episodes=8", "--set", "run.final_eval_episodes=8"])
    assert r.returncode == 0, r.stderr[-3000:]
    metrics = list(tmp_path.rglob("metrics.csv"))
    assert len(metrics) == 1, metrics
    rows = list(csv.DictReader(metrics[0].open()))
    tests = [row for row in rows if row["test_return_mean"]]
    assert len(tests) >= 3 and int(rows[-1]["t_env"]) >= 3000, rows
