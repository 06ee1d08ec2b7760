"""Residual policies: a trained correction added to a controller's action, the same in training and wherever the
model runs.

Runtime: one 256-step residual training (2 envs), a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.agents.controllers import ConstantPolicy, SlipFeedbackPolicy
from msdgrasp.agents.models import TrainConfig
from msdgrasp.agents.residual import ResidualPolicy, compose, residual_venv
from msdgrasp.physics.config import ConfigError, from_dict

SHORT = {
    "n_envs": 2, "torch_threads": 1, "total_timesteps": 256, "checkpoint_every": 256, "validation_episodes": 1,
    "validation_mu": [0.5], "residual_base": "slipfeedback", "residual_scale": 0.5,
    "ppo": {"n_steps": 128, "batch_size": 128, "n_epochs": 1, "learning_rate": 1e-4, "use_sde": True},
}


def test_compose_adds_the_scaled_correction_and_clips_to_the_action_range():
    base = np.array([[-0.4, 0.0], [0.9, -1.0]])
    out = compose(base, np.array([[1.0, -1.0], [1.0, 0.2]]), 0.5)
    assert out.dtype == np.float32
    assert np.allclose(out, [[0.1, -0.5], [1.0, -0.9]])
    # one scale per action: (jaw, pull); 0 leaves the pull to the controller
    assert np.allclose(compose(base, np.ones((2, 2)), (0.5, 0.0)), [[0.1, 0.0], [1.0, -1.0]])


def test_a_raising_correction_never_lowers_the_controllers_action():
    rng = np.random.default_rng(1)
    base = rng.uniform(-1.0, 1.0, size=(64, 2))
    residual = rng.uniform(-1.0, 1.0, size=(64, 2))
    out = compose(base, residual, (0.3, 0.0), mode="raise")
    assert np.all(out[:, 0] >= np.float32(base[:, 0]) - 1e-6)  # the grip only goes up
    assert np.allclose(out[:, 1], base[:, 1])  # scale 0: the pull is the controller's
    up = residual[:, 0] > 0
    assert np.allclose(out[up, 0], np.clip(base[up, 0] + 0.3 * residual[up, 0], -1, 1))
    assert np.allclose(out[~up, 0], base[~up, 0])
    with pytest.raises(ValueError, match="'add' or 'raise'"):
        compose(base, residual, 0.3, mode="lower")


def test_the_training_env_sends_the_controllers_action_plus_the_correction():
    from msdgrasp.envs.sb3 import GraspLiftSB3VecEnv

    config = from_dict(TrainConfig, SHORT)
    venv = residual_venv(GraspLiftSB3VecEnv(2, config.training_task(), seed=0), config)
    twin = SlipFeedbackPolicy(config.training_task())
    obs = venv.reset()
    twin.reset([{}, {}])
    rng = np.random.default_rng(0)
    for _ in range(30):
        residual = rng.uniform(-1.0, 1.0, size=(2, 2)).astype(np.float32)
        expected = compose(twin.act(obs), residual, 0.5)
        obs, _, dones, _ = venv.step(residual)
        assert np.allclose(venv.core.act, expected, atol=1e-6)  # the action the task received
        for i in np.flatnonzero(dones):
            twin.reset_one(int(i), {})


def test_a_trained_residual_model_runs_on_its_controller_wherever_it_is_loaded(tmp_path):
    from msdgrasp.agents.model_policy import ModelPolicy
    from msdgrasp.agents.learners import learner_of_model
    from msdgrasp.agents.training import train
    from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv

    train(from_dict(TrainConfig, SHORT), tmp_path, progress=False)
    path = tmp_path / "best_model.zip"
    policy = learner_of_model(path).load_policy(path)
    assert isinstance(policy, ResidualPolicy) and policy.scale == 0.5
    config = from_dict(TrainConfig, SHORT)
    env = GraspLiftVectorEnv(2, config.env)
    obs, _ = env.reset(seed=0)
    twin, bare = SlipFeedbackPolicy(config.env), ModelPolicy(path)
    policy.reset([{}, {}])
    twin.reset([{}, {}])
    for _ in range(20):
        action = policy.act(obs)  # (once per step: the controller keeps state)
        assert np.allclose(action, compose(twin.act(obs), bare.act(obs), 0.5))
        obs, *_ = env.step(action)


@pytest.mark.parametrize("over, needle", [
    ({"bc_teacher": "reactive"}, "either residual_base"),
    ({"residual_base": "oracle"}, "residual_base"),
    ({"residual_base": "slipfeedback:speed=0.2"}, "residual_base: .*takes keys initial, gain, pull, max"),
    ({"residual_base": "slipfeedback:pull=2"}, "residual_base"),
    ({"residual_scale": 0.0}, "residual_scale"),
    ({"residual_scale": [0.5, -0.1]}, "residual_scale"),
    ({"residual_mode": "lower"}, "residual_mode"),
    ({"asymmetric_critic": False, "env": {"pull_action": "travel"}}, "residual_base: slipfeedback needs"),
    ({"residual_start": "gate"}, "residual_start"),
    ({"residual_base": "slipfeedback:estimator=nope.json,gate=0.9"}, "residual_base: friction estimator nope.json"),
    ({"residual_start": "pull", "residual_base": "reactive"}, "residual_start: pull needs a slip-feedback"),
])
def test_bad_residual_settings_are_refused_naming_the_field(over, needle):
    with pytest.raises(ConfigError, match=needle):
        from_dict(TrainConfig, {**SHORT, **over})


def test_a_residual_on_a_slip_feedback_controller_with_its_settings():
    """residual_base takes the evaluation's spec of a slip-feedback controller with its settings: the model runs on
    that controller (its pull speed and gain), wherever it runs."""
    from msdgrasp.agents.residual import with_residual

    config = from_dict(TrainConfig, {**SHORT, "residual_base": "slipfeedback:initial=0.7,gain=0.8,pull=0.25"})
    policy = with_residual(ConstantPolicy([0.0, 0.0], "zero"), config)
    assert (policy.base.initial, policy.base.gain, policy.base.pull) == (0.7, 0.8, 0.25)


def test_a_raising_residual_model_acts_as_its_controller_where_it_would_lower_the_grip():
    """residual_mode: raise travels with the model's config: a correction of -1 leaves the controller's action."""
    from msdgrasp.agents.residual import with_residual
    from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv

    config = from_dict(TrainConfig, {**SHORT, "residual_mode": "raise"})
    policy = with_residual(ConstantPolicy([-1.0, -1.0], "lower"), config)
    assert policy.mode == "raise"
    env = GraspLiftVectorEnv(1, config.env)
    obs, _ = env.reset(seed=0)
    twin = SlipFeedbackPolicy(config.env)
    policy.reset([{}])
    twin.reset([{}])
    for _ in range(20):
        action = policy.act(obs)
        assert np.allclose(action, twin.act(obs))
        obs, *_ = env.step(action)


@pytest.mark.parametrize("where", ["policy", "training env"])
def test_a_correction_from_the_pull_leaves_the_closing_to_the_controller(where):
    """residual_start: pull: until the controller starts pulling, the action sent is the controller's alone (the
    correction of +1 is dropped); from that step on, the correction is added; in training and wherever it runs."""
    from msdgrasp.agents.residual import with_residual
    from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv
    from msdgrasp.envs.sb3 import GraspLiftSB3VecEnv

    config = from_dict(TrainConfig, {**SHORT, "residual_start": "pull", "residual_scale": [0.3, 0.0]})
    twin = SlipFeedbackPolicy(config.training_task() if where == "training env" else config.env)
    if where == "policy":
        policy = with_residual(ConstantPolicy([1.0, 1.0], "up"), config)
        env = GraspLiftVectorEnv(2, config.env)
        obs, _ = env.reset(seed=0)
        policy.reset([{}, {}])
    else:
        venv = residual_venv(GraspLiftSB3VecEnv(2, config.training_task(), seed=0), config)
        obs = venv.reset()
    twin.reset([{}, {}])
    corrected = np.zeros(2, dtype=bool)
    for _ in range(60):
        expected = twin.act(obs)
        pulling = twin.pulling
        if where == "policy":
            action = policy.act(obs)
            obs, _, term, trunc, _ = env.step(action)
            done = term | trunc
        else:
            obs, _, done, _ = venv.step(np.ones((2, 2), dtype=np.float32))
            action = venv.core.act
        assert np.allclose(action[~pulling], expected[~pulling], atol=1e-6)
        assert np.allclose(action[pulling], compose(expected[pulling], np.ones((int(pulling.sum()), 2)),
                                                    (0.3, 0.0)), atol=1e-6)
        corrected |= pulling
        for i in np.flatnonzero(done):
            twin.reset_one(int(i), {})
    assert corrected.all()  # both episodes reached their pull within 2 s
