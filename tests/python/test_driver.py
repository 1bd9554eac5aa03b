"""The env server's episode bookkeeping (Driver) on the real LBF environment: a terminated
episode restarts on the same row, a truncated one gets a final row (FLAG_FINAL) with the
observation after its last step, and the ended env is not stepped again before its reset."""
import numpy as np

from lmac_env.core import Batch
from lmac_env.registry import make
from lmac_env.server import FLAG_FINAL, FLAG_FIRST, FLAG_PREV_WON, Driver, Meta, _random_actions


def setup(envs=3, seed=0):
    env = make("lbf:8x8-2p-2f-s1-coop", envs, seed=seed)
    out, meta = Batch.allocate(env.schema, envs), Meta.allocate(env.schema, envs)
    drv = Driver(env, 0)
    drv.first(out, meta)
    return env, drv, out, meta


def test_a_truncated_episode_ends_with_a_final_row_then_a_clean_first_row():
    env, drv, out, meta = setup()
    limit = env.schema.episode_limit
    rng = np.random.default_rng(0)
    acts = np.zeros((3, 2), np.int32)
    seen_final = 0
    for _ in range(3 * limit):
        prev_ids = meta.episode_id.copy()
        prev_flags = meta.flags.copy()
        lbf_steps = [e.current_step for e in env.envs]
        _random_actions(rng, out.avail, acts)
        drv.advance(acts, out, meta)
        for e in range(3):
            if prev_flags[e] & FLAG_FINAL:
                # The row after a final row starts the next episode; the ended env was not stepped.
                assert meta.flags[e] & FLAG_FIRST and not meta.flags[e] & FLAG_FINAL
                assert out.reward[e] == 0 and out.terminated[e] == 0 and out.truncated[e] == 0
                assert meta.episode_id[e] != prev_ids[e] and meta.ep_step[e] == 0
                assert env.envs[e].current_step == 0, "reset, not stepped past its end"
                assert lbf_steps[e] == limit
            elif meta.flags[e] & FLAG_FINAL:
                seen_final += 1
                assert out.truncated[e] == 1 and out.terminated[e] == 0
                assert not meta.flags[e] & FLAG_FIRST
                assert meta.ep_step[e] == limit and meta.episode_id[e] == prev_ids[e]
                assert env.envs[e].current_step == limit, "the observation after the last step, not a reset"
            elif out.terminated[e]:
                assert meta.flags[e] & FLAG_FIRST and meta.flags[e] & FLAG_PREV_WON
    assert seen_final >= 3, "random play on LBF 8x8 mostly hits the time limit"


def test_every_ended_episode_is_counted_once():
    env, drv, out, meta = setup(envs=2)
    rng = np.random.default_rng(1)
    acts = np.zeros((2, 2), np.int32)
    ends = 0
    for _ in range(4 * (env.schema.episode_limit + 1)):
        _random_actions(rng, out.avail, acts)
        drv.advance(acts, out, meta)
        ends += int(((meta.flags & FLAG_FINAL) != 0).sum() + (out.terminated != 0).sum())
    assert ends >= 8 and drv.episodes_done == ends
