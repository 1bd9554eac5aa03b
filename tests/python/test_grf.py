"""Google Research Football through the env-server: real gfootball episodes (skipped only when
gfootball is not installed: run scripts/setup-grf.sh or scripts/setup.sh with LMAC_WITH_GRF=1).

    cd /work/main && PYTHONPATH=env-server .venv/bin/python -m pytest tests/python/test_grf.py -q
"""
from __future__ import annotations

import importlib.util
import os

import numpy as np
import pytest

if importlib.util.find_spec("gfootball") is None or importlib.util.find_spec(
        "gfootball_engine") is None:
    pytest.skip("gfootball is not installed (run scripts/setup-grf.sh, or scripts/setup.sh with "
                "LMAC_WITH_GRF=1)", allow_module_level=True)

from lmac_env import grf  # noqa: E402
from lmac_env.core import Batch, Schema, schema_path  # noqa: E402
from lmac_env.registry import make  # noqa: E402
from lmac_env.server import FLAG_PREV_WON, Driver, Meta  # noqa: E402

S3 = "grf:academy_3_vs_1_with_keeper"
RPS = "grf:academy_run_pass_and_shoot_with_keeper"
EXPECTED = {S3: (3, 26, 26), RPS: (2, 22, 22)}  # n_agents, obs_dim, state_dim (Table C.2)


def pipeline_batch(schema: Schema, num_envs: int, msg_cols: int):
    """A Batch whose obs is a strided view, as in a shared-memory slot (message columns follow
    every observation row)."""
    rows = np.full((num_envs, schema.n_agents, schema.obs_dim + msg_cols), -7.0, np.float32)
    out = Batch.allocate(schema, num_envs)
    out.obs = rows[:, :, :schema.obs_dim]
    return out, rows


# Message columns per receiver of the authors' designs (protocols/paper/README.md).
PAPER_DESIGN_COLUMNS = {S3: 110, RPS: 90}


@pytest.mark.parametrize("name", [S3, RPS])
def test_schema_and_dims(name):
    n, od, sd = EXPECTED[name]
    schema = Schema.load(schema_path(name))
    assert (schema.n_agents, schema.obs_dim, schema.state_dim, schema.n_actions) == (n, od, sd, 19)
    # FullComm always fits; the budget is the LMAC authors' wider design's (protocols/paper/)
    assert schema.message_columns == max((n - 1) * (od + n), PAPER_DESIGN_COLUMNS[name])
    assert schema.alpha == pytest.approx(0.002)
    assert len(schema.raw["actions"]) == 19
    for key, dim in (("obs_dims", od), ("state_dims", sd)):
        assert sum(g["count"] for g in schema.raw[key]) == dim

    env = make(name, 2, seed=0)
    try:
        out = Batch.allocate(env.schema, 2)
        env.reset(np.arange(2), out)
        assert out.obs.shape == (2, n, od) and out.state.shape == (2, sd)
        assert np.isfinite(out.obs).all() and np.isfinite(out.state).all()
        assert out.avail.all()
        st = out.state[0]
        # state: controlled players start in the opponents' half, keeper at its goal (x = +1)
        assert (st[0:2 * n:2] > 0.5).all()
        assert st[4 * n] == pytest.approx(1.0, abs=0.05)  # opponent goalkeeper x
        # obs/state consistency: own position, relative ball, relative opponents
        for i in range(n):
            ob = out.obs[0, i]
            me = st[2 * i:2 * i + 2]
            np.testing.assert_allclose(ob[0:2], me, atol=1e-6)
            k = 2 + 2 * (n - 1) + 2 + 2 * (n - 1)
            np.testing.assert_allclose(ob[k:k + 4], (st[4 * n:4 * n + 4].reshape(2, 2) - me).ravel(),
                                       atol=1e-6)
            ball = st[4 * n + 8:4 * n + 11]
            np.testing.assert_allclose(ob[od - 6:od - 4], ball[:2] - me, atol=1e-6)
            assert ob[od - 4] == pytest.approx(ball[2])
    finally:
        env.close()


@pytest.mark.parametrize("name", [S3, RPS])
def test_random_episodes_through_driver(name):
    """Real episodes with random actions through the server's episode driver (auto-reset,
    truncation) into strided slot-like views."""
    b = 4
    env = make(name, b, seed=1)
    try:
        schema = env.schema
        out, rows = pipeline_batch(schema, b, schema.message_columns)
        meta = Meta.allocate(schema, b)
        driver = Driver(env, member=0)
        driver.first(out, meta)
        rng = np.random.default_rng(0)
        ends = scoreless_ends = 0
        for _ in range(200):
            actions = rng.integers(0, 19, size=(b, schema.n_agents)).astype(np.int32)
            driver.advance(actions, out, meta)
            ends += int(((out.terminated != 0) | (out.truncated != 0)).sum())
            # won exactly when the episode ends on our goal (the win rate is the share that
            # scores): an early end without one is no win
            for e in np.nonzero(out.terminated != 0)[0]:
                assert bool(meta.flags[e] & FLAG_PREV_WON) == (out.reward[e] == 1.0), (e, out.reward[e])
                scoreless_ends += out.reward[e] != 1.0
            assert np.isfinite(out.obs).all() and np.isfinite(out.state).all()
            assert set(np.unique(out.reward)).issubset({-1.0, 0.0, 1.0})
            assert (meta.ep_step <= schema.episode_limit).all()
        # the message columns were never written
        assert (rows[:, :, schema.obs_dim:] == -7.0).all()
        # random play ends episodes (possession lost, ball out of play, 150-step limit)
        assert ends >= 2 and driver.episodes_done == ends and scoreless_ends >= 1
        # after auto-reset the rows are the first observation of a fresh episode
        first = np.nonzero(meta.flags & 1)[0]
        for e in first:
            assert out.state[e, 0] > 0.5
    finally:
        env.close()


def _scripted(obs: np.ndarray, n: int, state: np.ndarray) -> np.ndarray:
    """The agent nearest the ball runs at goal and shoots from close range; the others idle."""
    d = obs.shape[-1]
    b = obs.shape[0]
    acts = np.zeros((b, n), np.int32)
    for e in range(b):
        rel_ball = obs[e, :, d - 6:d - 4]
        carrier = int(np.argmin(np.linalg.norm(rel_ball, axis=1)))
        x, y = obs[e, carrier, 0:2]
        if x > 0.78 and abs(y) < 0.2:
            acts[e, carrier] = 12  # shot
        elif y < -0.08:
            acts[e, carrier] = 6   # bottom_right (towards the goal mouth)
        elif y > 0.08:
            acts[e, carrier] = 4   # top_right
        else:
            acts[e, carrier] = 5   # right
    return acts


def test_scripted_goal_gives_scoring_reward():
    """The wide attacker of run_pass_and_shoot carries the ball at goal and shoots: at least one
    of the episodes ends with a goal, rewarded +1 for the team in exactly the terminating step."""
    b = 4
    env = make(RPS, b, seed=3)
    try:
        schema = env.schema
        out = Batch.allocate(schema, b)
        meta = Meta.allocate(schema, b)
        driver = Driver(env, member=0)
        driver.first(out, meta)
        goals = 0
        for _ in range(300):
            acts = _scripted(out.obs, schema.n_agents, out.state)
            driver.advance(acts, out, meta)
            for e in np.nonzero(out.reward != 0)[0]:
                assert out.terminated[e] == 1      # the academy episode ends on the goal
                assert out.reward[e] in (1.0, -1.0)
                goals += out.reward[e] == 1.0
            for e in np.nonzero(out.terminated != 0)[0]:
                assert bool(meta.flags[e] & FLAG_PREV_WON) == (out.reward[e] == 1.0), (e, out.reward[e])
            if goals >= 2:
                break
        assert goals >= 1, "the scripted run-and-shoot never scored"
    finally:
        env.close()


def test_deterministic_and_worker_processes_agree():
    """Same seed -> same trajectories, in-process and with 2 worker processes."""
    b, steps = 2, 40
    trajs = []
    for workers in (0, 0, 2):
        env = grf.GrfVecEnv("academy_3_vs_1_with_keeper", b, seed=11, workers=workers)
        try:
            out = Batch.allocate(env.schema, b)
            meta = Meta.allocate(env.schema, b)
            driver = Driver(env, member=0)
            driver.first(out, meta)
            rng = np.random.default_rng(5)
            rec = [out.state.copy()]
            for _ in range(steps):
                driver.advance(rng.integers(0, 19, (b, 3)).astype(np.int32), out, meta)
                rec.append(np.concatenate([out.state.ravel(), out.obs.ravel(), out.reward,
                                           out.terminated.astype(np.float32)]))
            trajs.append(rec)
        finally:
            env.close()
    for other in trajs[1:]:
        for a, c in zip(trajs[0], other):
            np.testing.assert_array_equal(a, c)


@pytest.mark.skipif(importlib.util.find_spec("lmac_shm") is None,
                    reason="the lmac_shm bindings are not built (scripts/setup.sh builds them)")
def test_through_shared_memory_slab():
    """The env server's own write path: steps land in a shared-memory slot of the real slab."""
    import lmac_shm
    from lmac_env import server

    b = 2
    spath = schema_path(RPS)
    env = make(RPS, b, seed=4)
    name = f"lmac-grftest-{os.getpid()}"
    slab = lmac_shm.Slab.create(name, str(spath), b, env.schema.message_columns, 2)
    try:
        driver = Driver(env, member=0)
        lease = slab.lease(0, "env")
        server._write_first(driver, lease)
        st = np.array(lease.state)
        assert st.shape == (b, 22) and (st[:, 0] > 0.5).all()
        rng = np.random.default_rng(1)
        for _ in range(60):
            acts = lease.actions
            acts[:] = rng.integers(0, 19, (b, 2))
            del acts
            server._write_step(driver, lease)
            obs = np.array(lease.obs)
            assert obs.shape == (b, 2, 22) and np.isfinite(obs).all()
        assert driver.episodes_done >= 1 or (np.array(lease.ep_step) == 60).all()
        del obs, st
    finally:
        env.close()
        del slab
