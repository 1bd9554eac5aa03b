"""The `pz:` adapter: any PettingZoo parallel environment as an lmac batched environment."""
import pathlib
import types
import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from lmac_env import parallel_env, pz, registry
from lmac_env.core import SCHEMA_DIR, Batch, Schema
from lmac_env.server import FLAG_FINAL, FLAG_FIRST, Driver, Meta, _random_actions

SPREAD = "pz:mpe2.simple_spread_v3"
REFERENCE = "pz:mpe2.simple_reference_v3"
KAZ = "pz:pettingzoo.butterfly.knights_archers_zombies_v11,max_cycles=100"
SPREAD_MEAN = "pz:mpe2.simple_spread_v3,team_reward=mean"
SHIPPED = [SPREAD, SPREAD_MEAN, REFERENCE, KAZ]


def generated(tmp_path, name, **kw) -> Schema:
    path = tmp_path / "schema.toml"
    path.write_text(pz.generate(name, **kw))
    return Schema.load(path)


def vec(name, num_envs, seed, tmp_path=None):
    """A pz VecEnv; with tmp_path, on a freshly generated schema (for variants not shipped)."""
    schema = generated(tmp_path, name) if tmp_path is not None else None
    return pz.PettingZooVecEnv(name.partition(":")[2], num_envs, seed, schema=schema)


# -- names ------------------------------------------------------------------------------------

def test_variant_syntax():
    target, kwargs, opts = pz.parse_variant("mpe2.simple_spread_v3,N=4,local_ratio=0.25,team_reward=mean,"
                                            "continuous_actions=false,render_mode=none,tag=x")
    assert target == "mpe2.simple_spread_v3"
    assert kwargs == {"N": 4, "local_ratio": 0.25, "continuous_actions": False, "render_mode": None, "tag": "x"}
    assert opts == {"team_reward": "mean"}
    assert pz.parse_variant("mpe2.simple_spread_v3")[2] == {"team_reward": "sum"}
    for bad, words in [("mpe2.simple spread", "dotted"), ("mpe2.x,N", "KEY=VALUE"), ("m,N=1,N=2", "twice"),
                       ("m,team_reward=max", "sum, mean"), ("", "dotted")]:
        with pytest.raises(ValueError, match=words):
            pz.parse_variant(bad)


def test_targets_module_or_callable_and_clear_import_errors():
    assert pz.make_parallel("pz_toy", {}).possible_agents == ["a", "b", "c"]
    assert pz.make_parallel("pz_toy.parallel_env", {"max_cycles": 3}).max_cycles == 3
    with pytest.raises(ValueError, match="cannot import no_such_package.env_v1.*PYTHONPATH"):
        pz.make_parallel("no_such_package.env_v1", {})
    with pytest.raises(ValueError, match="no parallel_env"):
        pz.make_parallel("json", {})


# -- the shipped environments -----------------------------------------------------------------

def test_shipped_schemas_fit_their_environments():
    dims = {SPREAD: (3, 18, 54, 5, 25), SPREAD_MEAN: (3, 18, 54, 5, 25), REFERENCE: (2, 21, 42, 50, 25), KAZ: (4, 135, 104, 6, 100)}
    for name in SHIPPED:
        path = SCHEMA_DIR / "pz" / f"{name.partition(':')[2]}.toml"
        assert path.is_file(), path
        text = path.read_text()
        assert "EDIT" not in text.split("\n", 3)[-1], f"{path} still has placeholder descriptions"
        lay = pz.check(name)
        s = Schema.load(path)
        assert (s.n_agents, s.obs_dim, s.state_dim, s.n_actions, s.episode_limit) == dims[name]
        assert (lay.n_agents, lay.obs_dim, lay.state_dim, lay.n_actions) == dims[name][:4]


def test_spread_rows_are_pettingzoos_own_values():
    """Observations, state and rewards equal those of twin PettingZoo envs seeded the same way."""
    from mpe2 import simple_spread_v3
    env = vec(SPREAD, 2, seed=7)
    seeds = np.random.SeedSequence(7).generate_state(2)
    twins = [simple_spread_v3.parallel_env() for _ in range(2)]
    tw = [t.reset(seed=int(s))[0] for t, s in zip(twins, seeds)]
    out = Batch.allocate(env.schema, 2)
    env.reset(np.arange(2), out)
    rng = np.random.default_rng(0)
    agents = twins[0].possible_agents
    for t in range(25):
        for e in range(2):
            for i, a in enumerate(agents):
                np.testing.assert_array_equal(out.obs[e, i], tw[e][a].astype(np.float32))
            np.testing.assert_array_equal(out.state[e], twins[e].state().astype(np.float32))
            assert out.avail[e].all()
        acts = rng.integers(0, 5, (2, 3)).astype(np.int32)
        env.step(acts, out)
        for e in range(2):
            tw[e], rew, term, trunc, _ = twins[e].step({a: int(acts[e, i]) for i, a in enumerate(agents)})
            assert out.reward[e] == pytest.approx(sum(rew.values()), rel=1e-6)
            last = t == 24
            assert (out.terminated[e], out.truncated[e]) == (0, 1 if last else 0)
    # The time limit's row still shows the agents' observations (the learner bootstraps from it).
    assert np.abs(out.obs).sum() > 0 and env.alive.all()
    assert not np.array_equal(out.obs[0], out.obs[1]), "the copies are seeded apart"


def test_reference_action_is_move_times_word():
    """simple_reference's 50 actions: index = 5 x word + move; the partner hears the word."""
    env = vec(REFERENCE, 1, seed=3)
    out = Batch.allocate(env.schema, 1)
    env.reset(np.arange(1), out)
    assert out.avail.shape == (1, 2, 50) and out.avail.all()
    for word, move in [(7, 2), (0, 4), (9, 0)]:
        vel0 = out.obs[0, 0, :2].copy()
        env.step(np.array([[5 * word + move, 0]], np.int32), out)
        heard = out.obs[0, 1, 11:21]
        assert heard.argmax() == word and heard.sum() == 1.0
        np.testing.assert_array_equal(out.obs[0, 0, 11:21], np.eye(10, dtype=np.float32)[0])
        if move == 2:  # accelerate right: the x velocity grows
            assert out.obs[0, 0, 0] > vel0[0]


def test_kaz_deaths_are_dead_slots_and_terminations_stay_terminations(tmp_path):
    name = "pz:pettingzoo.butterfly.knights_archers_zombies_v11,max_cycles=400,spawn_delay=4"
    env = vec(name, 4, seed=1, tmp_path=tmp_path)
    s = env.schema
    out, meta = Batch.allocate(s, 4), Meta.allocate(s, 4)
    drv = Driver(env, 0)
    drv.first(out, meta)
    rng = np.random.default_rng(1)
    acts = np.zeros((4, 4), np.int32)
    deaths = terminated = 0
    was_alive = env.alive.copy()
    noop_only = np.eye(6, dtype=np.uint8)[0]
    for _ in range(600):
        _random_actions(rng, out.avail, acts)
        drv.advance(acts, out, meta)
        first = (meta.flags & FLAG_FIRST) != 0
        terminated += int(out.terminated.sum())
        assert not (out.terminated & out.truncated).any()
        for e in range(4):
            if first[e]:
                assert env.alive[e].all(), "a new episode starts with every agent"
            else:
                assert not (env.alive[e] & ~was_alive[e]).any(), "the dead stay dead"
            for i in np.nonzero(~env.alive[e])[0]:
                assert not out.obs[e, i].any(), "a dead slot sees zeros"
                np.testing.assert_array_equal(out.avail[e, i], noop_only)
            if (~env.alive[e]).any() and env.alive[e].any() and not first[e]:
                deaths += 1
                # The env got actions only from the living (a dead agent's action is not sent).
                assert set(env.envs[e].agents) == {a for a, ok in zip(env.agents, env.alive[e]) if ok}
        was_alive = env.alive.copy()
    assert deaths > 0, "no agent died: the test saw no dead slot"
    assert terminated > 0, "no episode terminated (a zombie reaching the bottom ends it)"


def test_kaz_truncation_at_max_cycles_keeps_observations():
    env = vec(KAZ, 1, seed=0)
    out = Batch.allocate(env.schema, 1)
    env.reset(np.arange(1), out)
    five = np.full((1, 4), 5, np.int32)  # "do nothing": the zombies need > 100 steps to walk down
    for t in range(100):
        env.step(five, out)
        if t < 99:
            assert (out.terminated[0], out.truncated[0]) == (0, 0)
    assert (out.terminated[0], out.truncated[0]) == (0, 1)
    assert env.alive[0].all() and np.abs(out.obs[0]).sum(axis=1).min() > 0
    assert out.state[0].shape == (104,) and out.state[0].any()


# -- every feature on a toy environment -------------------------------------------------------

def test_toy_padding_masks_decoding_dead_slots_and_state(tmp_path):
    name = "pz:pz_toy,max_cycles=4"
    env = vec(name, 2, seed=5, tmp_path=tmp_path)
    s = env.schema
    assert (s.n_agents, s.obs_dim, s.n_actions, s.state_dim) == (3, 6, 6, 18)
    out = Batch.allocate(s, 2)
    env.reset(np.arange(2), out)
    e0 = env.envs[0]
    # a: 4 values then zero padding, mask from the observation dict, padded actions unavailable
    assert out.obs[0, 0, 4:].sum() == 0 and out.obs[0, 0, :4].all()
    np.testing.assert_array_equal(out.avail[0, 0], [1, 1, 0, 0, 0, 0])
    # b: the 2 x 3 box flattened, all 6 joint MultiDiscrete actions
    np.testing.assert_array_equal(out.avail[0, 1], [1] * 6)
    # c: Discrete(4) observation one-hot, mask from info
    np.testing.assert_array_equal(out.obs[0, 2], [1, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(out.avail[0, 2], [0, 1, 0, 0, 0, 0])
    # no state(): the state is the padded observations side by side
    np.testing.assert_array_equal(out.state[0], out.obs[0].reshape(-1))
    env.step(np.array([[1, 5, 1]] * 2, np.int32), out)
    assert e0.received["a"] == 1 and e0.received["c"] == 2
    np.testing.assert_array_equal(e0.received["b"], [1, 2])  # joint 5 = (1, 2) row-major
    assert out.reward[0] == 111.0 and (out.terminated[0], out.truncated[0]) == (0, 0)
    np.testing.assert_array_equal(out.obs[0, 2], [0, 1, 0, 0, 0, 0])
    env.step(np.array([[0, 0, 1]] * 2, np.int32), out)  # b terminates at step 2
    assert out.reward[0] == 111.0, "the death step's reward counts"
    assert env.alive[0].tolist() == [True, False, True]
    assert not out.obs[0, 1].any() and out.avail[0, 1].tolist() == [1, 0, 0, 0, 0, 0]
    env.step(np.array([[0, 3, 1]] * 2, np.int32), out)
    assert "b" not in e0.received, "a dead agent's action is not sent"
    assert out.reward[0] == 101.0, "a dead agent adds 0"
    env.step(np.array([[0, 0, 1]] * 2, np.int32), out)  # step 4: the time limit
    assert (out.terminated[0], out.truncated[0]) == (0, 1)
    assert env.alive[0].tolist() == [True, False, True] and out.obs[0, 0, :4].all()
    env.reset(np.arange(2), out)
    assert env.alive.all()
    with pytest.raises(ValueError, match="action 2 is outside its 2 actions"):
        env.step(np.array([[0, 0, 2]] * 2, np.int32), out)


def test_dict_observation_without_observation_key_leaves_out_the_mask():
    from gymnasium import spaces
    o = pz._Obs("x", spaces.Dict({"pos": spaces.Box(-1, 1, (2,)), "id": spaces.Discrete(2),
                                  "action_mask": spaces.Box(0, 1, (3,), np.int8)}))
    x = o.flat({"pos": np.array([0.5, -0.5]), "id": 1, "action_mask": np.ones(3, np.int8)})
    np.testing.assert_array_equal(x, [0, 1, 0.5, -0.5])  # Dict entries in sorted key order
    assert o.dim == 4


def test_toy_termination_and_mean_reward(tmp_path):
    env = vec("pz:pz_toy,end=2,team_reward=mean", 1, seed=0, tmp_path=tmp_path)
    out = Batch.allocate(env.schema, 1)
    env.reset(np.arange(1), out)
    env.step(np.zeros((1, 3), np.int32), out)
    assert out.reward[0] == pytest.approx(111.0 / 3)
    env.step(np.zeros((1, 3), np.int32), out)
    assert (out.terminated[0], out.truncated[0]) == (1, 0)
    assert not env.alive[0].any() and not out.obs[0].any()


def test_seeding_is_per_copy_and_reproducible():
    def trace(seed):
        env = vec(SPREAD, 3, seed)
        out = Batch.allocate(env.schema, 3)
        env.reset(np.arange(3), out)
        rows = [out.obs.copy()]
        for _ in range(30):  # past one episode: the copies' own generators continue
            env.step(np.ones((3, 3), np.int32), out)
            if out.truncated.any():
                env.reset(np.nonzero(out.truncated)[0], out)
            rows.append(out.obs.copy())
        return np.stack(rows)
    a, b, c = trace(11), trace(11), trace(12)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a[:, 0], a[:, 1])
    assert not np.array_equal(a[0], a[26]), "a reset without a seed starts a different episode"


# -- schemas ----------------------------------------------------------------------------------

def test_schema_whose_dims_disagree_is_refused_naming_both_numbers(tmp_path):
    text = (SCHEMA_DIR / "pz" / "mpe2.simple_spread_v3.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("obs_dim = 18", "obs_dim = 20").replace("n_actions = 5", "n_actions = 4"))
    with pytest.raises(ValueError) as e:
        pz.PettingZooVecEnv("mpe2.simple_spread_v3", 1, 0, schema=Schema.load(bad))
    msg = str(e.value)
    assert "obs_dim = 20" in msg and "18 values" in msg and "n_actions = 4" in msg and "5 actions" in msg, msg
    assert str(bad) in msg and "--generate" in msg
    bad.write_text(text.replace('name = "pz:mpe2.simple_spread_v3"', 'name = "pz:mpe2.simple_spread_v2"'))
    with pytest.raises(ValueError, match="name = 'pz:mpe2.simple_spread_v2'"):
        pz.PettingZooVecEnv("mpe2.simple_spread_v3", 1, 0, schema=Schema.load(bad))


def test_schema_dir_follows_lmac_schema_dir(monkeypatch, tmp_path):
    from lmac_env.core import schema_path
    assert schema_path("pz:a.b") == SCHEMA_DIR / "pz" / "a.b.toml"
    monkeypatch.setenv("LMAC_SCHEMA_DIR", str(tmp_path))
    assert schema_path("pz:a.b,N=2") == tmp_path / "pz" / "a.b,N=2.toml"


def test_missing_schema_says_how_to_generate_it():
    with pytest.raises(ValueError, match=r"no schema file .*lmac envs --generate pz:pz_toy,max_cycles=9"):
        pz.PettingZooVecEnv("pz_toy,max_cycles=9", 1, 0)


def test_generated_schema_has_a_placeholder_for_every_dim(tmp_path):
    s = generated(tmp_path, "pz:mpe2.simple_speaker_listener_v4,team_reward=mean")
    assert (s.n_agents, s.obs_dim, s.state_dim, s.n_actions, s.episode_limit) == (2, 11, 14, 5, 25)
    assert s.message_columns == (2 - 1) * (11 + 2)
    assert len(s.raw["actions"]) == 5 and "only listener_0" in s.raw["actions"][4]
    groups = s.raw["obs_dims"]
    assert [g["count"] for g in groups] == [3, 8] and "padding" in groups[1]["meaning"]
    # The speaker and the listener observe different things: each kind its own meanings.
    kinds = s.raw["agent_obs"]
    assert [k["agents"] for k in kinds] == [[0], [1]]
    assert [[g["count"] for g in k["obs_dims"]] for k in kinds] == [[3, 8], [11]]
    assert "speaker_0" in kinds[0]["obs_dims"][0]["meaning"] and "padding" in kinds[0]["obs_dims"][1]["meaning"]
    assert "listener_0" in kinds[1]["obs_dims"][0]["meaning"]
    assert sum(g["count"] for g in s.raw["state_dims"]) == 14
    assert all(t.startswith("EDIT") for t in [s.raw["task"], s.raw["reward"], *s.raw["actions"]])
    toy = generated(tmp_path, "pz:pz_toy", episode_limit=7)
    assert toy.episode_limit == 7 and len(toy.raw["state_dims"]) == 3  # one group per agent
    with pytest.raises(ValueError, match="--episode-limit"):
        pz.generate("pz:pz_toy,max_cycles=none")
    kaz = generated(tmp_path, KAZ)
    assert kaz.raw["obs_dims"][0]["shape"] == [27, 5] and kaz.raw["state_dims"][0]["shape"] == [26, 4]


def test_generate_command_writes_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "x.toml"
    assert pz.main(["generate", "pz:pz_toy", "--out", str(out), "--episode-limit", "9"]) == 0
    assert Schema.load(out).episode_limit == 9
    assert pz.main(["generate", "pz:pz_toy", "--out", str(out), "--episode-limit", "9"]) == 2
    assert "--force" in capsys.readouterr().err
    assert pz.main(["check", "pz:pz_toy", "--schema", str(out)]) == 0
    spread = SCHEMA_DIR / "pz" / "mpe2.simple_spread_v3.toml"
    assert pz.main(["check", "pz:pz_toy", "--schema", str(spread)]) == 1
    assert "n_agents = 3 but possible_agents" not in capsys.readouterr().err  # same count: 3 agents
    assert pz.main(["generate", "pz:no_such_module_x", "--out", "-"]) == 1
    assert "cannot import" in capsys.readouterr().err


# -- PettingZoo's own API test on the adapted environments ------------------------------------

@pytest.mark.parametrize("name", SHIPPED + ["pz:pz_toy"])
def test_pettingzoo_parallel_api_test_on_the_adapted_env(name, tmp_path):
    make_vec = (lambda seed: vec(name, 1, seed, tmp_path=tmp_path)) if name == "pz:pz_toy" else None
    par = parallel_env(name, seed=0, make_vec=make_vec)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo reports API slips as warnings
        parallel_api_test(par, num_cycles=150)
    obs, _ = par.reset(seed=3)
    a = par.possible_agents[0]
    assert par.observation_space(a).contains(obs[a])


# -- families found without a registry edit ---------------------------------------------------

def test_family_by_module_path_and_entry_point(monkeypatch):
    made = []
    fake = types.ModuleType("lmac_fake_family")
    fake.make = lambda variant, num_envs, seed: made.append((variant, num_envs, seed)) or "env"
    monkeypatch.setitem(__import__("sys").modules, "lmac_fake_family", fake)
    assert registry.make("lmac_fake_family:v1", 2, seed=3) == "env"
    ep = types.SimpleNamespace(name="fakeep", load=lambda: fake)
    monkeypatch.setattr(registry.importlib.metadata, "entry_points",
                        lambda group: [ep] if group == registry.ENTRY_POINT_GROUP else [])
    assert registry.make("fakeep:v2", 1) == "env"
    assert made == [("v1", 2, 3), ("v2", 1, 0)]
    with pytest.raises(ValueError, match="unknown environment family 'nope_family_x'"):
        registry.make("nope_family_x:v", 1)
    with pytest.raises(ValueError, match="has no make"):
        registry.make("json:v", 1)
