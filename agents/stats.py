"""Small statistics for results over episodes and seeds (numpy and scipy do the work).

The aggregate estimators below follow Agarwal et al., "Deep Reinforcement Learning at the Edge of the Statistical
Precipice", NeurIPS 2021 (arXiv:2108.13264), with the definitions of their reference implementation, the rliable
package (github.com/google-research/rliable: rliable/metrics.py and rliable/library.py). rliable itself is not a
dependency: it pulls in arch, absl and more for what is a few lines of numpy here.

Vocabulary, as in rliable: a *run* is one independent repeat (one training seed), a *task* one evaluation
condition, and a run's score on a task is the mean of its episodes there, so per-run scores form a (runs, tasks)
matrix. Scores keep whatever unit their metric has (success as 0/1, forces in N, ratios dimensionless) and every
estimator returns that unit; probabilities and fractions are dimensionless, in [0, 1].
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence

import numpy as np

# a list over tasks of (runs, episodes) arrays, or one such array for a single task
Scores = Sequence[np.ndarray] | np.ndarray
Statistic = Callable[[np.ndarray], "float | np.ndarray"]


def iqm(values: Sequence[float]) -> float:
    """Interquartile mean (Agarwal et al. 2021): the mean of the middle 50% (scipy's trimmed mean)."""
    from scipy.stats import trim_mean

    return float(trim_mean(np.asarray(values, dtype=np.float64), 0.25))


def bootstrap_ci(values: Sequence[float], confidence: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile-bootstrap interval of the mean (scipy.stats.bootstrap, 10k resamples). One value or no
    spread: the value itself at both ends."""
    from scipy.stats import bootstrap

    x = np.asarray(values, dtype=np.float64)
    if len(x) < 2 or np.ptp(x) == 0.0:
        return float(np.mean(x)), float(np.mean(x))
    res = bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=10_000, method="percentile",
                    random_state=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a success rate (scipy.stats.binomtest): sensible at 0/n and n/n, where
    the normal approximation collapses to a zero-width interval."""
    from scipy.stats import binomtest

    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n and n >= 1, got {successes}/{n}")
    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def wilson_lower_bound(successes: int, n: int, confidence: float = 0.95) -> float:
    """Lower end of the two-sided Wilson interval at `confidence` (so a one-sided bound at (1 + confidence) / 2):
    the success rate (dimensionless, in [0, 1]) that `successes` out of `n` episodes support."""
    _check_confidence(confidence)
    return wilson_interval(successes, n, confidence)[0]


def episodes_for_lower_bound(target: float = 0.95, confidence: float = 0.95) -> int:
    """The fewest episodes n for which n successes out of n give a Wilson lower bound (`wilson_lower_bound` at
    `confidence`) of at least `target`: the smallest evaluation that can show a success rate >= target at all.
    73 for the defaults (72/72 reaches only 0.9494)."""
    from scipy.stats import norm

    if not 0.0 < target < 1.0:
        raise ValueError(f"target must be in (0, 1), got {target}")
    _check_confidence(confidence)
    z2 = float(norm.ppf(0.5 + confidence / 2)) ** 2
    # at n/n the Wilson lower end is n / (n + z^2), so n >= target z^2 / (1 - target); start just below the
    # closed form and settle on the interval itself, so that the answer agrees with wilson_lower_bound to the bit
    n = max(1, math.ceil(target * z2 / (1.0 - target)) - 1)
    while wilson_lower_bound(n, n, confidence) < target:
        n += 1
    while n > 1 and wilson_lower_bound(n - 1, n - 1, confidence) >= target:
        n -= 1
    return n


# ---------------------------------------------------------------------------------------------------------------
# aggregates of a (runs, tasks) matrix: rliable/metrics.py


def mean_of_runs(matrix: np.ndarray) -> float:
    """Mean over tasks of the per-task mean over runs (rliable's `aggregate_mean`); `matrix` is (runs, tasks)
    (a 1-D array is one task). Same unit as the scores."""
    m = _as_matrix(matrix)
    return float(np.mean(np.mean(m, axis=0)))


def iqm_of_runs(matrix: np.ndarray) -> float:
    """Interquartile mean over every run x task score together (rliable's `aggregate_iqm`): the mean of the middle
    50% after dropping the lowest and highest 25%. Robust to a few outlier runs, yet far less noisy than the
    median. `matrix` is (runs, tasks) (a 1-D array is one task); same unit as the scores."""
    from scipy.stats import trim_mean

    return float(trim_mean(_as_matrix(matrix), proportiontocut=0.25, axis=None))


def optimality_gap(matrix: np.ndarray, gamma: float = 1.0) -> float:
    """How far the scores fall short of `gamma` on average, scores above `gamma` counting as `gamma` (rliable's
    `aggregate_optimality_gap`): gamma - mean(min(score, gamma)). 0 when every run reaches gamma; lower is better.
    `matrix` is (runs, tasks) (a 1-D array is one task); `gamma` and the result in the scores' unit."""
    if not math.isfinite(gamma):
        raise ValueError(f"gamma must be finite, got {gamma}")
    return float(gamma - np.mean(np.minimum(_as_matrix(matrix), gamma)))


# ---------------------------------------------------------------------------------------------------------------
# stratified bootstrap: rliable/library.py (StratifiedBootstrap, get_interval_estimates)


def run_task_matrix(scores: Scores) -> np.ndarray:
    """The (runs, tasks) matrix of per-run per-task episode means that `stratified_bootstrap_ci` hands its
    statistic. `scores` as there."""
    return np.stack([a.mean(axis=1) for a in _as_tasks(scores)], axis=1)


def stratified_bootstrap_ci(scores: Scores, statistic: Statistic, confidence: float = 0.95, reps: int = 2000,
                            seed: int = 0, over_episodes: bool = True
                            ) -> tuple[float | np.ndarray, float | np.ndarray, float | np.ndarray]:
    """Stratified percentile-bootstrap interval of an aggregate statistic (Agarwal et al. 2021; rliable's
    `get_interval_estimates` with `StratifiedBootstrap` over runs, method "percentile").

    `scores`: a list over tasks of 2-D arrays (runs, episodes), the same number of runs in every task (episodes may
    differ between tasks), or one 2-D array (runs, episodes) for a single task; any unit.
    `statistic`: called with the (runs, tasks) matrix of per-run per-task episode means (rliable's input; see
    `run_task_matrix`), e.g. `iqm_of_runs`, `mean_of_runs`, `lambda m: optimality_gap(m, 1.0)`; it returns a float
    or a 1-D array (then each entry gets its interval).
    Each replicate resamples, within each task independently, the runs with replacement (rliable's stratified
    bootstrap: tasks fixed, seeds redrawn) and, with `over_episodes`, then the episodes with replacement within
    each resampled run, so that the interval covers both seed-to-seed and episode-to-episode variation (a
    two-stage bootstrap; rliable stops at runs: `over_episodes=False`). The run draws come from their own random
    stream, so the two settings redraw the same runs.
    `confidence` in (0, 1), `reps` >= 1 replicates, `seed` fixes them.
    Returns (point, lo, hi): the statistic of the data as observed and the (1 - confidence) / 2 and
    (1 + confidence) / 2 percentiles of its replicates, in the statistic's unit.
    """
    tasks = _as_tasks(scores)
    _check_confidence(confidence)
    _check_reps(reps)
    point = statistic(run_task_matrix(tasks))
    draws = np.array([statistic(np.stack([a.mean(axis=1) for a in resampled], axis=1))
                      for resampled in _resamples(tasks, reps, seed, over_episodes)], dtype=np.float64)
    lo, hi = _percentile_interval(draws, confidence)
    return _plain(point), _plain(lo), _plain(hi)


# ---------------------------------------------------------------------------------------------------------------
# probability of improvement: rliable/metrics.py (probability_of_improvement), StratifiedIndependentBootstrap


def probability_of_improvement(x: Sequence[np.ndarray] | np.ndarray, y: Sequence[np.ndarray] | np.ndarray) -> float:
    """P(X > Y): the chance that a score of X beats one of Y on the same task, averaged over tasks (Agarwal et
    al. 2021; rliable's `probability_of_improvement`). Per task it is the Mann-Whitney U statistic of X over Y
    divided by n_x n_y, i.e. the fraction of (x, y) pairs with x > y, ties counting 1/2: 1 when every x beats every
    y, 0.5 for identical samples, and P(X > Y) + P(Y > X) = 1. Only higher-is-better: for a lower-is-better metric
    pass the negated scores (or swap x and y, which counts ties the same way).
    `x`, `y`: lists over tasks (the same tasks, in the same order) of 1-D score arrays, e.g. per-episode or per-run
    scores; a 1-D array is one task. Unpaired: the lengths may differ, and a pairing of the samples is not used.
    Dimensionless, in [0, 1]."""
    xs, ys = _as_sample_pairs(x, y)
    return float(np.mean([_u_fraction(a[None, :], b[None, :])[0] for a, b in zip(xs, ys)]))


def probability_of_improvement_ci(x: Sequence[np.ndarray] | np.ndarray, y: Sequence[np.ndarray] | np.ndarray,
                                  confidence: float = 0.95, reps: int = 2000, seed: int = 0
                                  ) -> tuple[float, float, float]:
    """`probability_of_improvement` with its stratified percentile-bootstrap interval: each replicate resamples x
    and y independently, with replacement, within each task (rliable's `StratifiedIndependentBootstrap`).
    `x`, `y` as there; `confidence` in (0, 1), `reps` >= 1, `seed` fixes the draws. Returns (point, lo, hi),
    dimensionless."""
    xs, ys = _as_sample_pairs(x, y)
    _check_confidence(confidence)
    _check_reps(reps)
    rx, ry = _streams(seed)
    per_task = []
    for a, b in zip(xs, ys):
        # all replicates of a task at once: one (reps, n) resample of each side
        per_task.append(_u_fraction(a[rx.integers(len(a), size=(reps, len(a)))],
                                    b[ry.integers(len(b), size=(reps, len(b)))]))
    draws = np.mean(per_task, axis=0)
    lo, hi = _percentile_interval(draws, confidence)
    return probability_of_improvement(xs, ys), float(lo), float(hi)


# ---------------------------------------------------------------------------------------------------------------
# performance profiles: rliable/library.py (create_performance_profile with score distributions)


def performance_profile(values: np.ndarray | Sequence[float], taus: np.ndarray | Sequence[float]) -> np.ndarray:
    """Higher is better: the fraction of `values` above each threshold tau, i.e. the empirical tail P(score > tau)
    (rliable's `create_performance_profile` with run-score distributions, `run_score_deviation`). `values`: any
    array of scores, taken all together, e.g. a (runs, tasks) matrix as rliable does, or per-episode scores; `taus`
    1-D, in the scores' unit. Returns a 1-D array like `taus`, dimensionless, non-increasing in tau."""
    v, t = _profile_args(values, taus)
    # sorted once, a tau's count is one binary search: P(score > tau) = 1 - #(score <= tau) / n
    return 1.0 - np.searchsorted(v, t, side="right") / len(v)


def performance_profile_at_most(values: np.ndarray | Sequence[float],
                                taus: np.ndarray | Sequence[float]) -> np.ndarray:
    """Lower is better (e.g. the force ratio, peak over needed force): the fraction of `values` at or below each
    threshold tau, P(score <= tau), the complement of `performance_profile`. Arguments as there. Returns a 1-D array
    like `taus`, dimensionless, non-decreasing in tau."""
    v, t = _profile_args(values, taus)
    return np.searchsorted(v, t, side="right") / len(v)


def performance_profile_band(scores: Scores, taus: np.ndarray | Sequence[float], lower_is_better: bool = False,
                             per_episode: bool = False, confidence: float = 0.95, reps: int = 2000, seed: int = 0,
                             over_episodes: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A performance profile with its pointwise stratified-bootstrap band (rliable's `create_performance_profile`,
    which returns the profile and its percentile intervals at each tau).
    `scores`, `confidence`, `reps`, `seed`, `over_episodes` as in `stratified_bootstrap_ci`; `taus` 1-D, in the
    scores' unit. `lower_is_better` counts scores <= tau (`performance_profile_at_most`) rather than > tau.
    `per_episode=False`: the profile of the (runs, tasks) matrix of per-run means (rliable's run-score
    distribution); `per_episode=True`: of every episode's score, the fraction taken within each task and then
    averaged over tasks, so that each task weighs the same whatever its number of episodes (e.g. "the fraction of
    episodes with force ratio <= tau").
    Returns (profile, lo, hi), three 1-D arrays like `taus`, dimensionless."""
    tasks = _as_tasks(scores)
    _check_confidence(confidence)
    _check_reps(reps)
    profile = performance_profile_at_most if lower_is_better else performance_profile
    _profile_args(tasks[0], taus)  # checks taus up front

    def of(task_arrays: list[np.ndarray]) -> np.ndarray:
        if per_episode:
            return np.mean([profile(a, taus) for a in task_arrays], axis=0)
        return profile(np.stack([a.mean(axis=1) for a in task_arrays], axis=1), taus)

    draws = np.array([of(resampled) for resampled in _resamples(tasks, reps, seed, over_episodes)])
    lo, hi = _percentile_interval(draws, confidence)
    return of(tasks), lo, hi


# ---------------------------------------------------------------------------------------------------------------
# helpers


def _check_confidence(confidence: float) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")


def _check_reps(reps: int) -> None:
    if isinstance(reps, bool) or int(reps) != reps or reps < 1:
        raise ValueError(f"reps must be an integer >= 1, got {reps}")


def _as_matrix(matrix: np.ndarray) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.ndim == 1:
        m = m[:, None]
    if m.ndim != 2 or m.size == 0:
        raise ValueError(f"matrix must be a non-empty (runs, tasks) array, got shape {m.shape}")
    return m


def _as_tasks(scores: Scores) -> list[np.ndarray]:
    """A list over tasks of float (runs, episodes) arrays with the same number of runs, all finite."""
    if isinstance(scores, np.ndarray):
        if scores.ndim != 2:
            raise ValueError(f"scores must be a 2-D (runs, episodes) array or a list of them, got shape {scores.shape}")
        scores = [scores]
    tasks = [np.asarray(a, dtype=np.float64) for a in scores]
    if not tasks:
        raise ValueError("scores must hold at least one task, got none")
    for i, a in enumerate(tasks):
        if a.ndim != 2 or a.size == 0:
            raise ValueError(f"scores[{i}] must be a non-empty 2-D (runs, episodes) array (one score per run: "
                             f"reshape(-1, 1)), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"scores[{i}] must be finite, got NaN or inf")
    runs = sorted({a.shape[0] for a in tasks})
    if len(runs) > 1:
        raise ValueError(f"scores must have the same number of runs in every task, got {runs}")
    return tasks


def _as_samples(x: Sequence[np.ndarray] | np.ndarray, name: str) -> list[np.ndarray]:
    """A list over tasks of finite, non-empty 1-D float arrays."""
    if isinstance(x, np.ndarray):
        if x.ndim != 1:
            # a (runs, tasks) matrix m as rliable takes it is list(m.T); refusing 2-D avoids reading it transposed
            raise ValueError(f"{name} must be a 1-D array or a list over tasks of them (for a (runs, tasks) matrix "
                             f"m: list(m.T)), got shape {x.shape}")
        x = [x]
    out = [np.asarray(a, dtype=np.float64) for a in x]
    if not out:
        raise ValueError(f"{name} must hold at least one task, got none")
    for i, a in enumerate(out):
        if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
            raise ValueError(f"{name}[{i}] must be a non-empty, finite 1-D array, got shape {a.shape}")
    return out


def _as_sample_pairs(x: Sequence[np.ndarray] | np.ndarray,
                     y: Sequence[np.ndarray] | np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    xs, ys = _as_samples(x, "x"), _as_samples(y, "y")
    if len(xs) != len(ys):
        raise ValueError(f"x and y must cover the same number of tasks, got {len(xs)} and {len(ys)}")
    return xs, ys


def _u_fraction(xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Row by row, the Mann-Whitney U of x over y divided by n_x n_y, from the midranks of the pooled sample:
    U = (sum of x's ranks) - n_x (n_x + 1) / 2, and a tie's midrank counts it 1/2. xs (k, n_x), ys (k, n_y)."""
    from scipy.stats import rankdata

    n_x, n_y = xs.shape[1], ys.shape[1]
    ranks = rankdata(np.concatenate([xs, ys], axis=1), axis=1)
    return (ranks[:, :n_x].sum(axis=1) - n_x * (n_x + 1) / 2) / (n_x * n_y)


def _profile_args(values: np.ndarray | Sequence[float], taus: np.ndarray | Sequence[float]
                  ) -> tuple[np.ndarray, np.ndarray]:
    v = np.sort(np.asarray(values, dtype=np.float64).ravel())
    t = np.asarray(taus, dtype=np.float64)
    if v.size == 0:
        raise ValueError("values must hold at least one score, got none")
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"taus must be a non-empty 1-D array, got shape {t.shape}")
    return v, t


def _streams(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Two independent generators from one seed: one for runs (or x), one for episodes (or y)."""
    a, b = np.random.SeedSequence(seed).spawn(2)
    return np.random.default_rng(a), np.random.default_rng(b)


def _resamples(tasks: list[np.ndarray], reps: int, seed: int, over_episodes: bool) -> Iterator[list[np.ndarray]]:
    """`reps` stratified resamples of the tasks' (runs, episodes) arrays: runs with replacement within each task,
    then, with `over_episodes`, episodes with replacement within each drawn run."""
    run_rng, episode_rng = _streams(seed)
    for _ in range(reps):
        resampled = []
        for a in tasks:
            n_runs, n_episodes = a.shape
            # tasks are strata: each redraws its own runs, so no task is ever dropped or doubled
            drawn = a[run_rng.integers(n_runs, size=n_runs)]
            if over_episodes and n_episodes > 1:
                drawn = np.take_along_axis(drawn, episode_rng.integers(n_episodes, size=drawn.shape), axis=1)
            resampled.append(drawn)
        yield resampled


def _percentile_interval(draws: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """The (1 - confidence) / 2 and (1 + confidence) / 2 percentiles of the replicates, along the first axis."""
    tail = 100.0 * (1.0 - confidence) / 2.0
    return np.percentile(draws, tail, axis=0), np.percentile(draws, 100.0 - tail, axis=0)


def _plain(value: float | np.ndarray) -> float | np.ndarray:
    """A 0-d result as a float, anything else as an array."""
    a = np.asarray(value, dtype=np.float64)
    return float(a) if a.ndim == 0 else a
