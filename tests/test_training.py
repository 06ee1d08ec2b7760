"""Training helpers: discounted demonstration returns, the critic fit during behaviour cloning, config.

Runtime: one tiny cloning run (2 envs, ~600 teacher steps, 3 epochs), a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.agents.training import TrainConfig, _discounted_returns, behaviour_clone, collect_demonstrations
from msdgrasp.physics.config import ConfigError, builtin_config, from_dict, read_yaml, replace


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
    base = {"n_envs": 2, "bc_teacher": "reactive", "bc_steps": 640, "bc_epochs": 3, "torch_threads": 1,
            "total_timesteps": 1}
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


def test_the_from_scratch_config_spells_out_the_dataclass_defaults():
    config = from_dict(TrainConfig, read_yaml(builtin_config("train/ppo_scratch.yaml")))
    # one source of truth: the shipped YAML spells out exactly the dataclass defaults; PPO from scratch
    assert config == TrainConfig()
    assert config.algo == "ppo" and config.bc_teacher is None and config.residual_base is None
    with pytest.raises(ConfigError, match="bogus"):
        from_dict(TrainConfig, {**read_yaml(builtin_config("train/ppo_scratch.yaml")), "bogus": 1})


def test_the_default_run_corrects_the_estimating_controller_under_the_suites_perturbations():
    """configs/train/ppo.yaml (msdgrasp train without --config) is the from-scratch config with a correction on the
    slip-feedback controller that grips by the built-in friction estimate, acting from the pull, trained under the
    robustness suite's in-range perturbations (0.08 N of noise, 5 mm / 10 deg placement, a step of latency), on the
    same task dynamics and actor observation (its reward charges the peak force as it is made, and its critic reads
    the perturbations)."""
    from msdgrasp.agents.models import default_training
    from msdgrasp.agents.robustness import CONDITIONS, inside_ranges

    config = default_training()
    assert config == TrainConfig.load(builtin_config("train/ppo.yaml"))
    task = TrainConfig().env
    assert replace(config.env, reward=task.reward, privileged_perturbations=False) == task
    assert config.env.reward.peak_force_timing == "as_made"
    assert "estimator=builtin" in config.residual_base and config.residual_start == "pull"
    ranges = config.training_task().randomization
    inside = {c.name for c in CONDITIONS if inside_ranges(c, ranges)}
    assert {"force noise 0.08 N", "latency 1 step", "grasp up to 5 mm off, 10 deg tilt, 10 deg turn"} <= inside


# =================================================================================================
# end to end: a short run saves models that load and act, keeps the best, resumes; bad inputs
# =================================================================================================

SHORT = {
    "n_envs": 2, "bc_steps": 256, "bc_epochs": 2, "torch_threads": 1, "total_timesteps": 512,
    "checkpoint_every": 256, "validation_episodes": 1, "validation_mu": [0.5, 0.9],
    "ppo": {"n_steps": 128, "batch_size": 128, "n_epochs": 1, "learning_rate": 1e-4, "use_sde": True},
}


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    from msdgrasp.agents.training import train

    out = tmp_path_factory.mktemp("train")
    summary = train(from_dict(TrainConfig, SHORT), out, progress=False)
    return out, summary


def test_short_run_saves_models_that_load_and_act(short_run):
    import json

    from msdgrasp.agents.model_policy import ModelPolicy
    from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv

    out, summary = short_run
    assert summary["timesteps"] >= 512
    for name in ("final_model.zip", "best_model.zip", "config.yaml", "final_model.yaml", "validation.json",
                 "train_summary.json"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "checkpoints").glob("model_*.zip"))  # periodic checkpoints
    assert not list(out.rglob(".*.zip"))  # no temp files of the atomic writes left behind
    from msdgrasp.agents.learners.sb3_layout import model_train_config

    # a model runs on the task it was trained on (here with the critic's privileged entries)
    task = model_train_config(out / "final_model.zip").env
    assert task.privileged_obs
    env = GraspLiftVectorEnv(3, task)
    obs, _ = env.reset(seed=0)
    for path in (out / "final_model.zip", out / "best_model.zip"):
        act = ModelPolicy(path).act(obs)
        assert act.shape == (3, 2) and np.all(np.isfinite(act))
    # the best model is the validation history's best: highest success, then lowest force cost, which
    # weighs each mu's peak pinch as the default reward charges it (mu / peak_force_mu_ref = mu / 0.4)
    val = json.loads((out / "validation.json").read_text())
    hist = val["history"]
    assert len(hist) >= 2 and val["episodes_per_mu"] == 1 and val["validation_mu"] == [0.5, 0.9]
    assert task.reward.peak_force_mu_ref == 0.4
    for rec in hist:
        by_mu = rec["peak_pinch_by_mu"]
        assert rec["mean_peak_pinch_N"] == pytest.approx((by_mu["0.5"] + by_mu["0.9"]) / 2, abs=1e-3)
        assert rec["force_cost_N"] == pytest.approx((by_mu["0.5"] * 0.5 + by_mu["0.9"] * 0.9) / 2 / 0.4, abs=1e-3)
    best = max(hist, key=lambda r: (r["success_rate"], -r["force_cost_N"]))
    assert (val["best"]["success_rate"], val["best"]["force_cost_N"]) == (best["success_rate"], best["force_cost_N"])
    assert summary["best_validation"] == val["best"]


def test_resume_continues_the_step_count(short_run, tmp_path):
    import shutil

    from msdgrasp.agents.training import train

    src, first = short_run
    run = tmp_path / "run"
    shutil.copytree(src, run)
    cfg = from_dict(TrainConfig, {**SHORT, "total_timesteps": 1024})
    summary = train(cfg, run, resume=True, progress=False)
    assert summary["resumed_from"] >= 512
    assert summary["timesteps"] >= 1024 > summary["resumed_from"]
    # validation history continues from the first run's
    import json

    assert len(json.loads((run / "validation.json").read_text())["history"]) > len(
        json.loads((src / "validation.json").read_text())["history"])


def _policy_weights(path):
    from stable_baselines3.common.save_util import load_from_zip_file

    return load_from_zip_file(path, device="cpu")[1]["policy"]


def _same_weights(a, b) -> bool:
    import torch

    return set(a) == set(b) and all(torch.equal(a[k], b[k]) for k in a)


def test_early_stopping_ends_where_validation_stops_improving_as_the_full_runs_beginning(tmp_path):
    """validation_patience P: the run ends at the first checkpoint after which P validations in a row have not beaten
    the best, before that rollout's update (its final model is that checkpoint). Everything up to there is the full
    run's, step for step (the learning-rate schedule still counts to total_timesteps), so it ships the full run's best
    model wherever no later checkpoint beats it. A resumed run that had stopped stays stopped."""
    import json

    from msdgrasp.agents.training import train

    cfg = {**SHORT, "total_timesteps": 1024, "validation_mu": [0.5]}  # a checkpoint every 256 steps: four
    full_dir, stop_dir = tmp_path / "full", tmp_path / "stop"
    full = train(from_dict(TrainConfig, cfg), full_dir, progress=False)
    hist = json.loads((full_dir / "validation.json").read_text())["history"][:-1]  # (the checkpoints; not final)

    def key(rec):
        return rec["success_rate"], -rec["force_cost_N"]

    # where patience 1 must stop: the first checkpoint that does not beat every one before it
    k = next((k for k in range(1, len(hist)) if key(hist[k]) <= max(key(r) for r in hist[:k])), None)
    assert k is not None, "this recipe's validation improved at every checkpoint: nothing here to stop early"
    stop = train(from_dict(TrainConfig, {**cfg, "validation_patience": 1}), stop_dir, progress=False)
    steps = hist[k]["timesteps"]
    assert stop["stopped_early"] == {"timesteps": steps, "validation_patience": 1} and stop["timesteps"] == steps
    assert full["stopped_early"] is None and full["timesteps"] >= 1024
    got = json.loads((stop_dir / "validation.json").read_text())["history"]
    assert [(r["timesteps"], key(r)) for r in got] == [(r["timesteps"], key(r)) for r in hist[:k + 1]]
    best = max(hist[:k + 1], key=key)
    assert key(stop["best_validation"]) == key(best)
    last = _policy_weights(stop_dir / "checkpoints" / f"model_{steps}.zip")
    assert _same_weights(last, _policy_weights(full_dir / "checkpoints" / f"model_{steps}.zip"))  # step for step
    assert _same_weights(last, _policy_weights(stop_dir / "final_model.zip"))  # no update after the stop
    assert _same_weights(_policy_weights(stop_dir / "best_model.zip"),
                         _policy_weights(full_dir / "checkpoints" / f"model_{best['timesteps']}.zip"))
    # resumed, it trains no further
    again = train(from_dict(TrainConfig, {**cfg, "validation_patience": 1}), stop_dir, resume=True, progress=False)
    assert again["timesteps"] == steps and again["stopped_early"] == stop["stopped_early"]
    assert len(json.loads((stop_dir / "validation.json").read_text())["history"]) == k + 1
    with pytest.raises(ConfigError, match="validation_patience: 2 needs validation_episodes >= 1"):
        from_dict(TrainConfig, {**cfg, "validation_patience": 2, "validation_episodes": 0})


@pytest.mark.parametrize("over, needle", [
    ({"algo": "dqn"}, "algo"),
    ({"total_timesteps": "many"}, "total_timesteps"),
    ({"validation_mu": []}, "validation_mu"),
    ({"validation_mu": [0.3, 5.0]}, "validation_mu"),
    ({"validation_episodes": -1}, "validation_episodes"),
    ({"validation_patience": 0}, r"validation_patience = 0 is out of range; allowed \[1, inf\)"),
    ({"learning_rat": 0.1}, "learning_rat"),
    ({"ppo": {"learning_rat": 0.1}}, "ppo: unknown key 'learning_rat'; allowed keys: batch_size"),  # a typo inside
    ({"ppo": [1, 2]}, "ppo must be a mapping"),
    ({"ppo": {"learning_rate": "fast"}}, r"ppo\.learning_rate must be a number, got 'fast'"),  # values are typed
    ({"ppo": {"gamma": 1.5}}, r"ppo\.gamma = 1\.5 is out of range; allowed \[0, 1\]"),
    ({"sac": {"train_freq": [4, "epoch"]}}, r"sac\.train_freq"),
    ({"env": {"substep_safety": 1.5}}, r"^TrainConfig\.env\.substep_safety = 1\.5 is out of range; allowed \(0, 1\]$"),
])
def test_bad_training_config_is_a_clear_error(over, needle):
    """Every field, the algorithm's hyper-parameter blocks included, is checked before a run folder is made."""
    with pytest.raises(ConfigError, match=needle):
        from_dict(TrainConfig, {**SHORT, **over})


def test_cli_typo_in_the_ppo_block_fails_before_any_output(tmp_path):
    import yaml

    from msdgrasp.cli.main import main

    cfg = tmp_path / "typo.yaml"
    cfg.write_text(yaml.safe_dump({**SHORT, "ppo": {"n_step": 64}}))
    out = tmp_path / "run"
    assert main(["train", "--config", str(cfg), "--out", str(out), "--quiet"]) == 2
    assert not out.exists()  # nothing half-made


def test_broken_config_next_to_a_model_is_an_error_not_a_guess(tmp_path):
    from msdgrasp.agents.training import load_model

    model = tmp_path / "m.zip"
    import zipfile

    with zipfile.ZipFile(model, "w") as z:
        z.writestr("data", "{}")
    (tmp_path / "m.yaml").write_text("algo: dqn\n")
    with pytest.raises(ConfigError, match="training config .* is invalid"):
        load_model(model)


def test_missing_or_corrupt_model_is_a_clear_error(tmp_path):
    from msdgrasp.agents.training import load_model

    with pytest.raises(ConfigError, match="not found"):
        load_model(tmp_path / "nope.zip")
    bad = tmp_path / "bad.zip"
    bad.write_bytes(b"not a zip archive")
    with pytest.raises(ConfigError, match="corrupt"):
        load_model(bad)


def test_every_shipped_training_config_loads_strictly():
    """configs/train/*.yaml and the experiment configs behind docs/design.md stay valid."""
    paths = sorted(builtin_config("train/ppo.yaml").parent.rglob("*.yaml"))
    assert len(paths) >= 11
    from msdgrasp.agents.torch_ppo import TorchPPOConfig

    for path in paths:
        if path.name.startswith("rsl"):  # the torch PPO's (its shipped defaults: tests/test_torch_ppo.py)
            assert TorchPPOConfig.load(path).env == TrainConfig().env, path  # (the same task as SB3's)
            continue
        if path.name.startswith("recurrent"):  # the recurrent learner's (tests/test_recurrent.py)
            from msdgrasp.agents.models import default_training
            from msdgrasp.agents.recurrent_training import RecurrentConfig

            assert RecurrentConfig.load(path).env == default_training().env, path
            continue
        config = TrainConfig.load(path)
        assert config.algo in ("ppo", "sac"), path


def test_the_algorithm_blocks_only_offer_arguments_of_the_sb3_constructors():
    """The typed PPO/SAC blocks may not drift from SB3: each key is an argument of the algorithm's __init__."""
    import inspect

    from stable_baselines3 import PPO, SAC
    from typing_extensions import get_type_hints

    from msdgrasp.agents.models import PPOKwargs, SACKwargs

    for block, algo in ((PPOKwargs, PPO), (SACKwargs, SAC)):
        keys = set(get_type_hints(block))
        assert keys <= set(inspect.signature(algo.__init__).parameters), (
            keys - set(inspect.signature(algo.__init__).parameters))
        assert {"learning_rate", "batch_size", "gamma"} <= keys


def test_warm_start_begins_from_the_trained_models_weights(short_run, tmp_path):
    """init_model: the run's network starts as the saved model's (actor, critic, action noise), per seed."""
    import torch

    from msdgrasp.agents.training import new_model, warm_start
    from msdgrasp.envs.sb3 import GraspLiftSB3VecEnv

    src, _ = short_run
    cfg = from_dict(TrainConfig, {**SHORT, "seed": 3, "init_model": str(src / "{seed}" / ".." / "best_model.zip")})
    assert cfg.init_model_path() == src / "3" / ".." / "best_model.zip"
    venv = GraspLiftSB3VecEnv(cfg.n_envs, cfg.training_task(), seed=cfg.seed)
    fresh = new_model(cfg, venv)
    saved = new_model(cfg, venv)
    warm_start(saved, src / "best_model.zip")
    from stable_baselines3.common.save_util import load_from_zip_file

    want = load_from_zip_file(src / "best_model.zip", device="cpu")[1]["policy"]
    got, other = saved.policy.state_dict(), fresh.policy.state_dict()
    assert set(got) == set(want)
    assert all(torch.equal(got[k], want[k]) for k in want)
    assert not all(torch.equal(other[k], want[k]) for k in want)  # (a fresh network is not the saved one)

    # a model of another observation layout is refused, naming the field
    from dataclasses import replace

    wider = replace(cfg, env=replace(cfg.env, obs_history=2))
    with pytest.raises(ConfigError, match="init_model: .* observation_space of shape"):
        warm_start(new_model(wider, GraspLiftSB3VecEnv(wider.n_envs, wider.training_task(), seed=0)),
                   src / "best_model.zip")


def test_warm_start_errors_come_before_any_output(tmp_path):
    from msdgrasp.agents.training import train

    with pytest.raises(ConfigError, match="give either init_model .* or bc_teacher"):
        from_dict(TrainConfig, {**SHORT, "init_model": "a.zip", "bc_teacher": "reactive"})
    out = tmp_path / "run"
    with pytest.raises(ConfigError, match=r"init_model: .*seed_7.*best_model\.zip is not a file"):
        pattern = str(tmp_path / "seed_{seed}" / "best_model.zip")
        train(from_dict(TrainConfig, {**SHORT, "seed": 7, "init_model": pattern}), out, progress=False)
    assert not out.exists()


def test_a_multi_seed_warm_start_checks_every_seeds_model_before_any_seed_trains(short_run, tmp_path):
    import shutil

    import yaml

    from msdgrasp.cli.main import main

    src, _ = short_run
    (tmp_path / "seed_0").mkdir()
    shutil.copy(src / "best_model.zip", tmp_path / "seed_0" / "best_model.zip")  # seed 1's is missing
    cfg = tmp_path / "warm.yaml"
    cfg.write_text(yaml.safe_dump({**SHORT, "init_model": str(tmp_path / "seed_{seed}" / "best_model.zip")}))
    out = tmp_path / "runs"
    assert main(["train", "--config", str(cfg), "--seeds", "0-1", "--workers", "1", "--out", str(out), "--quiet"]) == 2
    assert not out.exists()  # seed 0 did not train either
