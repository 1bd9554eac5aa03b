"""lmac's environments as PettingZoo ParallelEnvs (`lmac_env.parallel_env`): the API test on every
family that runs here, and the same episodes, ends and state as the lmac pipeline's VecEnv."""
import importlib.util

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import lmac_env
from lmac_env.core import Batch
from lmac_env.registry import make

NAMES = [
    "smaclite:1o_10b_vs_1r", "smaclite:2o_20b_vs_2r", "smaclite:5z_vs_1ul", "smaclite:bane_vs_hM",
    "lbf:8x8-2p-2f-s1-coop", "lbf:11x11-6p-4f-s1-coop-entity",
    "pz:mpe2.simple_spread_v3", "pz:mpe2.simple_reference_v3",
    "lmac_env.examples.meet:line5-2ag",
]
if importlib.util.find_spec("rware") is not None:
    NAMES.append("rware:tiny-2ag")


@pytest.mark.parametrize("name", NAMES)
def test_parallel_api(name):
    env = lmac_env.parallel_env(name, seed=1)
    parallel_api_test(env, num_cycles=env.episode_limit + 5)
    obs, infos = env.reset(seed=2)
    assert env.state().shape == env.state_space.shape
    for agent in env.agents:
        assert env.observation_space(agent).contains(obs[agent])
        mask = infos[agent]["action_mask"]
        assert mask.shape == (env.action_space(agent).n,) and mask.any()


def _actions_from(env, rng):
    """A random available action per agent, from the adapter's masks."""
    return {a: int(rng.choice(np.flatnonzero(env._batch.avail[0, i])))
            for i, a in enumerate(env.possible_agents)}


@pytest.mark.parametrize("name", ["smaclite:1o_10b_vs_1r", "lbf:8x8-2p-2f-s1-coop"])
def test_same_episodes_as_the_pipeline_env(name):
    """A seed names the same episode in the adapter and in lmac_env.make(name, 1, seed): every
    observation, state, mask and reward matches step by step, and the episode ends on the same
    step with the same kind of end."""
    env = lmac_env.parallel_env(name, seed=5)
    vec = make(name, 1, seed=5)
    out = Batch.allocate(vec.schema, 1)
    obs, infos = env.reset()
    vec.reset(np.array([0]), out)
    rng = np.random.default_rng(0)
    for t in range(vec.schema.episode_limit):
        for i, a in enumerate(env.possible_agents):
            np.testing.assert_array_equal(obs[a]["observation"], out.obs[0, i])
            np.testing.assert_array_equal(obs[a]["action_mask"], out.avail[0, i])
            np.testing.assert_array_equal(infos[a]["action_mask"], out.avail[0, i])
        np.testing.assert_array_equal(env.state(), out.state[0])
        acts = _actions_from(env, rng)
        obs, rew, term, trunc, infos = env.step(acts)
        vec.step(np.array([[acts[a] for a in env.possible_agents]]), out)
        first = env.possible_agents[0]
        assert rew[first] == pytest.approx(float(out.reward[0]))
        assert all(r == rew[first] for r in rew.values()), "every agent gets the team reward"
        if term[first] or trunc[first]:
            assert term[first] == bool(out.terminated[0])
            assert trunc[first] == (not out.terminated[0])
            assert env.agents == []
            assert "won" in infos[first]
            return
    pytest.fail("the episode did not end at the schema's episode limit")


def test_time_limit_truncates_and_seeds_repeat():
    """1o_10b's lost episodes end at the 50-step limit as truncations (the Overseer cannot die
    while the agents idle); reset(seed) replays the same start."""
    env = lmac_env.parallel_env("smaclite:1o_10b_vs_1r")
    first, _ = env.reset(seed=7)
    steps = 0
    while env.agents:
        _, _, term, trunc, infos = env.step({a: 1 for a in env.agents})  # everyone stops
        steps += 1
    assert steps == env.episode_limit == 50
    assert trunc["agent_0"] and not term["agent_0"] and infos["agent_0"]["won"] is False
    with pytest.raises(RuntimeError, match="call reset"):
        env.step({})
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(first["agent_3"]["observation"], again["agent_3"]["observation"])


def test_state_without_last_actions():
    """state_last_action=False is SMAC's setting of that name: 1o_10b's state is 71 values (the
    LMAC authors' runs), the first 71 of the 148 lmac trains on; an env without last actions in
    its state refuses it."""
    full = lmac_env.parallel_env("smaclite:1o_10b_vs_1r", seed=3)
    short = lmac_env.parallel_env("smaclite:1o_10b_vs_1r", seed=3, state_last_action=False)
    full.reset(), short.reset()
    acts = {a: 1 for a in full.agents}
    full.step(acts), short.step(acts)
    assert short.state_space.shape == (71,) and full.state_space.shape == (148,)
    np.testing.assert_array_equal(short.state(), full.state()[:71])
    assert full.state()[71:].sum() == 11, "one one-hot last action per agent"
    with pytest.raises(ValueError, match="no last actions"):
        lmac_env.parallel_env("lbf:8x8-2p-2f-s1-coop", state_last_action=False)
