"""The four SMAC-Comm maps: terrain, spawns, units and the SMAC settings that shape the
observation, state and action layouts.

Terrain: every map is 32 x 32 with playable area (0,0)-(32,32) (MAP ``MapInfo``). The walkable
masks below are the cliff-level layer ``t3SyncCliffLevel`` of each SC2Map file, one character
per 1 x 1 cell ('.' = walkable ground, '#' = not walkable for ground units), printed with
y = 31 at the top:

- bane_vs_hM: the high-ground T (the bar y in [29, 32) across the map, a funnel, the stem
  x in [15, 17)); everything else is low ground without ramps, i.e. unreachable.
- 1o_10b_vs_1r / 2o_20b_vs_2r (same terrain file): ground level 1 everywhere except small
  raised cliff blocks (level 2) in the middle of the map.
- 5z_vs_1ul: the walkable band y in [7, 25).

Spawns follow each map's ``MapScript.galaxy`` (trigger ``gf_Spawn``) and ``Regions``/``Objects``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .units import LIBERTY_MAPS

BANE_T = [
    "................................",  # y=31
    "................................",  # y=30
    "................................",  # y=29
    "############........############",  # y=28
    "#############......#############",  # y=27
    "##############....##############",  # y=26
] + ["###############..###############"] * 26  # y=25..0

CLIFF_MAP = [
    "................................",  # y=31
    "................................",
    "................................",
    "................................",
    "................................",
    "................................",
    "................................",  # y=25
    ".........##..........##.........",  # y=24
    "........###..........###........",
    ".......####....####...###.......",
    ".......#####...####....##.......",
    "..........###...................",  # y=20
    "...........##...................",
    ".....................##.........",
    ".....................##.........",
    ".........##..........##.........",
    ".........##..........##.........",  # y=15
    ".........##.....................",
    ".........##.....................",
    "...................##...........",
    "...................###..........",
    ".......##....####...#####.......",  # y=10
    ".......###...####....####.......",
    "........###..........###........",
    ".........##..........##.........",
    "................................",
    "................................",  # y=5
    "................................",
    "................................",
    "................................",
    "................................",
    "................................",  # y=0
]

BAND_5Z = ["#" * 32] * 7 + ["." * 32] * 18 + ["#" * 32] * 7  # y=31..25, 24..7, 6..0


def mask_from_rows(rows: list[str]) -> np.ndarray:
    """Rows printed with y=31 first -> bool array indexed [y, x]."""
    assert len(rows) == 32 and all(len(r) == 32 for r in rows)
    return np.array([[c == "." for c in r] for r in rows[::-1]], dtype=bool)


@dataclasses.dataclass(frozen=True)
class MapSpec:
    name: str
    agents: tuple[str, ...]      # unit kinds of the agents in SMAC's order (sorted by type)
    enemies: tuple[str, ...]
    episode_limit: int
    walkable: tuple[str, ...]
    # SMAC settings of SMAC-Comm
    sight_range: float
    shoot_range: float
    obs_all_health: bool
    obs_enemy_health: bool
    obs_own_health: bool
    unit_type_bits: int
    ally_type_id: tuple[int, ...]   # per agent kind in `agents`
    enemy_type_id: tuple[int, ...]
    shield_bits_ally: int
    ally_max_cd: float              # SMAC's normaliser of weapon_cooldown in the state
    ally_max_shield: float          # SMAC's normaliser of ally shields (quirk: see README)
    description: str


MAPS = {
    "bane_vs_hM": MapSpec(
        name="bane_vs_hM", agents=("baneling",) * 3, enemies=("hydralisk", "medivac"),
        episode_limit=30, walkable=tuple(BANE_T), sight_range=2.0, shoot_range=2.0,
        obs_all_health=False, obs_enemy_health=False, obs_own_health=True, unit_type_bits=2,
        ally_type_id=(0, 0, 0), enemy_type_id=(0, 1), shield_bits_ally=0, ally_max_cd=1.0,
        ally_max_shield=1.0,
        description="3 Banelings vs a Hydralisk and a Medivac on a T-shaped high ground"),
    "1o_10b_vs_1r": MapSpec(
        name="1o_10b_vs_1r", agents=("baneling",) * 10 + ("overseer",), enemies=("roach",),
        episode_limit=50, walkable=tuple(CLIFF_MAP), sight_range=9.0, shoot_range=6.0,
        obs_all_health=True, obs_enemy_health=True, obs_own_health=True, unit_type_bits=2,
        ally_type_id=(1,) * 10 + (0,), enemy_type_id=(0,), shield_bits_ally=0,
        ally_max_cd=15.0, ally_max_shield=1.0,
        description="1 Overseer and 10 Banelings vs 1 Roach on a cliff map"),
    "2o_20b_vs_2r": MapSpec(
        name="2o_20b_vs_2r", agents=("baneling",) * 20 + ("overseer",) * 2,
        enemies=("roach", "roach"), episode_limit=50, walkable=tuple(CLIFF_MAP),
        sight_range=9.0, shoot_range=6.0, obs_all_health=True, obs_enemy_health=True,
        obs_own_health=True, unit_type_bits=2, ally_type_id=(1,) * 20 + (0, 0),
        enemy_type_id=(0, 0), shield_bits_ally=0, ally_max_cd=15.0, ally_max_shield=1.0,
        description="2 Overseers and 20 Banelings vs 2 Roaches on a cliff map"),
    "5z_vs_1ul": MapSpec(
        name="5z_vs_1ul", agents=("zealot",) * 5, enemies=("ultralisk",), episode_limit=150,
        walkable=tuple(BAND_5Z), sight_range=9.0, shoot_range=6.0, obs_all_health=True,
        obs_enemy_health=True, obs_own_health=True, unit_type_bits=0, ally_type_id=(0,) * 5,
        enemy_type_id=(0,), shield_bits_ally=1, ally_max_cd=35.0, ally_max_shield=80.0,
        description="5 Zealots vs 1 Ultralisk in a horizontal band"),
}

NO_LAST_ACTION = "-no-last-action"


@dataclasses.dataclass(frozen=True)
class Variant:
    """What a smaclite variant name selects: the map, its unit data and whether the state
    carries the agents' one-hot last actions (SMAC's ``state_last_action``)."""
    map_name: str
    unit_data: str = "liquipedia"
    state_last_action: bool = True

    @property
    def suffix(self) -> str:
        return (("" if self.unit_data == "liquipedia" else f"-{self.unit_data}")
                + ("" if self.state_last_action else NO_LAST_ACTION))


def split_variant(variant: str) -> Variant:
    """`1o_10b_vs_1r` -> the map with the Liquipedia unit data and SMAC's default state;
    `-liberty` takes the game's Liberty.SC2Mod unit data (units.py); `-no-last-action` drops
    the last actions from the state, as SMAC's ``state_last_action=False`` (the LMAC authors'
    setting). Both: `1o_10b_vs_1r-liberty-no-last-action`. `-liberty-roach` changes the Roach
    alone."""
    rest, last_action = variant, True
    if rest.endswith(NO_LAST_ACTION):
        rest, last_action = rest[:-len(NO_LAST_ACTION)], False
    name, sep, data = rest.partition("-")
    if name not in MAPS:
        raise ValueError(f"unknown smaclite map {name!r}; known: {', '.join(MAPS)}")
    if not sep:
        return Variant(name, "liquipedia", last_action)
    if data not in ("liberty", "liberty-roach") or name not in LIBERTY_MAPS:
        known = ", ".join(f"{m}-{d}" for m in LIBERTY_MAPS for d in ("liberty", "liberty-roach"))
        raise ValueError(f"unknown smaclite variant {variant!r}; the unit-data variants are {known}"
                         f" (each may end in {NO_LAST_ACTION}, as may every map)")
    return Variant(name, data, last_action)


def variants() -> list[Variant]:
    """Every variant the schemas describe: each map, the Liberty maps, each without last actions."""
    base = [Variant(m) for m in MAPS] + [Variant(m, d) for m in LIBERTY_MAPS for d in ("liberty", "liberty-roach")]
    return base + [dataclasses.replace(v, state_last_action=False) for v in base]


# Spawn data (MAP: Regions / Objects), rectangles as (x0, y0, x1, y1)
BANE_REGIONS = [(0.0, 30.0, 14.0, 32.0), (18.0, 30.0, 32.0, 32.0), (15.0, 0.5, 17.0, 30.5)]
BANE_ENEMY_POINT = (16.0, 31.0)
CLIFF_REGIONS = [  # Spawn 1, 4, 3, 2, 5 in the order of the script's RandomInt(1, 5) switch
    (0.0, 0.0, 32.0, 5.0), (1.0, 6.0, 6.0, 26.0), (26.0, 6.0, 31.0, 26.0),
    (0.0, 27.0, 32.0, 32.0), (12.0, 14.0, 20.0, 18.0)]
CLIFF_CORNERS = [(3.5, 2.0), (3.5, 28.8598), (28.5, 28.0), (28.5, 2.0)]
Z5_REGION = (0.993, 7.653, 30.939, 24.2827)
Z5_ATTACK_POINT = (9.0, 16.0)   # MAP:5z_vs_1ul gf_EnemyAttack: attack-move to point "Team 1"


def obs_layout(spec: MapSpec, state_last_action: bool = True) -> dict:
    """Feature counts exactly as SMAC's get_obs_size / get_state_size compute them."""
    n, e = len(spec.agents), len(spec.enemies)
    nf_al = 4 + spec.unit_type_bits
    nf_en = 4 + spec.unit_type_bits
    if spec.obs_all_health:
        nf_al += 1 + spec.shield_bits_ally
        nf_en += 1  # enemies here never have shields
    if spec.obs_enemy_health:
        nf_en += 1
    nf_own = spec.unit_type_bits + (1 + spec.shield_bits_ally if spec.obs_own_health else 0)
    obs_dim = 4 + e * nf_en + (n - 1) * nf_al + nf_own
    st_al = 4 + spec.shield_bits_ally + spec.unit_type_bits
    st_en = 3 + spec.unit_type_bits
    n_actions = 6 + e
    state_dim = n * st_al + e * st_en + (n * n_actions if state_last_action else 0)
    return dict(nf_al=nf_al, nf_en=nf_en, nf_own=nf_own, obs_dim=obs_dim, st_al=st_al,
                st_en=st_en, state_dim=state_dim, n_actions=n_actions)
