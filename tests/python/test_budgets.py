"""Budgets that fit long episodes, through a real `lmac train` on the worked example env:
metric rows never repeat a t_env (a test phase that falls due with a training row carries it),
test phases start on the run.test_interval grid, and a run whose update count will be tiny for
its episode length says so before it starts."""
import csv
import re

from test_pz_cli import run

NAME = "lmac_env.examples.meet:line5-2ag"


def test_one_row_per_t_env_tests_on_the_grid_and_a_warning_for_few_updates(tmp_path):
    # log_interval divides test_interval: every test phase falls due together with a training
    # row, and the run's last rows (the budget's log row and the final test) share a step.
    r = run(["train", "--env", NAME, "--algo", "qmix", "--steps", "3000", "--out", str(tmp_path),
             "--set", "run.envs=4", "--set", "run.log_interval=500", "--set", "run.test_interval=1000",
             "--set", "run.test_episodes=8", "--set", "run.final_eval_episodes=8"])
    assert r.returncode == 0, r.stderr[-3000:]
    # 3000 steps / 20-step episodes x 1 update per episode (the default)
    assert "= 150 updates if episodes run to their limit" in r.stderr, r.stderr[-3000:]
    assert "raise run.updates_per_episode (to 6.67 for 1000)" in r.stderr
    # The run's log says how fast acting was and how long it waited for the learner.
    acting = re.search(r"trainer: acting: (\d+) batched steps, the controller ([\d.]+) ms median / ([\d.]+) ms p99 "
                       r"per batched step; acting waited ([\d.]+) s of ([\d.]+) s for the learner", r.stderr)
    assert acting, r.stderr[-3000:]
    steps, median, p99, waited, total = (float(g) for g in acting.groups())
    assert steps >= 3000 / 4 and 0 < median <= p99 and 0 <= waited <= total, acting.group(0)
    rows = list(csv.DictReader(next(tmp_path.rglob("metrics.csv")).open()))
    t_env = [int(row["t_env"]) for row in rows]
    assert len(t_env) == len(set(t_env)), f"a t_env logged twice: {t_env}"
    assert t_env == sorted(t_env)
    tests = [int(row["t_env"]) for row in rows if row["test_return_mean"]]
    # One test phase at the start and one after each multiple of 1000 (the last one is the final
    # test at the budget), each ending before the next multiple.
    assert len(tests) == 4 and tests[0] < 1000, tests
    assert [t // 1000 for t in tests[1:]] == [1, 2, 3], tests
    # A test row that took over a training row carries its training return too.
    assert any(row["test_return_mean"] and row["train_return_mean"] for row in rows), rows
