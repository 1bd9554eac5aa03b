"""Vectorized simulation of the SMAC-Comm maps (numpy over B environments).

This is a re-implementation, NOT StarCraft II: continuous 2-D positions on the map's walkable
mask, the units' health, shields, armour, weapons, cooldowns and ranges (units.py), resolved
once per SMAC step (8 game loops). Observations, state, available actions, rewards, agent order
and termination follow SMAC's ``StarCraft2Env`` with the SMAC-Comm settings (maps.py). Every
simplification is listed in README.md.

Order of events inside one step:
  1. agents act: moves (with wall sliding), attack orders (Banelings roll to the target and
     burst on contact; Zealots close in and strike when their cooldown allows);
  2. Baneling bursts damage every enemy ground unit within the splash radius;
  3. the enemy acts (Hydralisk/Roach: fire at the nearest target in reach; Ultralisk:
     attack-move; Medivac: heal the Hydralisk); Banelings killed here burst on death;
  4. regeneration, cooldowns; reward, termination, observations.
"""
from __future__ import annotations

import numpy as np

from ..core import Batch, Schema, VecEnv, schema_path
from ..sizes import SizeMismatch
from . import units as U
from .maps import (BANE_ENEMY_POINT, BANE_REGIONS, CLIFF_CORNERS, CLIFF_REGIONS, MAPS,
                   Z5_ATTACK_POINT, Z5_REGION, mask_from_rows, obs_layout, split_variant)

MAP_SIZE = 32.0
PAD = 4            # walkable mask padding (cells of "not walkable" around the map)
N_SUB = 3          # sub-steps of one move (<= 0.5 map units each) for wall checks
LOOPS = float(U.LOOPS_PER_STEP)
EPS = 1e-6
# action -> unit displacement direction (SMAC: 2 north +y, 3 south -y, 4 east +x, 5 west -x)
_DIRS = np.array([[0, 0], [0, 0], [0, 1], [0, -1], [1, 0], [-1, 0]], dtype=np.float64)


class SmacliteVecEnv(VecEnv):
    def __init__(self, variant: str, num_envs: int, seed: int = 0):
        v = split_variant(variant)
        spec = self.spec = MAPS[v.map_name]
        self.unit_data = v.unit_data
        self.state_last_action = v.state_last_action
        units = U.unit_data(v.unit_data)
        self.bane_damage, self.bane_bonus_light = U.BANE_BURST[v.unit_data]
        self.schema = Schema.load(schema_path(f"smaclite:{variant}"))
        lay = self.layout = obs_layout(spec, v.state_last_action)
        for k in ("obs_dim", "state_dim", "n_actions"):
            if getattr(self.schema, k) != lay[k]:
                raise SizeMismatch(f"{self.schema.path}: {k} = {getattr(self.schema, k)} but the "
                                 f"simulation produces {lay[k]}")
        self.num_envs = B = num_envs
        self.N = N = len(spec.agents)
        self.E = E = len(spec.enemies)
        self.A = lay["n_actions"]
        kinds = list(spec.agents) + list(spec.enemies)
        ut = [units[k] for k in kinds]
        f = lambda attr: np.array([getattr(u, attr) for u in ut], dtype=np.float64)
        self.max_hp, self.max_sh, self.armor = f("hp"), f("shield"), f("armor")
        self.radius, self.speed, self.regen = f("radius"), f("speed"), f("regen")
        self.sh_regen, self.sh_delay = f("shield_regen"), f("shield_delay")
        self.light = np.array([u.light for u in ut])
        self.air = np.array([u.air for u in ut])
        self.kind = np.array(kinds)
        self.types = ut
        self.is_bane = self.kind[:N] == "baneling"
        self.is_zealot = self.kind[:N] == "zealot"
        self.ground_a = ~self.air[:N]
        self.walk = mask_from_rows(list(spec.walkable))
        wp = np.zeros((32 + 2 * PAD, 32 + 2 * PAD), bool)
        wp[PAD:PAD + 32, PAD:PAD + 32] = self.walk
        self._wside = wp.shape[1]
        self._wflat = wp.reshape(-1)
        self.rng = np.random.default_rng(seed)
        # SMAC: max_reward = n_enemies * death value + win reward + sum of enemy hp + shields
        self.max_reward = E * 10.0 + 200.0 + float(self.max_hp[N:].sum() + self.max_sh[N:].sum())
        self.reward_scale = 20.0 / self.max_reward
        # dynamic state
        self.pos = np.zeros((B, N + E, 2))
        self.hp = np.zeros((B, N + E))
        self.sh = np.zeros((B, N + E))
        self.cd = np.zeros((B, N + E))          # weapon cooldown left, game loops
        self.since_dmg = np.zeros((B, N + E))   # steps since last damage (shield regen)
        self.alive = np.zeros((B, N + E), bool)
        self.last_action = np.zeros((B, N), np.int64)
        self.t = np.zeros(B, np.int64)
        self.won = np.zeros(B, bool)            # outcome of the episode that ended last step
        self.episodes = 0
        self.wins = 0
        self._ar = np.arange(B)
        self._others = np.array([[j for j in range(N) if j != i] for i in range(N)],
                                dtype=np.int64).reshape(N, N - 1)
        self._st_last_off = N * lay["st_al"] + E * lay["st_en"]
        # Where the state's one-hot last actions start (SMAC's state_last_action; the PettingZoo
        # adapter can drop them, as the LMAC authors' runs do); the state's end without them.
        self.state_last_action_offset = self._st_last_off
        # static parts of the observation/state
        tb = spec.unit_type_bits
        self._ally_type = np.zeros((N, tb), np.float32)
        self._enemy_type = np.zeros((E, tb), np.float32)
        if tb:
            self._ally_type[np.arange(N), spec.ally_type_id] = 1
            self._enemy_type[np.arange(E), spec.enemy_type_id] = 1

    # ------------------------------------------------------------------ geometry helpers
    def _walkable(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground walkability of the points (x, y); outside the map is not walkable."""
        xi = (x + PAD).astype(np.int64)      # x + PAD > 0 for every position that occurs
        yi = (y + PAD).astype(np.int64)
        idx = np.minimum(np.maximum(yi * self._wside + xi, 0), self._wflat.size - 1)
        return self._wflat[idx]

    def _move(self, p: np.ndarray, disp: np.ndarray, ground: np.ndarray) -> np.ndarray:
        """Move positions p (b,k,2) by disp (b,k,2); ground units slide along walls and stop
        at non-walkable cells, flyers only stay on the map."""
        step = disp / N_SUB
        gnd = np.broadcast_to(ground, p.shape[:2])
        for _ in range(N_SUB):
            c = p + step
            ok = self._walkable(c[..., 0], c[..., 1]) | ~gnd
            if not ok.all():
                okx = self._walkable(c[..., 0], p[..., 1])
                oky = self._walkable(p[..., 0], c[..., 1])
                cx = c.copy()
                cx[..., 1] = p[..., 1]
                cy = c.copy()
                cy[..., 0] = p[..., 0]
                slide = np.where(okx[..., None], cx, np.where(oky[..., None], cy, p))
                c = np.where(ok[..., None], c, slide)
            p = c
        if not gnd.all():
            p = np.where(gnd[..., None], p, np.minimum(np.maximum(p, 0.0), MAP_SIZE - EPS))
        return p

    # ------------------------------------------------------------------ damage helpers
    def _hit(self, b: np.ndarray, u: np.ndarray, raw: np.ndarray) -> None:
        """Apply one hit of `raw` damage to unit u in env b (arrays); shields absorb first,
        armour reduces the part that reaches life (min 0.5)."""
        sh = self.sh[b, u]
        to_sh = np.minimum(sh, raw)
        rest = raw - to_sh
        life = np.where(rest > 0, np.maximum(rest - self.armor[u], U.MIN_DAMAGE), 0.0)
        self.sh[b, u] = sh - to_sh
        self.hp[b, u] = self.hp[b, u] - life
        self.since_dmg[b, u] = 0

    def _burst(self, mask: np.ndarray) -> None:
        """Volatile Burst of the Banelings in mask (B,N) at their current positions."""
        if not mask.any():
            return
        N = self.N
        pa = self.pos[:, :N]
        pe = self.pos[:, N:]
        d = np.linalg.norm(pe[:, None, :, :] - pa[:, :, None, :], axis=-1)   # (B,N,E)
        rad = U.BANE_SPLASH + self.radius[N:]
        hit = mask[:, :, None] & (d <= rad) & (self.alive[:, N:] & ~self.air[N:])[:, None, :]
        per = np.maximum(self.bane_damage + self.bane_bonus_light * self.light[N:] - self.armor[N:],
                         U.MIN_DAMAGE)
        dmg = hit.sum(1) * per                   # enemies here have no shields
        self.hp[:, N:] -= dmg
        self.since_dmg[:, N:] = np.where(dmg > 0, 0, self.since_dmg[:, N:])
        self.hp[:, :N] = np.where(mask, 0.0, self.hp[:, :N])
        self.alive &= self.hp > 0

    # ------------------------------------------------------------------ VecEnv interface
    def reset(self, env_ids: np.ndarray, out: Batch) -> None:
        ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if ids.size == 0:
            return
        self.pos[ids] = self._spawn(ids.size)
        N = self.N
        self.hp[ids] = self.max_hp
        self.sh[ids] = self.max_sh
        self.cd[ids] = 0.0
        self.since_dmg[ids] = 1e9
        self.alive[ids] = True
        self.last_action[ids] = 0
        self.t[ids] = 0
        self._write(out, ids, zero_last=True)

    def refresh(self, out: Batch) -> None:
        """Rewrite obs/state/avail of every env from the current unit state (for hand-set
        scenarios in tests and demos: change pos/hp/alive, then call this)."""
        self._write(out, None)

    def _spawn(self, k: int) -> np.ndarray:
        spec, rng, N, E = self.spec, self.rng, self.N, self.E
        pos = np.zeros((k, N + E, 2))
        if spec.name == "bane_vs_hM":
            for i, (x0, y0, x1, y1) in enumerate(BANE_REGIONS):
                pos[:, i, 0] = x0 + rng.random(k) * (x1 - x0)
                pos[:, i, 1] = y0 + rng.random(k) * (y1 - y0)
            # SMAC sorts agents by (type, x, y): left arm, corridor, right arm
            o = np.lexsort((pos[:, :N, 1], pos[:, :N, 0]), axis=-1)
            pos[:, :N] = np.take_along_axis(pos[:, :N], o[..., None], axis=1)
            pos[:, N:] = BANE_ENEMY_POINT
        elif spec.name in ("1o_10b_vs_1r", "2o_20b_vs_2r"):
            nb = int(self.is_bane.sum())
            reg = np.array(CLIFF_REGIONS)[rng.integers(0, 5, (k, nb))]          # (k,nb,4)
            u = rng.random((k, nb, 2))
            pb = reg[..., :2] + u * (reg[..., 2:] - reg[..., :2])
            pb = np.minimum(pb, MAP_SIZE - 1e-3)
            corner = np.array(CLIFF_CORNERS)[rng.integers(0, 4, k)]               # (k,2)
            n_o = N - nb
            po = np.zeros((k, n_o, 2))
            po[:, 0] = corner
            pos[:, N] = corner
            if n_o == 2:  # 2o_20b_vs_2r: the second pair spawns at the last Baneling's point
                po[:, 1] = pb[:, -1]
                pos[:, N + 1] = pb[:, -1]
                o = np.lexsort((po[..., 1], po[..., 0]), axis=-1)
                po = np.take_along_axis(po, o[..., None], axis=1)
            o = np.lexsort((pb[..., 1], pb[..., 0]), axis=-1)
            pos[:, :nb] = np.take_along_axis(pb, o[..., None], axis=1)
            pos[:, nb:N] = po
        elif spec.name == "5z_vs_1ul":
            x0, y0, x1, y1 = Z5_REGION
            p = np.stack([x0 + rng.random(k) * (x1 - x0), y0 + rng.random(k) * (y1 - y0)], -1)
            q = np.stack([x0 + rng.random(k) * (x1 - x0), y0 + rng.random(k) * (y1 - y0)], -1)
            pos[:, N] = p   # the Ultralisk is created at the 3 Zealots' point
            ang = rng.random(k)[:, None] * 2 * np.pi + np.arange(3) * (2 * np.pi / 3)
            ring = 1.0 + 0.5 + 0.1  # Ultralisk radius + Zealot radius + gap
            pz = np.zeros((k, N, 2))
            pz[:, :3] = p[:, None, :] + ring * np.stack([np.cos(ang), np.sin(ang)], -1)
            pz[:, 3] = q + [-0.55, 0.0]
            pz[:, 4] = q + [0.55, 0.0]
            pz[..., 0] = np.clip(pz[..., 0], 0.5, 31.5)
            pz[..., 1] = np.clip(pz[..., 1], 7.5, 24.5)
            o = np.lexsort((pz[..., 1], pz[..., 0]), axis=-1)
            pos[:, :N] = np.take_along_axis(pz, o[..., None], axis=1)
        return pos

    def step(self, actions: np.ndarray, out: Batch, active: np.ndarray | None = None) -> None:
        # Inactive envs (ended, reset by the server right after) are simulated with the rest,
        # which costs nothing extra in this vectorized simulator; only the tallies skip them.
        N, E, B = self.N, self.E, self.num_envs
        ar = self._ar
        a = np.asarray(actions, dtype=np.int64).reshape(B, N)
        alive_a = self.alive[:, :N].copy()
        a = np.where(alive_a, a, 0)
        self.last_action[:] = a
        prev_en = self.hp[:, N:] + self.sh[:, N:]
        en_dead_before = ~self.alive[:, N:]
        pos = self.pos
        pa = pos[:, :N]
        spd = self.speed[:N]

        # -- 1. agent actions -----------------------------------------------------------
        is_move = (a >= 2) & (a <= 5)
        disp = _DIRS[np.where(is_move, a, 0)] * spd[None, :, None]
        att = a >= 6
        tgt = np.clip(a - 6, 0, E - 1)
        tu = N + tgt                                             # target unit index (B,N)
        tpos = pos[ar[:, None], tu]                              # (B,N,2)
        t_alive = self.alive[ar[:, None], tu]
        t_air = self.air[tu]
        dvec = tpos - pa
        dist = np.sqrt((dvec ** 2).sum(-1))
        unit = dvec / np.maximum(dist, EPS)[..., None]
        valid = att & t_alive & alive_a
        rt = self.radius[tu]
        # Banelings roll to a ground target and burst on contact; air targets: order rejected
        b_att = valid & self.is_bane & ~t_air
        contact = U.UNITS["baneling"].reach + self.radius[:N] + rt
        # Zealots close in to melee reach and strike
        z_att = valid & self.is_zealot & ~t_air
        zreach = U.UNITS["zealot"].reach + self.radius[:N] + rt
        stop_at = np.where(self.is_bane, contact, zreach)
        chase = b_att | z_att
        clen = np.minimum(spd, np.maximum(dist - stop_at, 0.0))
        disp = np.where(chase[..., None], unit * clen[..., None], disp)
        moving = (is_move | chase) & alive_a
        if moving.any():
            newp = self._move(pa, disp, self.ground_a)
            pos[:, :N] = np.where(moving[..., None], newp, pa)
            pa = pos[:, :N]
        if chase.any():   # distance to the target after moving (walls may have stopped it)
            nd = np.sqrt(((pos[ar[:, None], tu] - pa) ** 2).sum(-1))
        else:
            nd = dist
        explode = b_att & (nd <= contact + 1e-6)
        if z_att.any():
            strike = z_att & (nd <= zreach + 1e-6) & (self.cd[:, :N] < LOOPS)
            if strike.any():
                zt = U.UNITS["zealot"]
                per = np.maximum(zt.damage - self.armor[tu], U.MIN_DAMAGE) * zt.hits
                dmg = np.zeros((B, E))
                np.add.at(dmg, (np.broadcast_to(ar[:, None], tgt.shape)[strike], tgt[strike]),
                          per[strike])
                self.hp[:, N:] -= dmg      # enemies have no shields on these maps
                self.cd[:, :N] = np.where(strike, self.cd[:, :N] + zt.period, self.cd[:, :N])
                self.alive &= self.hp > 0
        self._burst(explode)

        # -- 2. the enemy ------------------------------------------------------------
        for j in range(E):
            u = N + j
            kind = self.kind[u]
            if kind in ("hydralisk", "roach"):
                self._enemy_fire(u)
            elif kind == "medivac":
                h = N + int(np.flatnonzero(self.kind[N:] == "hydralisk")[0])
                ok = self.alive[:, u] & self.alive[:, h]
                self.hp[:, h] = np.where(ok, np.minimum(self.hp[:, h] + U.MEDIVAC_HEAL,
                                                        self.max_hp[h]), self.hp[:, h])
            elif kind == "ultralisk":
                self._ultralisk(u)

        # -- 3. regeneration and cooldowns --------------------------------------------
        al = self.alive
        self.hp = np.where(al, np.minimum(self.hp + self.regen, self.max_hp), self.hp)
        self.since_dmg += 1
        regen_sh = al & (self.since_dmg > self.sh_delay) & (self.sh_regen > 0)
        self.sh = np.where(regen_sh, np.minimum(self.sh + self.sh_regen, self.max_sh), self.sh)
        self.cd = np.maximum(self.cd - LOOPS, 0.0)
        self.t += 1

        # -- 4. reward and termination (SMAC reward_battle, reward_only_positive) --------
        en_alive = self.alive[:, N:]
        now = self.hp[:, N:] + self.sh[:, N:]
        newly = ~en_alive & ~en_dead_before
        delta = np.where(en_dead_before, 0.0, np.where(newly, prev_en, prev_en - now)).sum(1)
        deaths = 10.0 * newly.sum(1)
        ag_any = self.alive[:, :N].any(1)
        if self.spec.name == "bane_vs_hM":
            win = ~en_alive[:, 0]                       # only the Medivac left
            lose = ~win & ~ag_any
        else:
            en_any = en_alive.any(1)
            win = ag_any & ~en_any
            lose = ~ag_any & en_any
        draw = ~ag_any & ~en_alive.any(1) & ~win
        term = win | lose | draw
        reward = (np.abs(delta + deaths) + 200.0 * win) * self.reward_scale
        out.reward[:] = reward
        out.terminated[:] = term
        out.truncated[:] = (self.t >= self.spec.episode_limit) & ~term
        ended = term | (self.t >= self.spec.episode_limit)
        counted = ended if active is None else ended & active
        self.won = win
        self.episodes += int(counted.sum())
        self.wins += int((win & counted).sum())
        self._write(out, None)

    # ------------------------------------------------------------------ enemy behaviour
    def _enemy_fire(self, u: int) -> None:
        """A stationary shooter (Hydralisk, Roach): fire at the nearest agent in reach."""
        N = self.N
        ut = self.types[u]
        d = np.linalg.norm(self.pos[:, :N] - self.pos[:, u, None, :], axis=-1)
        can = (self.alive[:, :N]
               & np.where(self.air[:N], ut.hits_air, ut.hits_ground)[None, :]
               & (d <= ut.reach + ut.radius + self.radius[:N]))
        fire = can.any(1) & self.alive[:, u] & (self.cd[:, u] < LOOPS)
        if not fire.any():
            return
        k = np.where(can, d, np.inf).argmin(1)
        b = np.flatnonzero(fire)
        was = self.alive[:, :N].copy()
        self._hit(b, k[b], np.full(b.size, ut.damage * ut.hits))
        self.cd[:, u] = np.where(fire, self.cd[:, u] + ut.period, self.cd[:, u])
        self.alive &= self.hp > 0
        killed = was & ~self.alive[:, :N] & self.is_bane
        self._burst(killed)       # Banelings burst when killed

    def _ultralisk(self, u: int) -> None:
        """Attack-move towards the map's attack point: strike the nearest Zealot in reach,
        otherwise chase the nearest Zealot within the acquisition radius, otherwise walk on."""
        N, B = self.N, self.num_envs
        ut = self.types[u]
        alive_u = self.alive[:, u]
        pu = self.pos[:, u]
        d = np.linalg.norm(self.pos[:, :N] - pu[:, None, :], axis=-1)
        cand = self.alive[:, :N] & ~self.air[:N] & (d <= U.ULTRA_ACQUIRE)
        reach = ut.reach + ut.radius + self.radius[:N]
        inr = cand & (d <= reach)
        has_r = inr.any(1) & alive_u
        k_r = np.where(inr, d, np.inf).argmin(1)
        has_c = cand.any(1) & alive_u & ~has_r
        k_c = np.where(cand, d, np.inf).argmin(1)
        # movement
        goal = np.where(has_c[:, None], self.pos[self._ar, k_c], np.array(Z5_ATTACK_POINT))
        gd = np.linalg.norm(goal - pu, axis=-1)
        stop = np.where(has_c, reach[k_c], 0.0)
        step_len = np.minimum(ut.speed, np.maximum(gd - stop, 0.0))
        mv = alive_u & ~has_r & (step_len > 0)
        if mv.any():
            disp = (goal - pu) / np.maximum(gd, EPS)[:, None] * step_len[:, None]
            newp = self._move(pu[:, None, :], disp[:, None, :], np.array([True]))[:, 0]
            self.pos[:, u] = np.where(mv[:, None], newp, pu)
        # strike
        fire = has_r & (self.cd[:, u] < LOOPS)
        if fire.any():
            b = np.flatnonzero(fire)
            k = k_r[b]
            tp = self.pos[b, k]
            self._hit(b, k, np.full(b.size, ut.damage))
            dz = np.linalg.norm(self.pos[b, :N] - tp[:, None, :], axis=-1)
            spl = self.alive[b, :N] & (dz <= U.ULTRA_SPLASH_RADIUS)
            spl[np.arange(b.size), k] = False
            if spl.any():
                bb, kk = np.nonzero(spl)
                self._hit(b[bb], kk, np.full(bb.size, ut.damage * U.ULTRA_SPLASH_FRACTION))
            self.cd[:, u] = np.where(fire, self.cd[:, u] + ut.period, self.cd[:, u])
            self.alive &= self.hp > 0

    # ------------------------------------------------------------------ observations
    def _write(self, out: Batch, rows, zero_last: bool = False) -> None:
        spec, lay = self.spec, self.layout
        N, E, A = self.N, self.E, self.A
        sl = slice(None) if rows is None else rows
        P = self.pos[sl]
        al = self.alive[sl]
        hp, sh = self.hp[sl], self.sh[sl]
        b = P.shape[0]
        pa = P[:, :N]
        ala = al[:, :N]
        rel = P[:, None, :, :] - pa[:, :, None, :]              # (b,N,U,2)
        dist = np.sqrt(rel[..., 0] ** 2 + rel[..., 1] ** 2)     # (b,N,U)
        sight = spec.sight_range
        vis = (dist < sight) & al[:, None, :] & ala[:, :, None]
        hfrac = hp / self.max_hp
        # available actions
        x, y = pa[..., 0], pa[..., 1]
        m = 1.0  # SMAC can_move checks the cell move_amount/2 = 1 away
        cand = [(x, y + m), (x, y - m), (x + m, y), (x - m, y)]
        mv = np.empty((b, N, 4), bool)
        for i, (cx, cy) in enumerate(cand):
            gnd = self._walkable(cx, cy)
            inb = (cx >= 0) & (cx < MAP_SIZE) & (cy >= 0) & (cy < MAP_SIZE)
            mv[..., i] = np.where(self.ground_a, gnd, inb)
        mv &= ala[..., None]
        att = ala[..., None] & al[:, None, N:] & (dist[:, :, N:] <= spec.shoot_range)
        av = out.avail
        if rows is None:
            avv = av
        else:
            avv = np.zeros((b, N, A), np.uint8)
        avv[..., 0] = ~ala
        avv[..., 1] = ala
        avv[..., 2:6] = mv
        avv[..., 6:] = att
        if rows is not None:
            av[rows] = avv
        # observation (written straight into views of one buffer)
        o = np.zeros((b, N, lay["obs_dim"]), np.float32)
        o[..., 0:4] = mv
        off = 4
        inv = 1.0 / sight
        nf = lay["nf_en"]
        en = o[..., off:off + E * nf].reshape(b, N, E, nf)
        en[..., 0] = att
        en[..., 1] = dist[:, :, N:] * inv
        en[..., 2:4] = rel[:, :, N:] * inv
        ind = 4
        if spec.obs_all_health or spec.obs_enemy_health:
            en[..., ind] = hfrac[:, None, N:]
            ind += 1
        if spec.unit_type_bits:
            en[..., ind:ind + spec.unit_type_bits] = self._enemy_type
        en *= vis[:, :, N:, None]
        off += E * nf
        # allies: features of every (agent, agent) pair, then drop the diagonal (self)
        nf = lay["nf_al"]
        F = np.empty((b, N, N, nf), np.float32)
        F[..., 0] = 1.0
        F[..., 1] = dist[:, :, :N] * inv
        F[..., 2:4] = rel[:, :, :N] * inv
        ind = 4
        if spec.obs_all_health:
            F[..., ind] = hfrac[:, None, :N]
            ind += 1
            if spec.shield_bits_ally:
                F[..., ind] = (sh[:, :N] / spec.ally_max_shield)[:, None, :]
                ind += 1
        if spec.unit_type_bits:
            F[..., ind:ind + spec.unit_type_bits] = self._ally_type
        F *= vis[:, :, :N, None]
        offd = F.reshape(b, N * N, nf)[:, 1:].reshape(b, N - 1, N + 1, nf)[:, :, :N]
        o[..., off:off + (N - 1) * nf].reshape(b, N, N - 1, nf)[...] = \
            offd.reshape(b, N, N - 1, nf)
        off += (N - 1) * nf
        if spec.obs_own_health:
            o[..., off] = hfrac[:, :N]
            off += 1
            if spec.shield_bits_ally:
                o[..., off] = sh[:, :N] / spec.ally_max_shield
                off += 1
        if spec.unit_type_bits:
            o[..., off:off + spec.unit_type_bits] = self._ally_type
        o *= ala[..., None]
        if rows is None:
            out.obs[...] = o
        else:
            out.obs[rows] = o
        # state
        s = np.zeros((b, lay["state_dim"]), np.float32)
        st = np.zeros((b, N, lay["st_al"]), np.float32)
        st[..., 0] = hfrac[:, :N]
        st[..., 1] = self.cd[sl][:, :N] / spec.ally_max_cd   # 0 for weaponless/Banelings
        st[..., 2] = (pa[..., 0] - MAP_SIZE / 2) / MAP_SIZE
        st[..., 3] = (pa[..., 1] - MAP_SIZE / 2) / MAP_SIZE
        ind = 4
        if spec.shield_bits_ally:
            st[..., ind] = sh[:, :N] / spec.ally_max_shield
            ind += 1
        if spec.unit_type_bits:
            st[..., ind:] = self._ally_type
        st *= ala[..., None]
        s[:, :N * lay["st_al"]] = st.reshape(b, -1)
        se = np.zeros((b, E, lay["st_en"]), np.float32)
        se[..., 0] = hfrac[:, N:]
        se[..., 1] = (P[:, N:, 0] - MAP_SIZE / 2) / MAP_SIZE
        se[..., 2] = (P[:, N:, 1] - MAP_SIZE / 2) / MAP_SIZE
        if spec.unit_type_bits:
            se[..., 3:] = self._enemy_type
        se *= al[:, N:, None]
        s[:, N * lay["st_al"]:self._st_last_off] = se.reshape(b, -1)
        if self.state_last_action and not zero_last:
            la = np.zeros((b, N, A), np.float32)
            np.put_along_axis(la, self.last_action[sl][..., None], 1.0, axis=-1)
            s[:, self._st_last_off:] = la.reshape(b, -1)
        if rows is None:
            out.state[...] = s
        else:
            out.state[rows] = s


def make(variant: str, num_envs: int, seed: int = 0) -> VecEnv:
    return SmacliteVecEnv(variant, num_envs, seed)
