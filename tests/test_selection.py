"""``msdgrasp select`` (agents/selection.py): a finished run's checkpoints validated again, the pick written
into a new folder, the run untouched. Selecting with the run's own settings must give the run's own pick
(the same episodes on the same checkpoints); other settings change only the validation."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from msdgrasp.agents.models import TrainConfig
from msdgrasp.agents.protocol import EVALUATION_SEED
from msdgrasp.agents.selection import plan_selection, select
from msdgrasp.envs.core import GraspLiftConfig
from msdgrasp.physics.config import ConfigError, from_dict, to_dict


def _small_task() -> GraspLiftConfig:
    return from_dict(GraspLiftConfig, {**to_dict(TrainConfig().env), "time_limit_s": 0.2})  # 7 agent steps


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def torch_run(tmp_path_factory) -> Path:
    from msdgrasp.agents.torch_ppo import TorchPPOConfig, train_torch

    pytest.importorskip("rsl_rl")
    out = tmp_path_factory.mktemp("torch_run")
    data = {**to_dict(TorchPPOConfig()), "backend": "cpu", "num_envs": 4, "iterations": 5, "steps_per_env": 8,
            "checkpoint_every": 2, "validation_episodes": 2, "validation_mu": [0.3, 0.9], "env": to_dict(_small_task())}
    train_torch(from_dict(TorchPPOConfig, data), out, progress=False)
    return out


@pytest.fixture(scope="module")
def sb3_run(tmp_path_factory) -> Path:
    from msdgrasp.agents.training import train

    out = tmp_path_factory.mktemp("sb3_run")
    data = {"n_envs": 2, "torch_threads": 1, "total_timesteps": 512, "checkpoint_every": 256, "validation_episodes": 1,
            "validation_mu": [0.5, 0.9], "env": to_dict(_small_task()),
            "ppo": {"n_steps": 128, "batch_size": 128, "n_epochs": 1, "learning_rate": 1e-4, "use_sde": True}}
    train(from_dict(TrainConfig, data), out, progress=False)
    return out


def _validation(folder: Path) -> dict:
    return json.loads((folder / "validation.json").read_text())


def test_selecting_a_torch_run_again_with_its_own_settings_gives_its_own_pick(torch_run, tmp_path):
    before = _digest(torch_run)
    [result] = select(torch_run, tmp_path / "again")
    again, run = _validation(tmp_path / "again"), _validation(torch_run)
    assert again["history"] == run["history"] and again["best"] == run["best"]
    assert (tmp_path / "again" / "policy.pt").read_bytes() == (torch_run / "policy.pt").read_bytes()
    summary, trained = (json.loads((f / "summary.json").read_text()) for f in (tmp_path / "again", torch_run))
    for key in ("best_iteration", "validation", "validation_success", "checkpoints_validated", "train_s", "seed"):
        assert summary[key] == trained[key], key
    assert summary["selected_from"] == str(torch_run)
    assert result["learner"] == "rsl" and result["checkpoints_validated"] == 3 and result["best"] == run["best"]
    assert _digest(torch_run) == before  # the run is never touched


def test_more_validation_episodes_validate_every_checkpoint_again_and_ship_the_best(torch_run, tmp_path):
    out = tmp_path / "sel"
    select(torch_run, out, validation_episodes=4, validation_mu=[0.5])
    val = _validation(out)
    assert val["episodes_per_mu"] == 4 and val["validation_mu"] == [0.5]
    hist = val["history"]
    assert [h["model"] for h in hist] == [str(torch_run / "checkpoints" / f"policy_{i}.pt") for i in (0, 2, 4)]
    assert all(list(h["success_by_mu"]) == ["0.5"] and h["success_rate"] in (0, 0.25, 0.5, 0.75, 1) for h in hist)
    key = [(h["success_rate"], -h["force_cost_N"]) for h in hist]
    it = (0, 2, 4)[key.index(max(key))]
    assert (out / "policy.pt").read_bytes() == (torch_run / "checkpoints" / f"policy_{it}.pt").read_bytes()
    meta = json.loads((out / "policy.json").read_text())
    # the shipped policy's config says how it was chosen
    assert meta["iteration"] == it and meta["config"]["validation_episodes"] == 4
    assert meta["config"]["validation_mu"] == [0.5]
    assert json.loads((out / "summary.json").read_text())["best_iteration"] == it


def test_selecting_an_sb3_run_again_gives_its_best_model(sb3_run, tmp_path):
    before = _digest(sb3_run)
    [result] = select(sb3_run, tmp_path / "again")
    again, run = _validation(tmp_path / "again"), _validation(sb3_run)
    assert [h["model"] for h in again["history"]] == [h["model"] for h in run["history"]]  # checkpoints, then final
    assert again["history"] == run["history"] and again["best"] == run["best"]
    assert result["learner"] == "ppo" and (tmp_path / "again" / "best_model.yaml").is_file()
    from msdgrasp.agents.learners.sb3_layout import model_train_config

    assert model_train_config(tmp_path / "again" / "best_model.zip").validation_episodes == 1
    assert _digest(sb3_run) == before


def test_a_folder_of_seeds_is_selected_seed_by_seed(torch_run, tmp_path):
    runs = tmp_path / "runs"
    for k in (0, 3):
        shutil.copytree(torch_run, runs / f"seed_{k}")
    results = select(runs, tmp_path / "sel", validation_episodes=3, workers=2)
    assert [Path(r["run"]).name for r in results] == ["seed_0", "seed_3"]
    a, b = (_validation(tmp_path / "sel" / f"seed_{k}") for k in (0, 3))
    assert a["episodes_per_mu"] == 3 and [h["success_by_mu"] for h in a["history"]] == [
        h["success_by_mu"] for h in b["history"]]  # the same checkpoints, the same validation seed


def test_bad_selections_are_one_line_errors_before_anything_is_written(torch_run, tmp_path):
    with pytest.raises(ConfigError, match="validation_episodes must be an integer >= 1, got 0"):
        plan_selection(torch_run, validation_episodes=0)
    with pytest.raises(ConfigError, match="is not a training run"):
        plan_selection(tmp_path)
    empty = tmp_path / "empty"
    shutil.copytree(torch_run, empty)
    shutil.rmtree(empty / "checkpoints")
    with pytest.raises(ConfigError, match=r"has no checkpoints/policy_<number>\.pt to validate"):
        plan_selection(empty)
    unfinished = tmp_path / "unfinished"
    shutil.copytree(torch_run, unfinished)
    (unfinished / "summary.json").unlink()
    with pytest.raises(ConfigError, match="summary.json is missing: the run did not finish"):
        plan_selection(unfinished)

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", "select", *args], capture_output=True,
                              text=True)

    r = cli(str(torch_run), "--out", str(torch_run))
    assert r.returncode == 2 and "is the run itself" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    other = tmp_path / "other_run"
    shutil.copytree(torch_run, other)
    r = cli(str(torch_run), "--out", str(other))
    assert r.returncode == 2 and "is a training run of its own" in r.stderr
    assert _digest(other) == _digest(torch_run)
    r = cli(str(torch_run), "--out", str(tmp_path / "o"), "--validation-mu", "0.5,-1")
    assert r.returncode == 2 and "negative" in r.stderr
    r = cli(str(tmp_path / "missing"), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "is not a folder" in r.stderr
    assert not (tmp_path / "o").exists()


def test_report_makes_the_multi_seed_report_of_re_selected_sb3_seeds(sb3_run, torch_run, tmp_path):
    runs = tmp_path / "runs"
    for k in (0, 1):
        shutil.copytree(sb3_run, runs / f"seed_{k}")

    def cli(*args):
        return subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", *args], capture_output=True, text=True)

    r = cli("select", str(runs), "--out", str(tmp_path / "sel"), "--validation-episodes", "2", "--workers", "2")
    assert r.returncode == 0, r.stderr
    r = cli("report", str(tmp_path / "sel"), "--episodes", "1", "--quiet")
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "sel" / "seeds.json").read_text())
    assert report["training_seeds"] == [0, 1] and report["config"]["validation_episodes"] == 2
    assert report["seeds"] == {"first": EVALUATION_SEED, "count": 1, "sealed": True}  # (report's default seeds)
    trained = json.loads((sb3_run / "train_summary.json").read_text())
    for rec in report["per_seed"]:
        assert rec["model"].endswith("best_model.zip") and rec["timesteps"] == trained["timesteps"]
        assert len(rec["validation"]) == len(json.loads((sb3_run / "validation.json").read_text())["history"])
    # same copies, same pick: the two seeds' evaluations agree episode for episode
    assert report["per_seed"][0]["rows"] == report["per_seed"][1]["rows"]
    shutil.copytree(torch_run, tmp_path / "sel" / "seed_2")
    r = cli("report", str(tmp_path / "sel"))
    assert r.returncode == 2 and "mix learners" in r.stderr
