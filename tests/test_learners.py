"""The learner registry: learners by name, a run's or a model's learner by what its files record, and the
refusal of a model that does not say what it was trained on (docs/learners.md)."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from msdgrasp.agents.learners import (
    Learner, TrainOverrides, default_learner, get_learner, learner_names, learner_of_config, learner_of_model,
    learner_of_run, numbered_files,
)
from msdgrasp.agents.models import TrainConfig
from msdgrasp.physics.config import ConfigError, to_dict, write_yaml


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", *args], capture_output=True, text=True)


def _sb3_config(algo: str) -> dict:
    return to_dict(TrainConfig(algo=algo, asymmetric_critic=algo == "ppo"))


def _fake_zip(path: Path) -> Path:
    """A zip archive where a model would be (the registry never opens it: the record beside it decides)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("data", "{}")
    return path


def _torch_meta(learner: str | None = "rsl") -> dict:
    meta = {"name": "PPO-torch (seed 0)", "actor_columns": [0, 1], "config": {"env": to_dict(TrainConfig().env)}}
    if learner is not None:
        meta["learner"] = learner
    return meta


def test_every_registered_name_resolves_to_its_learner():
    assert set(learner_names()) >= {"ppo", "sac", "rsl"}
    for name in learner_names():
        learner = get_learner(name)
        assert isinstance(learner, Learner) and learner.name == name
        assert learner.backends and learner.layout.model and learner.layout.summary
    # the SB3 learners share one layout; a config knows its learner
    assert get_learner("ppo").layout == get_learner("sac").layout != get_learner("rsl").layout
    assert learner_of_config(TrainConfig()).name == "ppo"
    assert learner_of_config(TrainConfig(algo="sac", asymmetric_critic=False)).name == "sac"
    assert default_learner(None).name == "ppo" and default_learner("cuda").name == "rsl"


def test_an_unknown_learner_is_a_one_line_error_listing_the_known_ones():
    with pytest.raises(ConfigError) as err:
        get_learner("dqn")
    msg = str(err.value)
    assert "\n" not in msg and "'dqn'" in msg
    for name in learner_names():
        assert name in msg


def test_a_run_folder_is_recognised_by_its_recorded_learner(tmp_path):
    sac = tmp_path / "sac_run"
    write_yaml(sac / "config.yaml", _sb3_config("sac"))
    assert learner_of_run(sac).name == "sac"
    picked = tmp_path / "picked"  # what msdgrasp select writes: the best model's config, no config.yaml
    write_yaml(picked / "best_model.yaml", _sb3_config("ppo"))
    assert learner_of_run(picked).name == "ppo"
    rsl = tmp_path / "rsl_run"
    rsl.mkdir()
    (rsl / "policy.json").write_text(json.dumps(_torch_meta()))
    assert learner_of_run(rsl).name == "rsl"
    legacy = tmp_path / "legacy"  # a policy.json written before it recorded the learner
    legacy.mkdir()
    (legacy / "policy.json").write_text(json.dumps(_torch_meta(None)))
    assert learner_of_run(legacy).name == "rsl"
    # file names alone decide nothing: a model file without a record is not a run
    stray = tmp_path / "stray"
    _fake_zip(stray / "best_model.zip")
    with pytest.raises(ConfigError, match="is not a training run"):
        learner_of_run(stray)
    assert learner_of_run(stray, required=False) is None
    with pytest.raises(ConfigError, match="is not a folder"):
        learner_of_run(tmp_path / "missing")


def test_a_model_is_recognised_by_its_recorded_learner_without_loading_it(tmp_path):
    model = _fake_zip(tmp_path / "run" / "checkpoints" / "model_100.zip")  # (not a loadable SB3 archive)
    write_yaml(tmp_path / "run" / "config.yaml", _sb3_config("sac"))
    assert learner_of_model(model).name == "sac"  # the run's config.yaml
    write_yaml(model.with_suffix(".yaml"), _sb3_config("ppo"))
    assert learner_of_model(model).name == "ppo"  # the model's own beats the run's
    policy = tmp_path / "policy.pt"
    policy.write_bytes(b"")
    (tmp_path / "policy.json").write_text(json.dumps(_torch_meta("ppo")))
    with pytest.raises(ConfigError, match="records learner 'ppo', not 'rsl'"):
        learner_of_model(policy)
    other = tmp_path / "model.onnx"
    other.write_bytes(b"")
    with pytest.raises(ConfigError, match="not a saved model of a known learner"):
        learner_of_model(other)


def test_checkpoints_are_listed_by_number_from_the_layout(tmp_path):
    layout = get_learner("rsl").layout
    for it in (10, 2, 0):
        p = tmp_path / layout.checkpoint.format(it)
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(b"")
    (tmp_path / "checkpoints" / "policy_x.pt").write_bytes(b"")
    assert [k for k, _ in numbered_files(tmp_path, layout.checkpoint)] == [0, 2, 10]


def test_an_option_a_learner_does_not_take_is_refused():
    with pytest.raises(ConfigError, match="--total-timesteps is an option of the SB3 learners"):
        get_learner("rsl").make_config(None, TrainOverrides(total_timesteps=10, backend="cpu"))
    config = get_learner("ppo").make_config(None, TrainOverrides(learner="sac", seed=4))
    assert (config.algo, config.seed, config.asymmetric_critic) == ("sac", 4, False)


@pytest.mark.parametrize("suffix, missing", [(".zip", "m.yaml"), (".pt", "m.json")])
def test_a_model_without_its_training_config_is_refused_in_one_line_before_anything_is_written(tmp_path, suffix,
                                                                                               missing):
    model = tmp_path / "models" / f"m{suffix}"
    _fake_zip(model)
    out = tmp_path / "out"
    r = _cli("evaluate", "--policy", str(model), "--episodes", "1", "--out", str(out), "--quiet")
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert "\n" not in line and str(model) in line and missing in line, line
    assert not out.exists()
    rec = tmp_path / "rec" / "ep.rrd"
    r = _cli("record", "--policy", str(model), "--out", str(rec))
    assert r.returncode == 2 and str(model) in r.stderr and missing in r.stderr and len(r.stderr.splitlines()) == 1
    assert not rec.parent.exists()


def test_record_needs_a_policy(tmp_path):
    rec = tmp_path / "ep.rrd"
    r = _cli("record", "--out", str(rec))
    assert r.returncode == 2 and "--policy" in r.stderr
    assert not rec.exists()


def test_evaluate_without_a_policy_and_without_a_trained_run_is_an_error_not_a_controller(tmp_path):
    """No --policy and no run in logs/train: one line (exit 2), never a controller evaluated in its place."""
    out = tmp_path / "eval"
    r = subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", "evaluate", "--out", str(out), "--quiet"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2, r.stderr[-2000:]
    assert len(r.stderr.strip().splitlines()) == 1 and "--policy" in r.stderr and "logs/train" in r.stderr
    assert not out.exists()


def test_evaluate_runs_a_model_only_on_the_task_it_was_trained_on(tmp_path):
    from msdgrasp.agents.evaluation import task_of
    from msdgrasp.envs.core import GraspLiftConfig

    model = _fake_zip(tmp_path / "best_model.zip")
    write_yaml(tmp_path / "best_model.yaml", _sb3_config("ppo"))
    assert task_of([str(model), "fixed"], None) == (TrainConfig().env, str(tmp_path / "best_model.yaml"))
    assert TrainConfig().env != GraspLiftConfig()  # (the training task is not the default one)
    with pytest.raises(ConfigError, match="not the one the models were trained on"):
        task_of([str(model)], GraspLiftConfig())
    assert task_of(["fixed"], None) == (GraspLiftConfig(), None)  # controllers only: the default task
