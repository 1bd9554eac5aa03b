"""Renders the schema TOML files of the SMAC-Comm maps from the map specs, so the described
layout and the simulated layout cannot drift apart.

    python -m lmac_env.smaclite.schemas            # check the files are up to date
    python -m lmac_env.smaclite.schemas --write    # (re)write env-server/schemas/{smaclite,smac}
"""
from __future__ import annotations

import argparse
import json
import sys

from ..core import SCHEMA_DIR
from .maps import MAPS, MapSpec, Variant, obs_layout, variants

# Message columns per receiver of the LMAC authors' design for a map (protocols/paper/), where it
# is wider than FullComm's: the smaclite schema's budget is raised to fit it.
PAPER_DESIGN_COLUMNS = {"5z_vs_1ul": 280}

UNIT_NAMES = {"baneling": "Baneling", "overseer": "Overseer", "zealot": "Zealot",
              "hydralisk": "Hydralisk", "medivac": "Medivac", "roach": "Roach",
              "ultralisk": "Ultralisk"}
TYPE_NAMES = {  # SMAC-Comm's unit-type bits (get_unit_type_id)
    "bane_vs_hM": (["Baneling", "(unused)"], ["Hydralisk", "Medivac"]),
    "1o_10b_vs_1r": (["Overseer", "Baneling"], ["Roach", "(unused)"]),
    "2o_20b_vs_2r": (["Overseer", "Baneling"], ["Roach", "(unused)"]),
    "5z_vs_1ul": ([], []),
}

TASKS = {
    "bane_vs_hM": (
        "SMAC-Comm bane_vs_hM: 3 Banelings (the agents) must kill a Hydralisk that stands at the "
        "junction of a T-shaped high ground (absolute position x=16, y=31 on a 32x32 map) and is "
        "healed by a Medivac hovering above it. The T is a bar across the top of the map "
        "(y between 29 and 32) and a 2-cell-wide vertical corridor (x between 15 and 17) from "
        "the junction down to y=0. Agent 0 starts on the left arm of the bar, agent 1 somewhere "
        "in the corridor, agent 2 on the right arm. A Baneling explodes when it reaches its "
        "target (or when it is killed) and deals 35 damage to the Hydralisk (90 HP); the "
        "Hydralisk kills a Baneling with one shot (reach 3 from its centre, about one shot "
        "every 1.7 steps) and the Medivac heals it 3.5 HP per step, so only three Banelings "
        "exploding within a few steps of each other kill it: they must arrive together. "
        "Sight and attack range are only 2, observations carry no absolute position and no "
        "health of other units, so agents must infer where they are from which moves are "
        "possible and from their history, and coordinate the timing."),
    "1o_10b_vs_1r": (
        "SMAC-Comm 1o_10b_vs_1r: 10 Banelings (agents 0-9) and 1 Overseer (agent 10, a slow "
        "flying scout without weapon) must kill a Roach (145 HP, 1 armour) on a 32x32 map with "
        "small cliff blocks. The Overseer and the Roach spawn together at one of the four "
        "corners, chosen at random; the Banelings spawn at random points in five regions (the "
        "bottom band, the top band, the left and right strips, the centre). Each Baneling that "
        "explodes next to the Roach deals 15 damage, so all 10 are needed; the Roach shoots "
        "Banelings within 5 of its centre (16 damage every 2 steps, two shots kill one). Agents "
        "see units within 9 and can order an attack within 6; observations are relative, with "
        "no absolute position. The Overseer always sees the Roach at the start; most Banelings "
        "do not, so the Overseer must tell them where it is."),
    "2o_20b_vs_2r": (
        "SMAC-Comm 2o_20b_vs_2r (the LMAC paper's extension of 1o_10b_vs_1r): 20 Banelings "
        "(agents 0-19) and 2 Overseers (agents 20-21, slow flying scouts without weapon) must "
        "kill 2 Roaches (145 HP, 1 armour each) on the same 32x32 cliff map. Overseer and Roach "
        "pairs spawn together: one pair at a random corner, the other at a random point in one "
        "of the five Baneling spawn regions; the Banelings spawn at random points in those "
        "regions. Each Baneling burst deals 15 damage to every Roach within 2.2 of it, so ten "
        "Banelings per Roach are needed. Agents see units within 9 and can order an attack "
        "within 6; observations are relative, with no absolute position; the Overseers must "
        "tell the Banelings where the Roaches are."),
    "5z_vs_1ul": (
        "SMAC-Comm 5z_vs_1ul: 5 Zealots (100 HP + 50 shields, 1 armour, melee 2x8 damage) "
        "fight one Ultralisk (500 HP, 2 armour, 35 damage per strike with 33% splash on "
        "Zealots next to the target, faster than the Zealots) in a horizontal band of the map "
        "(y between 7 and 25). Three Zealots spawn next to the Ultralisk, two at another random "
        "point; the Ultralisk attack-moves towards x=9, y=16 and strikes the nearest Zealot in "
        "reach. The Zealots win only by focusing their attacks while spreading out and pulling "
        "the damaged Zealot back so that shields (regenerating after 10 s without damage) and "
        "lives last. Agents see units within 9 and can order an attack within 6."),
}

# The "-liberty" variants (units.py: the game's Liberty.SC2Mod unit data) describe their numbers.
LIBERTY_TASK = {  # (the unit the change belongs to, the multiplayer text, Liberty's)
    "1o_10b_vs_1r": [("baneling", "deals 15 damage, so all 10 are needed", "deals 19 damage, so 8 of the 10 "
                      "are needed"), ("roach", "within 5 of its centre", "within 3.9 of its centre")],
    "2o_20b_vs_2r": [("baneling", "deals 15 damage to every Roach within 2.2 of it, so ten Banelings per Roach",
                      "deals 19 damage to every Roach within 2.2 of it, so eight Banelings per "
                      "Roach")],
}


def task_text(name: str, data: str) -> str:
    task = TASKS[name]
    if data in ("liberty", "liberty-roach"):
        units = ("baneling", "roach") if data == "liberty" else ("roach",)
        for unit, old, new in LIBERTY_TASK[name]:
            assert old in task, (name, old)
            if unit in units:
                task = task.replace(old, new)
        task += (" Unit data of the game's Liberty.SC2Mod (the Baneling burst 20, +15 against "
                 "Light; the Roach's weapon range 3 and radius 0.5) in place of the multiplayer "
                 "values." if data == "liberty" else
                 " The Roach of the game's Liberty.SC2Mod (weapon range 3, radius 0.5); the "
                 "Baneling keeps the multiplayer burst (16, +19 against Light).")
    return task


REWARD = (
    "SMAC reward with reward_only_positive: each step |damage dealt to the enemy's health and "
    "shields (negative when the enemy is healed or regenerates, so healing also yields a "
    "positive reward, as in SMAC) + 10 per enemy unit killed| + 200 on a win, multiplied by "
    "20 / max_reward with max_reward = 10 x enemies + 200 + the enemies' total health and "
    "shields ({max_reward:g} here). The episode terminates on a win ({win}) or a loss "
    "({loss}) and is truncated after {limit} steps.")
WIN = {"bane_vs_hM": "the Hydralisk is dead", "1o_10b_vs_1r": "the Roach is dead",
       "2o_20b_vs_2r": "both Roaches are dead", "5z_vs_1ul": "the Ultralisk is dead"}
LOSS = {"bane_vs_hM": "all Banelings are dead",
        "1o_10b_vs_1r": "every agent is dead; the Roach cannot hit the flying Overseer, so in "
                        "practice this never happens",
        "2o_20b_vs_2r": "every agent is dead; the Roaches cannot hit the flying Overseers, so "
                        "in practice this never happens",
        "5z_vs_1ul": "all Zealots are dead"}


def _q(s: str) -> str:
    return json.dumps(s, ensure_ascii=False)


def _group(lines: list[str], kind: str, count: int, meaning: str, labels=None, shape=None):
    lines.append(f"\n[[{kind}]]")
    lines.append(f"count = {count}")
    if shape:
        lines.append(f"shape = [{', '.join(str(s) for s in shape)}]")
    lines.append(f"meaning = {_q(meaning)}")
    if labels is not None:
        assert len(labels) == count, (meaning, len(labels), count)
        lines.append("labels = [" + ", ".join(_q(label) for label in labels) + "]")


def actions_of(spec: MapSpec) -> list[str]:
    from .units import UNITS
    sp = ", ".join(sorted({f"{UNITS[k].name.split(' ')[0]} {UNITS[k].speed:.3g}"
                           for k in spec.agents}))
    acts = ["no-op (only available to, and required for, dead agents)", "stop",
            f"move north (+y; distance per step: {sp})", "move south (-y)",
            "move east (+x)", "move west (-x)"]
    for e, k in enumerate(spec.enemies):
        acts.append(f"attack enemy {e} ({UNIT_NAMES[k]}), available when it is alive and "
                    f"within {spec.shoot_range:g} of the agent")
    return acts


# Maps whose re-implementation steps so fast that half a batch costs about as much as a whole
# one: not double-buffered (2o_20b_vs_2r, 22 agents, is slow enough to gain from the split).
UNSPLIT = {"bane_vs_hM", "1o_10b_vs_1r", "5z_vs_1ul"}


def render(spec: MapSpec, family: str, variant: Variant | None = None) -> str:
    variant = variant or Variant(spec.name)
    data = variant.unit_data
    lay = obs_layout(spec, variant.state_last_action)
    n, e = len(spec.agents), len(spec.enemies)
    sr = spec.sight_range
    ally_types, enemy_types = TYPE_NAMES[spec.name]
    task = task_text(spec.name, data)
    if not variant.state_last_action:
        task += (" The state leaves out the agents' last actions (SMAC's state_last_action = "
                 "False, as the LMAC authors' runs set it).")
    if family == "smaclite":
        task = ("Lightweight re-implementation (numpy, not StarCraft II) of " + task)
        name = f"smaclite:{spec.name}{variant.suffix}"
    else:
        task = ("Runs the real StarCraft II game through the SMAC API (needs StarCraft II, "
                "pysc2 and smac installed, and the SMAC-Comm map files). " + task)
        name = f"smac:{spec.name}"
    kinds = spec.agents
    L = [f"name = {_q(name)}", f"task = {_q(task)}", f"n_agents = {n}",
         f"obs_dim = {lay['obs_dim']}", f"state_dim = {lay['state_dim']}",
         f"n_actions = {lay['n_actions']}", f"episode_limit = {spec.episode_limit}"]
    fullcomm = (n - 1) * (lay['obs_dim'] + n)
    wider = PAPER_DESIGN_COLUMNS.get(spec.name, 0)
    if family == "smaclite" and wider > fullcomm:
        L += [f"# The LMAC authors' own protocol for this task (protocols/paper/) needs {wider} columns, more than",
              f"# FullComm's {fullcomm}: the budget is raised to it so their design runs as they made it.",
              f"message_columns = {wider}"]
    else:
        L += [f"message_columns = {fullcomm}"]
    if family == "smaclite" and spec.name in UNSPLIT:
        L += ["# One vectorized numpy step for all environments costs about as much for half the batch as for",
              "# all of it, so the env server does not split its batch (lmac bench pipeline: 0.73-0.80 of raw",
              "# stepping with one sub-batch against 0.53-0.59 with two).",
              "double_buffer = false"]
    L.append(f"alpha = {0.005 if spec.name == 'bane_vs_hM' else 0.05}")
    from .units import unit_data
    units = unit_data(data)
    max_reward = e * 10 + 200 + sum(units[k].hp + units[k].shield for k in spec.enemies)
    L.append("reward = " + _q(REWARD.format(max_reward=max_reward, win=WIN[spec.name],
                                             loss=LOSS[spec.name], limit=spec.episode_limit)))
    L.append("actions = [" + ", ".join(_q(a) for a in actions_of(spec)) + "]")
    dead = " All observation values of a dead agent are 0."
    # --- observation
    _group(L, "obs_dims", 4,
           "move feature: 1 if this agent can move {label} now (the ground cell 1 map unit in "
           "that direction is walkable; flying units: inside the map), 0 otherwise or when "
           "the agent is dead", labels=["north (+y)", "south (-y)", "east (+x)", "west (-x)"])
    en_labels = [
        f"1 if this agent can attack it now (alive and within shoot range {spec.shoot_range:g}),"
        " else 0",
        f"distance from this agent divided by the sight range {sr:g}; 0 when not visible "
        f"(dead or not closer than {sr:g})",
        f"relative x (its x minus this agent's x) divided by {sr:g}; 0 when not visible",
        f"relative y (its y minus this agent's y) divided by {sr:g}; 0 when not visible"]
    if spec.obs_all_health or spec.obs_enemy_health:
        en_labels.append("its health divided by its maximum health; 0 when not visible")
    for t in range(spec.unit_type_bits):
        en_labels.append(f"unit-type bit {t}: 1 if it is a {enemy_types[t]} and visible, "
                         "else 0" if enemy_types[t] != "(unused)" else
                         f"unit-type bit {t}: unused by this map's enemies, always 0")
    while len(en_labels) < lay["nf_en"]:
        en_labels.append("always 0: SMAC-Comm reserves a second health slot when both "
                         "obs_all_health and obs_enemy_health are on and never fills it")
    for j, k in enumerate(spec.enemies):
        _group(L, "obs_dims", lay["nf_en"],
               f"enemy {j} ({UNIT_NAMES[k]}) as seen by this agent: {{label}}",
               labels=en_labels)
    al_labels = ["1 if that teammate is visible (alive and closer than the sight range "
                 f"{sr:g}), else 0",
                 f"distance to that teammate divided by {sr:g}; 0 when not visible",
                 f"relative x (teammate x minus own x) divided by {sr:g}; 0 when not visible",
                 f"relative y (teammate y minus own y) divided by {sr:g}; 0 when not visible"]
    if spec.obs_all_health:
        al_labels.append("teammate health divided by its maximum health; 0 when not visible")
        if spec.shield_bits_ally:
            al_labels.append("teammate shield divided by 80 (SMAC normalises this map's Zealot "
                             "shields by the Stalker's 80, so a full shield reads 0.625); 0 "
                             "when not visible")
    for t in range(spec.unit_type_bits):
        al_labels.append(f"unit-type bit {t}: 1 if the teammate is a {ally_types[t]} and "
                         "visible, else 0" if ally_types[t] != "(unused)" else
                         f"unit-type bit {t}: unused by this map's agents, always 0")
    _group(L, "obs_dims", (n - 1) * lay["nf_al"],
           "teammate slot {i0} (the other agents in id order, skipping this agent: it is agent "
           "{i0} if this agent's id is larger than {i0}, otherwise agent {i0}+1): {label}",
           labels=al_labels * (n - 1), shape=[n - 1, lay["nf_al"]])
    own = []
    if spec.obs_own_health:
        own.append("own health divided by own maximum health")
        if spec.shield_bits_ally:
            own.append("own shield divided by 80 (full shield = 0.625, SMAC's normalisation)")
    for t in range(spec.unit_type_bits):
        own.append(f"own unit-type bit {t}: 1 if this agent is a {ally_types[t]}"
                   if ally_types[t] != "(unused)" else
                   f"own unit-type bit {t}: unused by this map's agents, always 0")
    _group(L, "obs_dims", len(own), "own feature: {label}." + dead, labels=own)
    # --- state
    st = ["health divided by maximum health (0 when dead)",
          ("weapon cooldown left in game loops divided by 35 (SMAC's normaliser; 0 = ready)"
           if spec.name == "5z_vs_1ul" else
           "weapon cooldown divided by SMAC's normaliser; always 0 for this unit (Banelings "
           "and the Overseer have no weapon cooldown)"),
          "absolute x: (x - 16) / 32, from -0.5 (west edge) to 0.5 (east edge); 0 when dead",
          "absolute y: (y - 16) / 32, from -0.5 (south edge) to 0.5 (north edge); 0 when dead"]
    if spec.shield_bits_ally:
        st.append("shield divided by 80 (full shield = 0.625); 0 when dead")
    for t in range(spec.unit_type_bits):
        st.append(f"unit-type bit {t}: 1 if a {ally_types[t]} and alive" if ally_types[t] !=
                  "(unused)" else f"unit-type bit {t}: unused, always 0")
    groups = []
    for i, k in enumerate(kinds):
        if groups and groups[-1][0] == k:
            groups[-1][2] += 1
        else:
            groups.append([k, i, 1])
    for k, first, cnt in groups:
        if cnt == 1:
            _group(L, "state_dims", lay["st_al"], f"agent {first} ({UNIT_NAMES[k]}): {{label}}",
                   labels=st)
        else:
            _group(L, "state_dims", cnt * lay["st_al"],
                   f"agent {first}+{{i0}} ({UNIT_NAMES[k]}): {{label}}", labels=st * cnt,
                   shape=[cnt, lay["st_al"]])
    se = ["health divided by maximum health (0 when dead)",
          "absolute x: (x - 16) / 32; 0 when dead", "absolute y: (y - 16) / 32; 0 when dead"]
    for t in range(spec.unit_type_bits):
        se.append(f"unit-type bit {t}: 1 if a {enemy_types[t]} and alive" if enemy_types[t]
                  != "(unused)" else f"unit-type bit {t}: unused, always 0")
    for j, k in enumerate(spec.enemies):
        _group(L, "state_dims", lay["st_en"], f"enemy {j} ({UNIT_NAMES[k]}): {{label}}",
               labels=se)
    if variant.state_last_action:
        acts = ["no-op", "stop", "move north", "move south", "move east", "move west"] + [
            f"attack enemy {j}" for j in range(e)]
        _group(L, "state_dims", n * lay["n_actions"],
               "last action of agent {i0}: 1 if it was '{label}', else 0 (all 0 at the first step)",
               labels=acts * n, shape=[n, lay["n_actions"]])
    return "\n".join(L) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    stale = []
    files = [("smac", Variant(m)) for m in MAPS] + [("smaclite", v) for v in variants()]
    for family, variant in files:
        path = SCHEMA_DIR / family / f"{variant.map_name}{variant.suffix}.toml"
        text = render(MAPS[variant.map_name], family, variant)
        if args.write:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        elif not path.exists() or path.read_text() != text:
            stale.append(str(path))
    if stale:
        print("out of date (run with --write):\n  " + "\n  ".join(stale))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
