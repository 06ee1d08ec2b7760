"""Intervals on the evaluation's points (Wilson for success rates, bootstrap for forces) and the aggregate
statistics over runs and tasks (IQM, optimality gap, probability of improvement, performance profiles)."""

from __future__ import annotations

import pytest

from msdgrasp.agents.evaluation import display_name
from msdgrasp.agents.rollout import summarise
from msdgrasp.agents.stats import wilson_interval


def test_wilson_interval_matches_the_closed_form():
    z2 = 1.959963984540054**2
    # all successes: lower bound n / (n + z^2), upper 1; none: the mirror image
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + z2), 1.0))
    assert wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))
    lo, hi = wilson_interval(5, 10)
    assert lo == pytest.approx(1 - hi) and 0.23 < lo < 0.24  # symmetric about 0.5
    with pytest.raises(ValueError):
        wilson_interval(11, 10)


def test_summary_rows_carry_intervals_that_contain_their_estimates():
    import numpy as np

    ep = {"success": np.array([True] * 7 + [False] * 3), "peak_pinch_N": np.linspace(1.0, 2.0, 10),
          "peak_pinch_before_pull_N": np.linspace(0.5, 1.0, 10),
          "mean_pinch_N": np.ones(10), "setpoint_change_N": np.zeros(10), "return": np.zeros(10),
          "slip_mm": np.zeros(10),
          "peak_stress_kPa": np.zeros(10), "time_above_damage_s": np.zeros(10), "time_to_lift_s": np.full(10, 2.0),
          "steps": np.full(10, 100),
          "outcome": np.array(["success"] * 7 + ["slipped"] * 3)}
    row = summarise(0.5, ep)
    lo, hi = row["success_ci95"]
    assert lo < 0.7 < hi and hi - lo > 0.4  # 10 episodes: a wide interval
    lo, hi = row["peak_pinch_ci95_N"]
    assert row["mean_peak_pinch_N"] == pytest.approx(1.5)
    assert lo < 1.5 < hi and hi - lo < 0.7


def test_policies_are_named_by_what_they_are():
    assert display_name("reactive") == "slip-reactive"
    assert display_name("fixed2.5N") == "fixed 2.5 N"
    assert display_name("oracle").startswith("oracle")
    assert display_name("PPO (seed 3)") == "PPO (seed 3)"


# aggregate statistics of Agarwal et al. (2021), checked against closed forms and hand-counted cases

def test_iqm_of_runs_is_the_mean_of_the_middle_half():
    import numpy as np

    from msdgrasp.agents.stats import iqm, iqm_of_runs

    assert iqm(range(1, 9)) == pytest.approx(4.5)  # mean of 3..6
    assert iqm_of_runs(np.arange(1, 9).reshape(4, 2)) == pytest.approx(4.5)  # all runs x tasks together
    assert iqm_of_runs(np.array([[-100, 2], [3, 4], [5, 6], [7, 1000]])) == pytest.approx(4.5)  # outliers cut


def test_mean_of_runs_and_optimality_gap_match_hand_counts():
    import numpy as np

    from msdgrasp.agents.stats import mean_of_runs, optimality_gap

    assert mean_of_runs(np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 0.0]])) == pytest.approx((3.0 + 2.0) / 2)
    m = np.array([[0.5, 1.2], [0.9, 1.0]])
    assert optimality_gap(m, 1.0) == pytest.approx(1.0 - (0.5 + 1.0 + 0.9 + 1.0) / 4)  # 1.2 clipped to 1
    assert optimality_gap(m, 2.0) == pytest.approx(2.0 - 0.9)
    assert optimality_gap(np.full((3, 2), 1.5), 1.0) == 0.0
    with pytest.raises(ValueError, match="gamma"):
        optimality_gap(m, float("nan"))


def test_probability_of_improvement_is_the_fraction_of_winning_pairs():
    import numpy as np
    from scipy.stats import mannwhitneyu

    from msdgrasp.agents.stats import probability_of_improvement as poi

    a, b = np.array([3.0, 4.0, 5.0]), np.array([0.0, 1.0, 2.0, 2.5])
    assert poi([a], [b]) == 1.0 and poi([b], [a]) == 0.0
    assert poi([a], [a]) == 0.5 and poi(b, b.copy()) == 0.5
    # pairs (1,1) tie 1/2, (1,0), (2,1), (2,0) win: 3.5 / 4
    assert poi(np.array([1.0, 2.0]), np.array([1.0, 0.0])) == pytest.approx(0.875)
    assert poi([a, b], [b, a]) == pytest.approx(0.5)  # averaged over tasks
    rng = np.random.default_rng(3)
    x, y = rng.integers(0, 5, 40).astype(float), rng.integers(1, 6, 30).astype(float)  # many ties
    u = mannwhitneyu(x, y, alternative="greater").statistic
    assert poi(x, y) == pytest.approx(u / (40 * 30))
    assert poi(x, y) + poi(y, x) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="x must be a 1-D"):
        poi(np.ones((3, 2)), [np.ones(3)])
    with pytest.raises(ValueError, match="same number of tasks"):
        poi([a, b], [a])


def test_probability_of_improvement_interval_holds_its_estimate():
    import numpy as np

    from msdgrasp.agents.stats import probability_of_improvement_ci

    assert probability_of_improvement_ci([np.arange(3.0) + 10], [np.arange(4.0)]) == (1.0, 1.0, 1.0)
    rng = np.random.default_rng(4)
    x, y = [rng.normal(0.3, 1, 60), rng.normal(0, 1, 40)], [rng.normal(0, 1, 50), rng.normal(0, 1, 40)]
    p, lo, hi = probability_of_improvement_ci(x, y, reps=1000)
    assert 0.0 < lo < p < hi < 1.0 and hi - lo < 0.3
    assert probability_of_improvement_ci(x, y, reps=1000) == (p, lo, hi)  # seeded


def _runs(rng, n_runs, n_episodes, run_sd=1.0, episode_sd=1.0):
    # a per-run offset (seed-to-seed spread) plus per-episode noise, shape (runs, episodes)
    return rng.normal(0, run_sd, (n_runs, 1)) + rng.normal(0, episode_sd, (n_runs, n_episodes))


def test_stratified_bootstrap_ci_holds_its_estimate_and_shrinks_with_more_runs():
    import numpy as np

    from msdgrasp.agents.stats import iqm_of_runs, mean_of_runs, run_task_matrix, stratified_bootstrap_ci

    rng = np.random.default_rng(5)
    few = [_runs(rng, 5, 20), _runs(rng, 5, 30) + 2.0]
    many = [_runs(rng, 50, 20), _runs(rng, 50, 30) + 2.0]
    p5, lo5, hi5 = stratified_bootstrap_ci(few, mean_of_runs, reps=1000)
    p50, lo50, hi50 = stratified_bootstrap_ci(many, mean_of_runs, reps=1000)
    assert p5 == pytest.approx(np.mean([a.mean() for a in few]))
    assert lo5 < p5 < hi5 and lo50 < p50 < hi50
    assert hi50 - lo50 < 0.6 * (hi5 - lo5)  # ~ 1 / sqrt(10) in expectation
    p, lo, hi = stratified_bootstrap_ci(many, iqm_of_runs, reps=500)
    assert p == pytest.approx(iqm_of_runs(run_task_matrix(many))) and lo < p < hi


def test_stratified_bootstrap_ci_of_a_mean_matches_normal_theory():
    import numpy as np

    from msdgrasp.agents.stats import mean_of_runs, stratified_bootstrap_ci

    x = np.random.default_rng(6).normal(0, 1, (400, 1))  # one score per run
    p, lo, hi = stratified_bootstrap_ci(x, mean_of_runs, reps=2000)
    half = 1.959963984540054 * np.std(x) / np.sqrt(len(x))
    assert (hi - lo) / 2 == pytest.approx(half, rel=0.1) and (lo + hi) / 2 == pytest.approx(p, abs=0.2 * half)


def test_resampling_episodes_adds_their_spread_and_only_theirs():
    import numpy as np

    from msdgrasp.agents.stats import mean_of_runs, stratified_bootstrap_ci

    # every run saw the same episodes: runs agree exactly, so only episode resampling can move the mean
    same = np.tile(np.arange(10.0), (6, 1))
    assert stratified_bootstrap_ci(same, mean_of_runs, over_episodes=False, reps=300) == (4.5, 4.5, 4.5)
    p, lo, hi = stratified_bootstrap_ci(same, mean_of_runs, over_episodes=True, reps=300)
    assert p == 4.5 and lo < 4.5 < hi
    # constant within each run: episode resampling changes nothing, and the runs drawn are the same
    flat = np.repeat(np.arange(6.0)[:, None], 8, axis=1)
    assert (stratified_bootstrap_ci([flat, 2 * flat], mean_of_runs, over_episodes=True, reps=300)
            == stratified_bootstrap_ci([flat, 2 * flat], mean_of_runs, over_episodes=False, reps=300))


def test_stratified_bootstrap_ci_takes_vector_statistics_and_refuses_bad_input():
    import numpy as np

    from msdgrasp.agents.stats import stratified_bootstrap_ci

    rng = np.random.default_rng(7)
    tasks = [_runs(rng, 8, 5), _runs(rng, 8, 6)]
    p, lo, hi = stratified_bootstrap_ci(tasks, lambda m: m.mean(axis=0), reps=300)  # one interval per task
    assert p.shape == lo.shape == hi.shape == (2,) and np.all(lo <= p) and np.all(p <= hi)
    with pytest.raises(ValueError, match="confidence must be in"):
        stratified_bootstrap_ci(tasks, np.mean, confidence=1.5)
    with pytest.raises(ValueError, match="reps must be"):
        stratified_bootstrap_ci(tasks, np.mean, reps=0)
    with pytest.raises(ValueError, match="same number of runs"):
        stratified_bootstrap_ci([_runs(rng, 8, 5), _runs(rng, 7, 5)], np.mean)
    with pytest.raises(ValueError, match=r"scores\[0\]"):
        stratified_bootstrap_ci([np.ones(5)], np.mean)


def test_performance_profiles_count_scores_past_each_threshold():
    import numpy as np

    from msdgrasp.agents.stats import performance_profile, performance_profile_at_most

    values, taus = np.array([[1.0, 2.0], [3.0, 4.0]]), [0.0, 2.0, 4.0]
    assert performance_profile(values, taus) == pytest.approx([1.0, 0.5, 0.0])  # > tau
    assert performance_profile_at_most(values, taus) == pytest.approx([0.0, 0.5, 1.0])  # <= tau
    rng = np.random.default_rng(8)
    v, grid = rng.normal(size=200), np.linspace(-3, 3, 61)
    up, down = performance_profile(v, grid), performance_profile_at_most(v, grid)
    assert np.all(np.diff(up) <= 0) and np.all(np.diff(down) >= 0) and np.allclose(up + down, 1.0)
    with pytest.raises(ValueError, match="taus"):
        performance_profile(v, np.ones((2, 2)))


def test_performance_profile_band_brackets_the_profile():
    import numpy as np

    from msdgrasp.agents.stats import performance_profile, performance_profile_band

    rng = np.random.default_rng(9)
    tasks = [_runs(rng, 10, 20), _runs(rng, 10, 40) + 0.5]
    grid = np.linspace(-2, 2, 21)
    prof, lo, hi = performance_profile_band(tasks, grid, reps=500)
    assert prof == pytest.approx(performance_profile(np.stack([a.mean(1) for a in tasks], 1), grid))
    assert np.all(lo <= prof) and np.all(prof <= hi) and np.all(np.diff(lo) <= 0) and np.all(np.diff(hi) <= 0)
    # lower is better, per episode: each task's fraction of episodes <= tau, averaged over tasks
    # (pooled over all 10 episodes it would be 3 / 10)
    ratio = [np.array([[0.5, 1.5], [1.0, 3.0]]), np.array([[0.5, 2.0, 2.0], [2.0, 2.0, 2.0]])]
    prof, lo, hi = performance_profile_band(ratio, [1.0], lower_is_better=True, per_episode=True, reps=300)
    assert prof == pytest.approx([(2 / 4 + 1 / 6) / 2])
    assert lo[0] <= prof[0] <= hi[0]


def test_wilson_lower_bound_and_the_episodes_it_takes():
    from scipy.stats import norm

    from msdgrasp.agents.stats import episodes_for_lower_bound, wilson_lower_bound

    assert wilson_lower_bound(73, 73) >= 0.95 > wilson_lower_bound(72, 72)
    assert episodes_for_lower_bound() == 73
    z2 = norm.ppf(0.975) ** 2
    n = episodes_for_lower_bound(0.9)
    assert n == 35 and n / (n + z2) >= 0.9 > (n - 1) / (n - 1 + z2)  # closed form at n/n
    assert episodes_for_lower_bound(0.95, confidence=0.99) > 73
    with pytest.raises(ValueError, match="target must be in"):
        episodes_for_lower_bound(1.0)
