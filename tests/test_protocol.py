"""The sealed evaluation seeds (agents/protocol.py): evaluations start there and say so; everything that trains,
validates, fits, collects, sweeps or selects refuses a seed set that reaches into them, on the command line (exit
2, one line, nothing written) and through the Python API (ConfigError), before any episode runs."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
from pathlib import Path

import pytest

from msdgrasp.agents import controllers, evaluation, evaluation_jobs
from msdgrasp.agents.models import TrainConfig
from msdgrasp.agents.protocol import (
    DEMONSTRATION_SEED_OFFSET, EVALUATION_SEED, SEALED_SEEDS, VALIDATION_SEED_OFFSET, check_not_sealed, is_sealed,
    overlaps_sealed, seeds_record,
)
from msdgrasp.agents.seeds import MAX_SEEDS
from msdgrasp.cli.main import build_parser, main
from msdgrasp.physics.config import ConfigError, from_dict, to_dict, write_yaml

LO, HI = SEALED_SEEDS.start, SEALED_SEEDS.stop
RANGE = f"[{LO}, {HI})"


def _run_main(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def _refused(argv, field: str, tmp_path: Path, written: Path | None = None) -> str:
    """The command exits 2 with one line naming ``field`` and the sealed range, and writes nothing."""
    rc, out, err = _run_main(argv)
    assert rc == 2, (argv, out, err)
    assert err.count("\n") == 1 and field in err and RANGE in err and "allowed" in err, err
    if written is not None:
        assert not written.exists(), written
    return err


# ------------------------------------------------------------------------------------------------
# the range
# ------------------------------------------------------------------------------------------------


def test_the_sealed_range_lies_far_from_every_seed_a_training_derives():
    assert (LO, HI) == (1_000_000_000, 1_100_000_000) and EVALUATION_SEED == LO
    # the largest seed the project's trainings derive from seeds 0 .. MAX_SEEDS - 1: validation episodes
    assert MAX_SEEDS + VALIDATION_SEED_OFFSET + 10_000 < LO and DEMONSTRATION_SEED_OFFSET < VALIDATION_SEED_OFFSET


@pytest.mark.parametrize("first, count, overlaps, sealed", [
    (LO, 10, True, True), (HI - 10, 10, True, True), (HI - 9, 10, True, False), (LO - 1, 2, True, False),
    (LO - 10, 10, False, False), (HI, 5, False, False), (0, 10, False, False), (LO, 0, False, False),
])
def test_overlap_and_sealed_are_the_half_open_range(first, count, overlaps, sealed):
    assert overlaps_sealed(first, count) is overlaps and is_sealed(first, count) is sealed
    assert seeds_record(first, count) == {"first": first, "count": count, "sealed": sealed}


def test_the_refusal_names_the_field_the_seeds_and_the_allowed_range():
    check_not_sealed(LO - 10, 10, "seed")  # (just below: allowed)
    check_not_sealed(HI, 3, "seed")
    with pytest.raises(ConfigError) as exc:
        check_not_sealed(LO - 5, 10, "--seed")
    message = str(exc.value)
    assert "\n" not in message and message.startswith(f"--seed = {LO - 5}")
    assert f"seeds {LO - 5}..{LO + 4}" in message and RANGE in message and f"below {LO}" in message
    with pytest.raises(ConfigError, match="seeds must be integers >= 0"):
        check_not_sealed(-1, 1, "--seed")


# ------------------------------------------------------------------------------------------------
# training configs: the training envs, the validation episodes, the demonstrations
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("data, what", [
    ({"seed": LO}, "training envs"),
    ({"seed": LO - 16, "n_envs": 32}, "training envs"),
    ({"seed": LO - VALIDATION_SEED_OFFSET - 3}, "validation episodes"),
    ({"seed": LO - DEMONSTRATION_SEED_OFFSET, "bc_teacher": "reactive", "validation_episodes": 0}, "demonstrations"),
    ({"seed": HI - 1}, "training envs"),
])
def test_a_training_config_refuses_seeds_that_reach_the_sealed_range(data, what):
    with pytest.raises(ConfigError) as exc:
        from_dict(TrainConfig, data, where="train.yaml")
    assert what in str(exc.value) and RANGE in str(exc.value)
    with pytest.raises(ConfigError, match=what):  # (a seed set afterwards is checked too)
        dataclasses.replace(TrainConfig(), **data)


def test_the_validation_seeds_bound_the_seed_and_a_config_without_validation_does_not_use_them():
    seed = LO - VALIDATION_SEED_OFFSET - 3  # its validation episodes 0..2 fit below the range, 3.. do not
    assert from_dict(TrainConfig, {"seed": seed, "validation_episodes": 3}).seed == seed
    assert from_dict(TrainConfig, {"seed": seed, "validation_episodes": 0}).seed == seed
    with pytest.raises(ConfigError, match="validation episodes"):
        from_dict(TrainConfig, {"seed": seed, "validation_episodes": 4})


def test_the_torch_ppo_config_refuses_seeds_that_reach_the_sealed_range():
    from msdgrasp.agents.torch_ppo import TorchPPOConfig

    with pytest.raises(ConfigError, match="num_envs = 4096"):
        TorchPPOConfig(seed=LO - 4095)
    with pytest.raises(ConfigError, match="validation episodes"):
        TorchPPOConfig(seed=LO - VALIDATION_SEED_OFFSET, num_envs=8)
    below = LO - VALIDATION_SEED_OFFSET - 6  # the default's 4096 envs and 6 validation episodes fit below the range
    assert TorchPPOConfig(seed=below).seed == below


def test_model_selection_refuses_the_sealed_seeds_before_it_validates(monkeypatch):
    from msdgrasp.agents.training import BestModel

    config = from_dict(TrainConfig, {"seed": 0, "validation_episodes": 2})
    # (a config that escaped its checks: the selector itself refuses before an episode runs)
    object.__setattr__(config, "seed", LO - VALIDATION_SEED_OFFSET)
    monkeypatch.setattr("msdgrasp.agents.training.evaluate_policy",
                        lambda *a, **k: pytest.fail("validated on sealed seeds"))
    with pytest.raises(ConfigError, match="validation episodes"):
        BestModel(config, Path("unused")).consider_policy(None, 0, Path("m.zip"), lambda: None)


# ------------------------------------------------------------------------------------------------
# the commands and their Python APIs
# ------------------------------------------------------------------------------------------------


def test_train_refuses_a_sealed_seed_before_writing(tmp_path):
    out = tmp_path / "run"
    _refused(["train", "--seed", LO, "--out", out, "--quiet"], "seed", tmp_path, out)
    _refused(["train", "--seed", LO - 8, "--n-envs", 16, "--out", out, "--quiet"], "training envs", tmp_path, out)
    _refused(["train", "--seeds", f"{LO - 2}-{LO - 1}", "--out", out, "--quiet"], "seed", tmp_path, out)
    # the torch PPO (rsl) derives its env and validation seeds the same way
    _refused(["train", "--learner", "rsl", "--backend", "cpu", "--seed", LO - 3, "--out", out, "--quiet"],
             "num_envs", tmp_path, out)


def test_run_seeds_refuses_a_sealed_seed_before_any_job(tmp_path):
    from msdgrasp.agents.seeds import run_seeds

    out = tmp_path / "seeds"
    with pytest.raises(ConfigError, match="training envs"):
        run_seeds(TrainConfig(n_envs=2), [0, LO], out, workers=1, episodes=1, progress=False)
    assert not out.exists()


def test_fit_friction_refuses_a_sealed_seed(tmp_path):
    from msdgrasp.agents.friction_fit import collect_closing_features, fit_friction_estimator

    out = tmp_path / "est.json"
    config = Path(__file__).parents[1] / "configs" / "train" / "ppo.yaml"
    _refused(["fit-friction", "--config", config, "--seed", LO - 100, "--episodes", 768, "--out", out], "--seed",
             tmp_path, out)
    task = TrainConfig().env
    with pytest.raises(ConfigError, match="fitting episodes"):
        fit_friction_estimator(task, episodes=4, seed=LO)
    with pytest.raises(ConfigError, match="fitting episodes"):
        collect_closing_features(task, 4, LO - 2, 0.7)


def test_collect_and_clone_refuse_a_sealed_seed(tmp_path):
    out = tmp_path / "datasets"
    _refused(["collect", "--policy", "reactive", "--episodes", 3, "--seed", LO - 1, "--out", out, "--quiet"],
             "--seed", tmp_path, out)
    clone_out = tmp_path / "clone"
    _refused(["clone", "msdgrasp/grasplift/none-v0", "--datasets", out, "--seed", LO, "--out", clone_out], "seed",
             tmp_path, clone_out)
    from msdgrasp.agents.offline import check_clone_seed

    with pytest.raises(ConfigError, match="validation episodes"):
        check_clone_seed(LO - VALIDATION_SEED_OFFSET)
    pytest.importorskip("minari")
    from msdgrasp.agents.demonstrations import collect

    with pytest.raises(ConfigError, match="episodes: seed"):
        collect("reactive", 2, out, seed=LO, progress=False)
    assert not out.exists()


def _sweep_file(tmp_path: Path, **fields) -> Path:
    path = tmp_path / "sweep.yaml"
    path.write_text(json.dumps({"set": {"total_timesteps": 256, "n_envs": 2}, "grid": {"ppo.gamma": [0.9]},
                                **fields}))
    return path


def test_sweep_refuses_sealed_training_and_evaluation_seeds(tmp_path):
    from msdgrasp.agents.sweep import SweepConfig, run_sweep, sweep_points
    from msdgrasp.agents.parallel import Runner

    out = tmp_path / "out"
    _refused(["sweep", _sweep_file(tmp_path, seeds=f"{LO - 1}-{LO}"), "--dry-run"], "point 0", tmp_path)
    _refused(["sweep", _sweep_file(tmp_path, evaluation_seed=LO - 5), "--out", out], "evaluation_seed", tmp_path, out)
    with pytest.raises(ConfigError, match="evaluation_seed"):
        SweepConfig(grid={"ppo.gamma": [0.9]}, evaluation_seed=LO)
    sweep = SweepConfig(grid={"ppo.gamma": [0.9]}, seeds=f"0,{LO - VALIDATION_SEED_OFFSET}")
    with pytest.raises(ConfigError, match="validation episodes"):
        sweep_points(sweep)
    with pytest.raises(ConfigError):
        run_sweep(sweep, out, Runner.processes(1), progress=False)
    assert not out.exists()


def test_select_refuses_validation_that_would_reach_the_sealed_seeds(tmp_path):
    from msdgrasp.agents.selection import plan_selection

    run = tmp_path / "run"
    seed = LO - VALIDATION_SEED_OFFSET - 2  # the run validated 2 episodes per mu: seeds below the range
    write_yaml(run / "config.yaml", to_dict(from_dict(TrainConfig, {"seed": seed, "validation_episodes": 2,
                                                                    "n_envs": 2})))
    out = tmp_path / "picked"
    _refused(["select", run, "--validation-episodes", 3, "--out", out], "validation episodes", tmp_path, out)
    with pytest.raises(ConfigError, match="validation episodes"):
        plan_selection(run, validation_episodes=5)


# ------------------------------------------------------------------------------------------------
# evaluations start in the sealed range and say so
# ------------------------------------------------------------------------------------------------


def test_evaluation_commands_default_to_the_sealed_range():
    parser = build_parser()
    assert parser.parse_args(["evaluate"]).seed == EVALUATION_SEED
    assert parser.parse_args(["evaluate", "--suite", "robustness"]).seed == EVALUATION_SEED
    assert parser.parse_args(["report", "runs"]).seed == EVALUATION_SEED
    import inspect

    from msdgrasp.agents import robustness, seeds

    for fn in (evaluation.evaluate, robustness.run_suite):
        assert inspect.signature(fn).parameters["seed"].default == EVALUATION_SEED, fn
    for fn in (seeds.run_seeds, seeds.report_seed_runs, seeds.report_trained_seeds, seeds.train_points):
        assert inspect.signature(fn).parameters["evaluation_seed"].default == EVALUATION_SEED, fn


def test_an_evaluation_records_its_seeds_and_whether_they_are_sealed(tmp_path, monkeypatch):
    monkeypatch.setattr(evaluation_jobs, "minimal_force_job", lambda cfg, mu: 1.25)  # (the bisection: seconds)
    monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)
    sealed = evaluation.evaluate(["fixed"], [0.5], 2, tmp_path / "sealed", progress=False, conditions=())
    data = json.loads((tmp_path / "sealed" / "evaluation.json").read_text())
    assert data["seeds"] == sealed["seeds"] == {"first": EVALUATION_SEED, "count": 2, "sealed": True}
    assert data["evaluation"]["seeds"] == [EVALUATION_SEED, EVALUATION_SEED + 1]
    evaluation.evaluate(["fixed"], [0.5], 2, tmp_path / "dev", seed=0, progress=False, conditions=())
    data = json.loads((tmp_path / "dev" / "evaluation.json").read_text())
    assert data["seeds"] == {"first": 0, "count": 2, "sealed": False}
    # a run partly inside the range is neither sealed nor a development result: refused before it runs
    for first in (HI - 1, EVALUATION_SEED - 1):
        with pytest.raises(ConfigError, match="straddle the sealed evaluation seeds"):
            evaluation.evaluate(["fixed"], [0.5], 2, tmp_path / "edge", seed=first, progress=False, conditions=())
    assert not (tmp_path / "edge").exists()
    with pytest.raises(ConfigError, match="seed = -3"):
        evaluation.evaluate(["fixed"], [0.5], 1, tmp_path / "bad", seed=-3, progress=False, conditions=())
    assert not (tmp_path / "bad").exists()
