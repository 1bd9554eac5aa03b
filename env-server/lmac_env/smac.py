"""SMAC-Comm on the real StarCraft II game, through the SMAC API (family ``smac``).

Needs, on the user's machine (none of it is installed by this project, and StarCraft II cannot
be installed on ours; ``lmac_env.smaclite`` is the re-implementation that runs everywhere):

1. StarCraft II (Linux package 4.10 as SMAC recommends), with ``SC2PATH`` pointing at its
   directory (default ``~/StarCraftII``).
2. The SMAC-Comm map files ``bane_vs_hM.SC2Map``, ``1o_10b_vs_1r.SC2Map``, ``2o_20b_vs_2r.SC2Map``
   and ``5z_vs_1ul.SC2Map`` (public: the ``sc2_maps/`` folder of the LMAC reference code, the
   same files as NDQ's ``src/smac_plus/sc2_maps/``) copied into ``$SC2PATH/Maps/SMAC_Maps/``.
3. Python packages: ``pip install "protobuf<3.21" pysc2==4.0.0`` and SMAC from source
   (clone oxwhirl/smac, then ``pip install -e .`` in it).

Then ``lmac_env.registry.make("smac:bane_vs_hM", num_envs, seed)`` runs one game process per
environment. The observation, state and action layouts are SMAC-Comm's (the fork of SMAC used
by NDQ and by the LMAC paper), identical to ``smaclite``: this module subclasses SMAC's
``StarCraft2Env`` and adds what the fork changed (the four maps, their unit-type ids, the
``obs_enemy_health`` slot, bane_vs_hM's win rule); the features are built by the same pure
functions tested against the simulation (``obs_agent``/``state_of``).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import os
import pathlib

import numpy as np

from .core import Batch, EnvUnavailable, Schema, VecEnv, schema_path
from .smaclite.maps import MAPS, MapSpec, obs_layout

# SMAC-Comm's map registry (the fork's smac_plus/starcraft2/maps) and its env arguments
MAP_PARAMS = {
    "bane_vs_hM": dict(n_agents=3, n_enemies=2, limit=30, a_race="Z", b_race="T",
                       unit_type_bits=2, map_type="bZ_hM"),
    "1o_10b_vs_1r": dict(n_agents=11, n_enemies=1, limit=50, a_race="Z", b_race="Z",
                         unit_type_bits=2, map_type="overload_bane"),
    "2o_20b_vs_2r": dict(n_agents=22, n_enemies=2, limit=50, a_race="Z", b_race="Z",
                         unit_type_bits=2, map_type="overload_bane"),
    "5z_vs_1ul": dict(n_agents=5, n_enemies=1, limit=150, a_race="P", b_race="Z",
                      unit_type_bits=0, map_type="stalkers"),
}
COMMON_ARGS = dict(step_mul=8, move_amount=2, difficulty="7", obs_all_health=True,
                   obs_own_health=True, obs_last_action=False, obs_pathing_grid=False,
                   obs_terrain_height=False, obs_instead_of_state=False,
                   state_last_action=True, reward_sparse=False, reward_only_positive=True,
                   reward_death_value=10, reward_win=200, reward_defeat=0,
                   reward_scale=True, reward_scale_rate=20)
# sight/shoot ranges and health flags per map (the paper's reference code: bane_vs_hM gets
# sight_range=2 shoot_range=2 obs_all_health=False obs_enemy_health=False; the rest defaults)
COMM_ARGS = {name: dict(sight_range=s.sight_range, shoot_range=s.shoot_range,
                        obs_all_health=s.obs_all_health, obs_enemy_health=s.obs_enemy_health)
             for name, s in MAPS.items()}
MAP_FILES = [f"{m}.SC2Map" for m in MAP_PARAMS]

INSTALL = (
    "StarCraft II with the SMAC API is needed for the `smac` family:\n"
    "  1. install StarCraft II (Linux 4.10) and set SC2PATH to its directory;\n"
    "  2. copy the SMAC-Comm maps (" + ", ".join(MAP_FILES) + ") from the LMAC reference "
    "code's sc2_maps/ folder into $SC2PATH/Maps/SMAC_Maps/;\n"
    "  3. pip install \"protobuf<3.21\" pysc2==4.0.0, then SMAC from source: clone "
    "oxwhirl/smac and run `pip install -e .` inside it.\n"
    "Without the game, use the re-implementation: smaclite:<map> (same layouts).")


class SmacUnavailable(EnvUnavailable):
    """The real game or the SMAC API is missing; the message says what and how to install."""


def sc2_path() -> pathlib.Path:
    return pathlib.Path(os.environ.get("SC2PATH", os.path.expanduser("~/StarCraftII")))


def missing_requirements(variant: str) -> list[str]:
    """What is missing to run `smac:<variant>` here (empty list = everything is present)."""
    missing = []
    for mod, what in (("pysc2", "the pysc2 package (pip install pysc2==4.0.0)"),
                      ("smac", "the smac package (SMAC from source: oxwhirl/smac)"),
                      ("google.protobuf", "protobuf<3.21")):
        try:
            found = importlib.util.find_spec(mod) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            missing.append(what)
    root = sc2_path()
    if not root.is_dir():
        missing.append(f"StarCraft II at SC2PATH={root} (directory not found)")
    else:
        m = root / "Maps" / "SMAC_Maps" / f"{variant}.SC2Map"
        if not m.is_file():
            missing.append(f"the map file {m}")
    return missing


# ---------------------------------------------------------------------------------------------
# SMAC-Comm features from unit views (pure functions; the simulation produces the same layout)

@dataclasses.dataclass
class UnitView:
    x: float
    y: float
    health: float          # 0 = dead
    health_max: float
    shield: float = 0.0
    shield_norm: float = 1.0   # SMAC's max-shield normaliser for this unit
    type_id: int = 0
    cooldown: float = 0.0      # weapon_cooldown divided by SMAC's max cooldown


def obs_agent(spec: MapSpec, i: int, allies: list[UnitView], enemies: list[UnitView],
              avail: np.ndarray) -> np.ndarray:
    """SMAC-Comm ``get_obs_agent`` (move, enemy, ally, own features)."""
    lay = obs_layout(spec)
    n, e = len(allies), len(enemies)
    o = np.zeros(lay["obs_dim"], np.float32)
    me = allies[i]
    if me.health <= 0:
        return o
    sr = spec.sight_range
    tb = spec.unit_type_bits
    o[0:4] = avail[2:6]
    off = 4
    for j, u in enumerate(enemies):
        dist = float(np.hypot(u.x - me.x, u.y - me.y))
        f = o[off:off + lay["nf_en"]]
        if dist < sr and u.health > 0:
            f[0] = avail[6 + j]
            f[1] = dist / sr
            f[2] = (u.x - me.x) / sr
            f[3] = (u.y - me.y) / sr
            ind = 4
            if spec.obs_all_health or spec.obs_enemy_health:
                f[ind] = u.health / u.health_max
                ind += 1
            if tb:
                f[ind + u.type_id] = 1
        off += lay["nf_en"]
    for k in [k for k in range(n) if k != i]:
        u = allies[k]
        dist = float(np.hypot(u.x - me.x, u.y - me.y))
        f = o[off:off + lay["nf_al"]]
        if dist < sr and u.health > 0:
            f[0] = 1
            f[1] = dist / sr
            f[2] = (u.x - me.x) / sr
            f[3] = (u.y - me.y) / sr
            ind = 4
            if spec.obs_all_health:
                f[ind] = u.health / u.health_max
                ind += 1
                if spec.shield_bits_ally:
                    f[ind] = u.shield / u.shield_norm
                    ind += 1
            if tb:
                f[ind + u.type_id] = 1
        off += lay["nf_al"]
    if spec.obs_own_health:
        o[off] = me.health / me.health_max
        off += 1
        if spec.shield_bits_ally:
            o[off] = me.shield / me.shield_norm
            off += 1
    if tb:
        o[off + me.type_id] = 1
    return o


def state_of(spec: MapSpec, allies: list[UnitView], enemies: list[UnitView],
             last_action: np.ndarray, map_size=(32.0, 32.0), play_size=(32.0, 32.0)):
    """SMAC ``get_state``: ally features, enemy features, last actions one-hot."""
    lay = obs_layout(spec)
    tb = spec.unit_type_bits
    cx, cy = map_size[0] / 2, map_size[1] / 2
    al = np.zeros((len(allies), lay["st_al"]), np.float32)
    for i, u in enumerate(allies):
        if u.health > 0:
            al[i, 0] = u.health / u.health_max
            al[i, 1] = u.cooldown
            al[i, 2] = (u.x - cx) / play_size[0]
            al[i, 3] = (u.y - cy) / play_size[1]
            ind = 4
            if spec.shield_bits_ally:
                al[i, ind] = u.shield / u.shield_norm
                ind += 1
            if tb:
                al[i, ind + u.type_id] = 1
    en = np.zeros((len(enemies), lay["st_en"]), np.float32)
    for j, u in enumerate(enemies):
        if u.health > 0:
            en[j, 0] = u.health / u.health_max
            en[j, 1] = (u.x - cx) / play_size[0]
            en[j, 2] = (u.y - cy) / play_size[1]
            if tb:
                en[j, 3 + u.type_id] = 1
    return np.concatenate([al.ravel(), en.ravel(), np.asarray(last_action, np.float32).ravel()])


# ---------------------------------------------------------------------------------------------
# The StarCraft2Env subclass (built lazily: importing this module needs no game)

def _env_class():
    from smac.env import StarCraft2Env
    from smac.env.starcraft2.maps import smac_maps

    for name, params in MAP_PARAMS.items():
        smac_maps.map_param_registry.setdefault(name, dict(params))
        if not hasattr(smac_maps, name):  # pysc2 finds maps as subclasses of lib.Map
            setattr(smac_maps, name, type(name, (smac_maps.SMACMap,), dict(filename=name)))

    class SmacCommEnv(StarCraft2Env):
        """SMAC with SMAC-Comm's changes (the NDQ/LMAC fork's smac_plus StarCraft2Env)."""

        def __init__(self, map_name, sight_range, shoot_range, obs_enemy_health, **kw):
            super().__init__(map_name=map_name, **kw)
            self.spec = MAPS[map_name]
            self.sight_range = sight_range
            self.shoot_range = shoot_range
            self.obs_enemy_health = obs_enemy_health
            if self.map_type == "bZ_hM":
                self.medivac_id = 1   # as the fork: the Medivac is recognised by type 54

        def unit_shoot_range(self, agent_id):
            return self.shoot_range

        def unit_sight_range(self, agent_id):
            return self.sight_range

        def _init_ally_unit_types(self, min_unit_type):
            super()._init_ally_unit_types(min_unit_type)
            if self.map_type == "bZ_hM":
                self.baneling_id = min_unit_type

        def get_unit_type_id(self, unit, ally):
            if self.map_type == "overload_bane":
                if ally:
                    return 0 if unit.unit_type == 1971 else 1   # Overseer 0, Baneling 1
                return 0                                         # Roach
            if self.map_type == "bZ_hM":
                if ally:
                    return unit.unit_type - self._min_unit_type
                return 0 if unit.unit_type == 107 else 1         # Hydralisk 0, Medivac 1
            return super().get_unit_type_id(unit, ally)

        def only_medivac_left(self, ally):
            if self.map_type != "bZ_hM":
                return super().only_medivac_left(ally)
            if ally:
                return not any(a.health > 0 for a in self.agents.values())
            alive = [e for e in self.enemies.values() if e.health > 0]
            return len(alive) == 1 and alive[0].unit_type == 54

        def update_units(self):
            code = super().update_units()
            # the fork checks bane_vs_hM's win (only the Medivac left) before the loss
            if self.map_type == "bZ_hM" and self.only_medivac_left(ally=False):
                return 1
            return code

        def _view(self, u, ally):
            cd = 0.0
            if ally:
                cd = u.weapon_cooldown / self.unit_max_cooldown(u) if u.health > 0 else 0.0
            sh_norm = (self.unit_max_shield(u) or 1.0) if (u.shield_max or 0) > 0 else 1.0
            return UnitView(u.pos.x, u.pos.y, u.health, u.health_max, u.shield, sh_norm,
                            self.get_unit_type_id(u, ally) if self.unit_type_bits else 0, cd)

        def views(self):
            allies = [self._view(self.agents[i], True) for i in range(self.n_agents)]
            enemies = [self._view(self.enemies[j], False) for j in range(self.n_enemies)]
            return allies, enemies

        def get_obs_size(self):
            return obs_layout(self.spec)["obs_dim"]

        def get_state_size(self):
            return obs_layout(self.spec)["state_dim"]

        def get_obs_agent(self, agent_id):
            allies, enemies = self.views()
            avail = np.array(self.get_avail_agent_actions(agent_id))
            return obs_agent(self.spec, agent_id, allies, enemies, avail)

        def get_state(self):
            allies, enemies = self.views()
            return state_of(self.spec, allies, enemies, self.last_action,
                            (self.map_x, self.map_y), (self.max_distance_x, self.max_distance_y))

    return SmacCommEnv


class SmacVecEnv(VecEnv):
    """B real games, stepped one after the other (each is its own StarCraft II process)."""

    def __init__(self, variant: str, num_envs: int, seed: int):
        if variant not in MAP_PARAMS:
            raise ValueError(f"unknown SMAC-Comm map {variant!r}; known: {', '.join(MAP_PARAMS)}")
        self.schema = Schema.load(schema_path(f"smac:{variant}"))
        self.num_envs = num_envs
        missing = missing_requirements(variant)
        if missing:
            raise SmacUnavailable(f"smac:{variant} cannot run here; missing: "
                                  + "; ".join(missing) + ".\n" + INSTALL)
        cls = _env_class()
        kw = dict(COMMON_ARGS)
        kw.update(COMM_ARGS[variant])
        self.envs = [cls(map_name=variant, seed=seed + i, **kw) for i in range(num_envs)]
        self.limit = MAP_PARAMS[variant]["limit"]
        self.won = np.zeros(num_envs, bool)

    def _write(self, e: int, out: Batch) -> None:
        env = self.envs[e]
        out.obs[e] = np.asarray(env.get_obs(), np.float32)
        out.state[e] = env.get_state()
        out.avail[e] = np.asarray(env.get_avail_actions(), np.uint8)

    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        for e in np.asarray(env_ids).reshape(-1):
            self.envs[int(e)].reset()
            self._write(int(e), out)

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        for e, env in enumerate(self.envs):
            if active is not None and not active[e]:
                continue   # its game ended; stepping it would fail (the server resets it next)
            reward, terminated, info = env.step([int(a) for a in actions[e]])
            won = bool(info.get("battle_won", False))
            timeout = terminated and not won and env._episode_steps >= self.limit \
                and env.death_tracker_ally.sum() < env.n_agents
            out.reward[e] = reward
            out.terminated[e] = int(terminated and not timeout)
            out.truncated[e] = int(timeout)
            self.won[e] = won
            self._write(e, out)   # the final observation; the server then resets the env

    def close(self) -> None:
        for env in getattr(self, "envs", []):
            env.close()


def make(variant: str, num_envs: int, seed: int = 0) -> VecEnv:
    return SmacVecEnv(variant, num_envs, seed)


if __name__ == "__main__":   # python -m lmac_env.smac: what is missing to run the real game
    import sys
    bad = {m: missing_requirements(m) for m in MAP_PARAMS}
    for m, miss in bad.items():
        print(f"smac:{m}: " + ("ready" if not miss else "missing " + "; ".join(miss)))
    if any(bad.values()):
        print(INSTALL)
    sys.exit(1 if any(bad.values()) else 0)
