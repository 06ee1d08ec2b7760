"""The torch-native PPO (rsl-rl-lib, agents/torch_ppo.py) on the CPU core: its env adapter, a short run, the
exported policy and the command line. (The same learner on the GPU task: tests/test_cuda_task.py.)"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from msdgrasp.agents.models import TrainConfig
from msdgrasp.agents.torch_ppo import TorchPPOConfig, TorchScriptPolicy, actor_columns, make_torch_env, train_torch
from msdgrasp.envs.core import OBS_NAMES, GraspLiftConfig, GraspLiftCore
from msdgrasp.physics.config import ConfigError, builtin_config, from_dict, read_yaml, to_dict


def test_the_shipped_configs_are_the_defaults_and_train_the_sb3_task():
    assert TorchPPOConfig.load(builtin_config("train/rsl_ppo.yaml")) == TorchPPOConfig()
    assert TorchPPOConfig().env == TrainConfig().env
    sb3_env = from_dict(GraspLiftConfig, read_yaml(builtin_config("train/ppo_scratch.yaml"))["env"])
    assert from_dict(GraspLiftConfig, read_yaml(builtin_config("train/rsl_ppo.yaml"))["env"]) == sb3_env
    # the CPU-sized run: the defaults but for where it runs and its size, on twice the SB3 training's step
    # budget (on the same budget, experiments/rsl-0m9.yaml, 3 of 5 seeds gripped >= 1.5x the oracle's force)
    cpu = TorchPPOConfig.load(builtin_config("train/rsl_ppo_cpu.yaml"))
    assert cpu.env == sb3_env
    assert cpu == TorchPPOConfig(backend="cpu", num_envs=64, iterations=880, checkpoint_every=24)
    sb3_steps = TrainConfig().total_timesteps
    assert cpu.total_steps == pytest.approx(2 * sb3_steps, rel=0.01)
    same_budget = TorchPPOConfig.load(builtin_config("train/experiments/rsl-0m9.yaml"))
    assert same_budget == TorchPPOConfig(backend="cpu", num_envs=64, iterations=440, checkpoint_every=12)
    assert same_budget.total_steps == pytest.approx(sb3_steps, rel=0.01)


def test_the_command_line_picks_the_config_sized_for_where_it_runs():
    from msdgrasp.agents.learners.rsl_layout import config_path as torch_config_path

    assert torch_config_path(None, "cpu") == builtin_config("train/rsl_ppo_cpu.yaml")  # 64 envs, not 4,096
    assert torch_config_path(None, "cuda") == builtin_config("train/rsl_ppo.yaml")
    assert torch_config_path(None, None) == builtin_config("train/rsl_ppo.yaml")  # (its backend: cuda)
    assert torch_config_path("my.yaml", "cpu").name == "my.yaml"


def test_float32_is_an_option_of_either_backend_and_other_precisions_are_refused():
    for backend in ("cpu", "cuda"):
        assert TorchPPOConfig(backend=backend, precision="float32").precision == "float32"
    with pytest.raises(ConfigError, match=r"precision"):
        TorchPPOConfig(backend="cpu", precision="float16")


def test_squashed_actions_are_a_tanh_gaussian_whose_density_integrates_to_one():
    from msdgrasp.agents.rsl_distributions import SquashedGaussianDistribution

    torch.manual_seed(0)
    dist = SquashedGaussianDistribution(2, init_std=0.37, std_type="log")
    mean = torch.tensor([[0.3, -1.2]])
    dist.update(mean)
    a = torch.stack([dist.sample() for _ in range(2000)])[:, 0]
    assert a.abs().max() < 1.0  # every action inside the bounds: nothing for the env to clip
    # the change of variables: p(a) = N(atanh a; mean, std) / (1 - a^2), per action entry
    u = torch.atanh(a)
    expected = (torch.distributions.Normal(mean, 0.37).log_prob(u) - torch.log(1 - a * a)).sum(-1)
    torch.testing.assert_close(dist.log_prob(a), expected, rtol=1e-5, atol=1e-4)
    # a density: on a grid over (-1, 1)^2 it integrates to 1 (trapezoid, both axes)
    grid = torch.linspace(-1 + 1e-6, 1 - 1e-6, 2001, dtype=torch.float64)
    dist.update(mean.double())
    aa = torch.stack(torch.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    p = dist.log_prob(aa).exp().reshape(2001, 2001)
    assert float(torch.trapezoid(torch.trapezoid(p, grid), grid)) == pytest.approx(1.0, abs=1e-3)
    # the deterministic action (the exported policy's) is tanh of the mean, inside the bounds
    torch.testing.assert_close(dist.deterministic_output(mean), torch.tanh(mean))
    torch.testing.assert_close(dist.as_deterministic_output_module()(mean), torch.tanh(mean))


def test_a_squashed_run_exports_a_policy_inside_the_action_bounds(tmp_path):
    data = to_dict(TorchPPOConfig())
    data.update(backend="cpu", num_envs=4, iterations=2, steps_per_env=8, validation_episodes=0, squash_actions=True)
    config = from_dict(TorchPPOConfig, data)
    assert config.runner_cfg()["actor"]["distribution_cfg"]["class_name"].endswith(":SquashedGaussianDistribution")
    train_torch(config, tmp_path, progress=False)
    policy = TorchScriptPolicy(tmp_path / "policy.pt")
    core = GraspLiftCore(config.env, 2)
    for i in range(2):
        core.seed(i, i)
        core.reset(i)
    # observations far outside the training's drive the linear head far past +-1; the squash keeps them inside
    a = policy.act(1e4 * core.obs)
    assert np.all(np.abs(a) <= 1.0) and np.abs(a).max() > 0.99


def _small_task(**changes) -> GraspLiftConfig:
    return from_dict(GraspLiftConfig, {**to_dict(TrainConfig().env), "time_limit_s": 0.2, **changes})  # 7 steps


def test_the_adapter_hands_rsl_rl_the_core_s_steps_with_time_outs_and_episode_logs():
    config = _small_task()
    env = make_torch_env(GraspLiftCore(config, 3), "cpu", seed=5)
    reference = GraspLiftCore(config, 3)
    for i in range(3):
        reference.seed(i, 5 + i)
        reference.reset(i)
    obs = env.get_observations()
    cols = actor_columns(config, reference.frame_dim)
    assert len(cols) == len(OBS_NAMES) and obs["critic"].shape == (3, reference.obs_dim)  # actor: no privileged entry
    np.testing.assert_array_equal(obs["policy"].numpy(), reference.obs[:, cols].astype(np.float32))
    actions = np.array([[0.2, -0.5], [1.0, 1.0], [-1.0, 0.0]], dtype=np.float32)
    for k in range(config.max_episode_steps):
        obs, rew, dones, extras = env.step(torch.as_tensor(actions))
        o_ref, r_ref, term, trunc, info = reference.step(actions)
        np.testing.assert_array_equal(rew.numpy(), r_ref.astype(np.float32))
        np.testing.assert_array_equal(dones.numpy().astype(bool), term | trunc)
        np.testing.assert_array_equal(extras["time_outs"].numpy(), trunc)
        if not (term | trunc).any():
            np.testing.assert_array_equal(obs["critic"].numpy(), o_ref)
            assert extras["log"] == {}
    assert (term | trunc).all() and trunc.any()
    ended = term | trunc
    assert float(extras["log"]["/episode/success"]) == pytest.approx(info["is_success"][ended].mean())
    assert float(extras["log"]["/episode/peak_pinch_N"]) == pytest.approx(info["peak_pinch_N"][ended].mean(), rel=1e-6)
    # the ended envs were reset: their observation is a new episode's first (time fraction 0)
    assert np.all(obs["critic"].numpy()[:, OBS_NAMES.index("time_fraction")] == 0.0)
    assert env.episode_length_buf.tolist() == [0, 0, 0]


def test_a_short_cpu_run_exports_a_policy_that_acts_as_the_trained_actor(tmp_path):
    data = to_dict(TorchPPOConfig())
    data.update(backend="cpu", num_envs=8, iterations=2, steps_per_env=8, validation_episodes=2, validation_mu=[0.5])
    config = from_dict(TorchPPOConfig, data)
    summary = train_torch(config, tmp_path, progress=False)
    assert summary["agent_steps"] == 2 * 8 * 8 and summary["train_s"] > 0
    row, = summary["validation"]
    assert row["mu"] == 0.5 and 0.0 <= row["success_rate"] <= 1.0 and row["mean_peak_pinch_N"] >= 0.0
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    policy = TorchScriptPolicy(tmp_path / "policy.pt")
    core = GraspLiftCore(config.env, 4)
    for i in range(4):
        core.seed(i, i)
        core.reset(i)
    a = policy.act(core.obs)
    assert a.shape == (4, 2) and np.all(np.isfinite(a))
    # the policy reads only the actor's entries: changing the privileged ones changes nothing
    perturbed = core.obs.copy()
    perturbed[:, len(OBS_NAMES):] += 1.0
    np.testing.assert_array_equal(policy.act(perturbed), a)
    perturbed[:, 4] += 1.0  # a force reading does
    assert not np.array_equal(policy.act(perturbed), a)
    # msdgrasp evaluate takes it like an SB3 model: by path, on the task it was trained on, in worker processes
    from msdgrasp.agents.evaluation import task_of
    from msdgrasp.agents.evaluation_jobs import policy_of, policy_payload

    spec = str(tmp_path / "policy.pt")
    assert task_of([spec], None) == (config.env, str(tmp_path / "policy.json"))
    shipped = policy_of(policy_payload(spec, "torch"), config.env)
    assert shipped.name == "torch" and np.array_equal(shipped.act(core.obs), a)


def test_the_shipped_policy_is_the_best_validated_checkpoint(tmp_path):
    data = to_dict(TorchPPOConfig())
    data.update(backend="cpu", num_envs=4, iterations=5, steps_per_env=8, checkpoint_every=2, validation_episodes=2,
                validation_mu=[0.3, 0.9], env=to_dict(_small_task()))
    config = from_dict(TorchPPOConfig, data)
    summary = train_torch(config, tmp_path, progress=False)
    history = json.loads((tmp_path / "validation.json").read_text())["history"]
    # checkpoints after iterations 0, 2, 4 (the last), each validated once, in order, at its agent steps
    assert summary["checkpoints_validated"] == 3
    assert [h["timesteps"] for h in history] == [1 * 32, 3 * 32, 5 * 32]
    assert [h["model"] for h in history] == [str(tmp_path / "checkpoints" / f"policy_{i}.pt") for i in (0, 2, 4)]
    # the best by the SB3 training's key (success, then the reward's force charge; the first of equals)
    key = [(h["success_rate"], -h["force_cost_N"]) for h in history]
    best = key.index(max(key))
    assert summary["best_iteration"] == (0, 2, 4)[best]
    assert ((tmp_path / "policy.pt").read_bytes()
            == (tmp_path / "checkpoints" / f"policy_{(0, 2, 4)[best]}.pt").read_bytes())
    assert json.loads((tmp_path / "policy.json").read_text())["iteration"] == summary["best_iteration"]
    assert summary["validation_success"] == history[best]["success_rate"]
    assert [r["mu"] for r in summary["validation"]] == [0.3, 0.9]


def test_the_command_line_refuses_sb3_options_for_the_torch_learner(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", "train", *args, "--out", str(tmp_path / "o")],
                              capture_output=True, text=True)

    r = run("--learner", "rsl", "--total-timesteps", "10")
    assert r.returncode == 2 and "--total-timesteps is an option of the SB3 learners" in r.stderr
    r = run("--backend", "cuda", "--learner", "ppo")
    assert r.returncode == 2 and "--backend cuda: learner ppo runs on cpu; on cuda train with --learner rsl" in r.stderr
    r = run("--learner", "rsl", "--n-envs", "0")
    assert r.returncode == 2 and "--n-envs: allowed 1..65536, got 0" in r.stderr
    assert not (tmp_path / "o").exists()


def test_torch_seeds_get_the_multi_seed_report_of_sb3_seeds_and_report_remakes_it(tmp_path):
    from msdgrasp.agents.seeds import EVAL_MU

    cfg = tmp_path / "tiny.yaml"
    data = {**to_dict(TorchPPOConfig(backend="cpu", num_envs=4, iterations=2, steps_per_env=8, validation_episodes=0)),
            "env": {**to_dict(_small_task())}}
    cfg.write_text(json.dumps(data))  # (JSON is YAML)
    out = tmp_path / "runs"

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", *args], capture_output=True, text=True)

    stale = out / "seed_7"  # an older, unfinished run in the same folder: not one of these seeds
    stale.mkdir(parents=True)
    (stale / "policy.pt").write_bytes(b"")
    r = cli("train", "--learner", "rsl", "--config", str(cfg), "--seeds", "0-1", "--out", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    shutil.rmtree(stale)
    first = json.loads((out / "seeds.json").read_text())
    assert first["training_seeds"] == [0, 1] and [s["seed"] for s in first["per_seed"]] == [0, 1]
    assert first["seeds"]["sealed"] is True  # (evaluated on the sealed evaluation seeds)
    for rec in first["per_seed"]:  # every seed evaluated at every mu of the multi-seed grid, as SB3's seeds are
        assert [row["mu"] for row in rec["rows"]] == list(EVAL_MU) and rec["model"].endswith("policy.pt")
        assert rec["timesteps"] == 2 * 8 * 4 and 0.0 <= rec["success_ref"] <= 1.0
    assert set(first["baselines"]) == {"reactive", "oracle"}
    assert "| PPO-torch (seed 1) |" in (out / "seeds.md").read_text()
    # msdgrasp report remakes it from the runs: the same evaluation episodes, the same numbers
    (out / "seeds.json").unlink()
    r = cli("report", str(out), "--quiet")
    assert r.returncode == 0, r.stderr
    again = json.loads((out / "seeds.json").read_text())
    for a, b in zip(first["per_seed"], again["per_seed"]):
        assert a["rows"] == b["rows"]
    assert again["baselines"] == first["baselines"]
    (out / "seed_1" / "summary.json").unlink()
    r = cli("report", str(out))
    assert r.returncode == 2 and "seed_1/summary.json is missing: the run did not finish" in r.stderr


def test_the_linear_schedule_lowers_the_learning_rate_each_update_to_the_last(tmp_path):
    data = to_dict(TorchPPOConfig())
    data.update(backend="cpu", num_envs=4, iterations=3, steps_per_env=8, validation_episodes=0, schedule="linear",
                learning_rate=3e-4, env=to_dict(_small_task()))
    config = from_dict(TorchPPOConfig, data)
    assert config.runner_cfg()["algorithm"]["schedule"] == "fixed"  # (rsl-rl's; train_torch anneals it)
    train_torch(config, tmp_path, progress=False)
    saved = torch.load(tmp_path / "tb" / "model_2.pt", map_location="cpu", weights_only=False)
    # updates 0, 1, 2 of 3 ran at 3e-4 x (1, 2/3, 1/3): the optimizer keeps the last one's rate
    assert [g["lr"] for g in saved["optimizer_state_dict"]["param_groups"]] == pytest.approx([1e-4])
    with pytest.raises(ConfigError, match="schedule"):
        from_dict(TorchPPOConfig, {**data, "schedule": "cosine"})
