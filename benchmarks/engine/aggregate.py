"""Aggregates over tasks for few-seed RL comparisons (Agarwal et al., "Deep RL at the Edge of the Statistical
Precipice", NeurIPS 2021): interquartile mean (IQM) with stratified bootstrap CIs over tasks and seeds, and
performance profiles.

Written with numpy and scipy: rliable 1.2 does not run beside today's pandas (its arch 7 fails to import under
pandas 3, and arch 8 rejects rliable's ``random_state`` argument). The estimators are rliable's: the IQM is the mean
of the middle 50 % of all runs pooled over tasks (``scipy.stats.trim_mean(..., 0.25)``); a bootstrap replicate
resamples the seeds *within each task* with replacement (stratified), so every task keeps its weight; the CI is the
percentile interval of the replicates.

Scores are made comparable across tasks by dividing each run's score by the baseline's mean score on its task
(the baseline's mean is 1.0 on every task).
"""

import numpy as np
from scipy.stats import trim_mean

#: task -> runs' scores (one per seed; tasks may have different seed counts)
TaskScores = dict[str, np.ndarray]


def normalized(scores: TaskScores, baseline: TaskScores) -> TaskScores:
    """Each task's scores divided by the baseline's mean score on that task."""
    return {task: np.asarray(values, float) / float(np.mean(baseline[task])) for task, values in scores.items()}


def iqm(scores: TaskScores) -> float:
    """Interquartile mean of all runs pooled over tasks: ``scipy.stats.trim_mean(runs, 0.25)``, computed as scipy
    computes it (the same partition, so the same number to the bit) without its checks, which took 0.7 ms of each
    bootstrap replicate; scipy's own call where it answers otherwise (no runs, a NaN: NaN)."""
    runs = np.concatenate(list(scores.values()))
    low = int(0.25 * len(runs))
    high = len(runs) - low
    if low >= high or np.isnan(runs).any():
        return float(trim_mean(runs, 0.25))
    return float(np.mean(np.partition(runs, (low, high - 1))[low:high]))


def mean(scores: TaskScores) -> float:
    """Mean over tasks of the mean over seeds."""
    return float(np.mean([np.mean(values) for values in scores.values()]))


def stratified_bootstrap_ci(
    scores: TaskScores, statistic=iqm, reps: int = 2000, seed: int = 0, confidence: float = 0.95
) -> tuple[float, float]:
    """Percentile CI of ``statistic`` under resampling the seeds within each task (rliable's stratified bootstrap)."""
    rng = np.random.default_rng(seed)
    replicates = []
    for _ in range(reps):
        resampled = {task: values[rng.integers(len(values), size=len(values))] for task, values in scores.items()}
        replicates.append(statistic(resampled))
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(replicates, [tail, 100 - tail])
    return float(low), float(high)


def normalized_bootstrap_ci(
    scores: TaskScores, baseline: TaskScores, statistic=iqm, reps: int = 2000, seed: int = 0, confidence: float = 0.95
) -> tuple[float, float]:
    """Percentile CI of ``statistic`` of the baseline-normalized scores, resampling the seeds of both the scores and
    the baseline within each task, so that the baseline's own spread is in the interval."""
    rng = np.random.default_rng(seed)
    replicates = []
    for _ in range(reps):
        resample = {t: np.asarray(v, float)[rng.integers(len(v), size=len(v))] for t, v in scores.items()}
        base = {t: np.asarray(baseline[t], float)[rng.integers(len(baseline[t]), size=len(baseline[t]))] for t in scores}
        replicates.append(statistic(normalized(resample, base)))
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(replicates, [tail, 100 - tail])
    return float(low), float(high)


def best_within(returns, times, budget: float, default: float = float("nan")) -> float:
    """The best of ``returns`` whose ``times`` (seconds or steps, one per return) are within ``budget``; ``default``
    where none is: the best-so-far return of a run at a budget of time."""
    within = [value for value, at in zip(returns, times) if at <= budget]
    return max(within) if within else default


def performance_profile(scores: TaskScores, taus: np.ndarray) -> np.ndarray:
    """Fraction of runs (each task weighted equally) whose score exceeds each tau."""
    above = [np.asarray(values).reshape(-1, 1) > np.asarray(taus).reshape(1, -1) for values in scores.values()]
    return np.mean([np.mean(runs, axis=0) for runs in above], axis=0)


def profile_band(scores: TaskScores, taus: np.ndarray, reps: int = 2000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """95 % stratified bootstrap band of :func:`performance_profile`."""
    rng = np.random.default_rng(seed)
    replicates = [
        performance_profile({t: v[rng.integers(len(v), size=len(v))] for t, v in scores.items()}, taus) for _ in range(reps)
    ]
    return np.percentile(replicates, 2.5, axis=0), np.percentile(replicates, 97.5, axis=0)
