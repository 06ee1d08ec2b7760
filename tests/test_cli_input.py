"""Bad command-line input is one line naming the field, exit status 2, before anything runs or is written.

Each case is a mistake a user makes (a typo in a number, an output path that cannot be written, a config that is not
text or gives a key twice, a mesh file that is not a mesh); the test checks the status, that stderr is one line naming
what is wrong, and that the working folder is left as it was.
"""

from __future__ import annotations

import pytest

from msdgrasp.cli.main import main
from msdgrasp.physics.config import MAX_ENVS, ConfigError, read_yaml
from msdgrasp.physics.mesh import MeshError
from msdgrasp.physics.mesh_io import load_mesh


def _run(argv: list[str], capsys) -> tuple[int, str]:
    status = main(argv)  # (argparse's own errors too: main returns their status)
    return status, capsys.readouterr().err.strip()


def _assert_refused(argv: list[str], capsys, tmp_path, *needles: str) -> None:
    before = sorted(p.name for p in tmp_path.iterdir())
    status, err = _run(argv, capsys)
    assert status == 2, err
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written


@pytest.mark.parametrize("argv, needles", [
    (["train", "--n-envs", "abc"], ["--n-envs", "expected an integer"]),
    (["train", "--total-timesteps", "1e5x"], ["--total-timesteps", "invalid"]),
    (["train", "--n-envs", str(MAX_ENVS + 1)], ["--n-envs", f"1..{MAX_ENVS}"]),
    (["record", "--policy", "zero", "--seed", "-1"], ["--seed: must be an integer >= 0"]),
    (["soak", "--seed", "-3"], ["--seed", ">= 0"]),
    (["train", "--seeds", "0-999999999999"], ["--seeds", "between 1 and"]),
    (["evaluate", "--suite", "in_range", "--task-version", "3"], ["--task-version", "invalid choice"]),
])
def test_a_bad_option_is_one_line_naming_it(argv, needles, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _assert_refused(argv, capsys, tmp_path, *needles)


def test_an_output_path_that_cannot_be_written_is_refused_before_the_command_runs(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    (tmp_path / "folder.json").mkdir()
    _assert_refused(["train", "--out", "afile"], capsys, tmp_path, "--out must be a folder", "afile")
    _assert_refused(["leaderboard", "s.json", "--track", "a=b", "--out", "afile/sub"], capsys, tmp_path,
                    "under the file afile")
    _assert_refused(["headroom", "--out", "folder.json"], capsys, tmp_path, "--out must be a file", "folder.json")
    _assert_refused(["record", "--policy", "zero", "--video", "afile/v.mp4"], capsys, tmp_path, "--video")


def test_a_config_that_is_not_utf8_yaml_or_gives_a_key_twice_is_refused_naming_the_file(tmp_path):
    dup = tmp_path / "dup.yaml"
    dup.write_text("n_envs: 4\nseed: 1\nn_envs: 8\n")
    with pytest.raises(ConfigError, match="'n_envs' is given twice"):
        read_yaml(dup)
    nested = tmp_path / "nested.yaml"
    nested.write_text("env:\n  mu: 0.3\n  mu: 0.5\n")
    with pytest.raises(ConfigError, match="'mu' is given twice"):
        read_yaml(nested)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\x00\xff\xfe")
    with pytest.raises(ConfigError, match="binary.yaml is not UTF-8"):
        read_yaml(binary)
    broken = tmp_path / "broken.yaml"
    broken.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="broken.yaml is not valid YAML") as info:
        read_yaml(broken)
    assert "\n" not in str(info.value)
    same_key_in_two_mappings = tmp_path / "ok.yaml"
    same_key_in_two_mappings.write_text("a: {x: 1}\nb: {x: 2}\n")
    assert read_yaml(same_key_in_two_mappings) == {"a": {"x": 1}, "b": {"x": 2}}


def test_a_config_with_too_many_envs_is_refused_before_the_run_writes(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "big.yaml").write_text(f"n_envs: {MAX_ENVS + 1}\n")
    _assert_refused(["train", "--config", "big.yaml", "--out", "run"], capsys, tmp_path, "n_envs",
                    f"[1, {MAX_ENVS}]")


def test_a_file_that_is_not_a_mesh_is_one_line_naming_it(tmp_path, capsys):
    garbage = tmp_path / "garbage.vtu"
    garbage.write_text("not a mesh")
    with pytest.raises(MeshError, match="garbage.vtu") as info:
        load_mesh(garbage)
    assert "\n" not in str(info.value)
    assert capsys.readouterr().out == ""  # what the mesh reader printed is in the error, not on the console


def test_data_that_is_not_utf8_is_refused_naming_the_file(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "curves.csv").write_bytes(b"\x00\xff\xfe")
    _assert_refused(["calibrate", "--data", "curves.csv", "--out", "cal.yaml"], capsys, tmp_path,
                    "curves.csv: not UTF-8")


@pytest.mark.parametrize("policy, needles", [
    ("fixed:1e9", ["force_N = 1e+09 N", "max_pinch_force_N", "(0, 5] N"]),
    ("slipfeedback:max=6", ["max_force_N = 6 N", "(0, 5] N"]),
    ("slipfeedback:gain=1,gain=2", ["gain is given twice"]),
    ("slipfeedback:gain=1e300", ["gain_N_per_mm must be in [0, 100]"]),
])
def test_a_policy_spec_beyond_the_jaw_or_with_a_key_twice_is_refused(policy, needles, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _assert_refused(["evaluate", "--policy", policy, "--no-unseen", "--episodes", "1", "--mu-grid", "0.5", "--out",
                     "ev"], capsys, tmp_path, *needles)


def test_an_empty_grid_or_seeds_straddling_the_sealed_ones_are_refused(capsys, tmp_path, monkeypatch):
    from msdgrasp.agents.protocol import SEALED_SEEDS

    monkeypatch.chdir(tmp_path)
    base = ["evaluate", "--policy", "fixed:2", "--no-unseen", "--out", "ev"]
    _assert_refused([*base, "--mu-grid", ""], capsys, tmp_path, "mu grid '' is empty")
    _assert_refused([*base, "--mu-grid", "0.5", "--episodes", "2", "--seed", str(SEALED_SEEDS.start - 1)], capsys,
                    tmp_path, "straddle the sealed evaluation seeds")


def test_a_leaderboard_track_named_twice_is_refused(capsys, tmp_path, monkeypatch):
    import json

    monkeypatch.chdir(tmp_path)
    suite = {"suite": "in_range", "version": 2, "seeds": {"first": 7, "count": 1, "sealed": False}, "episodes": 1,
             "config": {}, "conditions": [{"name": "nominal"}],
             "results": [{"spec": s, "policy": s, "cells": [{"condition": "nominal", "rows": []}]}
                         for s in ("light", "heavy")]}
    (tmp_path / "s.json").write_text(json.dumps(suite))
    _assert_refused(["leaderboard", "s.json", "--track", "a=light", "--track", "a=heavy", "--out", "b"], capsys,
                    tmp_path, "--track 'a' is given twice")


def test_config_values_are_checked_when_the_config_is_read(tmp_path):
    from msdgrasp.agents.models import TrainConfig
    from msdgrasp.envs.core import POSE_LIMITS

    train = tmp_path / "t.yaml"
    train.write_text("train_randomization:\n  pose_offset_m: 5\n")
    with pytest.raises(ConfigError, match=rf"train_randomization.pose_offset_m = 5 is out of range; allowed \[0, "
                                          rf"{POSE_LIMITS['pose_offset_m']:g}\]"):
        TrainConfig.load(train)
    train.write_text("residual_scale: 5\n")  # (a field that is a number or a pair: the message names the field)
    with pytest.raises(ConfigError, match=r"t.yaml.residual_scale = 5 is out of range; allowed \(0, 2\]"):
        TrainConfig.load(train)
    train.write_text("residual_scale: [-1, 0]\n")  # (the pair's member is named, with its own range)
    with pytest.raises(ConfigError, match=r"t.yaml.residual_scale\[0\] = -1 is out of range; allowed \[0, 2\]"):
        TrainConfig.load(train)


def test_a_value_given_twice_in_a_grid_is_refused(tmp_path):
    from msdgrasp.agents.evaluation import parse_mu_grid
    from msdgrasp.agents.sweep import SweepConfig
    from msdgrasp.physics.config import from_dict

    with pytest.raises(ConfigError, match="a value is given twice"):
        parse_mu_grid("0.5,0.3,0.5")
    with pytest.raises(ConfigError, match="the value 0.0001 is given twice"):
        from_dict(SweepConfig, {"grid": {"ppo.learning_rate": [1e-4, 3e-4, 1e-4]}, "evaluation_seed": 7})


def test_experiment_frictions_and_pinches_outside_what_the_task_takes_are_refused(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _assert_refused(["experiment", "grasp", "--mu", "100", "--out", "g"], capsys, tmp_path, "--mu", "(0, 10]")
    _assert_refused(["experiment", "pinch-hold", "--pinch", "1e9"], capsys, tmp_path, "--pinch", "(0, 50]")


def test_a_data_row_with_too_many_columns_is_one_line(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "curves.csv").write_text("rate_mm_per_min,deformation_mm,force_N\n6,0.1,0.01\n6,0.2,0.02,9,9\n")
    _assert_refused(["calibrate", "--data", "curves.csv", "--out", "cal.yaml"], capsys, tmp_path,
                    "curves.csv: cannot parse numbers")


def test_a_training_teacher_that_names_nothing_or_grips_beyond_the_jaw_is_refused_when_read(capsys, tmp_path,
                                                                                           monkeypatch):
    monkeypatch.chdir(tmp_path)
    import msdgrasp
    from pathlib import Path

    scratch = f"extends: {Path(msdgrasp.__file__).parent / 'configs' / 'train' / 'ppo_scratch.yaml'}\n"
    (tmp_path / "none.yaml").write_text(f"{scratch}bc_teacher: nosuch\n")
    (tmp_path / "hard.yaml").write_text(f"{scratch}bc_teacher: 'fixed:9'\n")
    _assert_refused(["train", "--config", "none.yaml", "--out", "run"], capsys, tmp_path,
                    "bc_teacher: 'nosuch' is neither a controller spec")
    _assert_refused(["train", "--config", "hard.yaml", "--out", "run"], capsys, tmp_path, "force_N = 9 N")


def test_a_dataset_id_that_is_not_a_minari_id_is_refused_before_minari_loads(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _assert_refused(["clone", "bad id", "--out", "c"], capsys, tmp_path, "'bad id' is not a Minari id")
    _assert_refused(["clone", "a/../b-v0", "--out", "c"], capsys, tmp_path, "is not a Minari id")
