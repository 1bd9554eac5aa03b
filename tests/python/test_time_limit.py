"""`lmac_env.core.split_done`: a gym-style `done` at the env's own step limit becomes a
truncation (the learner bootstraps from the next observation), an earlier one a termination."""
import numpy as np

from lmac_env.core import split_done


def test_scalars_at_and_before_the_limit():
    assert split_done(False, 3, 500) == (False, False)
    assert split_done(True, 499, 500) == (True, False), "an end before the limit is real"
    assert split_done(True, 500, 500) == (False, True), "rware's done at max_steps is a time limit"


def test_the_envs_own_word_wins_where_it_has_one():
    assert split_done(True, 500, 500, terminal=True) == (True, False), "won on the last step"
    assert split_done(True, 10, 500, terminal=False) == (False, True), "another kind of time limit"


def test_arrays_one_entry_per_env_write_straight_into_a_batch():
    done = np.array([1, 1, 0, 1], np.uint8)
    steps = np.array([500, 20, 500, 499])
    term, trunc = split_done(done, steps, 500)
    out_term, out_trunc = np.zeros(4, np.uint8), np.zeros(4, np.uint8)
    out_term[:], out_trunc[:] = term, trunc
    assert out_term.tolist() == [0, 1, 0, 1] and out_trunc.tolist() == [1, 0, 0, 0]
