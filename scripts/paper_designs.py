#!/usr/bin/env python3
"""Writes protocols/paper/: the LMAC authors' GPT-4.1 protocols (their repository's
src/llm_source_archive/<task>/) restated in lmac's protocol language.

The translation was done by reading their Python by hand; nothing of theirs is imported or run
here. This script only spells the hand translation out as JSON so that the many repeated
sub-expressions (one-hot components, windows per past step) are written once, and so a reader
can check a field against their code in one place. Rerun it after changing a design:

    python3 scripts/paper_designs.py            # rewrites protocols/paper/<env>/...

What each field reads is checked by trainer/cli/tests/paper_designs.rs against a table written by
hand from their code, not from this file.
"""

import json
import pathlib

ROOT = pathlib.Path(__file__).resolve().parent.parent / "protocols" / "paper"
ARCHIVE = "https://github.com/SaaangJun/LMAC (commit dd30c5c), src/llm_source_archive"


# ---- expression helpers (each returns one JSON expression of lmac's language) ----


def obs(*dims):
    return {"obs": list(dims)}


def obs_slice(a, b):
    return {"obs_slice": {"start": a, "end": b}}


def const(x):
    return {"const": x}


def consts(values):
    return {"concat": [const(v) for v in values]}


def concat(*parts):
    return {"concat": list(parts)}


def add(a, b):
    return {"add": [a, b]}


def sub(a, b):
    return {"sub": [a, b]}


def mul(a, b):
    return {"mul": [a, b]}


def gt(a, b):
    return {"gt": [a, b]}


def neg(a):
    return {"neg": a}


def abs_(a):
    return {"abs": a}


def clip(a, lo, hi):
    return {"clip": {"of": a, "min": lo, "max": hi}}


def rsum(a):
    return {"reduce": {"op": "sum", "of": a}}


def window(op, k, of):
    return {"window": {"op": op, "k": k, "of": of}}


LAST_ACTION = {"last_action": "one_hot"}
SENDER_ID = "sender_one_hot"


def pick(onehot, width, c, weight=1.0):
    """Component c of a one-hot expression (last action or sender id), as one column.

    A masked sum rather than `eq(last_action index, c)`: inside a window the padding steps before
    the episode hold -1 in every one-hot column (as the authors' history did), which a masked
    sum keeps and an index comparison would turn into 0."""
    mask = [0.0] * width
    mask[c] = weight
    return rsum(mul(onehot, consts(mask)))


def dx():
    """The x move of the previous action by their action-to-delta table (west -1, east +1)."""
    return rsum(mul(LAST_ACTION, consts([0.0, 0.0, 0.0, -1.0, 1.0, 0.0])))


def dy():
    """The y move of the previous action by their table (north -1, south +1)."""
    return rsum(mul(LAST_ACTION, consts([0.0, -1.0, 1.0, 0.0, 0.0, 0.0])))


def picks(onehot, width, cs):
    return concat(*[pick(onehot, width, c) for c in cs])


def field(name, description, value, senders="all", receivers="broadcast"):
    return {"name": name, "description": description, "senders": senders, "receivers": receivers, "value": value}


def past_steps(expr_of_step, steps):
    """The value of an expression `steps` steps back (1 = the previous step), as a window `last`."""
    return window("last", steps + 1, expr_of_step)


# ---- the designs ----

DESIGNS = {}


def design(env, task, critical, reasoning, phases, notes):
    DESIGNS[env] = dict(task=task, critical=critical, reasoning=reasoning, phases=phases, notes=notes)


def phase(k, name, instruction, fields):
    return dict(k=k, name=name, instruction=instruction, fields=fields)


# 1o_10b_vs_1r: 11 agents (Banelings 0-9, Overseer 10), 7 actions, obs as SMAC's (same order here).
banelings = list(range(10))
design(
    "smaclite:1o_10b_vs_1r",
    "1o_10b_vs_1r",
    [62, 63, 67, 68],
    "Their choice: where the Overseer and the Roach are (absolute x and y of each); the Banelings "
    "cannot see the Roach, so its position is what the messages must make recoverable.",
    [
        phase(0, "paper_1o10b_phase0",
              "The Overseer alone talks: it tells every Baneling the Roach's offset from itself, whether "
              "it can attack the Roach, and who is speaking.",
              [field("overseer_roach", "Overseer's view of the Roach: relative x, relative y, the attack-available flag "
                     "(their code calls obs 4 'visible'), then the sender's id one-hot",
                     concat(obs(6, 7, 4), SENDER_ID), senders=[10], receivers={"agents": banelings})]),
        phase(1, "paper_1o10b_phase1",
              "The Overseer adds its previous action and the offsets of all ten Banelings as it sees them, "
              "so a Baneling can place itself relative to the Overseer.",
              [field("overseer_last_action", "the Overseer's previous action, one-hot (7)", LAST_ACTION,
                     senders=[10], receivers={"agents": banelings}),
               field("overseer_to_banelings", "relative x and y of teammate slots 0-9 (Banelings 0-9) seen by the Overseer",
                     obs(*[d for i in range(10) for d in (14 + 7 * i, 15 + 7 * i)]),
                     senders=[10], receivers={"agents": banelings})]),
        phase(2, "paper_1o10b_phase2",
              "The Overseer sends an anchor for its own position (a constant zero in their code), the Roach "
              "offset added to that anchor, how recently it could attack the Roach within the last ten "
              "steps, and which Banelings it sees.",
              [field("overseer_anchor", "the Overseer's 'canonical' x and y: constant 0 in their code (placeholder)",
                     concat(const(0.0), const(0.0)), senders=[10], receivers={"agents": banelings}),
               field("roach_from_anchor", "anchor (0) + Roach relative x and y", add(const(0.0), obs(6, 7)),
                     senders=[10], receivers={"agents": banelings}),
               field("roach_recency",
                     "1 - (last step index in the 10-step window with obs 4 > 0.5) / 9; 1 when never "
                     "(their max over an all-zero mask gives index 0)",
                     # index of the latest step j (0 oldest .. 9 now) with the flag: 9 - (steps back to it).
                     # Written as: 1 - max_j(j * flag_j) / 9, flag_j = gt(obs4 at t-(9-j), 0.5).
                     sub(const(1.0), mul(const(1.0 / 9.0), {"max": [
                         mul(const(9.0), gt(obs(4), const(0.5))),
                         {"max": [mul(const(8.0), past_steps(gt(obs(4), const(0.5)), 1)),
                          {"max": [mul(const(7.0), past_steps(gt(obs(4), const(0.5)), 2)),
                           {"max": [mul(const(6.0), past_steps(gt(obs(4), const(0.5)), 3)),
                            {"max": [mul(const(5.0), past_steps(gt(obs(4), const(0.5)), 4)),
                             {"max": [mul(const(4.0), past_steps(gt(obs(4), const(0.5)), 5)),
                              {"max": [mul(const(3.0), past_steps(gt(obs(4), const(0.5)), 6)),
                               {"max": [mul(const(2.0), past_steps(gt(obs(4), const(0.5)), 7)),
                                mul(const(1.0), past_steps(gt(obs(4), const(0.5)), 8))]}]}]}]}]}]}]}]})),
                     senders=[10], receivers={"agents": banelings}),
               field("baneling_visible", "visible flags of teammate slots 0-9 (Banelings 0-9) seen by the Overseer",
                     obs(*[12 + 7 * i for i in range(10)]), senders=[10], receivers={"agents": banelings})]),
    ],
    ["Their obs 4 is SMAC's 'can attack the enemy' flag; their code and docstrings call it 'visible'. "
     "The translation reads the same dim (4), so it carries what their code carried.",
     "Phase 2's step-index term reads the window from step t-9 (their time_seq = 10); "
     "the steps before the episode hold -1 in both codes, which never passes > 0.5.",
     "Phase 2's anchor is a constant 0 in their code; it is kept as two const columns and added to "
     "the Roach offset, so `lmac protocol check --dataset` reports it as constant."],
)

# 2o_20b_vs_2r: 22 agents (Banelings 0-19, Overseers 20, 21), 8 actions.
ov2 = [20, 21]


def roach_fields():
    return concat(obs(4, 6, 7), obs(12, 14, 15))


design(
    "smaclite:2o_20b_vs_2r",
    "2o_20b_vs_2r",
    [133, 134, 138, 139, 122, 123, 128, 129],
    "Their choice: both Roaches' absolute x and y (what the Banelings lack) and both Overseers' "
    "absolute x and y (the reference the Roach offsets are measured from).",
    [
        phase(0, "paper_2o20b_phase0",
              "Each Overseer tells everyone else what it sees of both Roaches (the attack-available flag "
              "their code calls 'visible', relative x and y) and who it is.",
              [field("roaches", "Roach 0 then Roach 1 as seen by the Overseer: obs 4, 6, 7 and 12, 14, 15, then the sender id",
                     concat(roach_fields(), SENDER_ID), senders=ov2)]),
        phase(1, "paper_2o20b_phase1",
              "Each Overseer adds which directions it can move in and its previous action.",
              [field("overseer_moves", "can-move flags north, south, east, west (obs 0-3)", obs_slice(0, 4), senders=ov2),
               field("overseer_last_action", "the Overseer's previous action, one-hot (8)", LAST_ACTION, senders=ov2)]),
        phase(2, "paper_2o20b_phase2",
              "Each Overseer replays its last nine steps (previous action and both Roach readings per "
              "step, oldest first) and the offset to the other Overseer nine steps ago.",
              [field(f"history_t{j}", f"{j} steps back: previous action one-hot (8), Roach 0 obs 4, 6, 7, Roach 1 obs 12, 14, 15",
                     past_steps(concat(LAST_ACTION, roach_fields()), j), senders=ov2)
               for j in range(9, 0, -1)]
              + [field("anchor", "obs 162, 163 nine steps back (teammate slot 20's relative x, y: the other Overseer; "
                       "their code calls it the sender's own position at t = 0)",
                       past_steps(obs(162, 163), 9), senders=ov2)]),
    ],
    ["Their 'o[:, 0]' in phase 2 is the oldest step of the 10-step window (t-9), not the episode's "
     "first step; the translation reads t-9 as their code does.",
     "Obs 162, 163 are teammate slot 20's relative position (for each Overseer, the other Overseer), "
     "not the sender's own position as their comment says; the same dims are read.",
     "In their history the previous action at the episode's first step is -1 in every column; in lmac it is "
     "0 there (-1 only before the episode)."],
)

# 5z_vs_1ul: 5 Zealots, 7 actions; their o = obs(36) | last action(7) | id(5).
design(
    "smaclite:5z_vs_1ul",
    "5z_vs_1ul",
    list(range(25)) + [25, 26, 27],
    "Their choice: every Zealot's health, cooldown, x, y and shield, and the Ultralisk's health, x and y.",
    [
        phase(0, "paper_5z_phase0",
              "Every Zealot broadcasts its reading of the Ultralisk gated by obs 4, its own health, its "
              "previous action and its id.",
              [field("ultralisk", "obs 5, 6, 7 each times obs 4 (their names: relative x, y, distance, gated by 'visible')",
                     mul(obs(5, 6, 7), obs(4))),
               field("own_health", "obs 34, own health", obs(34)),
               field("last_action", "previous action, one-hot (7)", LAST_ACTION),
               field("sender_id", "the sender's id one-hot (5)", SENDER_ID)]),
        phase(1, "paper_5z_phase1",
              "Every Zealot estimates its own position as minus the offset of the first teammate it sees, "
              "adds its shield, a ready flag (can attack and last action was stop or attack), and the "
              "Ultralisk's readings placed at that estimate.",
              [field("own_position", "minus (relative x, y) of the first visible teammate slot (0 when none)",
                     neg(add(add(mul(obs(10), obs(12, 13)),
                                 mul(mul(sub(const(1.0), obs(10)), obs(16)), obs(18, 19))),
                             add(mul(mul(mul(sub(const(1.0), obs(10)), sub(const(1.0), obs(16))), obs(22)), obs(24, 25)),
                                 mul(mul(mul(mul(sub(const(1.0), obs(10)), sub(const(1.0), obs(16))), sub(const(1.0), obs(22))), obs(28)),
                                     obs(30, 31)))))),
               field("own_shield", "obs 35", obs(35)),
               field("ready", "obs 4 times (previous action was stop or attack)",
                     mul(obs(4), gt(add(pick(LAST_ACTION, 7, 6), pick(LAST_ACTION, 7, 1)), const(0.0)))),
               field("ultralisk_placed",
                     "(own position estimate + obs 5, 6 gated by obs 4) gated by obs 4; obs 8, 9 gated by obs 4; obs 4",
                     concat(
                         mul(add(neg(add(add(mul(obs(10), obs(12, 13)),
                                             mul(mul(sub(const(1.0), obs(10)), obs(16)), obs(18, 19))),
                                         add(mul(mul(mul(sub(const(1.0), obs(10)), sub(const(1.0), obs(16))), obs(22)), obs(24, 25)),
                                             mul(mul(mul(mul(sub(const(1.0), obs(10)), sub(const(1.0), obs(16))), sub(const(1.0), obs(22))), obs(28)),
                                                 obs(30, 31))))),
                                 mul(obs(5, 6), obs(4))), obs(4)),
                         mul(obs(8, 9), obs(4)),
                         obs(4)))]),
        phase(2, "paper_5z_phase2",
              "Every Zealot replays, for each of its last nine steps (oldest first), obs 0 and 1 (which "
              "their code took for absolute x and y), its health, its shield and the first column of its "
              "previous action (which their code took for the weapon cooldown).",
              [field("hist_obs0", "obs 0 at t-9 .. t-1", concat(*[past_steps(obs(0), j) for j in range(9, 0, -1)])),
               field("hist_obs1", "obs 1 at t-9 .. t-1", concat(*[past_steps(obs(1), j) for j in range(9, 0, -1)])),
               field("hist_health", "obs 34 at t-9 .. t-1", concat(*[past_steps(obs(34), j) for j in range(9, 0, -1)])),
               field("hist_shield", "obs 35 at t-9 .. t-1", concat(*[past_steps(obs(35), j) for j in range(9, 0, -1)])),
               field("hist_noop", "previous-action column 0 (no-op) at t-9 .. t-1",
                     concat(*[past_steps(pick(LAST_ACTION, 7, 0), j) for j in range(9, 0, -1)]))]),
    ],
    ["Their labels for the enemy block are shifted by one: they read obs 4 as 'visible', 5/6 as relative x/y and "
     "7 as distance, where SMAC's order (and ours) is can-attack, distance, relative x, relative y, health. "
     "The translation reads the dims their code read.",
     "Phase 1 in the archive cannot run as written: it expands the 9-column message to 22 columns "
     "(`expand(B, N, N, 22)`), a shape error in PyTorch. The translation is the 9-column message the rest of the "
     "function builds.",
     "Phase 1's 'first visible teammate' (an argmax over the visible flags) is written as products of "
     "(1 - flag) terms, exact for 0/1 flags.",
     "Phase 2's 'absolute x, y' are obs 0 and 1 (can move north / south) and 'cooldown' is the previous action's "
     "no-op column (their o[36]); the same dims are read."],
)

# bane_vs_hM: 3 Banelings, 8 actions; their o = obs(31) | last action(8) | id(3).
design(
    "smaclite:bane_vs_hM",
    "bane_vs_hM",
    [0, 2, 3, 6, 8, 9, 12, 14, 15, 18, 19, 20],
    "Their choice: each Baneling's health, x and y, and the Hydralisk's health, x and y.",
    [
        phase(0, "paper_bane_phase0",
              "Every Baneling broadcasts the Hydralisk's relative x and y, its own obs 29 and its id.",
              [field("hydralisk_and_self", "obs 6, 7 (Hydralisk relative x, y), obs 29 (their 'own health'; ours: own unit-type bit 0), sender id",
                     concat(obs(6, 7, 29), SENDER_ID))]),
        phase(1, "paper_bane_phase1",
              "Every Baneling broadcasts three visibility-style flags, its move flags, a timestamp that "
              "is always zero, and the first seven columns of its previous action.",
              [field("flags", "obs 4 (Hydralisk attack-available), 16 and 22 (teammate slots 0 and 1 visible)", obs(4, 16, 22)),
               field("moves", "can-move flags (obs 0-3)", obs_slice(0, 4)),
               field("timestamp", "constant 0 in their code (placeholder)", const(0.0)),
               field("last_action_7", "previous-action columns 0-6 (their o[31:38] drops the eighth)",
                     picks(LAST_ACTION, 8, range(7)))]),
        phase(2, "paper_bane_phase2",
              "Every Baneling broadcasts ten-step averages of its move flags and of two previous-action "
              "columns (attack Hydralisk, no-op), teammate slot 0's offset gated by its visibility, and a "
              "freshness value that is always one.",
              [field("move_rates", "mean over 10 steps of obs 0-3", window("mean", 10, obs_slice(0, 4))),
               field("attack_rate", "mean over 10 steps of previous-action column 6", window("mean", 10, pick(LAST_ACTION, 8, 6))),
               field("noop_rate", "mean over 10 steps of previous-action column 0", window("mean", 10, pick(LAST_ACTION, 8, 0))),
               field("teammate0", "obs 18, 19 times obs 16", mul(obs(18, 19), obs(16))),
               field("freshness", "(T-1)/max(T-1,1) = 1 in their code (placeholder)", const(1.0))]),
    ],
    ["Their obs 29 is called 'own health' in their code; in SMAC's order (and ours) own health is obs 28 and obs 29 "
     "is the own unit-type bit. The translation reads 29.",
     "Phase 1's timestamp (0) and phase 2's freshness (1) are constants in their code and stay constants here.",
     "The archive also holds 'imp_state_select copy.py' (an earlier reply); the design uses imp_state_select.py."],
)

# LBF 8x8, 2 agents: their o = grid obs(27) | last action(6) | id(2); ours = the same 27 grid values | own row, col.
non_centre = [0, 1, 2, 3, 5, 6, 7, 8]


def field_cells(side):
    pad = side + 2
    return [layer * pad * pad + r * pad + c for layer in range(3) for r in range(1, side + 1) for c in range(1, side + 1)]


def seen_since(cell):
    """For one view cell: how many steps ago (1..9) it last held a value > 0.5, 0 when it holds one
    now or held none in the last nine steps.

    Their buffer keeps, per cell empty now, the most recent step back with a value > 0.5; the
    count of leading unseen steps, 1 + sum over j=1..8 of (not seen in steps 1..j), is that step.
    Window max over k=j+1 includes the current step, which is 0 for the cells that count."""
    now_empty = gt(const(0.5), obs(cell))
    seen = lambda j: window("max", j + 1, gt(obs(cell), const(0.5)))
    steps = add(const(1.0), rsum(concat(*[sub(const(1.0), seen(j)) for j in range(1, 9)])))
    return mul(mul(now_empty, seen(9)), steps)


design(
    "lbf:8x8-2p-2f-s1-coop",
    "Foraging-8x8-2p-2f-s1True",
    field_cells(8),
    "Their choice: every field cell (not the wall padding) of the three state layers (agents, food, access).",
    [
        phase(0, "paper_lbf8_phase0",
              "Each agent sends the other its id, its previous action, and the food and access layers of its 3x3 view.",
              [field("sender_id", "sender id one-hot (2)", SENDER_ID),
               field("last_action", "previous action one-hot (6)", LAST_ACTION),
               field("food_view", "food layer of the 3x3 view (obs 9-17)", obs_slice(9, 18)),
               field("access_view", "access layer of the 3x3 view (obs 18-26)", obs_slice(18, 27))]),
        phase(1, "paper_lbf8_phase1",
              "Each agent sends its position normalised to [0, 1]; their code fills it with zeros, so both columns are constant.",
              [field("position", "constant 0, 0 in their code (placeholder; our obs 27, 28 hold the real position but theirs had none)",
                     concat(const(0.0), const(0.0)))]),
        phase(2, "paper_lbf8_phase2",
              "Each agent sends how often it took each action in the last ten steps, for every view cell "
              "empty now whether food or an agent was there in the last nine steps and how long ago, and a "
              "timestamp that is always nine.",
              [field("action_counts", "sum over 10 steps of the previous-action one-hot", window("sum", 10, LAST_ACTION)),
               field("food_seen", "per non-centre view cell of the food layer: steps since food was last there (0: there now, or not in 9 steps)",
                     concat(*[seen_since(9 + c) for c in non_centre])),
               field("agent_seen", "per non-centre view cell of the agent layer: steps since an agent was last there (0: there now, or not in 9 steps)",
                     concat(*[seen_since(c) for c in non_centre])),
               field("timestamp", "(T-1) mod 10 = 9 in their code (placeholder)", const(9.0))]),
    ],
    ["Observation mapping: their per-agent input is the 3x3x3 grid view (27 values: agent, food, access layers, "
     "row-major), then the previous action one-hot (6) and the agent id one-hot (2) -- 35 values; their docstrings "
     "say 39, the 11x11 size. Our obs has the same 27 grid values first, then the agent's own row and column. "
     "So their o[0:27] is our obs 0-26, their o[27:33] is `last_action` and their o[33:35] is `sender_one_hot`. "
     "Their grid holds levels divided by the maximum level; ours holds the levels.",
     "State mapping: their state is the same padded 10x10 grid in three layers as lbf:8x8-2p-2f-s1-coop's "
     "(not the -entity variant), so the critical dims are the same indices.",
     "Phase 2's event buffer (up to three most recent sightings outside the current view, sorted by age, each "
     "[type, dx, dy, age]) needs sorting and top-3 selection, which lmac's language has not. The translation sends "
     "what the buffer is built from, per non-centre cell and layer: how many steps ago it last held a value > 0.5 "
     "while empty now (0 when not seen in nine steps); type, dx and dy are the column's position. 16 columns "
     "instead of 12, and every sighting rather than the three most recent.",
     "Phase 1 sends constant zeros as in their code; phase 2's timestamp is the constant 9 (their T is always 10)."],
)

# LBF 11x11, 6 agents: their o = grid obs(27) | last action(6) | id(6) = 39.
design(
    "lbf:11x11-6p-4f-s1-coop",
    "Foraging-11x11-6p-4f-s1True",
    field_cells(11),
    "The archive has no imp_state_select.py for this task; the 363 dims are those its "
    "feedback_data_summary.json reports on: every field cell of the three state layers, as for 8x8.",
    [
        phase(0, "paper_lbf11_phase0",
              "Every agent broadcasts its id, the food and access layers of its 3x3 view and its previous action.",
              [field("sender_id", "sender id one-hot (6)", SENDER_ID),
               field("food_view", "food layer of the 3x3 view (obs 9-17)", obs_slice(9, 18)),
               field("access_view", "access layer of the 3x3 view (obs 18-26)", obs_slice(18, 27)),
               field("last_action", "previous action one-hot (6)", LAST_ACTION)]),
        phase(1, "paper_lbf11_phase1",
              "Every agent broadcasts what their code takes for its position: obs 0 and 1, the top-left and "
              "top-centre cells of the agent layer of its view.",
              [field("position", "obs 0, 1 (agent layer, view row 0, cols 0 and 1)", obs(0, 1))]),
        phase(2, "paper_lbf11_phase2",
              "Every agent broadcasts a dead-reckoned position from its last three moves (starting at 0.5, "
              "0.5; values at t-1 and t), its food view at t-2 and t-1, and the non-centre cells of its "
              "agent view at t-2, t-1 and t.",
              [field("track", "0.5 + summed move deltas: (x, y) after the moves read at t-2 and t-1, then also t",
                     concat(
                         add(const(0.5), add(past_steps(dx(), 2), past_steps(dx(), 1))),
                         add(const(0.5), add(past_steps(dy(), 2), past_steps(dy(), 1))),
                         add(const(0.5), add(add(past_steps(dx(), 2), past_steps(dx(), 1)), dx())),
                         add(const(0.5), add(add(past_steps(dy(), 2), past_steps(dy(), 1)), dy())))),
               field("food_history", "food layer (obs 9-17) at t-2 then t-1",
                     concat(past_steps(obs_slice(9, 18), 2), past_steps(obs_slice(9, 18), 1))),
               field("agent_history", "non-centre agent-layer cells at t-2, t-1, t",
                     concat(past_steps(obs(*non_centre), 2), past_steps(obs(*non_centre), 1), obs(*non_centre)))]),
    ],
    ["Observation mapping as for 8x8: their o[0:27] is our obs 0-26, o[27:33] the previous action, o[33:39] the id.",
     "Phase 1's 'position' reads obs 0 and 1 (their function's default indices), which are agent-layer cells of the "
     "view, not a position; the translation reads the same dims. Our obs 27, 28 (the real position) are not used.",
     "Phase 2 reads the previous action at t-2, t-1 and t (their o[-4:] also takes t-3, whose delta their "
     "trajectory never uses). Before the episode the previous action is -1 in every column in both codes, so its "
     "move delta is 0; at the episode's first step theirs is -1 (delta 0) and ours 0 (delta 0): the same."],
)

# GRF academy_3_vs_1_with_keeper: 3 agents, 19 actions; their o = obs(26) | last action(19) | id(3),
# their obs the same 26 values in the same order as ours (CDS's simple observation).
rel_gk_cb = obs_slice(12, 16)
design(
    "grf:academy_3_vs_1_with_keeper",
    "academy_3_vs_1_with_keeper",
    list(range(26)),
    "Their choice: the whole state (teammates' positions and directions, opponents' positions and directions, ball).",
    [
        phase(0, "paper_grf3v1_phase0",
              "Every player broadcasts its position and direction, the ball's offset and direction, its "
              "teammates' and opponents' offsets, four flags from its previous action (dribble, any pass, "
              "shot, sprint) and its id.",
              [field("ego", "own position (obs 0, 1), own direction (obs 6, 7)", obs(0, 1, 6, 7)),
               field("ball", "ball offset (obs 20, 21), obs 23, 24 (ball direction x, y)", obs(20, 21, 23, 24)),
               field("others", "teammate offsets (obs 2-5), opponent offsets (obs 12-15)", concat(obs_slice(2, 6), rel_gk_cb)),
               field("action_flags", "previous action: start dribbling; any of long/high/short pass (clipped to 1); shot; sprint",
                     concat(pick(LAST_ACTION, 19, 17),
                            clip(rsum(mul(LAST_ACTION, consts([1.0 if a in (9, 10, 11) else 0.0 for a in range(19)]))), 0.0, 1.0),
                            pick(LAST_ACTION, 19, 12), pick(LAST_ACTION, 19, 13))),
               field("sender_id", "sender id one-hot (3)", SENDER_ID)]),
        phase(1, "paper_grf3v1_phase1",
              "Every player broadcasts absolute positions it computes from its own: ball (with height), "
              "both opponents and both teammates; a weighted score of its previous action; and its id "
              "(their 'cm flags' are the id columns).",
              [field("ball_abs", "own position + ball offset; ball height (obs 22)", concat(add(obs(0, 1), obs(20, 21)), obs(22))),
               field("opponents_abs", "own position + goalkeeper offset, own position + centre-back offset",
                     concat(add(obs(0, 1), obs(12, 13)), add(obs(0, 1), obs(14, 15)))),
               field("teammates_abs", "own position + teammate slot 0 and slot 1 offsets",
                     concat(add(obs(0, 1), obs(2, 3)), add(obs(0, 1), obs(4, 5)))),
               field("action_score", "previous action weighted (dribble 1, passes 0.8, shot 1.2, sprint 0.5), clipped to [0, 1]",
                     clip(rsum(mul(LAST_ACTION, consts([{17: 1.0, 9: 0.8, 10: 0.8, 11: 0.8, 12: 1.2, 13: 0.5}.get(a, 0.0)
                                                         for a in range(19)]))), 0.0, 1.0)),
               field("cm_flags", "their o[45:48]: the sender id one-hot (3)", SENDER_ID)]),
        phase(2, "paper_grf3v1_phase2",
              "Every player broadcasts its teammates' directions and whether it sees them, their velocities "
              "over the ten-step window, whether it sees each opponent and the ball, and the ball's and its "
              "own velocities over the window.",
              [field("teammate_dirs", "teammate slots' directions (obs 8-11)", obs_slice(8, 12)),
               field("teammate_seen", "sum |offset| > 1e-5 for teammate slots 0 and 1",
                     concat(gt(rsum(abs_(obs(2, 3))), const(1e-5)), gt(rsum(abs_(obs(4, 5))), const(1e-5)))),
               field("teammate_vel", "(own position + teammate offset) now minus 9 steps back, / 9, slots 0 and 1",
                     mul(const(1.0 / 9.0), concat(window("delta", 10, add(obs(0, 1), obs(2, 3))),
                                                  window("delta", 10, add(obs(0, 1), obs(4, 5)))))),
               field("opponent_seen", "sum |offset| > 1e-5 for the goalkeeper and the centre back",
                     concat(gt(rsum(abs_(obs(12, 13))), const(1e-5)), gt(rsum(abs_(obs(14, 15))), const(1e-5)))),
               field("ball_seen", "sum |ball offset| > 1e-5", gt(rsum(abs_(obs(20, 21))), const(1e-5))),
               field("ball_vel", "(own position + ball offset) now minus 9 steps back, / 9",
                     mul(const(1.0 / 9.0), window("delta", 10, add(obs(0, 1), obs(20, 21))))),
               field("ego_vel", "own position now minus 9 steps back, / 9", mul(const(1.0 / 9.0), window("delta", 10, obs(0, 1))))]),
    ],
    ["Observation mapping: their obs is the same 26 values in the same order as ours (position, teammate offsets, "
     "directions, opponents, ball); their o[26:45] is the previous action and o[45:48] the id.",
     "Their velocities divide the change across the 10-step window by T - 1 = 9; the steps before the episode hold "
     "-1 in both codes, so early in an episode the velocity is measured from -1 as theirs was.",
     "The 'seen' flags are always 1 in practice (GRF observations are full); they are kept as their code computes them."],
)

# GRF academy_run_pass_and_shoot_with_keeper: 2 agents; their o = obs(22) | last action(19) | id(2).
design(
    "grf:academy_run_pass_and_shoot_with_keeper",
    "academy_run_pass_and_shoot_with_keeper",
    list(range(22)),
    "Their choice: the whole state.",
    [
        phase(0, "paper_grf_rps_phase0",
              "Each player sends the other its position, direction, the ball's offset and direction, its "
              "previous action, the centre back's offset and direction, the goalkeeper's offset and its id.",
              [field("ego", "own position (obs 0, 1), own direction (obs 4, 5)", obs(0, 1, 4, 5)),
               field("ball", "ball offset (obs 16, 17), ball direction (obs 19-21)", concat(obs(16, 17), obs_slice(19, 22))),
               field("last_action", "previous action one-hot (19)", LAST_ACTION),
               field("centre_back", "centre-back offset (obs 10, 11) and direction (obs 14, 15)", obs(10, 11, 14, 15)),
               field("goalkeeper", "goalkeeper offset (obs 8, 9)", obs(8, 9)),
               field("sender_id", "sender id one-hot (2)", SENDER_ID)]),
        phase(1, "paper_grf_rps_phase1",
              "Each player sends the goalkeeper's absolute position and direction, the centre back's "
              "absolute position and direction placed in one of two slots by the sender's id (their code "
              "took the id columns for 'is centre back 1/2'), and the ball's absolute position.",
              [field("goalkeeper", "own position + goalkeeper offset; goalkeeper direction (obs 12, 13)",
                     concat(add(obs(0, 1), obs(8, 9)), obs(12, 13))),
               field("centre_back_slot0", "(own position + centre-back offset, centre-back direction) times id column 0",
                     mul(concat(add(obs(0, 1), obs(10, 11)), obs(14, 15)), pick(SENDER_ID, 2, 0))),
               field("centre_back_slot1", "the same times id column 1",
                     mul(concat(add(obs(0, 1), obs(10, 11)), obs(14, 15)), pick(SENDER_ID, 2, 1))),
               field("ball_abs", "own position + ball offset", add(obs(0, 1), obs(16, 17)))]),
        phase(2, "paper_grf_rps_phase2",
              "Each player sends its change of position and direction over the last three steps, its "
              "teammate's offset and direction and their change, whether it sees the centre back (and a "
              "second centre back that does not exist: constant 0), the ball's height and change of "
              "absolute position, how often it took each action in ten steps, and three seen flags.",
              [field("ego_change", "obs 0, 1, 4, 5 now minus 3 steps back", window("delta", 4, obs(0, 1, 4, 5))),
               field("teammate", "teammate offset and direction (obs 2, 3, 6, 7)", obs(2, 3, 6, 7)),
               field("teammate_change", "obs 2, 3, 6, 7 now minus 3 steps back", window("delta", 4, obs(2, 3, 6, 7))),
               field("cb_flags", "sum |obs 10, 11, 14, 15| > 0; constant 0 for the second centre back (placeholder)",
                     concat(gt(rsum(abs_(obs(10, 11, 14, 15))), const(0.0)), const(0.0))),
               field("ball_height", "obs 18", obs(18)),
               field("ball_change", "(own position + ball offset, ball height) now minus 3 steps back",
                     window("delta", 4, concat(add(obs(0, 1), obs(16, 17)), obs(18)))),
               field("action_rates", "mean over 10 steps of the previous-action one-hot", window("mean", 10, LAST_ACTION)),
               field("seen_flags", "teammate seen (sum |obs 2, 3, 6, 7| > 0), centre back seen, second centre back (constant 0)",
                     concat(gt(rsum(abs_(obs(2, 3, 6, 7))), const(0.0)),
                            gt(rsum(abs_(obs(10, 11, 14, 15))), const(0.0)), const(0.0)))]),
    ],
    ["Observation mapping: their obs is the same 22 values in the same order as ours; o[22:41] is the previous "
     "action and o[41:43] the id.",
     "Phase 1 gates the centre back's values by the sender's id columns (their o[41], o[42], which their code names "
     "'is centre back 1/2'); the translation gates by the same id columns.",
     "Phase 2's 'three steps back' is their back_t = window - 4 (t-3), a window delta with k = 4.",
     "The second centre back's flag is a constant 0 in their code (there is one centre back) and stays constant."],
)


# ---- writing ----


def write():
    for env, d in DESIGNS.items():
        out = ROOT / env.replace(":", "_")
        for ph in d["phases"]:
            protocol = {
                "name": ph["name"],
                "phase": ph["k"],
                "message_design_instruction": ph["instruction"],
                "critical_state_dims": d["critical"],
                "critical_state_reasoning": d["reasoning"],
                # Their messages carry no separate sender block: a field lists the id where their code
                # put one in the message.
                "sender_one_hot": False,
                "history_padding": "minus_one",
                "fields": ph["fields"],
            }
            pd = out / f"phase{ph['k']}"
            pd.mkdir(parents=True, exist_ok=True)
            (pd / "protocol.json").write_text(json.dumps(protocol, indent=2) + "\n")
            (pd / "source.txt").write_text(f"{ARCHIVE}/{d['task']}/{SOURCES[ph['k']]}\n")
        options = {
            "env": env,
            "designer": "paper: the LMAC authors' GPT-4.1 replies, translated by hand into lmac's protocol language",
            "task": d["task"],
            "source": f"{ARCHIVE}/{d['task']}/",
            "critical_dims_source": f"{ARCHIVE}/{d['task']}/"
            + ("imp_state_select.py" if d["task"] != "Foraging-11x11-6p-4f-s1True" else "feedback_data_summary.json"),
            "phases": [f"phase{ph['k']}/protocol.json" for ph in d["phases"]],
            "notes": d["notes"],
        }
        (out / "options.json").write_text(json.dumps(options, indent=2) + "\n")
        lines = [f"# {env}: the LMAC authors' design for {d['task']}", "",
                 f"Translated by hand from `{options['source']}` (nothing of theirs is run or copied).", "",
                 f"Critical state dims ({len(d['critical'])}; from `{options['critical_dims_source'].rsplit('/', 1)[1]}`): "
                 + d["reasoning"], ""]
        for ph in d["phases"]:
            lines += [f"## Phase {ph['k']} (`phase{ph['k']}/protocol.json`, from `{SOURCES[ph['k']]}`)", "", ph["instruction"], ""]
        lines += ["## Where the translation differs or could not follow", ""] + [f"- {n}" for n in d["notes"]] + [""]
        (out / "README.md").write_text("\n".join(lines))


SOURCES = {0: "comm_init.py", 1: "comm_update.py", 2: "comm_update_timestep_wise2.py"}

if __name__ == "__main__":
    write()
    print(f"wrote {len(DESIGNS)} designs under {ROOT}")
