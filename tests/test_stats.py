"""Intervals on the evaluation's points: Wilson for success rates, bootstrap for forces."""

from __future__ import annotations

import pytest

from msdgrasp.agents.evaluation import _summarise, display_name
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
    row = _summarise(0.5, ep)
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
