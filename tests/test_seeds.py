"""Seeds are the unit of a result: parsing, the statistics of the aggregate, and a tiny multi-seed run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msdgrasp.agents.seeds import aggregate, bootstrap_ci, iqm, parse_seeds, run_seeds
from msdgrasp.agents.models import TrainConfig
from msdgrasp.agents.protocol import EVALUATION_SEED
from msdgrasp.physics.config import ConfigError, from_dict


@pytest.mark.parametrize("text, seeds", [("0-4", [0, 1, 2, 3, 4]), ("3", [3]), ("0,3,7", [0, 3, 7]), (" 2-3 ", [2, 3])])
def test_parse_seeds(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text", ["", "a-b", "4-1", "1,1", "-3", "0-99", "1.5"])
def test_parse_seeds_rejects(text):
    with pytest.raises(ConfigError, match="--seeds"):
        parse_seeds(text)


def test_iqm_is_the_mean_of_the_middle_half():
    # 8 values: the middle half is 3, 4, 5, 6 -> 4.5, whatever the outliers do
    assert iqm([-100, 2, 3, 4, 5, 6, 7, 1000]) == pytest.approx(4.5)


def test_bootstrap_interval_brackets_the_mean_and_shrinks_with_agreement():
    rng = np.random.default_rng(0)
    wide = rng.normal(0.8, 0.1, 5)
    lo, hi = bootstrap_ci(wide)
    assert lo < wide.mean() < hi and hi - lo < 0.3
    assert bootstrap_ci([0.9, 0.9, 0.9]) == (0.9, 0.9)  # no spread, no interval
    agg = aggregate([1.0, 0.9, 0.7, 1.0, 0.95])
    assert agg["n"] == 5 and agg["min"] == 0.7 and agg["max"] == 1.0
    assert agg["mean"] == pytest.approx(0.91) and agg["ci95"][0] <= agg["mean"] <= agg["ci95"][1]


def test_the_aggregate_leaves_out_seeds_with_nothing_to_measure():
    """A seed whose episodes never lifted has no time to lift (NaN, null in JSON): the aggregate is over the others."""
    agg = aggregate([1.0, float("nan"), 3.0, None])
    assert agg["n"] == 2 and agg["mean"] == 2.0 and agg["min"] == 1.0 and agg["max"] == 3.0
    assert aggregate([float("nan")])["n"] == 0 and np.isnan(aggregate([float("nan")])["mean"])


def test_a_tiny_two_seed_run_writes_per_seed_and_aggregate_results(tmp_path):
    """Two seeds in two processes: per-seed runs, seeds.json / .md / learning_curves.png; the aggregate is
    computed from the per-seed numbers it reports (so a wrong aggregation fails here)."""
    config = from_dict(TrainConfig, {"total_timesteps": 512, "n_envs": 2, "checkpoint_every": 256,
                                     "validation_episodes": 1, "validation_mu": [0.5],
                                     "ppo": {"n_steps": 128, "batch_size": 128, "n_epochs": 1, "use_sde": True}})
    res = run_seeds(config, [0, 1], tmp_path, workers=2, episodes=1, mus=(0.2, 0.5), progress=False)
    for name in ("seeds.json", "seeds.md", "learning_curves.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert (tmp_path / "learning_curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads((tmp_path / "seeds.json").read_text())
    assert [r["seed"] for r in data["per_seed"]] == [0, 1] and data["training_seeds"] == [0, 1]
    # every seed evaluated on the sealed evaluation seeds, and the report says so
    assert data["seeds"] == {"first": EVALUATION_SEED, "count": 1, "sealed": True}
    for rec in data["per_seed"]:
        assert (tmp_path / f"seed_{rec['seed']}" / "best_model.zip").is_file()
        assert rec["timesteps"] >= 512 and len(rec["validation"]) >= 2  # a checkpoint and the final model
    ratios = [r["peak_pinch_over_oracle_min"] for r in data["per_seed"]]
    assert data["aggregate"]["peak_pinch_over_oracle_min"]["mean"] == pytest.approx(np.mean(ratios))
    assert data["aggregate"]["peak_pinch_over_oracle_min"]["min"] == pytest.approx(min(ratios))
    # and how far each seed trained (fewer steps than total_timesteps where early stopping ended it)
    assert data["aggregate"]["timesteps"]["mean"] == pytest.approx(np.mean([r["timesteps"] for r in data["per_seed"]]))
    # the baselines are part of every multi-seed result; the oracle succeeds on the nominal-ish tissue
    assert set(data["baselines"]) == {"reactive", "oracle"}
    assert data["baselines"]["oracle"]["success_by_mu"]["0.5"] == 1.0
    md = (tmp_path / "seeds.md").read_text()
    assert "PPO (seed 0)" in md and "PPO (seed 1)" in md and "slip-reactive" in md and "bootstrap" in md
    assert "| timesteps |" in md and "time to lift 0.3-0.9 (s)" in md and "| time_to_lift_ref_s |" in md
    assert f"seeds {EVALUATION_SEED}..{EVALUATION_SEED}: sealed" in md
    # the time to lift of a seed: its row's mean over the episodes that lifted (mu 0.5 is its one reference mu)
    for rec in data["per_seed"]:
        [row] = [r for r in rec["rows"] if r["mu"] == 0.5]
        assert rec["time_to_lift_ref_s"] == row["mean_time_to_lift_s"]
    assert res["files"]["json"] == str(tmp_path / "seeds.json")
