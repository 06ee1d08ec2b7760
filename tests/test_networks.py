"""Asymmetric actor-critic (privileged critic), the learning-rate schedule and mu sampling, as specs.

Runtime: one 512-step PPO run on 2 envs (a few seconds).
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.agents.training import TrainConfig, load_model, train
from msdgrasp.envs.core import OBS, OBS_NAMES, GraspLiftConfig, GraspLiftCore, actor_mask
from msdgrasp.physics.config import ConfigError, from_dict


def test_actor_mask_keeps_the_task_entries_of_every_frame():
    mask = actor_mask(3, 5, 2)
    assert mask == [True, True, True, False, False] * 2
    with pytest.raises(ValueError, match="n_task"):
        actor_mask(6, 5, 1)
    # hidden task entries: by name, or a per-jaw group by its prefix
    n = len(OBS_NAMES)
    mask = actor_mask(n, n + 2, 2, ("friction_use", "peak_pinch"))
    hidden = {OBS["friction_use_0"], OBS["friction_use_1"], OBS["friction_use_2"], OBS["peak_pinch"], n, n + 1}
    assert mask == [i not in hidden for i in range(n + 2)] * 2
    with pytest.raises(ConfigError, match="actor_hidden: 'friction' is no observation entry"):
        actor_mask(n, n, 1, ("friction",))


@pytest.fixture(scope="module")
def asymmetric_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("asym")
    cfg = from_dict(TrainConfig, {
        "total_timesteps": 512, "n_envs": 2, "checkpoint_every": 10**6, "validation_episodes": 0,
        "asymmetric_critic": True, "actor_hidden": ["normal_force"], "lr_schedule": "linear", "log_std_init": -1.0,
        "ppo": {"learning_rate": 1e-3, "n_steps": 128, "batch_size": 64, "n_epochs": 2, "use_sde": True},
        "env": {"privileged_obs": True, "obs_history": 2}})
    train(cfg, out, progress=False)
    return load_model(out / "final_model.zip")


def test_the_saved_actor_is_blind_to_privileged_and_hidden_entries_and_the_critic_is_not(asymmetric_run):
    import torch

    model = asymmetric_run
    n = model.observation_space.shape[0]
    mask = np.array(model.policy.actor_mask)
    # the task entries of both frames but the hidden normal-force readings survive the load
    assert mask.sum() == 2 * (len(OBS_NAMES) - 3) and len(mask) == n
    frame = n // 2
    assert not mask[[OBS["normal_force_0"], OBS["normal_force_2"], frame + OBS["normal_force_1"]]].any()
    obs = np.random.default_rng(0).normal(size=(8, n)).astype(np.float32)
    other = obs.copy()
    other[:, ~mask] += 3.0  # change only mu, the scales, the node displacements and the normal-force readings
    a0, _ = model.predict(obs, deterministic=True)
    a1, _ = model.predict(other, deterministic=True)
    np.testing.assert_array_equal(a0, a1)
    with torch.no_grad():
        v0 = model.policy.predict_values(torch.as_tensor(obs))
        v1 = model.policy.predict_values(torch.as_tensor(other))
    assert float((v0 - v1).abs().max()) > 1e-4  # the critic uses them
    # and the task entries do reach the actor
    other = obs.copy()
    other[:, mask] += 3.0
    a2, _ = model.predict(other, deterministic=True)
    assert np.abs(a2 - a0).max() > 1e-4


def test_log_std_init_sets_the_initial_action_noise(asymmetric_run):
    # 512 steps with 2 epochs of updates at lr <= 1e-3 move a log std by far less than 0.1
    np.testing.assert_allclose(asymmetric_run.policy.log_std.detach().numpy(), -1.0, atol=0.1)


def test_linear_schedule_anneals_the_learning_rate_to_zero(asymmetric_run):
    sched = asymmetric_run.lr_schedule
    assert sched(1.0) == pytest.approx(1e-3)
    assert sched(0.5) == pytest.approx(5e-4)
    assert sched(0.0) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("over, field", [
    ({"asymmetric_critic": True, "env": {}}, "privileged_obs"),
    ({"asymmetric_critic": True, "algo": "sac", "env": {"privileged_obs": True}}, "algo 'ppo' only"),
    ({"asymmetric_critic": "yes"}, "asymmetric_critic"),
    ({"lr_schedule": "cosine"}, "lr_schedule"),
    ({"log_std_init": 3.0}, "log_std_init"),
    ({"actor_hidden": ["normal_forces"], "env": {"privileged_obs": True}}, "actor_hidden: 'normal_forces' is no"),
    ({"actor_hidden": ["normal_force"], "asymmetric_critic": False}, "actor_hidden needs asymmetric_critic"),
])
def test_bad_training_options_name_the_field(over, field):
    with pytest.raises(ConfigError, match=field):
        from_dict(TrainConfig, over)


def _drawn_mu(distribution: str, n: int = 2000) -> np.ndarray:
    cfg = from_dict(GraspLiftConfig, {"randomization": {"mu_range": [0.2, 0.9], "mu_distribution": distribution}})
    core = GraspLiftCore(cfg, 1)
    core.seed(0, 123)
    return np.array([core.reset(0)["mu"] for _ in range(n)])


@pytest.mark.parametrize("distribution, p_low", [("uniform", 0.1 / 0.7), ("log_uniform", np.log(1.5) / np.log(4.5))])
def test_mu_distribution_puts_the_expected_share_below_0_3(distribution, p_low):
    mu = _drawn_mu(distribution)
    assert mu.min() >= 0.2 and mu.max() <= 0.9
    # binomial standard error for 2000 draws is <= 0.011: 4 sigma
    assert np.mean(mu < 0.3) == pytest.approx(p_low, abs=0.045)


def test_log_uniform_needs_a_positive_lower_bound():
    with pytest.raises(ConfigError, match="mu_range"):
        from_dict(GraspLiftConfig, {"randomization": {"mu_range": [0.0, 0.9], "mu_distribution": "log_uniform"}})
    with pytest.raises(ConfigError, match="mu_distribution"):
        from_dict(GraspLiftConfig, {"randomization": {"mu_distribution": "normal"}})


def test_actor_privileged_shows_the_actor_mu_and_nothing_else_privileged():
    from msdgrasp.envs.core import OBS_NAMES, actor_mask
    from msdgrasp.physics.config import ConfigError

    n = len(OBS_NAMES)
    mask = actor_mask(n, n + 5, 2, privileged=["mu"])
    assert mask == ([True] * n + [True, False, False, False, False]) * 2
    with pytest.raises(ConfigError, match="actor_privileged"):
        actor_mask(n, n, 1, privileged=["mu"])  # (no privileged entries in this observation)


def test_actor_privileged_perturbations_show_the_episodes_draws_only():
    """The perturbation block is the frame's last entries; the node displacements before it stay hidden, and without
    the block the name is refused rather than showing whatever entries end the frame."""
    from msdgrasp.envs.core import OBS_NAMES, actor_mask
    from msdgrasp.envs.perturbations import privileged_names
    PRIVILEGED_PERTURBATIONS = privileged_names()
    from msdgrasp.physics.config import ConfigError

    n, k = len(OBS_NAMES), len(PRIVILEGED_PERTURBATIONS)
    frame = n + 51 + k  # task, mu + scales + 16 nodes' displacements, perturbations
    mask = actor_mask(n, frame, 1, privileged=["mu", "perturbations"], perturbations=True)
    assert mask == [True] * n + [True] + [False] * 50 + [True] * k
    with pytest.raises(ConfigError, match="privileged_perturbations"):
        actor_mask(n, n + 51, 1, privileged=["perturbations"])
    with pytest.raises(ConfigError, match="privileged_perturbations"):
        from_dict(TrainConfig, {"actor_privileged": ["perturbations"]})
