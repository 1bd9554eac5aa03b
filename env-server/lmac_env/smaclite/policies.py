"""Reference policies for the SMAC-Comm re-implementation and the win-rate check.

- ``random``: uniform over the available actions.
- ``local``: the same tactics without shared information (each agent acts on what it sees).
- ``scripted``: a hand-written policy that reads the simulator's privileged state (true
  positions of every unit, the Roach assignment, the Ultralisk's position), i.e. exactly the
  information a communication protocol would have to share. It winning often while the random
  policy almost never does shows that the maps are solvable and that shared information is
  what it takes.

    python -m lmac_env.smaclite.policies winrates [--episodes 200] [--envs 32] [--seed 0]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ..core import Batch
from .env import SmacliteVecEnv
from .maps import MAPS

_DIRV = np.array([[0, 1], [0, -1], [1, 0], [-1, 0]], dtype=np.float64)  # actions 2..5


def random_actions(env: SmacliteVecEnv, out: Batch, rng: np.random.Generator) -> np.ndarray:
    av = out.avail.astype(np.float64)
    p = av / av.sum(-1, keepdims=True)
    return (p.cumsum(-1) > rng.random(p.shape[:2])[..., None]).argmax(-1)


def _greedy_move(env: SmacliteVecEnv, out: Batch, goal: np.ndarray) -> np.ndarray:
    """For every agent, the available move (2..5) that brings it closest to goal (B,N,2)."""
    pa = env.pos[:, :env.N]
    spd = env.speed[:env.N][None, :, None]
    cand = pa[:, :, None, :] + _DIRV[None, None] * spd[..., None]            # (B,N,4,2)
    d = np.linalg.norm(cand - goal[:, :, None, :], axis=-1)
    d = np.where(out.avail[..., 2:6] > 0, d, np.inf)
    return 2 + d.argmin(-1)


_FIELDS: dict = {}


def _field(walk: np.ndarray, cell: tuple[int, int]) -> np.ndarray:
    """Breadth-first walking distance (in cells, 4-neighbourhood) to `cell` on the mask."""
    key = (id(walk), cell)
    f = _FIELDS.get(key)
    if f is None:
        f = np.full(walk.shape, np.inf)
        f[cell] = 0
        frontier = [cell]
        while frontier:
            nxt = []
            for y, x in frontier:
                for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < 32 and 0 <= xx < 32 and walk[yy, xx] and f[yy, xx] == np.inf:
                        f[yy, xx] = f[y, x] + 1
                        nxt.append((yy, xx))
            frontier = nxt
        _FIELDS[key] = f
    return f


def _path_move(env: SmacliteVecEnv, out: Batch, goal: np.ndarray) -> np.ndarray:
    """Like _greedy_move, but around the cliffs: follows the walking distance to the goal
    cell (privileged path planning), breaking ties by straight-line distance."""
    B, N = env.num_envs, env.N
    pa = env.pos[:, :N]
    spd = env.speed[:N][None, :, None]
    cand = pa[:, :, None, :] + _DIRV[None, None] * spd[..., None]            # (B,N,4,2)
    cand = np.clip(cand, 0, 31.999)
    eu = np.linalg.norm(cand - goal[:, :, None, :], axis=-1)
    score = eu.copy()
    gc = np.clip(np.floor(goal).astype(int), 0, 31)
    for b in range(B):
        for i in range(N):
            if not env.ground_a[i]:
                continue
            f = _field(env.walk, (int(gc[b, i, 1]), int(gc[b, i, 0])))
            cc = np.floor(cand[b, i]).astype(int)
            score[b, i] = f[cc[:, 1], cc[:, 0]] * 2.0 + eu[b, i] * 0.01
    score = np.where(out.avail[..., 2:6] > 0, score, np.inf)
    return 2 + score.argmin(-1)


def scripted_actions(env: SmacliteVecEnv, out: Batch, rng: np.random.Generator) -> np.ndarray:
    N, B = env.N, env.num_envs
    name = env.spec.name
    pa = env.pos[:, :N]
    alive = env.alive[:, :N]
    av = out.avail
    act = np.ones((B, N), np.int64)                   # stop
    if name == "bane_vs_hM":
        h = env.pos[:, N]                             # the Hydralisk (privileged position)
        d = np.linalg.norm(pa - h[:, None], axis=-1)
        reach = 3.0                                   # Hydralisk reach, centre to centre
        step = env.speed[0]
        staged = ~alive | (d - step <= reach + 0.02)
        go = staged.all(1, keepdims=True)
        mv = _greedy_move(env, out, np.broadcast_to(h[:, None], pa.shape))
        act = np.where(go | (d - step > reach + 0.02), mv, 1)
        act = np.where(av[..., 6] > 0, 6, act)
    elif name in ("1o_10b_vs_1r", "2o_20b_vs_2r"):
        E = env.E
        pr = env.pos[:, N:]                           # the Roaches (privileged positions)
        d = np.linalg.norm(pa[:, :, None] - pr[:, None], axis=-1)          # (B,N,E)
        bane = env.is_bane
        if E == 1:
            tgt = np.zeros((B, N), np.int64)
        else:  # send the ten Banelings relatively closest to Roach 0 there, the rest to 1
            key = np.where(bane, d[..., 0] - d[..., 1], np.inf)
            order = key.argsort(1)
            rank = np.empty_like(order)
            np.put_along_axis(rank, order, np.arange(N)[None], axis=1)
            tgt = np.where(rank < 10, 0, 1)
            ralive = env.alive[:, N:]
            tgt = np.where(ralive[np.arange(B)[:, None], tgt], tgt, 1 - tgt)
        goal = pr[np.arange(B)[:, None], tgt]
        # walk to the assigned Roach around the cliffs, attack as soon as it is in range
        act = _path_move(env, out, goal)
        att = av[np.arange(B)[:, None], np.arange(N)[None], 6 + tgt] > 0
        act = np.where(att, 6 + tgt, act)
        act = np.where(bane[None], act, 1)            # the Overseer holds still
    elif name == "5z_vs_1ul":
        u = env.pos[:, N]
        d = np.linalg.norm(pa - u[:, None], axis=-1)
        dm = np.where(alive, d, np.inf)
        nearest = dm.argmin(1)
        # pull back the Zealot the Ultralisk is about to strike when its shield is gone and a
        # teammate can take over; everybody else attacks
        life = env.hp[:, :N] + env.sh[:, :N]
        victim = np.zeros((B, N), bool)
        victim[np.arange(B), nearest] = True
        others_close = ((dm < 3.5).sum(1) >= 2)[:, None]
        retreat = victim & (env.sh[:, :N] < 1) & others_close & (life < 150)
        away = pa + (pa - u[:, None]) * 3.0
        mv = _greedy_move(env, out, away)
        act = np.where(av[..., 6] > 0, 6, _greedy_move(env, out, np.broadcast_to(
            u[:, None], pa.shape)))
        act = np.where(retreat, mv, act)
    act = np.where(alive, act, 0)
    # never emit an unavailable action
    ok = np.take_along_axis(av, act[..., None], -1)[..., 0] > 0
    return np.where(ok, act, np.where(alive, 1, 0))


def local_actions(env: SmacliteVecEnv, out: Batch, rng: np.random.Generator) -> np.ndarray:
    """The scripted policy's tactics without shared information: every agent acts on what it
    sees itself. bane_vs_hM: rush the Hydralisk without waiting for the others; 1o/2o: a
    Baneling heads for a Roach only once it sees it (within 9), otherwise wanders; 5z_vs_1ul:
    everybody attacks, nobody pulls back."""
    N, B = env.N, env.num_envs
    name = env.spec.name
    pa = env.pos[:, :N]
    alive = env.alive[:, :N]
    av = out.avail
    if name in ("bane_vs_hM", "5z_vs_1ul"):
        goal = np.broadcast_to(env.pos[:, N][:, None], pa.shape)
        act = np.where(av[..., 6] > 0, 6, _greedy_move(env, out, goal))
    else:
        pr = env.pos[:, N:]
        d = np.linalg.norm(pa[:, :, None] - pr[:, None], axis=-1)
        d = np.where(env.alive[:, None, N:], d, np.inf)
        seen = d < env.spec.sight_range
        tgt = d.argmin(-1)
        goal = pr[np.arange(B)[:, None], tgt]
        act = np.where(seen.any(-1), _path_move(env, out, goal), random_actions(env, out, rng))
        att = av[np.arange(B)[:, None], np.arange(N)[None], 6 + tgt] > 0
        act = np.where(att, 6 + tgt, act)
        act = np.where(env.is_bane[None], act, 1)
    act = np.where(alive, act, 0)
    ok = np.take_along_axis(av, act[..., None], -1)[..., 0] > 0
    return np.where(ok, act, np.where(alive, 1, 0))


POLICIES = {"random": random_actions, "scripted": scripted_actions, "local": local_actions}


def evaluate(variant: str, policy: str, episodes: int = 200, num_envs: int = 32,
             seed: int = 0) -> dict:
    env = SmacliteVecEnv(variant, num_envs, seed)
    out = Batch.allocate(env.schema, num_envs)
    rng = np.random.default_rng(seed + 1)
    fn = POLICIES[policy]
    env.reset(np.arange(num_envs), out)
    ret = np.zeros(num_envs)
    done_eps, wins, rets, lens = 0, 0, [], []
    while done_eps < episodes:
        env.step(fn(env, out, rng), out)
        ret += out.reward
        done = (out.terminated | out.truncated) > 0
        if done.any():
            take = np.flatnonzero(done)[:episodes - done_eps]
            wins += int(env.won[take].sum())
            rets += ret[take].tolist()
            lens += env.t[take].tolist()
            done_eps += take.size
            ret[done] = 0
            env.reset(np.flatnonzero(done), out)
    return dict(map=variant, policy=policy, episodes=done_eps, win_rate=wins / done_eps,
                mean_return=float(np.mean(rets)), mean_length=float(np.mean(lens)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lmac_env.smaclite.policies")
    ap.add_argument("command", choices=["winrates"])
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--envs", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--maps", nargs="*", default=list(MAPS))
    args = ap.parse_args(argv)
    print(f"{'map':21s} {'policy':9s} {'episodes':>8s} {'win rate':>8s} {'return':>7s} "
          f"{'length':>6s}")
    for m in args.maps:
        for p in ("scripted", "local", "random"):
            r = evaluate(m, p, args.episodes, args.envs, args.seed)
            print(f"{m:21s} {p:9s} {r['episodes']:8d} {r['win_rate']:8.3f} "
                  f"{r['mean_return']:7.2f} {r['mean_length']:6.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
