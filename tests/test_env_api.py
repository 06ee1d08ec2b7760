"""The env classes' contract beyond the physics: step only after reset, only supported render modes,
and an env that has rendered can still be copied and pickled (the render cache stays out of its state)."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest
from gymnasium.error import ResetNeeded

from msdgrasp.envs.grasp_lift import GraspLiftEnv, GraspLiftVectorEnv

SHORT = {"time_limit_s": 0.5}  # 15 agent steps: enough to grip, nothing here needs a full episode


@pytest.mark.parametrize("make", [lambda: GraspLiftEnv(SHORT), lambda: GraspLiftVectorEnv(2, SHORT)],
                         ids=["single", "vector"])
def test_step_before_the_first_reset_is_refused(make):
    env = make()
    action = np.zeros(env.action_space.shape, dtype=np.float32)
    with pytest.raises(ResetNeeded, match=rf"^{type(env).__name__}: .*call reset\(\) first$"):
        env.step(action)
    env.reset(seed=0)
    obs, reward, *_ = env.step(action)  # after a reset it steps
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))


@pytest.mark.parametrize("cls", [GraspLiftEnv, GraspLiftVectorEnv])
@pytest.mark.parametrize("mode", ["human", "rgb", "ansi"])
def test_unsupported_render_modes_are_refused_by_both_envs(cls, mode):
    with pytest.raises(ValueError,
                       match=rf"^{cls.__name__}: render_mode must be one of \['rgb_array'\] or None, got '{mode}'$"):
        cls(SHORT, render_mode=mode) if cls is GraspLiftEnv else cls(1, SHORT, render_mode=mode)
    assert cls.metadata["render_modes"] == ["rgb_array"]


@pytest.mark.parametrize("vector", [False, True], ids=["single", "vector"])
def test_an_env_that_has_rendered_deepcopies_and_pickles_and_the_copy_steps_and_renders(vector):
    env = (GraspLiftVectorEnv(2, SHORT, render_mode="rgb_array") if vector
           else GraspLiftEnv(SHORT, render_mode="rgb_array"))
    env.reset(seed=3)
    action = np.tile(np.float32([0.5, -1.0]), (2, 1)) if vector else np.float32([0.5, -1.0])
    for _ in range(4):
        env.step(action)
    first = env.render()
    assert env.core._render_cache  # the figure is cached on the core ...
    twins = [copy.deepcopy(env), pickle.loads(pickle.dumps(env))]
    assert env.core._render_cache  # ... and stays there for the original
    obs, reward, *_ = env.step(action)
    for twin in twins:
        assert getattr(twin.core, "_render_cache", None) is None  # a copy builds its own figure
        # the copy carries the whole episode state and random streams: the same step gives the same result
        t_obs, t_reward, *_ = twin.step(action)
        np.testing.assert_array_equal(t_obs, obs)
        np.testing.assert_array_equal(t_reward, reward)
        frame = twin.render()
        assert frame.shape == first.shape and frame.dtype == np.uint8 and frame.std() > 5
    assert env.render().shape == first.shape  # the original's cached figure still renders


def test_vector_reset_options_pin_one_value_for_every_env_or_one_per_env():
    from msdgrasp.physics.config import ConfigError

    env = GraspLiftVectorEnv(3, SHORT)
    _, info = env.reset(seed=0, options={"mu": 0.45})
    assert info["mu"].tolist() == [0.45, 0.45, 0.45]
    _, info = env.reset(seed=0, options={"mu": [0.2, 0.5, 0.8], "stiffness_scale": 1.0})
    assert info["mu"].tolist() == [0.2, 0.5, 0.8] and info["stiffness_scale"].tolist() == [1.0, 1.0, 1.0]
    # each env as a single env reset with its own value
    single = GraspLiftEnv(SHORT)
    _, one = single.reset(seed=1, options={"mu": 0.5})
    assert one["mu"] == 0.5 and np.array_equal(single.reset(seed=1, options={"mu": 0.5})[0],
                                               env.reset(seed=0, options={"mu": [0.2, 0.5, 0.8]})[0][1])
    with pytest.raises(ConfigError,
                       match=r"^reset options\['mu'\] must be one number or 3 numbers \(one per env\), got 2$"):
        env.reset(seed=0, options={"mu": [0.2, 0.5]})
