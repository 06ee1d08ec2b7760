"""Training helpers: discounted demonstration returns, the critic fit during behaviour cloning, config.

Runtime: one tiny cloning run (2 envs, ~600 teacher steps, 3 epochs), a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.agents.training import TrainConfig, _discounted_returns, behaviour_clone, collect_demonstrations
from msdgrasp.physics.config import ConfigError, builtin_config, from_dict, read_yaml


def test_discounted_returns_restart_at_episode_ends_and_unknown_tails_are_nan():
    rewards = np.ones((5, 2))
    dones = np.zeros((5, 2), dtype=bool)
    dones[2, 0] = True  # env 0: episode ends at t=2, then a new one runs past the end of collection
    dones[4, 1] = True
    ret = _discounted_returns(rewards, dones, 0.5)
    assert ret[:, 0][:3] == pytest.approx([1.75, 1.5, 1.0])
    assert np.isnan(ret[3:, 0]).all()
    assert ret[:, 1] == pytest.approx([1.9375, 1.875, 1.75, 1.5, 1.0])


def _tiny_config(**over) -> TrainConfig:
    base = {"n_envs": 2, "bc_steps": 640, "bc_epochs": 3, "torch_threads": 1, "total_timesteps": 1}
    return from_dict(TrainConfig, {**base, **over})


def test_demonstrations_have_returns_of_finished_episodes():
    demos = collect_demonstrations(_tiny_config())
    assert demos.obs.shape[0] == demos.actions.shape[0] == demos.returns.shape[0] == 640
    known = np.isfinite(demos.returns)
    assert known.any(), "no teacher episode finished within 320 steps per env"
    # the teacher lifts: its episodes earn the success bonus, so some returns are clearly positive
    assert demos.returns[known].max() > 10.0


@pytest.mark.parametrize("fit", [False, True])
def test_value_fit_moves_the_critic_toward_teacher_returns(fit):
    import torch
    from stable_baselines3 import PPO

    from msdgrasp.envs.sb3 import GraspLiftSB3VecEnv

    torch.manual_seed(0)
    config = _tiny_config(bc_value_fit=fit, bc_epochs=20)
    model = PPO("MlpPolicy", GraspLiftSB3VecEnv(2, config.env, seed=0), device="cpu", seed=0,
                policy_kwargs={"net_arch": [16, 16]}, n_steps=64, batch_size=64)
    demos = collect_demonstrations(config)
    known = np.isfinite(demos.returns)
    x = torch.as_tensor(demos.obs[known])
    target = torch.as_tensor(demos.returns[known], dtype=torch.float32)

    def value_error() -> float:
        with torch.no_grad():
            return float(torch.mean((model.policy.predict_values(x).squeeze(-1) - target) ** 2))

    before = value_error()
    info = behaviour_clone(model, config)
    after = value_error()
    if fit:
        assert after < 0.5 * before, (before, after)
        assert info["value_fit_steps"] == int(known.sum())
    else:
        assert after == pytest.approx(before, rel=1e-6)  # the critic is untouched
        assert "value_fit_steps" not in info


def test_bc_value_fit_must_be_a_boolean():
    with pytest.raises(ConfigError, match="bc_value_fit"):
        from_dict(TrainConfig, {"bc_value_fit": "yes"})


def test_default_training_config_loads_strictly():
    config = from_dict(TrainConfig, read_yaml(builtin_config("train/ppo.yaml")))
    assert config.algo == "ppo" and config.bc_teacher == "reactive"
    with pytest.raises(ConfigError, match="bogus"):
        from_dict(TrainConfig, {**read_yaml(builtin_config("train/ppo.yaml")), "bogus": 1})
