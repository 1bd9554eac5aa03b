"""The SMAC-Comm re-implementation (lmac_env.smaclite): layouts, determinism, hand-set
mechanics scenarios and solvability (privileged scripted policy vs random)."""
from __future__ import annotations

import pathlib
import sys
import tomllib

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "env-server"))

from lmac_env.core import Batch, Schema, schema_path  # noqa: E402
from lmac_env.registry import make as registry_make  # noqa: E402
from lmac_env.smaclite import MAPS, SmacliteVecEnv  # noqa: E402
from lmac_env.smaclite import policies  # noqa: E402
from lmac_env.smaclite.maps import split_variant, variants  # noqa: E402
from lmac_env.smaclite.schemas import render  # noqa: E402

# map: (obs, state, actions, agents, episode limit) -- SMAC-Comm (paper Table C.1; 2o_20b_vs_2r
# follows from SMAC's formulas with 22 agents and 2 enemies)
TABLE = {
    "bane_vs_hM": (31, 52, 8, 3, 30),
    "1o_10b_vs_1r": (85, 148, 7, 11, 50),
    "2o_20b_vs_2r": (170, 318, 8, 22, 50),
    "5z_vs_1ul": (36, 63, 7, 5, 150),
}


def new(variant, b=4, seed=0):
    env = SmacliteVecEnv(variant, b, seed)
    out = Batch.allocate(env.schema, b)
    env.reset(np.arange(b), out)
    return env, out


@pytest.mark.parametrize("variant", list(TABLE))
def test_sizes_match_table(variant):
    obs, state, acts, n, limit = TABLE[variant]
    env, out = new(variant)
    s = env.schema
    assert (s.obs_dim, s.state_dim, s.n_actions, s.n_agents, s.episode_limit) == \
        (obs, state, acts, n, limit)
    assert out.obs.shape == (4, n, obs) and out.state.shape == (4, state)
    assert out.avail.shape == (4, n, acts)
    # FullComm always fits; 5z_vs_1ul's budget is the authors' wider design's (protocols/paper/)
    assert s.message_columns == max((n - 1) * (obs + n), 280 if variant == "5z_vs_1ul" else 0)
    assert s.alpha == (0.005 if variant == "bane_vs_hM" else 0.05)
    # the real-game schema declares the same layout
    r = Schema.load(schema_path(f"smac:{variant}"))
    assert (r.obs_dim, r.state_dim, r.n_actions, r.n_agents, r.episode_limit) == \
        (obs, state, acts, n, limit)


@pytest.mark.parametrize("family", ["smaclite", "smac"])
@pytest.mark.parametrize("variant", list(TABLE))
def test_schema_files_up_to_date_and_complete(family, variant):
    path = schema_path(f"{family}:{variant}")
    assert path.read_text() == render(MAPS[variant], family), \
        "run python -m lmac_env.smaclite.schemas --write"
    raw = tomllib.loads(path.read_text())
    assert raw["name"] == f"{family}:{variant}"
    assert len(raw["actions"]) == raw["n_actions"]
    for field, dim in (("obs_dims", raw["obs_dim"]), ("state_dims", raw["state_dim"])):
        total = 0
        for g in raw[field]:
            assert g["meaning"].strip()
            if "labels" in g:
                assert len(g["labels"]) == g["count"]
            if "shape" in g:
                assert int(np.prod(g["shape"])) == g["count"]
            total += g["count"]
        assert total == dim
    if family == "smac":
        assert "StarCraft II" in raw["task"]
    else:
        assert "not StarCraft II" in raw["task"]


@pytest.mark.parametrize("variant", list(TABLE))
def test_deterministic_for_a_seed(variant):
    def run(seed):
        env, out = new(variant, 8, seed)
        rng = np.random.default_rng(5)
        trace = []
        for _ in range(40):
            env.step(policies.random_actions(env, out, rng), out)
            trace.append((out.obs.copy(), out.state.copy(), out.avail.copy(),
                          out.reward.copy(), out.terminated.copy()))
            done = np.flatnonzero((out.terminated | out.truncated) > 0)
            env.reset(done, out)
        return trace
    a, b, c = run(3), run(3), run(4)
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            np.testing.assert_array_equal(u, v)
    assert any(not np.array_equal(x[1], y[1]) for x, y in zip(a, c))


@pytest.mark.parametrize("variant", list(TABLE))
def test_values_and_avail_rules(variant):
    env, out = new(variant, 16, 1)
    rng = np.random.default_rng(0)
    for _ in range(60):
        env.step(policies.random_actions(env, out, rng), out)
        assert out.obs.dtype == np.float32 and out.state.dtype == np.float32
        assert np.isfinite(out.obs).all() and np.abs(out.obs).max() <= 1.0 + 1e-6
        assert np.abs(out.state).max() <= 1.0 + 1e-6
        assert (out.reward >= 0).all()
        alive = env.alive[:, :env.N]
        # dead agents: only no-op, all-zero observation; alive: no no-op, stop always
        assert (out.avail[~alive][:, 0] == 1).all() and (out.avail[~alive][:, 1:] == 0).all()
        assert (out.obs[~alive] == 0).all()
        assert (out.avail[alive][:, 0] == 0).all() and (out.avail[alive][:, 1] == 1).all()
        # ground units stay on walkable ground
        p = env.pos[:, :env.N][alive & env.ground_a[None]]
        assert env._walkable(p[:, 0], p[:, 1]).all()
        done = np.flatnonzero((out.terminated | out.truncated) > 0)
        env.reset(done, out)


def test_agent_order_and_spawns():
    env, _ = new("bane_vs_hM", 64, 0)
    x = env.pos[:, :3, 0]
    assert (x[:, 0] < 14.01).all() and ((x[:, 1] >= 15) & (x[:, 1] < 17)).all() \
        and (x[:, 2] >= 18).all()
    np.testing.assert_allclose(env.pos[:, 3:], np.broadcast_to([16.0, 31.0], (64, 2, 2)))
    env, _ = new("1o_10b_vs_1r", 64, 0)
    xb = env.pos[:, :10, 0]
    assert (np.diff(xb, axis=1) >= 0).all()              # Banelings sorted by x (SMAC order)
    np.testing.assert_array_equal(env.pos[:, 10], env.pos[:, 11])   # Overseer on the Roach
    corners = {(3.5, 2.0), (3.5, 28.8598), (28.5, 28.0), (28.5, 2.0)}
    assert {tuple(p) for p in env.pos[:, 11].tolist()} <= corners
    env, _ = new("2o_20b_vs_2r", 64, 0)
    assert env.kind[20] == env.kind[21] == "overseer"
    env, _ = new("5z_vs_1ul", 64, 0)
    y = env.pos[:, :, 1]
    assert ((y >= 7) & (y < 25)).all()


def _place(env, out, agents, enemies=None, dead=()):
    env.pos[0, :len(agents)] = agents
    if enemies is not None:
        env.pos[0, env.N:] = enemies
    for i in dead:
        env.alive[0, i] = False
        env.hp[0, i] = 0
    env.refresh(out)


def test_bane_three_kill_two_do_not_and_medivac_heals():
    env, out = new("bane_vs_hM", 1)
    h = np.array([16.0, 31.0])
    near = [h + [-1.9, -0.3], h + [0.0, -1.9], h + [1.9, -0.3]]
    _place(env, out, near)
    assert (out.avail[0, :, 6] == 1).all()
    env.step(np.array([[6, 6, 6]]), out)
    assert not env.alive[0, 3] and env.alive[0, 4]       # Hydralisk dead, Medivac alive
    assert out.terminated[0] == 1 and env.won[0]
    assert out.reward[0] == pytest.approx((90 + 10 + 200) * 20 / 460)
    # two exploding together are not enough, and the Medivac heals the Hydralisk back
    env, out = new("bane_vs_hM", 1)
    _place(env, out, [near[0], [16.0, 2.0], near[2]])
    env.step(np.array([[6, 1, 6]]), out)
    assert env.alive[0, 3] and out.terminated[0] == 0
    assert env.hp[0, 3] == pytest.approx(90 - 70 + 3.5 + 0.1367, abs=1e-3)
    for _ in range(20):
        env.step(np.array([[0, 1, 0]]), out)
    assert env.hp[0, 3] == pytest.approx(90.0)
    assert out.terminated[0] == 0


def test_bane_hydralisk_shoots_and_bursts_on_death():
    env, out = new("bane_vs_hM", 1)
    h = np.array([16.0, 31.0])
    # out of its reach (3.0 from the centre): nothing happens
    _place(env, out, [h + [-3.2, 0.0], [16.0, 2.0], [30.0, 31.0]])
    env.step(np.array([[1, 1, 1]]), out)
    assert env.alive[0, :3].all()
    # inside reach but beyond burst range: shot dead, no damage to the Hydralisk
    env, out = new("bane_vs_hM", 1)
    _place(env, out, [h + [-2.9, 0.0], [16.0, 2.0], [30.0, 31.0]])
    env.step(np.array([[1, 1, 1]]), out)
    assert not env.alive[0, 0] and env.hp[0, 3] == pytest.approx(90.0)
    assert (out.avail[0, 0] == [1, 0, 0, 0, 0, 0, 0, 0]).all()
    # shot at 2.5: the death burst still hits it (2.2 + Hydralisk radius 0.625)
    env, out = new("bane_vs_hM", 1)
    _place(env, out, [h + [-2.5, 0.0], [16.0, 2.0], [30.0, 31.0]])
    env.step(np.array([[1, 1, 1]]), out)
    assert not env.alive[0, 0]
    assert env.hp[0, 3] == pytest.approx(90 - 35 + 3.5 + 0.1367, abs=1e-3)
    assert out.reward[0] > 0


def test_bane_corridor_walls_and_limited_sight():
    env, out = new("bane_vs_hM", 1)
    _place(env, out, [[5.0, 30.5], [15.5, 10.0], [25.0, 31.5]])
    av = out.avail[0]
    assert av[1, 2] == 1 and av[1, 3] == 1 and av[1, 4] == 1 and av[1, 5] == 0  # x=15.5
    assert av[2, 2] == 0                                  # top edge of the map
    for _ in range(5):
        env.step(np.array([[1, 5, 2]]), out)              # push into the walls
    assert env.pos[0, 1, 0] >= 15.0 and env.pos[0, 2, 1] < 32.0
    # nothing within sight 2: enemy and ally features are all zero
    assert (out.obs[0, :, 4:4 + 12 + 12] == 0).all()


def test_roach_ten_banelings_kill_nine_do_not():
    for n, dies in ((10, True), (9, False)):
        env, out = new("1o_10b_vs_1r", 1)
        r = np.array([16.0, 2.0])
        ang = np.linspace(0, np.pi, 10)
        ring = r + 1.5 * np.stack([np.cos(ang), np.sin(ang)], -1)
        _place(env, out, list(ring) + [r], [r])
        a = np.array([[6] * n + [1] * (10 - n) + [1]])
        env.step(a, out)
        assert (not env.alive[0, 11]) == dies
        if not dies:
            assert env.hp[0, 11] == pytest.approx(145 - 9 * 15 + 0.1367, abs=1e-3)
            assert out.terminated[0] == 0
        else:
            assert out.terminated[0] == 1 and env.won[0]


def test_liberty_variant_eight_banelings_kill_and_the_roach_reaches_less():
    """`-liberty` takes the game's Liberty.SC2Mod numbers: 19 per burst against the Roach, so 8
    of 10 kill it (7 do not), and its weapon reaches 3 + 0.5 + 0.375 from its centre, not 5."""
    for n, dies in ((8, True), (7, False)):
        env, out = new("1o_10b_vs_1r-liberty", 1)
        r = np.array([16.0, 2.0])
        ang = np.linspace(0, np.pi, 10)
        ring = r + 1.5 * np.stack([np.cos(ang), np.sin(ang)], -1)
        _place(env, out, list(ring) + [r], [r])
        env.step(np.array([[6] * n + [1] * (10 - n) + [1]]), out)
        assert (not env.alive[0, 11]) == dies
        if not dies:
            assert env.hp[0, 11] == pytest.approx(145 - 7 * 19 + 0.1367, abs=1e-3)
    for data, dist, hit in (("1o_10b_vs_1r", 4.5, True), ("1o_10b_vs_1r-liberty", 4.5, False),
                            ("1o_10b_vs_1r-liberty", 3.8, True)):
        env, out = new(data, 1)
        r = np.array([16.0, 16.0])
        agents = [[2.0 + i, 30.0] for i in range(10)] + [[16.0, 3.0]]
        agents[0] = [16.0 + dist, 16.0]
        _place(env, out, agents, [r])
        env.step(np.array([[1] * 11]), out)
        assert (env.hp[0, 0] < 30) == hit, (data, dist)
    for m in ("1o_10b_vs_1r", "2o_20b_vs_2r"):
        path = schema_path(f"smaclite:{m}-liberty")
        assert path.read_text() == render(MAPS[m], "smaclite", split_variant(f"{m}-liberty")), \
            "run python -m lmac_env.smaclite.schemas --write"
        assert "Liberty.SC2Mod" in tomllib.loads(path.read_text())["task"]
    with pytest.raises(ValueError, match="unit-data variants"):
        SmacliteVecEnv("5z_vs_1ul-liberty", 1)


def test_liberty_roach_changes_the_roach_alone():
    """`-liberty-roach` takes Liberty's Roach (reach 3 + 0.5 + 0.375) and keeps our Baneling
    burst (15 per burst against the Roach, so 8 Banelings do not kill it)."""
    env, _ = new("1o_10b_vs_1r-liberty-roach", 1)
    assert (env.bane_damage, env.bane_bonus_light) == (16.0, 19.0)
    roach = env.types[-1]
    assert (roach.reach, roach.radius) == (3.0, 0.5)
    env, out = new("1o_10b_vs_1r-liberty-roach", 1)
    r = np.array([16.0, 2.0])
    ang = np.linspace(0, np.pi, 10)
    _place(env, out, list(r + 1.5 * np.stack([np.cos(ang), np.sin(ang)], -1)) + [r], [r])
    env.step(np.array([[6] * 8 + [1] * 2 + [1]]), out)
    assert env.alive[0, 11], "8 bursts of 15 leave the Roach alive"
    assert "weapon range 3" in tomllib.loads(schema_path("smaclite:1o_10b_vs_1r-liberty-roach").read_text())["task"]


@pytest.mark.parametrize("variant", ["1o_10b_vs_1r", "1o_10b_vs_1r-liberty", "5z_vs_1ul"])
def test_no_last_action_state_is_the_full_state_without_its_last_actions(variant):
    """`-no-last-action` is SMAC's state_last_action=False: the same episode (same seed and
    actions) writes the same observations and the full state's values up to where the last
    actions begin, and nothing after; its schema says so and describes the shorter state."""
    full, a = new(variant, 2, seed=5)
    short, b = new(f"{variant}-no-last-action", 2, seed=5)
    k = full.state_last_action_offset
    assert short.schema.state_dim == k < full.schema.state_dim
    assert short.schema.obs_dim == full.schema.obs_dim
    rng = np.random.default_rng(0)
    for _ in range(12):
        np.testing.assert_array_equal(a.obs, b.obs)
        np.testing.assert_array_equal(a.state[:, :k], b.state)
        acts = np.array([[rng.choice(np.flatnonzero(m)) for m in env_avail] for env_avail in a.avail])
        full.step(acts, a)
        short.step(acts, b)
    assert a.state[:, k:].any(), "the full state carries last actions after a step"
    raw = tomllib.loads(schema_path(f"smaclite:{variant}-no-last-action").read_text())
    assert "state_last_action = False" in raw["task"]
    assert not any("last action" in g["meaning"] for g in raw["state_dims"])


def test_every_smaclite_variant_has_its_schema_file():
    """Each variant the schemas script renders is on disk as rendered, and its name parses back."""
    for v in variants():
        name = f"{v.map_name}{v.suffix}"
        assert split_variant(name) == v
        assert schema_path(f"smaclite:{name}").read_text() == render(MAPS[v.map_name], "smaclite", v), \
            "run python -m lmac_env.smaclite.schemas --write"
    with pytest.raises(ValueError, match="no-last-action"):
        split_variant("5z_vs_1ul-liberty-no-last-action")


def test_roach_cannot_hit_the_flying_overseer():
    env, out = new("1o_10b_vs_1r", 1)
    r = np.array([16.0, 2.0])
    _place(env, out, [[5.0 + i, 30.0] for i in range(10)] + [r], [r])
    for _ in range(10):
        env.step(np.array([[1] * 11]), out)
    assert env.alive[0, 10] and env.hp[0, 10] == pytest.approx(200)
    # the Overseer sees the Roach, Banelings far away do not
    o = out.obs[0]
    assert o[10, 4] == 1 and o[10, 4 + 4] == pytest.approx(1.0) and o[10, 4 + 5] == 1
    assert (o[:10, 4:12] == 0).all()


def test_zealot_shields_absorb_and_ultralisk_fights():
    env, out = new("5z_vs_1ul", 1)
    u = np.array([16.0, 16.0])
    _place(env, out, [u + [2.4, 0.0], [3.0, 10.0], [3.0, 12.0], [3.0, 14.0], [3.0, 20.0]], [u])
    env.step(np.array([[1] * 5]), out)
    # one strike of 35: the 50 shield absorbs it, life untouched
    assert env.sh[0, 0] == pytest.approx(15.0) and env.hp[0, 0] == pytest.approx(100.0)
    assert out.obs[0, 0, -1] == pytest.approx(15 / 80)   # SMAC's shield normalisation
    # a Zealot strike: 2 x (8 - 2 armour)
    env, out = new("5z_vs_1ul", 1)
    _place(env, out, [u + [1.55, 0.0], [3.0, 10.0], [3.0, 12.0], [3.0, 14.0], [3.0, 20.0]], [u])
    env.step(np.array([[6, 1, 1, 1, 1]]), out)
    assert env.hp[0, 5] == pytest.approx(500 - 12 + 0.1367, abs=1e-3)


def test_registry_and_truncation():
    env = registry_make("smaclite:bane_vs_hM", 2, seed=0)
    out = Batch.allocate(env.schema, 2)
    env.reset(np.arange(2), out)
    for t in range(30):
        env.step(np.ones((2, 3), np.int64), out)        # everybody stops
    assert (out.truncated == 1).all() and (out.terminated == 0).all()


def test_scripted_wins_random_does_not():
    for variant in TABLE:
        s = policies.evaluate(variant, "scripted", episodes=48, num_envs=16, seed=0)
        r = policies.evaluate(variant, "random", episodes=48, num_envs=16, seed=0)
        assert s["win_rate"] >= 0.5, s
        assert r["win_rate"] <= 0.05, r


@pytest.mark.parametrize("variant", ["bane_vs_hM", "1o_10b_vs_1r"])
def test_writes_into_strided_shared_memory_views(variant):
    """In the pipeline obs rows are followed by message columns: a strided view."""
    a, oa = new(variant, 4, 7)
    b = SmacliteVecEnv(variant, 4, 7)
    s = b.schema
    slab = np.full((4, s.n_agents, s.obs_dim + s.message_columns), 9.0, np.float32)
    ob = Batch.allocate(s, 4)
    ob.obs = slab[..., :s.obs_dim]
    b.reset(np.arange(4), ob)
    rng1, rng2 = np.random.default_rng(0), np.random.default_rng(0)
    for _ in range(30):
        a.step(policies.random_actions(a, oa, rng1), oa)
        b.step(policies.random_actions(b, ob, rng2), ob)
        for env, out in ((a, oa), (b, ob)):
            env.reset(np.flatnonzero((out.terminated | out.truncated) > 0), out)
        np.testing.assert_array_equal(oa.obs, ob.obs)
        np.testing.assert_array_equal(oa.state, ob.state)
    assert (slab[..., s.obs_dim:] == 9.0).all()       # message columns untouched
