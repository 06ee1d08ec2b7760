"""The training's domain randomisation and its curriculum: what the ramp draws at each level, that an env moved along it
draws from the new ranges, that the model's task stays the benchmark task, and bad ramps as one-line errors.

Runtime: one tiny training run (2 envs, 1,024 agent steps, 1 epoch), about 15 s.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.agents.models import TrainConfig
from msdgrasp.envs.core import GraspLiftCore, RandomizationConfig, benchmark_config, ramp_randomization
from msdgrasp.envs.task import D_BIAS
from msdgrasp.physics.config import ConfigError, from_dict, replace

ROBUST = RandomizationConfig(mu_distribution="log_uniform", sensor_noise_N=0.08, force_bias_N=0.05, pose_offset_m=0.005,
                             pose_tilt_deg=10.0, pose_azimuth_deg=10.0, latency_steps=(0, 3),
                             force_loop_gain_error=0.2, slip_sensing="binary")


def test_the_ramp_starts_at_the_start_ends_at_the_end_and_is_linear_between():
    start = benchmark_config().randomization
    assert ramp_randomization(start, ROBUST, 0.0) == start
    assert ramp_randomization(start, ROBUST, 1.0) == ROBUST
    assert ramp_randomization(start, ROBUST, 7.0) == ROBUST  # (clamped)
    half = ramp_randomization(start, ROBUST, 0.5)
    assert half.sensor_noise_N == pytest.approx(0.5 * (start.sensor_noise_N + 0.08))
    assert half.pose_offset_m == pytest.approx(0.5 * (start.pose_offset_m + 0.005))
    assert half.force_loop_gain_error == pytest.approx(0.1)
    assert half.mu_range == start.mu_range  # (unchanged where both agree)
    assert half.latency_steps == (0, 2)  # whole steps: 1.5 rounds to 2
    assert half.slip_sensing == "binary"  # a choice switches to the end's as soon as the ramp begins


def test_a_noise_level_range_ramps_from_the_tasks_one_level():
    """The task's noise, one level (no lowest), is the range [s, s]: the ramp widens it to the training's range and
    never puts the lowest level above the highest on the way."""
    start = benchmark_config().randomization
    end = replace(ROBUST, sensor_noise_low_N=0.01)
    for level in np.linspace(0.05, 0.95, 19):
        mid = ramp_randomization(start, end, level)
        assert mid.sensor_noise_low_N == pytest.approx(start.sensor_noise_N + level * (0.01 - start.sensor_noise_N))
        assert mid.sensor_noise_low_N <= mid.sensor_noise_N
    assert ramp_randomization(start, end, 1.0) == end
    assert ramp_randomization(end, start, 1.0).sensor_noise_low_N is None  # (back to one level)


def test_the_training_task_follows_the_ramp_over_the_run():
    config = TrainConfig(train_randomization=ROBUST, randomization_ramp=(0.2, 0.6))
    nominal = config.env.randomization
    assert config.training_task(0.0).randomization == nominal
    assert config.training_task(0.2).randomization == nominal
    assert config.training_task(0.4).randomization.sensor_noise_N == pytest.approx(
        0.5 * (nominal.sensor_noise_N + 0.08))
    assert config.training_task(0.6).randomization == ROBUST
    assert config.training_task().randomization == ROBUST  # what validation runs on
    # without a ramp the randomisation is the training's from the first step; without it, env's
    assert TrainConfig(train_randomization=ROBUST).training_task(0.0).randomization == ROBUST
    assert TrainConfig().training_task(0.0) == TrainConfig().env


@pytest.mark.parametrize("over, field", [
    ({"randomization_ramp": [0.2, 0.6]}, "train_randomization"),
    ({"randomization_ramp": [0.6, 0.2], "train_randomization": {}}, "randomization_ramp"),
    ({"randomization_ramp": [0.2, 1.5], "train_randomization": {}}, "randomization_ramp"),
    ({"train_randomization": {"sensor_noise": 0.1}}, "sensor_noise"),
    # a ramp starts from env's ranges: the training's must hold them (the env is built on the training's)
    ({"randomization_ramp": [0.2, 0.6], "train_randomization": {"stiffness_scale_range": [0.9, 1.1]}},
     "train_randomization.stiffness_scale_range"),
])
def test_bad_curricula_are_one_line_errors_naming_the_field(over, field):
    with pytest.raises(ConfigError, match=field) as info:
        from_dict(TrainConfig, over)
    assert "\n" not in str(info.value)


def test_an_env_moved_along_the_ramp_draws_its_new_episodes_from_the_new_ranges():
    built = replace(benchmark_config(), randomization=ROBUST)
    core = GraspLiftCore(built, 8)
    core.set_randomization(benchmark_config().randomization)
    for b in range(8):
        core.seed(b, b)
        core.reset(b)
    assert (core.draws[:, D_BIAS:D_BIAS + 3] == 0).all()  # the bias axis is off: nothing drawn, no bias
    core.set_randomization(ROBUST)
    for b in range(8):
        core.reset(b)
    bias = core.draws[:, D_BIAS:D_BIAS + 3]
    assert (np.abs(bias) <= 0.05).all() and np.abs(bias).max() > 0.01
    # an env cannot draw stiffer or lighter tissue than it was built for (its substeps assume them)
    with pytest.raises(ConfigError, match="stiffness_scale_range"):
        core.set_randomization(replace(ROBUST, stiffness_scale_range=(0.8, 3.0)))


def test_a_curriculum_training_moves_the_env_and_keeps_the_benchmark_task_as_the_models(tmp_path, monkeypatch):
    pytest.importorskip("stable_baselines3")
    from msdgrasp.agents.learners.sb3_layout import model_train_config
    from msdgrasp.agents.training import train

    levels = []
    original = GraspLiftCore.set_randomization

    def spy(self, randomization):
        levels.append(randomization.sensor_noise_N)
        return original(self, randomization)

    monkeypatch.setattr(GraspLiftCore, "set_randomization", spy)
    config = from_dict(TrainConfig, {
        "n_envs": 2, "total_timesteps": 1024, "checkpoint_every": 512, "validation_episodes": 1,
        "validation_mu": [0.5], "torch_threads": 1, "train_randomization": {"sensor_noise_N": 0.08},
        "randomization_ramp": [0.25, 0.5], "ppo": {"n_steps": 128, "batch_size": 64, "n_epochs": 1, "use_sde": True}})
    train(config, tmp_path, progress=False)
    # rollouts start at 0, 256, 512 and 768 of 1,024 steps: levels 0, 0, 1 (set once per change), then unchanged
    assert levels == pytest.approx([0.02, 0.08])
    assert model_train_config(tmp_path / "best_model.zip").env == config.env
    # the suite reads the ranges the model was trained under (its in-range conditions) from the model
    from msdgrasp.agents.evaluation import trained_ranges_of

    assert trained_ranges_of(["reactive", str(tmp_path / "best_model.zip")]).sensor_noise_N == 0.08
