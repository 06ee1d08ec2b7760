"""The task's two backends draw their episodes from the same distributions, and the task's records follow the config.

The CPU core draws with NumPy's per-env generators, the GPU core (numba's CUDA simulator here) with xoroshiro
streams on the device; both turn the variates into friction, scales and pose by envs/task.py. A two-sample
Kolmogorov-Smirnov test at the 0.1 % level compares 192 episodes of each (a fixed seed: the test is
deterministic), on what the simulation is given: mu, the stiffness and mass scales, the tip offset and the
axis tilt of the grasp pose.
"""

from __future__ import annotations

import math

import numpy as np

from msdgrasp.envs.core import GraspLiftConfig, GraspLiftCore
from msdgrasp.envs.task import (
    D_BIAS, D_GAIN, D_LATENCY, D_NOISE, OBS, OBS_NAMES, REWARD_TERMS, config_record, obs_group,
)
from msdgrasp.physics.config import from_dict

N = 192
RANDOMIZATION = {"mu_range": (0.2, 0.9), "mu_distribution": "log_uniform", "stiffness_scale_range": (0.8, 1.2),
                 "mass_scale_range": (0.9, 1.1), "pose_offset_m": 0.002, "pose_tilt_deg": 3.0, "pose_azimuth_deg": 5.0}


def _config(**randomization) -> GraspLiftConfig:
    return from_dict(GraspLiftConfig, {"resolution": 60, "physics_steps_per_action": 2,
                                       "randomization": {**RANDOMIZATION, **randomization}})


def _episode_draws(mu_s, kscale, mscale, tip, axis, pose) -> dict[str, np.ndarray]:
    """What the simulation was given at the episode start, per env."""
    return {"mu": mu_s, "stiffness_scale": kscale, "mass_scale": mscale,
            "tip_offset_m": np.linalg.norm(tip - pose.tip, axis=1),
            "tilt_rad": np.arccos(np.clip(axis @ pose.axis, -1.0, 1.0))}


def _cpu_draws(config: GraspLiftConfig) -> dict[str, np.ndarray]:
    core = GraspLiftCore(config, N)
    for i in range(N):
        core.seed(i, 1000 + i)
        core.reset(i)
    sim = core.sim
    return _episode_draws(sim.mu_s.copy(), sim.kscale.copy(), sim.mscale.copy(), sim.g_tip.copy(), sim.g_axis.copy(),
                          core.scene.pose)


def _ks_statistic(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance between the two samples' empirical distribution functions."""
    grid = np.concatenate([a, b])
    fa = np.searchsorted(np.sort(a), grid, side="right") / len(a)
    fb = np.searchsorted(np.sort(b), grid, side="right") / len(b)
    return float(np.abs(fa - fb).max())


# critical value of the two-sample KS statistic at the 0.1 % level, N and N samples
KS_CRITICAL = 1.949 * math.sqrt(2.0 / N)


def test_cpu_and_gpu_episode_draws_follow_the_same_distributions():
    from msdgrasp.envs.cuda_core import CudaGraspLiftCore

    config = _config()
    gpu = CudaGraspLiftCore(config, N, seed=5, threads=2)
    gpu.reset()
    got = gpu.download("mu_s", "kscale", "mscale", "g_tip", "g_axis")
    gpu_draws = _episode_draws(got["mu_s"], got["kscale"], got["mscale"], got["g_tip"], got["g_axis"],
                               gpu.host.scene.pose)
    cpu_draws = _cpu_draws(config)
    for name, cpu_values in cpu_draws.items():
        assert len(np.unique(cpu_values)) == len(np.unique(gpu_draws[name])) == N, name  # every env its own draw
        assert _ks_statistic(cpu_values, gpu_draws[name]) < KS_CRITICAL, name
    # within the configured bounds on both
    for draws in (cpu_draws, gpu_draws):
        assert draws["mu"].min() >= 0.2 and draws["mu"].max() <= 0.9
        assert draws["tip_offset_m"].max() <= 0.002 + 1e-12 and draws["tilt_rad"].max() <= math.radians(3.0) + 1e-9
    # the test can fail: another range, or uniform instead of log-uniform friction, is told apart
    shifted = _cpu_draws(_config(mu_range=(0.3, 0.9), mu_distribution="uniform"))
    assert _ks_statistic(shifted["mu"], gpu_draws["mu"]) > KS_CRITICAL


def test_the_task_record_follows_the_config_fields():
    config = from_dict(GraspLiftConfig, {"pull_action": "forward_speed", "max_pull_speed_m_s": 0.01,
                                         "reward": {"peak_force_timing": "as_made"}})
    record = config_record(config)
    # numbers and flags as they are; a choice as one flag per option; None as NaN; strings left out
    assert record.lift_target_m == config.lift_target_m and record.obs_history == config.obs_history
    assert record.terminate_on_damage is True and record.max_pull_speed_m_s == 0.01
    assert (record.pull_action_travel, record.pull_action_speed,
            record.pull_action_forward_speed) == (False, False, True)
    assert record.jaw_action_force and not record.jaw_action_speed
    assert record.reward.peak_force_timing_as_made and not record.reward.peak_force_timing_at_success
    assert math.isnan(record.reward.peak_force_mu_ref) and record.randomization.mu_range == (0.2, 0.9)
    assert not hasattr(record, "resolution") and not hasattr(record, "tissue_config")
    assert math.isnan(config_record(GraspLiftConfig()).max_pull_speed_m_s)
    assert type(record) is type(config_record(GraspLiftConfig()))  # one record type per config class


def test_the_observation_and_reward_layouts_are_named_once():
    assert [OBS[n] for n in OBS_NAMES] == list(range(len(OBS_NAMES)))
    assert OBS_NAMES[obs_group("normal_force")] == ("normal_force_0", "normal_force_1", "normal_force_2")
    core = GraspLiftCore(_config(), 1)
    core.reset(0)
    _, _, _, _, info = core.step(np.zeros((1, 2)))
    assert tuple(info["reward_terms"]) == REWARD_TERMS


def test_cpu_and_gpu_draw_the_robustness_axes_from_the_same_distributions():
    """Force bias, latency, force-loop gain error and the force-noise level, drawn per episode on both backends (KS
    at 0.1 %), within their ranges; latency takes each of its integer values."""
    from msdgrasp.envs.cuda_core import CudaGraspLiftCore

    config = _config(force_bias_N=0.1, latency_steps=(0, 3), force_loop_gain_error=0.3, sensor_noise_N=0.08,
                     sensor_noise_low_N=0.02)
    gpu = CudaGraspLiftCore(config, N, seed=7, threads=2)
    gpu.reset()
    gpu_draws = gpu.download("draws")["draws"]
    core = GraspLiftCore(config, N)
    for i in range(N):
        core.seed(i, 3000 + i)
        core.reset(i)
    cpu_draws = core.draws.copy()
    for draws in (cpu_draws, gpu_draws):
        bias = draws[:, D_BIAS:D_BIAS + 3]
        assert np.abs(bias).max() <= 0.1 and bias.min() < -0.08 and bias.max() > 0.08
        assert set(np.unique(draws[:, D_LATENCY])) == {0.0, 1.0, 2.0, 3.0}
        assert 0.7 <= draws[:, D_GAIN].min() and draws[:, D_GAIN].max() <= 1.3
        assert 0.02 <= draws[:, D_NOISE].min() < 0.025 and 0.075 < draws[:, D_NOISE].max() <= 0.08
    for col in (D_BIAS, D_BIAS + 2, D_LATENCY, D_GAIN, D_NOISE):
        assert _ks_statistic(cpu_draws[:, col], gpu_draws[:, col]) < KS_CRITICAL, col
    # the axes that are off draw nothing and leave the nominal episode's values: no bias, no latency, gain x 1
    nominal = GraspLiftCore(_config(), 1)
    nominal.seed(0, 1)
    nominal.reset(0)
    assert nominal.draws[0, D_BIAS:D_BIAS + 3].tolist() == [0.0, 0.0, 0.0]
    assert nominal.draws[0, D_LATENCY] == 0.0 and nominal.draws[0, D_GAIN] == 1.0
    assert nominal.draws[0, D_NOISE] == nominal.config.randomization.sensor_noise_N
