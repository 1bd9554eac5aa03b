"""Level-Based Foraging in the paper's variant, built on lbforaging's own dynamics."""
import hashlib

import numpy as np
import pytest

from lmac_env.core import Batch
from lmac_env.registry import make
from lmac_env.server import Driver, Meta, _random_actions


def rollout(seed, steps=60, envs=3):
    env = make("lbf:8x8-2p-2f-s1-coop", envs, seed=seed)
    out, meta = Batch.allocate(env.schema, envs), Meta.allocate(env.schema, envs)
    drv = Driver(env, 0)
    drv.first(out, meta)
    rng = np.random.default_rng(seed)
    acts = np.zeros((envs, 2), np.int32)
    trace = []
    for _ in range(steps):
        _random_actions(rng, out.avail, acts)
        drv.advance(acts, out, meta)
        trace.append((out.obs.copy(), out.state.copy(), out.reward.copy(), meta.flags.copy()))
    return env, trace


def test_dims_match_schema():
    env, trace = rollout(0, steps=2)
    s = env.schema
    assert (s.n_agents, s.obs_dim, s.state_dim, s.n_actions) == (2, 29, 300, 6)
    obs, state, _, _ = trace[-1]
    assert obs.shape == (3, 2, 29) and state.shape == (3, 300)
    big = make("lbf:11x11-6p-4f-s1-coop", 1, seed=0).schema
    assert (big.n_agents, big.state_dim) == (6, 507)


def test_observation_is_the_window_of_the_state():
    env, trace = rollout(1, steps=5)
    obs, state, _, _ = trace[-1]
    e = env.envs[0]
    grid = state[0].reshape(3, 10, 10)
    for i, pl in enumerate(e.players):
        r, c = pl.position
        np.testing.assert_array_equal(obs[0, i, :27].reshape(3, 3, 3), grid[:, r:r + 3, c:c + 3])
        assert obs[0, i, :27].reshape(3, 3, 3)[0, 1, 1] == pl.level  # the agent itself at the centre
        np.testing.assert_allclose(obs[0, i, 27:], [r / 7, c / 7])  # own row and column, scaled
    # food layer holds the field; access layer is 0 on the padding
    np.testing.assert_array_equal(grid[1, 1:-1, 1:-1], e.field)
    assert grid[2, 0, :].sum() == 0 and grid[2, :, 0].sum() == 0


def test_deterministic_for_a_seed():
    _, a = rollout(7)
    _, b = rollout(7)
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            np.testing.assert_array_equal(u, v)
    _, c = rollout(8)
    assert any(not np.array_equal(x[1], y[1]) for x, y in zip(a, c))


def test_episodes_truncate_at_limit_and_reset():
    _, trace = rollout(3, steps=60, envs=2)
    # with random actions most episodes run to the 25-step limit; the first flag follows
    firsts = [t for t, (_, _, _, f) in enumerate(trace) if f[0]]
    assert firsts, "episodes reset automatically"
    assert all(b - a <= 25 for a, b in zip([-1] + firsts, firsts))


def digest(name, seed, envs=3, steps=80, limit=25):
    """sha256 of every row (obs, state, avail, reward, terminated) of `steps` batched steps with
    random available actions, resetting at termination and after `limit` steps."""
    env = make(name, envs, seed=seed)
    out = Batch.allocate(env.schema, envs)
    env.reset(np.arange(envs), out)
    rng = np.random.default_rng(seed)
    h = hashlib.sha256()
    t = np.zeros(envs, int)
    for _ in range(steps):
        for a in (out.obs, out.state, out.avail, out.reward, out.terminated):
            h.update(np.ascontiguousarray(a).tobytes())
        keys = rng.random(out.avail.shape) + out.avail
        env.step(keys.argmax(-1).astype(np.int32), out)
        t += 1
        done = np.flatnonzero((out.terminated == 1) | (t >= limit))
        for a in (out.obs, out.state, out.avail, out.reward, out.terminated):
            h.update(np.ascontiguousarray(a).tobytes())
        if len(done):
            env.reset(done, out)
            t[done] = 0
    return h.hexdigest()


@pytest.mark.parametrize("name,seed,expected", [
    ("lbf:8x8-2p-2f-s1-coop", 5, "15d19e3777e531ef5d048013d7f22f4cf682e8742e560d0aae52aa27275cd548"),
    ("lbf:11x11-6p-4f-s1-coop", 6, "43f02df0af99abece29ea55a1c0576dac8247c2b753ba7009b65525aaa93b1ac"),
])
def test_grid_variant_unchanged(name, seed, expected):
    """The same numbers as before the entity-state variant was added (digests recorded with the
    grid-only lbf.py of commit b233096), so datasets and results on the grid variants stay valid."""
    assert digest(name, seed) == expected
