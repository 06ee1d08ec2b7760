"""Fitting a friction estimator (:class:`.friction.FrictionEstimator`) on a training's randomised task: the closing
seen by the slip-feedback controller with a probe grip, mu known from each episode's draws."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..envs.core import GraspLiftConfig
from .controllers import SlipFeedbackPolicy, minimal_force
from .friction import MU_GRID, FrictionEstimator, fit_ridge
from .protocol import check_not_sealed


class _FeatureTap:
    """Stands in for an estimator in the controller that collects: keeps the features the controller computes when
    its gate opens (so a fit reads exactly what the deployed controller will) and leaves its grip at the probe."""

    def __init__(self, probe_force_N: float) -> None:
        self.probe_force_N = probe_force_N
        self.features: list[np.ndarray] = []

    def mu(self, features: np.ndarray) -> float:
        self.features.append(features)
        return 1.0

    def grip_N(self, mu: float) -> float:
        return 0.0


def collect_closing_features(task: GraspLiftConfig, episodes: int, seed: int, probe_force_N: float,
                             batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The closing features and the true mu of ``episodes`` episodes of ``task`` (reset seeds seed, seed + 1, ...),
    each as the slip-feedback controller with a friction estimator computes them, closing to ``probe_force_N``
    with a pinch-gated pull. Refuses (ConfigError) seeds that reach the sealed evaluation seeds (:mod:`.protocol`):
    an estimator is fitted, and its controller tuned, on these episodes."""
    from ..envs.grasp_lift import GraspLiftVectorEnv

    check_not_sealed(seed, episodes, "seed", via=f"fitting episodes: seed + i, i < episodes = {episodes}")

    features, mus = [], []
    for start in range(0, episodes, batch):
        n = min(batch, episodes - start)
        env = GraspLiftVectorEnv(n, task)
        obs, info = env.reset(seed=seed + start)
        tap = _FeatureTap(probe_force_N)
        pol = SlipFeedbackPolicy(task, initial_force_N=probe_force_N, gain_N_per_mm=0.0, pinch_gate=0.9,
                                 friction_estimator=tap)
        pol.reset([{}] * n)
        order: list[int] = []  # the episode of each feature vector, in the order the controller computed them
        for _ in range(task.max_episode_steps):
            closing = np.isnan(pol.mu_estimate)
            action = pol.act(obs)
            order += list(np.flatnonzero(closing & ~np.isnan(pol.mu_estimate)))  # (ascending, as it estimates)
            if not np.isnan(pol.mu_estimate).any():
                break
            obs, *_ = env.step(action)
        if len(order) != n:
            raise RuntimeError(f"{n - len(order)} of {n} episodes never opened the gate within the episode")
        batch_features = np.empty((n, len(tap.features[0])))
        batch_features[order] = tap.features
        features += list(batch_features)
        mus += list(np.asarray(info["mu"], dtype=np.float64))
    return np.array(features), np.array(mus)


def fit_friction_estimator(task: GraspLiftConfig, episodes: int = 768, seed: int = 20000, probe_force_N: float = 0.7,
                           pull: float = 0.3, ridge: float = 1.0, mu_grid: Sequence[float] = MU_GRID,
                           table_task: GraspLiftConfig | None = None,
                           fitted_on: str = "") -> tuple[FrictionEstimator, dict[str, Any]]:
    """Fit an estimator on ``episodes`` episodes of ``task`` (the randomised task whose sensing it must read; reset
    seeds ``seed .. seed + episodes - 1``, none of them sealed: :mod:`.protocol`) and tabulate the oracle's minimal
    fixed force at ``mu_grid`` and ``pull`` on ``table_task`` (the benchmark task; default ``task``); returns it and
    its fit's report (relative errors on the fitting episodes)."""
    x, mu = collect_closing_features(task, episodes, seed, probe_force_N)
    mean, scale, weights = fit_ridge(x, mu, ridge)
    table = tuple(minimal_force(table_task or task, m, pull, 0.05) for m in mu_grid)
    est = FrictionEstimator(tuple(mean), tuple(scale), tuple(weights), float(probe_force_N), float(pull),
                            tuple(float(m) for m in mu_grid), tuple(float(f) for f in table), fitted_on)
    rel = np.abs(np.array([est.mu(f) for f in x]) / mu - 1)
    report = {"episodes": int(len(mu)), "median_relative_error": float(np.median(rel)),
              "p90_relative_error": float(np.percentile(rel, 90))}
    return est, report
