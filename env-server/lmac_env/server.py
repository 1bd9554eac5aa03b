"""The env server: steps B environments and writes every batched step straight into a slot of
its shared-memory slab, then hands the slot to the protocol runner. The trainer hands it back
with the chosen actions. Started by `lmac` (one process per env server); also usable by hand:

    python -m lmac_env.server --env lbf:8x8-2p-2f-s1-coop --envs 32 --sub-batches 2 --run myrun \
        --first-member 0 --members 2 --slots 4 --msg-dim 29

`python -m lmac_env.server --raw --steps 2000 ...` steps the same environments with random
available actions and no pipeline (the baseline of `lmac bench pipeline`); with `--compare-raw K`
a pipeline env server alternates blocks of K batched steps through the ring and of that baseline in
this process (how `lmac bench pipeline` measures one env server).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys
import time

import numpy as np

from .core import Batch, Schema, VecEnv, schema_path
from .registry import UnknownFamily, make
from .sizes import SizeChecked, SizeMismatch


# Optional environment packages that set-up installs on request: what to run when one is missing.
INSTALL_HINTS = {
    "gfootball": "; install it with `LMAC_WITH_GRF=1 bash scripts/setup.sh` (or `bash scripts/setup-grf.sh`)",
}

FLAG_FIRST = 1     # shm-schema layout.rs FLAG_FIRST: this row starts an episode
FLAG_PREV_WON = 2  # FLAG_PREV_WON: the episode that ended at this row was won
FLAG_FINAL = 4     # FLAG_FINAL: this row is the observation after a truncated episode's last step


@dataclasses.dataclass
class Meta:
    """Per-env bookkeeping written next to each step (views of the slot in the pipeline)."""
    episode_id: np.ndarray    # uint64 (B,)
    ep_step: np.ndarray       # uint32 (B,)
    flags: np.ndarray         # uint32 (B,)
    last_actions: np.ndarray  # int32 (B, n_agents)

    @staticmethod
    def allocate(schema: Schema, num_envs: int) -> "Meta":
        return Meta(np.zeros(num_envs, np.uint64), np.zeros(num_envs, np.uint32),
                    np.zeros(num_envs, np.uint32), np.zeros((num_envs, schema.n_agents), np.int32))


class Driver:
    """Episode bookkeeping shared by the pipeline and the raw baseline: auto-reset, episode ids,
    step counters, truncation at the schema's episode limit.

    How an episode ends on the rows of an env:
    - terminated (the env ended it: no successor to learn from): the same row already starts
      the next episode (FLAG_FIRST) and carries the final step's reward and terminated = 1;
    - truncated (a time limit: the learner bootstraps from what came next): the row carries the
      final step's reward, truncated = 1, FLAG_FINAL and the observation, state and available
      actions after the last step, with the runner's messages on it like any row. The actions
      chosen on it are ignored: the next row starts the next episode (reward 0, no end flags).
    FLAG_PREV_WON marks the row that ends a won episode."""

    def __init__(self, env: VecEnv, member: int):
        self.env = env
        b = env.num_envs
        self.limit = env.schema.episode_limit
        self.ep_step = np.zeros(b, np.uint32)
        # Episode ids are unique across members: member index in the high bits.
        self.episode_id = (np.uint64(member) << np.uint64(40)) + np.arange(b, dtype=np.uint64)
        self.next_id = self.episode_id[-1] + np.uint64(1)
        self.episodes_done = 0
        self.return_sum = 0.0
        self._returns = np.zeros(b, np.float64)
        self._final = np.zeros(b, bool)   # envs whose last row was FLAG_FINAL: reset next

    def first(self, out: Batch, meta: Meta) -> None:
        self.env.reset(np.arange(self.env.num_envs), out)
        out.reward[:] = 0
        out.terminated[:] = 0
        out.truncated[:] = 0
        self._final[:] = False
        meta.episode_id[:] = self.episode_id
        meta.ep_step[:] = 0
        meta.flags[:] = FLAG_FIRST
        meta.last_actions[:] = -1

    def advance(self, actions: np.ndarray, out: Batch, meta: Meta) -> None:
        final = self._final
        live = ~final
        self.env.step(actions, out, live if final.any() else None)
        self.ep_step[live] += 1
        term = live & (out.terminated != 0)
        trunc = live & ~term & ((out.truncated != 0) | (self.ep_step >= self.limit))
        ended = term | trunc
        out.terminated[:] = term
        out.truncated[:] = trunc
        out.reward[final] = 0.0
        self._returns[live] += out.reward[live]
        meta.last_actions[:] = actions
        meta.flags[:] = 0
        if ended.any():
            ids = np.nonzero(ended)[0]
            # Success of the finished episodes: the env's own `won` (SMAC) or, by default,
            # termination before the time limit (LBF: all food eaten).
            won = getattr(self.env, "won", None)
            won = term if won is None else np.asarray(won, bool)
            meta.flags[ids[won[ids]]] |= FLAG_PREV_WON
            self.episodes_done += len(ids)
            self.return_sum += float(self._returns[ids].sum())
            self._returns[ids] = 0.0
        meta.flags[trunc] |= FLAG_FINAL
        restart = term | final
        if restart.any():
            ids = np.nonzero(restart)[0]
            self.env.reset(ids, out)
            self.ep_step[ids] = 0
            self.episode_id[ids] = self.next_id + np.arange(len(ids), dtype=np.uint64)
            self.next_id += np.uint64(len(ids))
            meta.flags[ids] |= FLAG_FIRST
            meta.last_actions[ids] = -1
        self._final = trunc
        meta.episode_id[:] = self.episode_id
        meta.ep_step[:] = self.ep_step


def _views(lease):
    out = Batch(obs=lease.obs, state=lease.state, avail=lease.avail, reward=lease.reward,
                terminated=lease.terminated, truncated=lease.truncated)
    meta = Meta(episode_id=lease.episode_id, ep_step=lease.ep_step, flags=lease.flags,
                last_actions=lease.last_actions)
    return out, meta


def _write_first(driver: Driver, lease) -> None:
    out, meta = _views(lease)
    driver.first(out, meta)


def _write_step(driver: Driver, lease) -> None:
    actions = np.array(lease.actions)  # copy: the step below overwrites this same slot
    out, meta = _views(lease)
    driver.advance(actions, out, meta)
    # The views die with this frame, so the caller may hand the slot over.


class _SubBatch:
    """One sub-batch of this process: its environments, its slab and its ring port. To the
    protocol runner and the trainer each sub-batch is a ring member of its own (index `member`)."""

    def __init__(self, args, member: int, num_envs: int, lmac_shm):
        self.member = member
        self.env = make(args.env, num_envs, seed=args.seed + 1_000_003 * member)
        # The first reset and step go through probes checked against the schema, so a size
        # mistake stops this server naming the schema file and field, not inside numpy.
        self.driver = Driver(SizeChecked(self.env), member)
        self.slab = lmac_shm.Slab.create(f"lmac-{args.run}-s{member}", str(schema_path(args.env)), num_envs,
                                         args.msg_dim, args.slots)
        self.port = lmac_shm.Port(args.run, "env", member, args.members, args.slots,
                                  startup_timeout=args.startup_timeout)
        self.seq = 0
        self.open = True
        self.held = None    # a returned slot message `hold` keeps back
        self.waited = 0.0   # seconds waiting for this sub-batch's slot to come back
        self.stepped = 0.0  # seconds stepping its environments

    def start(self) -> None:
        lease = self.slab.lease(0, "env")
        _write_first(self.driver, lease)
        lease.seq = self.seq
        lease.release()
        self.port.send_slot(self.member, 0, self.seq)

    def _next(self):
        """The next slot message: the one `hold` kept back, else wait (up to 0.25 s) for one."""
        if self.held is not None:
            msg, self.held = self.held, None
            return msg
        t0 = time.perf_counter()
        msg = self.port.recv(0.25)
        self.waited += time.perf_counter() - t0
        if msg is not None and msg[0] == "bye":
            self.open = False
        return msg

    def serve_one(self) -> bool:
        """Take this sub-batch's slot back with actions, step it and hand it over again.
        False when nothing was stepped (a wait timed out or the trainer said goodbye)."""
        msg = self._next()
        if msg is None or msg[0] != "slot":
            return False
        t1 = time.perf_counter()
        _, _, slot, _ = msg
        self.seq += 1
        lease = self.slab.lease(slot, "env")
        _write_step(self.driver, lease)
        self.stepped += time.perf_counter() - t1
        lease.seq = self.seq
        lease.release()
        self.port.send_slot(self.member, slot, self.seq)
        return True

    def hold(self) -> None:
        """Wait until this sub-batch's slot is back and keep it unstepped: with every slot held
        the ring is paused (`lmac bench pipeline` steps the raw baseline meanwhile)."""
        while self.open and self.held is None:
            msg = self._next()
            if msg is not None and msg[0] == "slot":
                self.held = msg

    def close(self) -> None:
        self.env.close()
        del self.port
        del self.slab  # unlinks the shared memory


def serve(args) -> int:
    """Serve `--sub-batches` H sub-batches of `--envs / H` environments each (ring
    members `--first-member` .. `--first-member + H - 1`). With H = 2 the process steps one half while
    the other half's slot is with the protocol runner and the trainer, so it never sleeps
    waiting for actions (double buffering); with H = 1 stepping and the round trip alternate."""
    import lmac_shm

    stop = {"flag": False}

    def on_signal(signum, frame):
        stop["flag"] = True
        lmac_shm.request_stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    last = args.first_member + args.sub_batches - 1
    who = f"env server, ring member {args.first_member} ({args.env})" if args.sub_batches == 1 else \
        f"env server, ring members {args.first_member}-{last} ({args.env})"
    units: list[_SubBatch] = []
    try:
        try:
            for k in range(args.sub_batches):
                units.append(_SubBatch(args, args.first_member + k, args.envs // args.sub_batches, lmac_shm))
        except (ImportError, UnknownFamily) as e:
            # The env's module cannot be found or imported: one line, no traceback (an error
            # from inside a module that did load is the module's own bug and keeps its traceback).
            hint = INSTALL_HINTS.get(getattr(e, "name", None) or "", "")
            print(f"lmac: {who}: {e} (python: {sys.executable}){hint}", file=sys.stderr, flush=True)
            return 2
        for u in units:
            u.port.handshake(args.startup_timeout)
        for u in units:
            u.start()
        t0 = time.perf_counter()
        baseline_s = _compare(args, units, stop) if args.compare_raw else 0.0
        # Strict round robin: each sub-batch's slot comes back in the order it was sent.
        while not stop["flag"] and any(u.open for u in units):
            for u in units:
                if u.open:
                    u.serve_one()
        dt = time.perf_counter() - t0
        if not stop["flag"] and units:
            # Every unit forwarded the trainer's goodbye to the protocol runner; it stays
            # readable only while this process lives, so wait until the runner is gone (it
            # exits once every member's goodbye is in) before closing the ports.
            units[0].port.wait_downstream_gone(5.0)
        steps = sum(u.seq * u.env.num_envs for u in units)
        episodes = sum(u.driver.episodes_done for u in units)
        waited, stepped = sum(u.waited for u in units), sum(u.stepped for u in units)
        # Waiting is what the pipeline costs this process: with double buffering it stays near 0.
        baseline = f", raw baseline blocks {baseline_s:.1f} s" if args.compare_raw else ""
        print(f"lmac: {who}: {steps} env steps, {episodes} episodes in {dt:.1f} s "
              f"(stepping {stepped:.1f} s, waiting for actions {waited:.1f} s{baseline}); goodbye",
              file=sys.stderr, flush=True)
        return 0
    except lmac_shm.StoppedError:
        return 0
    except (SizeMismatch, lmac_shm.RefusedError) as e:
        # A refused set-up (a layout mismatch, a namespace that is not this user's alone): one
        # line saying what and where, no traceback.
        print(f"lmac: {who}: {e}", file=sys.stderr, flush=True)
        return 2
    except lmac_shm.PeerError as e:
        print(f"lmac: {who}: {e}", file=sys.stderr, flush=True)
        return 3
    finally:
        for u in units:
            u.close()


class _RawStepper:
    """The baseline: the same environments stepped in this process with random available
    actions, no pipeline (what `lmac bench pipeline` compares the pipeline against)."""

    def __init__(self, env_name: str, num_envs: int, seed: int):
        self.env = make(env_name, num_envs, seed=seed)
        self.driver = Driver(self.env, 0)
        self.out = Batch.allocate(self.env.schema, num_envs)
        self.meta = Meta.allocate(self.env.schema, num_envs)
        self.rng = np.random.default_rng(seed)
        self.actions = np.zeros((num_envs, self.env.schema.n_agents), np.int32)
        self.driver.first(self.out, self.meta)

    def run(self, batched_steps: int) -> float:
        """Step `batched_steps` times; seconds taken."""
        t0 = time.perf_counter()
        for _ in range(batched_steps):
            _random_actions(self.rng, self.out.avail, self.actions)
            self.driver.advance(self.actions, self.out, self.meta)
        return time.perf_counter() - t0


def _random_actions(rng, avail: np.ndarray, out: np.ndarray) -> None:
    """Uniform over available actions, vectorized: argmax of random keys masked by avail."""
    keys = rng.random(avail.shape, dtype=np.float32) + avail  # available actions score >= 1
    out[:] = keys.argmax(-1)


def raw(args) -> int:
    """No pipeline: step the environments with random available actions in this process."""
    r = _RawStepper(args.env, args.envs, args.seed)
    r.run(args.warmup)
    dt = r.run(args.steps)
    print(json.dumps({"mode": "raw", "env": args.env, "envs": args.envs, "batched_steps": args.steps,
                      "env_steps": args.steps * args.envs, "seconds": dt,
                      "env_steps_per_s": args.steps * args.envs / dt,
                      "episodes": r.driver.episodes_done}))
    r.env.close()
    return 0


def _compare(args, units: list[_SubBatch], stop: dict) -> float:
    """`--compare-raw K`: alternate, in this process, a block of K batched steps through the
    pipeline and a block of K batched steps of the raw baseline (a second set of the same
    environments, stepped here with random actions, the ring paused), `--compare-blocks` times.
    Adjacent blocks see the same machine, so their ratio is immune to the slow drifts of a shared
    host that separate runs suffer. A pipeline block starts with every slot back here and ends
    when every slot is back again, so it pays all of its round trips."""
    def pipeline_round() -> None:
        for u in units:
            while not u.serve_one() and u.open and not stop["flag"]:
                pass

    baseline = _RawStepper(args.env, args.envs, args.seed + 999_983)
    baseline.run(args.warmup)
    for _ in range(args.warmup):
        pipeline_round()
    blocks = []
    for _ in range(args.compare_blocks):
        for u in units:
            u.hold()
        stepped0 = sum(u.stepped for u in units)
        t0 = time.perf_counter()
        for _ in range(args.compare_raw):
            pipeline_round()
        for u in units:
            u.hold()
        pipeline_s = time.perf_counter() - t0
        if stop["flag"] or not all(u.open for u in units):
            break
        raw_s = baseline.run(args.compare_raw)
        # stepping_s: the part of pipeline_s spent stepping (the rest is hand-over and waiting).
        blocks.append({"pipeline_s": pipeline_s, "stepping_s": sum(u.stepped for u in units) - stepped0,
                       "raw_s": raw_s})
    baseline.env.close()
    report = {"env": args.env, "envs": args.envs, "sub_batches": args.sub_batches,
              "block_env_steps": args.compare_raw * args.envs, "blocks": blocks}
    with open(args.compare_out, "w") as f:
        json.dump(report, f)
    return sum(b["raw_s"] for b in blocks)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lmac_env.server", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", required=True, help="environment name, e.g. lbf:8x8-2p-2f-s1-coop")
    p.add_argument("--envs", type=int, default=8, help="environments stepped together (B)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run", help="run id (names the shared memory and iceoryx2 services)")
    p.add_argument("--first-member", type=int, default=0, help="ring member index of this process's first sub-batch")
    p.add_argument("--sub-batches", type=int, default=1,
                   help="split --envs into this many sub-batches stepped in turn (2: double buffering)")
    p.add_argument("--members", type=int, default=1, help="ring members in the run: env server processes x sub-batches")
    p.add_argument("--slots", type=int, default=4, help="slots in the slab")
    p.add_argument("--msg-dim", type=int, default=0, help="message columns reserved per row")
    p.add_argument("--startup-timeout", type=float, default=60.0)
    p.add_argument("--raw", action="store_true", help="baseline: no pipeline, random actions")
    p.add_argument("--steps", type=int, default=1000, help="--raw: batched steps to time")
    p.add_argument("--warmup", type=int, default=20, help="--raw, --compare-raw: batched steps before timing")
    p.add_argument("--compare-raw", type=int, default=0, metavar="K",
                   help="bench: alternate blocks of K batched steps through the pipeline and of the raw "
                        "baseline in this process (see _compare); needs --compare-out")
    p.add_argument("--compare-blocks", type=int, default=9, help="--compare-raw: block pairs")
    p.add_argument("--compare-out", help="--compare-raw: write the block timings (JSON) here")
    args = p.parse_args(argv)
    if args.envs < 1:
        p.error("--envs must be at least 1")
    if args.sub_batches < 1 or args.envs % args.sub_batches:
        p.error(f"--sub-batches must be at least 1 and divide --envs ({args.envs})")
    if args.compare_raw and not args.compare_out:
        p.error("--compare-raw needs --compare-out")
    if args.raw:
        return raw(args)
    if not args.run:
        p.error("--run is required (or use --raw)")
    return serve(args)


if __name__ == "__main__":
    sys.exit(main())
