"""Unit data of the SMAC-Comm re-implementation, with the source of every number.

Time base. StarCraft II advances in game loops, 16 per game second at "Normal" speed (22.4 per
real second at "Faster", the speed Liquipedia quotes). SMAC steps the game 8 loops per
environment step (``step_mul=8``), so one step is 0.5 game seconds. The map XML files give
speeds, periods and regeneration rates per game second; Liquipedia gives "Faster" values
(divide by 1.4 to get per game second). Below every number is converted to per-step or
game-loop units, with its source next to it.

Sources (abbreviations used below):
  MAP:<map>   the SC2Map file of SMAC-Comm (SaaangJun/LMAC ``sc2_maps/``, identical to
              TonghanWang/NDQ ``src/smac_plus/sc2_maps/``): ``Base.SC2Data/GameData/*.xml``,
              ``MapScript.galaxy``, ``Regions``, ``Objects``, ``t3SyncCliffLevel``.
  LIQ         Liquipedia StarCraft II unit pages (LotV, patch 4.x, the game SMAC runs: 4.10).
  SMAC        oxwhirl/smac ``starcraft2.py`` and the SMAC-Comm fork ``smac_plus/starcraft2``.
  ASSUMED     not published anywhere we could read; chosen and documented (README.md).
"""
from __future__ import annotations

import dataclasses

LOOPS_PER_STEP = 8            # SMAC step_mul (SMAC)
LOOPS_PER_SECOND = 16         # game loops per game second (Normal speed)
STEP_SECONDS = LOOPS_PER_STEP / LOOPS_PER_SECOND   # 0.5 game seconds per env step
FASTER = 1.4                  # "Faster" seconds per game second (LIQ values / 1.4)


def per_step(per_game_second: float) -> float:
    return per_game_second * STEP_SECONDS


def faster_to_loops(seconds_faster: float) -> float:
    """A Liquipedia ("Faster") duration in game loops (22.4 loops per Faster second)."""
    return seconds_faster * LOOPS_PER_SECOND * FASTER


@dataclasses.dataclass(frozen=True)
class UnitType:
    name: str
    hp: float
    shield: float
    armor: float
    light: bool          # attribute "Light" (Baneling bonus damage)
    air: bool
    radius: float
    speed: float         # distance per env step
    damage: float        # per hit, before armour (0 = no weapon)
    hits: int            # hits per attack (Zealot: 2)
    reach: float         # weapon range, edge to edge (SC2 ranges are between unit edges)
    period: float        # weapon cooldown in game loops
    hits_air: bool
    hits_ground: bool
    regen: float         # life regeneration per env step
    shield_regen: float  # shield regeneration per step once the regen delay has passed
    shield_delay: int    # steps without damage before shields regenerate
    source: str


ZERG_REGEN = per_step(0.2734)  # MAP: <LifeRegenRate value="0.2734"/> per game second

UNITS = {
    # Player 1 (the agents)
    "baneling": UnitType(
        "Baneling", hp=30, shield=0, armor=0, light=False, air=False, radius=0.375,
        speed=per_step(2.5), damage=16, hits=1, reach=0.25, period=0, hits_air=False,
        hits_ground=True, regen=ZERG_REGEN, shield_regen=0, shield_delay=0,
        source="MAP:bane_vs_hM/1o_10b_vs_1r CUnit Baneling_RL: LifeMax 30, Speed 2.5, Radius "
               "0.375, attribute Biological only (not Light), passive. LIQ Volatile Burst "
               "(patch 4.0+): 16 (+19 vs Light), range 0.25, splash radius 2.2, no friendly "
               "fire, explodes when killed too, ground targets only."),
    "overseer": UnitType(
        "Overseer (Overload_RL)", hp=200, shield=0, armor=0, light=False, air=True, radius=1.0,
        speed=per_step(0.4687), damage=0, hits=0, reach=0, period=0, hits_air=False,
        hits_ground=False, regen=ZERG_REGEN, shield_regen=0, shield_delay=0,
        source="MAP:1o_10b_vs_1r CUnit Overload_RL: LifeMax 200, Speed 0.4687, Radius 1, "
               "Mover Fly, Sight 4, no weapon (abilities stop/move only)."),
    "zealot": UnitType(
        "Zealot (Zealot_RL)", hp=100, shield=50, armor=1, light=True, air=False, radius=0.5,
        speed=per_step(2.25), damage=8, hits=2, reach=0.1, period=faster_to_loops(0.857),
        hits_air=False, hits_ground=True, regen=0, shield_regen=per_step(2.0),
        shield_delay=int(10 / STEP_SECONDS),
        source="MAP:5z_vs_1ul CUnit Zealot_RL: LifeMax 100, ShieldsMax 50, LifeArmor 1, Speed "
               "2.25 (no Charge), ShieldRegenDelay 10, ShieldRegenRate 2, Light. LIQ Psi "
               "Blades 8 (x2), range 0.1, cooldown 0.857 (Faster); radius 0.5 (LIQ)."),
    # Player 2 (the built-in AI)
    "hydralisk": UnitType(
        "Hydralisk", hp=90, shield=0, armor=0, light=True, air=False, radius=0.625,
        speed=per_step(2.25), damage=30, hits=1, reach=2.0, period=faster_to_loops(0.59),
        hits_air=True, hits_ground=True, regen=ZERG_REGEN, shield_regen=0, shield_delay=0,
        source="MAP:bane_vs_hM EffectData NeedleSpinesDamage Amount 30, WeaponData NeedleSpines "
               "Range 2 (both overridden by the map); LIQ Hydralisk 90 HP, armour 0, Light, "
               "cooldown 0.59 (Faster), radius 0.625."),
    "medivac": UnitType(
        "Medivac", hp=150, shield=0, armor=1, light=False, air=True, radius=0.75,
        speed=per_step(2.5), damage=0, hits=0, reach=4.0, period=0, hits_air=False,
        hits_ground=False, regen=0, shield_regen=0, shield_delay=0,
        source="MAP:bane_vs_hM EffectData MedivacHeal RechargeVitalRate 7 (HP per game "
               "second, overridden by the map); LIQ Medivac 150 HP, armour 1, flying."),
    "roach": UnitType(
        "Roach", hp=145, shield=0, armor=1, light=False, air=False, radius=0.625,
        speed=per_step(2.25), damage=16, hits=1, reach=4.0, period=1.0 * LOOPS_PER_SECOND,
        hits_air=False, hits_ground=True, regen=ZERG_REGEN, shield_regen=0, shield_delay=0,
        source="MAP:1o_10b_vs_1r CUnit Roach Sight 4, WeaponData AcidSaliva Period 1 (game "
               "second; overridden); Roach_RL LifeMax 145, LifeArmor 1, Speed 2.25, Armored; "
               "LIQ Acid Saliva 16 damage, range 4, ground only, radius 0.625."),
    "ultralisk": UnitType(
        "Ultralisk", hp=500, shield=0, armor=2, light=False, air=False, radius=1.0,
        speed=per_step(4.13 / FASTER), damage=35, hits=1, reach=1.0,
        period=faster_to_loops(0.61), hits_air=False, hits_ground=True, regen=ZERG_REGEN,
        shield_regen=0, shield_delay=0,
        source="LIQ Ultralisk (not modified by MAP:5z_vs_1ul): 500 HP, armour 2 (no Chitinous "
               "Plating), speed 4.13 (Faster), Kaiser Blades 35 damage, range 1, cooldown "
               "0.61 (Faster), 33% splash; radius 1."),
}

# Baneling Volatile Burst (LIQ, patch 4.0+; SMAC runs SC2 4.10)
BANE_DAMAGE = 16.0
BANE_BONUS_LIGHT = 19.0
BANE_SPLASH = 2.2            # area radius, measured to the victim's edge
MEDIVAC_HEAL = per_step(7.0)  # MAP:bane_vs_hM MedivacHeal RechargeVitalRate 7 -> 3.5 per step
ULTRA_SPLASH_FRACTION = 0.33  # LIQ: Kaiser Blades splash 33%
ULTRA_SPLASH_RADIUS = 1.0     # ASSUMED: victims whose centre is within 1.0 of the primary target
ULTRA_ACQUIRE = 6.0           # ASSUMED: attack-move acquisition radius (centre distance)
MIN_DAMAGE = 0.5             # SC2: armour never reduces a hit below 0.5

# The SMAC-Comm map files depend only on the game's ``Liberty.SC2Mod``, not on the multiplayer
# mod the Liquipedia values above describe. Where the two differ, "liberty" takes the Liberty
# values, read from Blizzard's XML of game versions 5.0.10-5.0.14 (SMAC runs 4.10, whose data
# could not be read here): the Baneling's burst, the Roach's weapon range and radius, the
# Hydralisk's life. Not modelled: the Roach's missile (a 0.17 s wind-up, within one step) and
# the Ultralisk's 180-degree cleave, so only the cliff maps have a "liberty" variant.
# "liberty-roach" takes Liberty's Roach alone (the Baneling keeps its multiplayer burst), to
# tell the two changes apart on the cliff maps.
UNIT_DATA = ("liquipedia", "liberty", "liberty-roach")
LIBERTY_CHANGES = {
    "roach": dict(reach=3.0, radius=0.5, source="Liberty.SC2Mod Roach: AcidSaliva range 3, "
                  "radius 0.5 (InnerRadius 0.625); MAP as above"),
    "hydralisk": dict(hp=80.0, source="Liberty.SC2Mod Hydralisk LifeMax 80; MAP as above"),
}
BANE_BURST = {"liquipedia": (BANE_DAMAGE, BANE_BONUS_LIGHT),  # (damage, bonus vs Light)
              "liberty": (20.0, 15.0),                        # Liberty.SC2Mod Volatile Burst
              "liberty-roach": (BANE_DAMAGE, BANE_BONUS_LIGHT)}
LIBERTY_MAPS = ("1o_10b_vs_1r", "2o_20b_vs_2r")


def unit_data(name: str) -> dict[str, UnitType]:
    """The unit table of one data set (`UNIT_DATA`)."""
    if name == "liquipedia":
        return UNITS
    if name == "liberty":
        return {k: dataclasses.replace(u, **LIBERTY_CHANGES.get(k, {})) for k, u in UNITS.items()}
    if name == "liberty-roach":
        return {k: dataclasses.replace(u, **LIBERTY_CHANGES["roach"]) if k == "roach" else u for k, u in UNITS.items()}
    raise ValueError(f"unknown unit data {name!r}; known: {', '.join(UNIT_DATA)}")
