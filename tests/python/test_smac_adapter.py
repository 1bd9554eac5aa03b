"""The real-game adapter (lmac_env.smac): construction, schemas, a clear error without the
game, and its feature builders agreeing with the re-implementation's layout."""
from __future__ import annotations

import pathlib
import sys

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[2] / "env-server"))

from lmac_env import smac  # noqa: E402
from lmac_env.core import Batch, Schema, schema_path  # noqa: E402
from lmac_env.registry import make as registry_make  # noqa: E402
from lmac_env.smaclite import MAPS, SmacliteVecEnv  # noqa: E402
from lmac_env.smaclite.policies import random_actions  # noqa: E402

VARIANTS = list(MAPS)


@pytest.mark.parametrize("variant", VARIANTS)
def test_map_params_agree_with_schema(variant):
    p = smac.MAP_PARAMS[variant]
    s = Schema.load(schema_path(f"smac:{variant}"))
    assert (p["n_agents"], p["limit"], 6 + p["n_enemies"]) == \
        (s.n_agents, s.episode_limit, s.n_actions)
    spec = MAPS[variant]
    assert (len(spec.agents), len(spec.enemies)) == (p["n_agents"], p["n_enemies"])
    args = smac.COMM_ARGS[variant]
    if variant == "bane_vs_hM":   # SMAC-Comm: sight 2, shoot 2, no health in observations
        assert args == dict(sight_range=2.0, shoot_range=2.0, obs_all_health=False,
                            obs_enemy_health=False)
    else:
        assert (args["sight_range"], args["shoot_range"]) == (9.0, 6.0)


def test_clear_error_without_the_game(monkeypatch, tmp_path):
    monkeypatch.setenv("SC2PATH", str(tmp_path / "no-starcraft"))
    with pytest.raises(smac.SmacUnavailable) as e:
        registry_make("smac:bane_vs_hM", 1, seed=0)
    msg = str(e.value)
    assert "SC2PATH" in msg and "no-starcraft" in msg
    assert "pysc2==4.0.0" in msg and "protobuf<3.21" in msg and "oxwhirl/smac" in msg
    assert "bane_vs_hM.SC2Map" in msg and "smaclite:" in msg
    missing = smac.missing_requirements("bane_vs_hM")
    assert any("StarCraft II" in m for m in missing)


def test_missing_map_file_is_named(monkeypatch, tmp_path):
    (tmp_path / "Maps" / "SMAC_Maps").mkdir(parents=True)
    monkeypatch.setenv("SC2PATH", str(tmp_path))
    missing = smac.missing_requirements("5z_vs_1ul")
    assert any(m.endswith("5z_vs_1ul.SC2Map") for m in missing)
    (tmp_path / "Maps" / "SMAC_Maps" / "5z_vs_1ul.SC2Map").write_bytes(b"")
    assert not any("SC2Map" in m for m in smac.missing_requirements("5z_vs_1ul"))


def test_unknown_map():
    with pytest.raises(ValueError, match="unknown SMAC-Comm map"):
        smac.make("3m", 1, 0)


def _views(env, b):
    N, E, spec = env.N, env.E, env.spec
    def view(u, ally):
        t = (spec.ally_type_id[u] if ally else spec.enemy_type_id[u - N]) \
            if spec.unit_type_bits else 0
        hp = env.hp[b, u] if env.alive[b, u] else 0.0
        return smac.UnitView(env.pos[b, u, 0], env.pos[b, u, 1], hp, env.max_hp[u],
                             env.sh[b, u], spec.ally_max_shield if ally else 1.0, t,
                             env.cd[b, u] / spec.ally_max_cd if ally else 0.0)
    return [view(i, True) for i in range(N)], [view(N + j, False) for j in range(E)]


@pytest.mark.parametrize("variant", VARIANTS)
def test_feature_builders_match_the_reimplementation(variant):
    """The adapter builds SMAC-Comm features from unit views; fed the simulation's units it
    must reproduce the simulation's observation and state exactly (one layout, two backends)."""
    env = SmacliteVecEnv(variant, 4, 2)
    out = Batch.allocate(env.schema, 4)
    env.reset(np.arange(4), out)
    rng = np.random.default_rng(1)
    for t in range(25):
        env.step(random_actions(env, out, rng), out)
        for b in range(4):
            allies, enemies = _views(env, b)
            for i in range(env.N):
                o = smac.obs_agent(env.spec, i, allies, enemies, out.avail[b, i])
                np.testing.assert_allclose(o, out.obs[b, i], atol=1e-6)
            onehot = np.eye(env.A, dtype=np.float32)[env.last_action[b]]
            s = smac.state_of(env.spec, allies, enemies, onehot)
            np.testing.assert_allclose(s, out.state[b], atol=1e-6)
        env.reset(np.flatnonzero((out.terminated | out.truncated) > 0), out)


def test_game_construction_when_available():
    """Runs only where StarCraft II, pysc2 and smac are installed (never on our machines)."""
    if smac.missing_requirements("bane_vs_hM"):
        pytest.skip("StarCraft II / SMAC not installed: " +
                    "; ".join(smac.missing_requirements("bane_vs_hM")))
    env = smac.make("bane_vs_hM", 1, 0)
    out = Batch.allocate(env.schema, 1)
    env.reset(np.arange(1), out)
    assert out.obs.shape == (1, 3, 31) and out.state.shape == (1, 52)
    env.close()
