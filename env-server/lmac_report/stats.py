"""The aggregate statistics of rliable (Agarwal et al., "Deep RL at the Edge of the Statistical
Precipice", NeurIPS 2021), written with numpy alone.

Scores come as one 1-D array per task (environment): the final scores of that task's runs.
Tasks may have different numbers of runs (rliable needs a full runs x tasks matrix; with one
it gives the same numbers as here).

- IQM: the 25% trimmed mean of all runs of all tasks pooled (rliable's `aggregate_iqm`,
  `scipy.stats.trim_mean(scores, 0.25, axis=None)`: int(n/4) scores cut from each end).
- mean / median: the mean / median over tasks of each task's mean score (rliable's
  `aggregate_mean` / `aggregate_median`; with one task both are that task's mean).
- Confidence intervals: the stratified percentile bootstrap: each replicate resamples, with
  replacement, each task's runs within that task (rliable's `StratifiedBootstrap`, percentile
  method), and the interval is the 2.5th and 97.5th percentiles of the replicates' statistic.
- Performance profile: the fraction of runs whose score is above tau, averaged over tasks
  (rliable's score distribution; the same as pooling runs when tasks have equal run counts).

Why not rliable itself: rliable 1.2.0 (the latest) requires arch<8, and arch 7.2.0 fails to
import with pandas 3 (pandas' deprecate_kwarg changed), which this environment has; rliable also
brings statsmodels and seaborn. tests/python/test_report.py checks these against hand-computed
values and scipy.stats.trim_mean.
"""

from __future__ import annotations

import zlib
from typing import Callable, Sequence

import numpy as np

Tasks = Sequence[np.ndarray]  # one array per task; runs on the last axis


def trimmed_mean(x: np.ndarray, cut: float = 0.25) -> np.ndarray:
    """Mean of x along its last axis after dropping int(cut * n) values from each end."""
    x = np.sort(np.asarray(x, dtype=float), axis=-1)
    n = x.shape[-1]
    if n == 0:
        raise ValueError("trimmed mean of no scores")
    lo = int(cut * n)
    return x[..., lo : n - lo].mean(axis=-1)


def iqm(tasks: Tasks) -> np.ndarray:
    """Interquartile mean of all runs of all tasks pooled."""
    return trimmed_mean(np.concatenate([np.asarray(t, dtype=float) for t in tasks], axis=-1))


def _task_means(tasks: Tasks) -> np.ndarray:
    return np.stack([np.asarray(t, dtype=float).mean(axis=-1) for t in tasks], axis=-1)


def mean(tasks: Tasks) -> np.ndarray:
    """Mean over tasks of each task's mean score."""
    return _task_means(tasks).mean(axis=-1)


def median(tasks: Tasks) -> np.ndarray:
    """Median over tasks of each task's mean score."""
    return np.median(_task_means(tasks), axis=-1)


AGGREGATES: dict[str, Callable[[Tasks], np.ndarray]] = {"iqm": iqm, "median": median, "mean": mean}


# Below this many runs a row reports the mean, the sample SD and every run's score, not an IQM
# and a bootstrap CI: with 3 runs the IQM trims nothing and the CI is the runs' own range.
FEW_RUNS = 5


def sample_sd(x: np.ndarray) -> np.ndarray | float:
    """Sample standard deviation over the first axis (n - 1 in the divisor; 0 for one value):
    the spread over seeds every lmac table and plot states."""
    x = np.asarray(x, dtype=float)
    if x.shape[0] < 2:
        return np.zeros(x.shape[1:]) if x.ndim > 1 else 0.0
    return x.std(0, ddof=1)


def rng_for(seed: int, key: str) -> np.random.Generator:
    """A generator for one group's bootstrap: the same seed and key give the same intervals
    whatever other groups are in the report."""
    return np.random.default_rng([seed, zlib.crc32(key.encode())])


def resample(tasks: Tasks, reps: int, rng: np.random.Generator) -> list[np.ndarray]:
    """`reps` stratified bootstrap replicates: each task's runs resampled within the task.
    Returns one (reps, n_task) array per task."""
    out = []
    for t in tasks:
        t = np.asarray(t, dtype=float)
        out.append(t[rng.integers(0, t.shape[-1], size=(reps, t.shape[-1]))])
    return out


def interval(
    tasks: Tasks, func: Callable[[Tasks], np.ndarray], reps: int, rng: np.random.Generator, size: float = 0.95
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(point estimate, lower, upper): func on the data and the percentile interval of func over
    `reps` stratified bootstrap replicates. func maps runs on the last axis to a scalar (or
    a vector on a new last axis, e.g. a profile over thresholds)."""
    tasks = [np.asarray(t, dtype=float) for t in tasks]
    if not tasks or any(t.ndim != 1 or t.size == 0 for t in tasks):
        raise ValueError("every task needs a 1-D array of at least one score")
    if reps < 1:
        raise ValueError("reps must be at least 1")
    point = np.asarray(func(tasks))
    boot = np.asarray(func(resample(tasks, reps, rng)))
    lo, hi = np.percentile(boot, [50 * (1 - size), 50 * (1 + size)], axis=0)
    return point, lo, hi


def profile(taus: np.ndarray) -> Callable[[Tasks], np.ndarray]:
    """The performance profile function at thresholds `taus`: for each tau, the fraction of each
    task's runs scoring above tau, averaged over tasks (a vector over taus)."""
    taus = np.asarray(taus, dtype=float)

    def f(tasks: Tasks) -> np.ndarray:
        per_task = [(np.asarray(t)[..., None] > taus).mean(axis=-2) for t in tasks]
        return np.mean(per_task, axis=0)

    return f


def normalise_min_max(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(v - lo) / (hi - lo); a task whose scores are all equal maps to 0."""
    span = hi - lo
    return (np.asarray(values, dtype=float) - lo) / (span if span > 0 else 1.0)
