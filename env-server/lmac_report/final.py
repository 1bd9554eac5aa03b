"""The one rule for a training run's final figure when it has no final evaluation: the mean of
its last FINAL_TEST_PHASES test phases (one phase is only `run.test_episodes` greedy episodes, so
a single phase is noisy), and its peak, the best mean of that many consecutive phases. `lmac
experiment`'s comparison table (trainer/cli/src/cli/experiment.rs, FINAL_TESTS) uses the same
number."""

FINAL_TEST_PHASES = 5


def final_of(values, n: int = FINAL_TEST_PHASES) -> float:
    """Mean of the last `n` values (all of them when there are fewer)."""
    if len(values) == 0:
        raise ValueError("no test phases")
    last = list(values)[-n:]
    return sum(last) / len(last)


def peak_of(values, n: int = FINAL_TEST_PHASES) -> float:
    """Best mean of `n` consecutive values (the mean of all when there are fewer)."""
    values = list(values)
    if not values:
        raise ValueError("no test phases")
    if len(values) <= n:
        return sum(values) / len(values)
    return max(sum(values[i:i + n]) / n for i in range(len(values) - n + 1))
