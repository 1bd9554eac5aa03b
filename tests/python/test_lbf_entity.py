"""LBF's entity-state variant (`lbf:<field>-entity`): the same environment as the grid variant,
with the global state given as the agents' and foods' positions and levels (lmac_env.lbf)."""

import numpy as np
import pytest

from lmac_env.core import Batch, schema_path
from lmac_env.registry import make

SMALL, BIG = "lbf:8x8-2p-2f-s1-coop", "lbf:11x11-6p-4f-s1-coop"
MOVES = {1: (-1, 0), 2: (1, 0), 3: (0, -1), 4: (0, 1)}  # north, south, west, east
LOAD = 5


def forage(lb, rng, eps=0.2):
    """A scripted team that eats food (random actions almost never do): agent i heads for side
    i % 4 of the first food still on the field and loads there; with probability eps, or when
    no move gets closer, a random valid action."""
    food = np.argwhere(lb.field > 0)
    acts = []
    for i, pl in enumerate(lb.players):
        valid = [a.value for a in lb._valid_actions[pl]]
        if len(food) == 0 or rng.random() < eps:
            acts.append(int(rng.choice(valid)))
            continue
        dr, dc = list(MOVES.values())[i % 4]
        tr, tc = food[0][0] + dr, food[0][1] + dc
        r, c = pl.position
        if (r, c) == (tr, tc):
            acts.append(LOAD if LOAD in valid else 0)
            continue
        closer = [a for a, (mr, mc) in MOVES.items() if a in valid
                  and abs(r + mr - tr) + abs(c + mc - tc) < abs(r - tr) + abs(c - tc)]
        acts.append(int(rng.choice(closer or valid)))
    return acts


def episodes(name, seed, envs=3, steps=120):
    """Step `envs` envs of `name` with the scripted team, resetting at termination and at the
    schema's episode limit. Yields (env, out, first) after every reset/step; `first` marks the
    envs whose row starts an episode."""
    env = make(name, envs, seed=seed)
    out = Batch.allocate(env.schema, envs)
    env.reset(np.arange(envs), out)
    yield env, out, np.ones(envs, bool)
    rng = np.random.default_rng(seed)
    t = np.zeros(envs, int)
    for _ in range(steps):
        acts = np.array([forage(lb, rng) for lb in env.envs], np.int32)
        env.step(acts, out)
        t += 1
        yield env, out, np.zeros(envs, bool)
        done = np.flatnonzero((out.terminated == 1) | (t >= env.schema.episode_limit))
        if len(done):
            env.reset(done, out)
            t[done] = 0
            first = np.zeros(envs, bool)
            first[done] = True
            yield env, out, first


def test_entity_dims_match_schema():
    for name, dims in [(SMALL, (2, 29, 14, 6)), (BIG, (6, 29, 34, 6))]:
        env = make(name + "-entity", 2, seed=0)
        s = env.schema
        assert (s.n_agents, s.obs_dim, s.state_dim, s.n_actions) == dims
        assert s.name == name + "-entity" and env.state_kind == "entity"
        grid = make(name, 1, seed=0).schema
        # only the state differs: same limit, message budget, actions, reward text, observation
        for field in ("n_agents", "obs_dim", "n_actions", "episode_limit", "message_columns"):
            assert getattr(s, field) == getattr(grid, field), field
        for key in ("task", "reward", "actions", "obs_dims"):
            assert s.raw[key] == grid.raw[key], key
        assert s.alpha == 0.25  # raw cells and levels: within half a cell / half a level


@pytest.mark.parametrize("name,seed", [(SMALL, 0), (SMALL, 1), (SMALL, 2), (BIG, 3), (BIG, 4)])
def test_entity_state_matches_lbforagings_fields(name, seed):
    """Step by step, the state is lbforaging's player positions and levels and its food field;
    foods keep their spawn cell for the episode; an eaten food keeps it with level 0, flag 0."""
    eaten_seen = 0
    spawn = {}
    for env, out, first in episodes(name + "-entity", seed):
        players, foods = len(env.envs[0].players), env.n_foods
        for e, lb in enumerate(env.envs):
            st = out.state[e]
            agents = st[:3 * players].reshape(players, 3)
            for i, pl in enumerate(lb.players):
                np.testing.assert_array_equal(agents[i], [pl.position[0], pl.position[1], pl.level])
            food = st[3 * players:].reshape(foods, 4)
            if first[e]:  # a new episode: every food on the field, in row-major order
                cells = sorted((int(r), int(c)) for r, c in zip(*np.nonzero(lb.field)))
                assert len(cells) == foods
                spawn[e] = cells
                assert (food[:, 3] == 1).all()
            for j, (r, c) in enumerate(spawn[e]):
                level = lb.field[r, c]
                np.testing.assert_array_equal(food[j], [r, c, level, 1.0 if level > 0 else 0.0])
                eaten_seen += level == 0
            on_field = {(int(r), int(c)) for r, c, _, f in food if f == 1}
            assert on_field == {(int(r), int(c)) for r, c in zip(*np.nonzero(lb.field))}
            assert ((food[:, 2] > 0) == (food[:, 3] == 1)).all()
            assert (food[:, 2][food[:, 3] == 1] == (2 if players == 2 else 3)).all()
    assert eaten_seen > 0, "the scripted team ate no food: the eaten-food case went untested"


@pytest.mark.parametrize("name,seed", [(SMALL, 5), (BIG, 6)])
def test_entity_and_grid_variants_are_the_same_environment(name, seed):
    """Same seed, same actions: identical observations, available actions, rewards and
    terminations; the entity state says what the grid state says."""
    runs = zip(episodes(name, seed), episodes(name + "-entity", seed))
    rewarded = 0
    for (g_env, g, g_first), (e_env, x, e_first) in runs:
        np.testing.assert_array_equal(g_first, e_first)
        for field in ("obs", "avail", "reward", "terminated", "truncated"):
            np.testing.assert_array_equal(getattr(g, field), getattr(x, field), err_msg=field)
        rewarded += (x.reward > 0).sum()
        size = g_env.size
        players = g.obs.shape[1]
        for e in range(g_env.num_envs):
            grid = g.state[e].reshape(3, size + 2, size + 2)[:, 1:-1, 1:-1]
            agents = x.state[e, :3 * players].reshape(players, 3)
            food = x.state[e, 3 * players:].reshape(-1, 4)
            agent_layer = np.zeros((size, size), np.float32)
            agent_layer[agents[:, 0].astype(int), agents[:, 1].astype(int)] = agents[:, 2]
            np.testing.assert_array_equal(grid[0], agent_layer)
            food_layer = np.zeros((size, size), np.float32)
            live = food[food[:, 3] == 1]
            food_layer[live[:, 0].astype(int), live[:, 1].astype(int)] = live[:, 2]
            np.testing.assert_array_equal(grid[1], food_layer)
    assert rewarded > 0


def test_entity_variant_is_deterministic_for_a_seed():
    a = [out.state.copy() for _, out, _ in episodes(SMALL + "-entity", 9, steps=40)]
    b = [out.state.copy() for _, out, _ in episodes(SMALL + "-entity", 9, steps=40)]
    np.testing.assert_array_equal(np.array(a), np.array(b))


def _schema_copy(tmp_path, monkeypatch, name, edit):
    src = schema_path(name)
    d = tmp_path / "lbf"
    d.mkdir(exist_ok=True)
    text = src.read_text()
    (d / src.name).write_text(edit(text))
    monkeypatch.setenv("LMAC_SCHEMA_DIR", str(tmp_path))
    return d / src.name


@pytest.mark.parametrize("name,old,new,message", [
    (SMALL + "-entity", "state_dim = 14", "state_dim = 300", "state_dim = 300, but lbf:8x8-2p-2f-s1-coop-entity (entity state) writes 14"),
    (SMALL, "state_dim = 300", "state_dim = 14", "state_dim = 14, but lbf:8x8-2p-2f-s1-coop (grid state) writes 300"),
    (BIG + "-entity", "obs_dim = 29", "obs_dim = 27", "obs_dim = 27, but lbf:11x11-6p-4f-s1-coop-entity (entity state) writes 29"),
    (BIG + "-entity", "n_agents = 6", "n_agents = 5", "n_agents = 5, but lbf:11x11-6p-4f-s1-coop-entity"),
])
def test_schema_dims_mismatch_fails_clearly(tmp_path, monkeypatch, name, old, new, message):
    path = _schema_copy(tmp_path, monkeypatch, name, lambda t: t.replace(old, new, 1))
    with pytest.raises(ValueError) as err:
        make(name, 1, seed=0)
    assert str(err.value).startswith(f"{path}: {message}")


def test_unknown_variant_names_the_known_ones():
    with pytest.raises(ValueError, match="8x8-2p-2f-s1-coop-entity"):
        make("lbf:8x8-2p-2f-s1-coop-objects", 1, seed=0)
    with pytest.raises(ValueError, match="unknown LBF variant"):
        make("lbf:-entity", 1, seed=0)
