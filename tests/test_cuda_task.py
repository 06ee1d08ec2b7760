"""The GraspLift task on the GPU (envs/cuda_core.py) against the CPU core (envs/core.py).

Run in numba's CUDA simulator (conftest.py sets NUMBA_ENABLE_CUDASIM=1 unless told otherwise): a 60-node
spleen, 2 envs, blocks of 4 threads, 2 ms agent steps. The GPU draws its own random numbers; the CPU core is
given the same friction and scales through ``reset(options=...)``, with the pose jitter and the sensor noise
off, so both run the same episodes.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.envs.core import GraspLiftConfig, GraspLiftCore, perturbed_pose
from msdgrasp.envs.task import REWARD_TERMS
from msdgrasp.physics.config import ConfigError, from_dict, to_dict

# positions within 1e-12 m after an episode with contact (the GPU port's tolerance, as in
# tests/test_cuda_physics.py); the task's scalars are sums and ratios of them: 1e-9 relative
POSITION_TOL_M = 1e-12
TASK_RTOL = 1e-9


def _config(**changes) -> GraspLiftConfig:
    data = {
        "resolution": 60, "physics_steps_per_action": 2, "time_limit_s": 0.016,  # 8 agent steps
        "privileged_obs": True, "privileged_nodes": 4, "obs_history": 2, "pinch_action_exponent": 2.0,
        "pull_action_exponent": 2.0,
        "pull_action": "forward_speed", "terminate_on_damage": False,  # (the 60-node mesh's nodal stress is high)
        "reward": {"peak_force_mu_ref": 0.4, "force_per_s": 1.0, "grasp": 2.0, "peak_force_timing": "as_made"},
        "randomization": {"pose_offset_m": 0.0, "pose_tilt_deg": 0.0, "pose_azimuth_deg": 0.0, "sensor_noise_N": 0.0,
                          "mu_distribution": "log_uniform"},
    }
    data.update(changes)
    return from_dict(GraspLiftConfig, data)


def _gpu(config: GraspLiftConfig, num_envs: int = 2, seed: int = 3, precision: str = "float64"):
    from msdgrasp.envs.cuda_core import CudaGraspLiftCore

    return CudaGraspLiftCore(config, num_envs, seed=seed, threads=4, precision=precision)


def _pin_cpu_to(cpu: GraspLiftCore, gpu) -> None:
    """Reset the CPU envs to the friction and scales the GPU drew for its current episodes."""
    got = gpu.download("mu", "kscale", "mscale")
    for b in range(cpu.num_envs):
        cpu.reset(b, {"mu": got["mu"][b], "stiffness_scale": got["kscale"][b], "mass_scale": got["mscale"][b]})


def _close(name: str, gpu_value, cpu_value, rtol: float = TASK_RTOL) -> None:
    cpu_value = np.asarray(cpu_value, dtype=np.float64)
    scale = max(1e-12, float(np.abs(cpu_value).max()))
    np.testing.assert_allclose(np.asarray(gpu_value, dtype=np.float64), cpu_value, rtol=0, atol=rtol * scale,
                               err_msg=name)


# the deterministic robustness axes (drawn ones are compared by distribution: tests/test_task_backends.py)
AXES = {"latency_steps": (1, 1), "pinch_ceiling_N": 1.5, "slip_sensing": "binary"}


@pytest.mark.parametrize("axes", [{}, AXES], ids=["nominal", "latency_ceiling_binary_slip_kneed_charge_setpoint_moves"])
def test_the_gpu_task_steps_rewards_ends_and_resets_as_the_cpu_core(axes):
    config = _config()
    # (with the axes, the privileged robustness entries too: compared with the observation; and the peak-force
    # charge with a knee at 1 point, which the closing jaws pass, and the set-point's moves charged)
    knee = {"peak_force_knee": 1.0, "peak_force_beyond_knee": 0.5, "setpoint_change": 0.5} if axes else {}
    config = from_dict(GraspLiftConfig, {**to_dict(config), "privileged_perturbations": bool(axes),
                                         "randomization": {**to_dict(config.randomization), **axes},
                                         "reward": {**to_dict(config.reward), **knee}})
    gpu = _gpu(config)
    cpu = GraspLiftCore(config, 2)
    obs = gpu.reset().copy_to_host()
    _pin_cpu_to(cpu, gpu)
    np.testing.assert_allclose(obs, cpu.obs.astype(np.float32), rtol=1e-6, atol=1e-7)
    # start the jaws 4 mm in on both: contact within the first steps
    radius = gpu.download("g_radius")["g_radius"] - 0.004
    gpu.arrays()["g_radius"].copy_to_device(radius)
    cpu.sim.g_radius[:] = radius
    actions = np.array([[1.0, -1.0], [0.3, -1.0]])
    seen_contact = seen_damage = 0
    returns = np.zeros(2)
    for k in range(config.max_episode_steps):
        if k >= 4:  # pull at 25 % and 75 % of the top speed, the second env with a lighter grip
            actions[:, 1] = [-0.5, 0.5]
        o_gpu, r_gpu, term_gpu, trunc_gpu = gpu.step(actions.astype(np.float32))
        o_cpu, r_cpu, term_cpu, trunc_cpu, info = cpu.step(actions.astype(np.float32))
        got = gpu.download("x", "terminal_obs", "terms", "pinch", "stress", "contact", "lift", "slip_total",
                           "peak_pinch", "min_volume_ratio", "contact_state", "episode_slip", "episode_peak_pinch",
                           "damaged", "episode_return")
        np.testing.assert_array_equal(got["damaged"], info["damaged"])
        seen_damage += int(info["damaged"].sum())
        np.testing.assert_array_equal(term_gpu.copy_to_host(), term_cpu)
        np.testing.assert_array_equal(trunc_gpu.copy_to_host(), trunc_cpu)
        done = term_cpu | trunc_cpu
        if not done.any():  # (after an end, the GPU has already started the next episode)
            assert np.abs(got["x"] - cpu.sim.x).max() <= POSITION_TOL_M
            np.testing.assert_array_equal(got["contact_state"], cpu.sim.contact_state)  # identical stick/slip
            _close("lift", got["lift"], info["lifted_m"])
        _close("reward", r_gpu.copy_to_host(), r_cpu)
        returns += r_cpu
        _close("episode return", got["episode_return"], returns)  # (where done: of the episode that ended)
        for j, name in enumerate(REWARD_TERMS):
            _close(f"reward term {name}", got["terms"][:, j], info["reward_terms"][name])
        # the step's readouts; the episode's totals (where an episode ended: as it ended)
        episode = ("episode_slip", "episode_peak_pinch") if done.any() else ("slip_total", "peak_pinch")
        for name, cpu_name in (("pinch", "pinch_force_N"), ("stress", "peak_stress_pa"), ("contact", "contact_nodes"),
                               ("min_volume_ratio", "min_volume_ratio"), (episode[0], "slip_distance_m"),
                               (episode[1], "peak_pinch_N")):
            _close(name, got[name], info[cpu_name])
        last = got["terminal_obs"] if done.any() else o_gpu.copy_to_host()
        np.testing.assert_allclose(last, o_cpu, rtol=1e-6, atol=1e-7)
        seen_contact += int((info["contact_nodes"] > 0).sum())
    assert done.all() and trunc_cpu.all()  # both episodes ran into the time limit at step 8
    assert seen_contact > 0 and info["peak_pinch_N"].min() > 0.1  # the jaws held the tissue
    assert info["slip_distance_m"].max() > 0  # and the pull made it slip
    assert seen_damage > 0  # the damage flag and its reward term were compared when set
    # the GPU reset both envs in the same call: its observation is the new episodes' first, with new draws
    before = cpu.mu.copy()
    _pin_cpu_to(cpu, gpu)
    assert not np.array_equal(cpu.mu, before)
    np.testing.assert_allclose(gpu.arrays()["obs"].copy_to_host(), cpu.obs.astype(np.float32), rtol=1e-6, atol=1e-7)
    assert np.abs(gpu.download("x")["x"] - cpu.sim.x).max() == 0.0  # the settled tissue, exactly
    for _ in range(2):
        o_gpu, r_gpu, _, _ = gpu.step(actions)
        o_cpu, r_cpu, *_ = cpu.step(actions)
        np.testing.assert_allclose(o_gpu.copy_to_host(), o_cpu, rtol=1e-6, atol=1e-7)
        _close("reward", r_gpu.copy_to_host(), r_cpu)
    assert gpu.download("steps")["steps"].tolist() == [2, 2]


def test_gpu_draws_follow_the_randomisation_and_the_pose_is_the_cpu_formula():
    config = _config(randomization={"mu_range": (0.2, 0.9), "mu_distribution": "log_uniform",
                                    "stiffness_scale_range": (0.8, 1.2), "mass_scale_range": (0.9, 1.1),
                                    "pose_offset_m": 0.002, "pose_tilt_deg": 3.0, "pose_azimuth_deg": 5.0})
    gpu = _gpu(config, num_envs=64, seed=11)
    gpu.reset()
    got = gpu.download("draws", "mu", "kscale", "mscale", "mu_s", "mu_k", "g_tip", "g_axis", "g_e1", "tip0")
    d = got["draws"]
    assert np.all((d[:, 0] >= 0.2) & (d[:, 0] <= 0.9)) and np.all((d[:, 1] >= 0.8) & (d[:, 1] <= 1.2))
    assert np.all((d[:, 2] >= 0.9) & (d[:, 2] <= 1.1)) and np.all(np.abs(d[:, 10:12]) <= 1.0)
    assert np.all((d[:, 6] >= 0) & (d[:, 6] <= 1))
    assert len(np.unique(d[:, 0])) == 64  # every env has its own stream
    np.testing.assert_array_equal(got["mu"], d[:, 0])
    np.testing.assert_array_equal(got["mu_s"], d[:, 0])
    np.testing.assert_array_equal(got["mu_k"], d[:, 0])
    np.testing.assert_array_equal(got["kscale"], d[:, 1])
    np.testing.assert_array_equal(got["mscale"], d[:, 2])
    rnd = config.randomization
    scene = gpu.host.scene
    for b in range(64):
        draws = {"offset_dir": d[b, 3:6], "offset_r": d[b, 6], "tilt_axis": d[b, 7:10], "tilt": d[b, 10],
                 "azimuth": d[b, 11]}
        pose = perturbed_pose(scene.pose, draws, rnd.pose_offset_m, rnd.pose_tilt_deg, rnd.pose_azimuth_deg)
        np.testing.assert_allclose(got["g_tip"][b], pose.tip, rtol=0, atol=1e-15)
        np.testing.assert_allclose(got["g_axis"][b], pose.axis, rtol=0, atol=1e-15)
        np.testing.assert_allclose(got["g_e1"][b], pose.e1, rtol=0, atol=1e-15)
    offset = got["tip0"] - scene.pose.tip
    assert np.abs(offset @ scene.pose.axis).max() < 1e-15 and np.linalg.norm(offset, axis=1).max() <= 0.002
    # pinned values hold for the episodes after (until the next reset), the rest is drawn anew
    gpu.reset({"mu": 0.35, "mass_scale": np.linspace(0.9, 1.1, 64)})
    got = gpu.download("mu", "mu_s", "kscale", "mscale")
    assert np.all(got["mu"] == 0.35) and np.all(got["mu_s"] == 0.35)
    np.testing.assert_array_equal(got["mscale"], np.linspace(0.9, 1.1, 64))
    assert len(np.unique(got["kscale"])) == 64
    # the same seed, the same episodes
    again = _gpu(config, num_envs=64, seed=11)
    again.reset()
    np.testing.assert_array_equal(again.download("draws")["draws"], d)


def test_gpu_vector_force_noise_draws_the_tangential_components_with_the_sensors_sigma():
    for model, sigma in (("vector", 0.05), ("magnitude", 0.05)):
        gpu = _gpu(_config(randomization={"sensor_noise_N": sigma, "force_noise": model}), num_envs=8, seed=3)
        gpu.reset()
        gpu.step(np.zeros((8, 2)))
        noise = gpu.download("noise")["noise"]
        assert 0.03 < noise[:, :3].std() < 0.07
        if model == "vector":
            assert 0.035 < noise[:, 6:].std() < 0.065  # 48 draws of N(0, 0.05)
        else:  # (not drawn: the magnitude model's random stream is the one it always was)
            assert np.all(noise[:, 6:] == 0.0)


def test_gpu_task_input_errors_name_the_field_and_the_range():
    gpu = _gpu(_config(), num_envs=2)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['pose_offset_m'\]; allowed on the GPU: \['mu', "):
        gpu.reset({"pose_offset_m": 0.0})
    with pytest.raises(ConfigError, match=r"options\['mu'\] = -0.1 is out of range; allowed \[0, 10\]"):
        gpu.reset({"mu": -0.1})
    with pytest.raises(ConfigError, match=r"actions must have shape \(2, 2\), got \(3, 2\)"):
        gpu.step(np.zeros((3, 2)))
    with pytest.raises(ConfigError, match=r"unknown field\(s\) \['obz'\]"):
        gpu.download("obz")


def test_the_torch_ppo_trains_on_the_gpu_task_and_reads_its_device_arrays(tmp_path):
    import torch

    from msdgrasp.agents.torch_ppo import TorchPPOConfig, make_torch_env, train_torch
    from msdgrasp.physics.config import to_dict

    data = to_dict(TorchPPOConfig())
    data.update(backend="cuda", precision="float32", num_envs=2, iterations=1, steps_per_env=3, validation_episodes=0)
    data["env"].update(resolution=60, physics_steps_per_action=2, time_limit_s=0.004)  # 2 steps: an autoreset
    config = from_dict(TorchPPOConfig, data)
    summary = train_torch(config, tmp_path, progress=False)
    assert summary["backend"] == "cuda" and summary["agent_steps"] == 6 and (tmp_path / "policy.pt").is_file()
    assert summary["precision"] == "float32"  # (the core's own: the config reached it)
    # the adapter hands over the GPU core's own arrays (views on a GPU; copies in the simulator)
    gpu = _gpu(config.env, num_envs=2, seed=1)
    env = make_torch_env(gpu, "cpu")
    for k in range(2):
        obs, rew, dones, extras = env.step(torch.tensor([[0.5, 0.0], [-0.5, 1.0]]))
        np.testing.assert_array_equal(obs["critic"].numpy(), gpu.state.obs.copy_to_host())
        np.testing.assert_array_equal(rew.numpy(), gpu.state.reward.copy_to_host().astype(np.float32))
        np.testing.assert_array_equal(extras["time_outs"].numpy(), gpu.state.truncated.copy_to_host())
    assert dones.tolist() == [1, 1] and set(extras["log"]) == {"/episode/success", "/episode/peak_pinch_N",
                                                                "/episode/slip_mm"}
    np.testing.assert_array_equal(gpu.download("episode_length")["episode_length"], [2, 2])


def test_float32_stores_the_big_arrays_in_float32_and_stays_within_its_resolution_of_float64():
    from msdgrasp.benchmarks.bench import bench_precision
    from msdgrasp.benchmarks.report import markdown
    from msdgrasp.physics.cuda_step import FLOAT32_FIELDS

    gpu = _gpu(_config(), precision="float32")
    arrays = gpu.arrays()
    for name in ("x", "v", "fv", "dl_prev", "f_ext", "contact_force"):
        assert name in FLOAT32_FIELDS and arrays[name].dtype == np.float32, name
    for name in ("t", "mu_s", "g_radius", "g_force", "jaw_out", "anchor_out"):  # per tissue: float64
        assert arrays[name].dtype == np.float64, name
    assert gpu.physics.model.k1.dtype == np.float32 and gpu.physics.scratch.fe.dtype == np.float32
    # a download into the host's float64 records converts; an upload back rounds to float32 again
    host = gpu.host.sim.kernel_state()
    host.x[:] = np.pi
    gpu.physics.download(state=host, fields=("x",))
    np.testing.assert_array_equal(host.x, arrays["x"].copy_to_host().astype(np.float64))
    host.x[0, 0, 0] = 0.1
    gpu.physics.upload(state=host, fields=("x",))
    assert arrays["x"].copy_to_host()[0, 0, 0] == np.float32(0.1)
    # the same 8-step episodes as the parity test (jaws 4 mm in: contact at once), float32 against float64
    res = bench_precision(_config(), num_envs=2, seed=3, threads=4, jaws_in_m=0.004)
    assert res["agent_steps"] == 8 and res["max_pinch_rel_diff"] > 0.0  # the jaws held the tissue in both
    # float32 really rounds (float64 stays within 1e-12 m of the CPU), and by little more than its resolution:
    # float32's spacing near 0.1 m is 7.5e-9 m; 1e-6 m is a 2000th of the task's 2 mm slip tolerance
    assert 1e-12 < res["max_position_diff_m"] <= 1e-6
    assert res["env_steps_in_contact"] >= 6  # of 16: the stick / slip decisions below were compared
    assert res["contact_state_agreement"] == 1.0  # and were the same
    # rewards and the pinch within a thousandth: the stiff contact amplifies float32's 6e-8 relative rounding (on
    # a GPU, with fused multiply-adds, 2.4e-4 of the reward was seen); 1e-3 of the 2-5 N pinch is 2-5 mN, far
    # below the task's sensor noise
    assert res["max_reward_diff"] <= 1e-3 and res["max_pinch_rel_diff"] <= 1e-3
    assert res["envs_ended_on_another_step"] == 0 and res["envs_with_another_outcome"] == 0
    from msdgrasp.benchmarks.report import machine_info

    text = markdown({"what": "precision", "quick": True, "machine": machine_info(), "elapsed_s": 1.0, "targets": {},
                     "precision": res})
    from numba import config as numba_config

    where = "On numba's CUDA simulator" if numba_config.ENABLE_CUDASIM else "On a GPU"
    assert where in text and "| contact_state_agreement | 1 |" in text


def test_an_unknown_precision_is_a_one_line_error():
    from msdgrasp.envs.cuda_core import CudaGraspLiftCore

    with pytest.raises(ConfigError, match=r"precision = 'float16' is not allowed; choose one of 'float64', 'float32'"):
        CudaGraspLiftCore(_config(), 2, precision="float16")


def test_sb3_steps_the_gpu_task_through_host_copies_with_its_episode_infos():
    from msdgrasp.envs.sb3 import CudaSB3VecEnv

    venv = CudaSB3VecEnv(_gpu(_config(time_limit_s=0.004)))  # 2 agent steps per episode
    obs = venv.reset()
    assert obs.shape == (2, venv.core.obs_dim) and obs.dtype == np.float32
    returns = np.zeros(2)
    for k in range(2):
        venv.step_async(np.array([[0.5, 0.0], [-0.5, 1.0]]))
        obs, reward, dones, infos = venv.step_wait()
        returns += reward
        np.testing.assert_array_equal(obs, venv.core.state.obs.copy_to_host())
    assert dones.tolist() == [True, True]
    ended = venv.core.download("terminal_obs")["terminal_obs"]
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] and info["episode"]["l"] == 2 and info["is_success"] is False
        np.testing.assert_allclose(info["episode"]["r"], returns[i], rtol=1e-6)  # (rewards are float32 to SB3)
        np.testing.assert_array_equal(info["terminal_observation"], ended[i])
    with pytest.raises(ValueError, match=r"action must have shape \(2, 2\)"):
        venv.step_async(np.zeros((3, 2)))


def test_the_learner_bench_runs_sb3_and_rsl_rl_on_the_gpu_task_and_says_whether_it_timed_a_gpu():
    from msdgrasp.benchmarks.bench import bench_learners
    from msdgrasp.benchmarks.report import machine_info, markdown
    from numba import config as numba_config

    res = bench_learners(_config(time_limit_s=0.004), batch=2, iterations=1, steps_per_env=4, threads=4, force=True)
    assert res["agent_steps"] == 8
    if numba_config.ENABLE_CUDASIM:  # the simulator's numbers are no timings, and the bench says so
        assert not res["available"] and "simulator" in res["reason"]
    else:
        assert res["available"] and res["reason"] is None
    assert min(res["env_steps_per_s"], res["rsl_steps_per_s"], res["sb3_steps_per_s"]) > 0
    text = markdown({"what": "learners", "quick": True, "machine": machine_info(), "elapsed_s": 1.0, "targets": {},
                     "learners": res})
    assert "| env alone | rsl-rl PPO | SB3 PPO | SB3 / rsl-rl |" in text
