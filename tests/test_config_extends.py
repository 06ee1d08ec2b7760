"""``extends:`` in a training or tissue config: a file built on another one (physics/config.py: read_extending_yaml).

The file is its parent's mapping deep-merged with its own: nested mappings merge key by key, lists and scalars
replace, the file's own value wins; a parent may extend another; the path is relative to the file's folder. A
missing parent, a cycle, an ``extends`` that is not a path or one below the top level is one line naming the file
and the field; the merged mapping is checked as strictly as any config (an unknown key is refused wherever in the
chain it was written); a run saves the merged config, so it does not depend on the files it was built from.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from msdgrasp.agents.learners.base import read_train_yaml
from msdgrasp.agents.models import TrainConfig
from msdgrasp.agents.torch_ppo import TorchPPOConfig
from msdgrasp.envs.core import GraspLiftConfig
from msdgrasp.physics.config import (
    CONFIG_DIR, ConfigError, builtin_config, from_dict, merge_mappings, read_extending_yaml, read_yaml, to_dict,
)

EXPERIMENTS = sorted((CONFIG_DIR / "train" / "experiments").glob("*.yaml"))


def _file(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return path


def _base(folder: Path, name: str = "base.yaml") -> Path:
    """A copy of configs/train/ppo_scratch.yaml (TrainConfig's defaults spelled out) in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(builtin_config("train/ppo_scratch.yaml").read_text())
    return path


def _expected(changes: dict) -> dict:
    """The from-scratch config with ``changes`` (a nested mapping of new values) applied by hand."""
    return to_dict(from_dict(TrainConfig, merge_mappings(read_yaml(builtin_config("train/ppo_scratch.yaml")), changes)))


# =================================================================================================
# merge semantics
# =================================================================================================


def test_merge_mappings_merges_nested_mappings_and_replaces_everything_else():
    base = {"a": 1, "s": {"x": 1, "y": [1, 2], "t": {"p": 1, "q": 2}}, "l": [1, 2, 3], "m": {"k": 1}}
    over = {"a": 2, "s": {"y": [3], "t": {"q": 5}}, "l": [9], "m": None, "n": {"new": 1}}
    merged = merge_mappings(base, over)
    assert merged == {"a": 2, "s": {"x": 1, "y": [3], "t": {"p": 1, "q": 5}}, "l": [9], "m": None, "n": {"new": 1}}
    assert base == {"a": 1, "s": {"x": 1, "y": [1, 2], "t": {"p": 1, "q": 2}}, "l": [1, 2, 3], "m": {"k": 1}}
    assert merge_mappings({"m": 3}, {"m": {"k": 1}}) == {"m": {"k": 1}}  # a mapping over a scalar replaces it


def test_a_nested_key_overrides_only_itself(tmp_path):
    _base(tmp_path)
    child = _file(tmp_path / "child.yaml", """\
        extends: base.yaml
        total_timesteps: 1000
        ppo:
          gamma: 0.99
        env:
          reward:
            peak_force_mu_ref: 0.5
        """)
    config = TrainConfig.load(child)
    assert to_dict(config) == _expected({"total_timesteps": 1000, "ppo": {"gamma": 0.99},
                                         "env": {"reward": {"peak_force_mu_ref": 0.5}}})
    # the siblings of an overridden key are the parent's
    assert config.ppo["gae_lambda"] == 0.95 and config.ppo["use_sde"] is True
    assert config.env.pull_action == "forward_speed" and config.env.randomization.mu_distribution == "log_uniform"


def test_a_list_replaces_the_parents_list(tmp_path):
    _base(tmp_path)
    child = _file(tmp_path / "child.yaml", """\
        extends: base.yaml
        validation_mu: [0.3]
        policy_net: [32, 32, 32]
        env:
          randomization:
            mu_range: [0.3, 0.9]
        train_randomization: null
        """)
    config = TrainConfig.load(child)
    assert config.validation_mu == (0.3,)
    assert config.policy_net == (32, 32, 32)
    assert tuple(config.env.randomization.mu_range) == (0.3, 0.9)
    assert to_dict(config) == _expected({"validation_mu": [0.3], "policy_net": [32, 32, 32],
                                         "env": {"randomization": {"mu_range": [0.3, 0.9]}}})


def test_a_chain_of_two_each_relative_to_its_own_folder(tmp_path, monkeypatch):
    """child -> ../a/sub/parent.yaml -> ../grand.yaml, read from another working directory."""
    _base(tmp_path / "a", "grand.yaml")
    _file(tmp_path / "a" / "sub" / "parent.yaml", """\
        extends: ../grand.yaml
        total_timesteps: 2000
        n_envs: 8
        ppo: {learning_rate: 0.0005}
        """)
    child = _file(tmp_path / "b" / "child.yaml", """\
        extends: ../a/sub/parent.yaml
        n_envs: 4
        ppo: {n_epochs: 5}
        """)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert to_dict(TrainConfig.load(child)) == _expected(
        {"total_timesteps": 2000, "n_envs": 4, "ppo": {"learning_rate": 0.0005, "n_epochs": 5}})
    # every loader of a training YAML reads the chain: the record's, the command line's, the env section's
    assert read_train_yaml(child) == read_extending_yaml(child)
    assert "extends" not in read_extending_yaml(child)
    assert GraspLiftConfig.from_yaml(child) == TrainConfig.load(child).env


def test_a_torch_ppo_config_extends_too(tmp_path):
    cpu = builtin_config("train/rsl_ppo_cpu.yaml")
    child = _file(tmp_path / "rsl_child.yaml", f"extends: {cpu}\niterations: 10\n")
    assert TorchPPOConfig.load(child) == from_dict(TorchPPOConfig, {**read_yaml(cpu), "iterations": 10})


def test_scene_files_are_read_from_the_folder_of_the_file_that_names_them(tmp_path):
    """A parent's relative tissue_config is its folder's, not the child's (a config and its files move together)."""
    _file(tmp_path / "a" / "parent.yaml", "algo: ppo\nenv: {tissue_config: tissue.yaml}\n")
    child = _file(tmp_path / "b" / "child.yaml", "extends: ../a/parent.yaml\nenv: {grasper_config: grasper.yaml}\n")
    env = read_train_yaml(child)["env"]
    assert env["tissue_config"] == str((tmp_path / "a").resolve() / "tissue.yaml")
    assert env["grasper_config"] == str((tmp_path / "b").resolve() / "grasper.yaml")


# =================================================================================================
# bad input: one line naming the file and the field, never a fallback
# =================================================================================================

BAD_EXTENDS = [
    ("missing-parent", "extends: nothere.yaml\n", r"child\.yaml: extends: config file not found: .*nothere\.yaml"),
    ("a-list", "extends: [base.yaml]\n", r"child\.yaml: extends must be the path of the config file .* got \['base"),
    ("a-number", "extends: 3\n", r"child\.yaml: extends must be the path .* got 3$"),
    ("null", "extends: null\n", r"child\.yaml: extends must be the path .* got None$"),
    ("empty", "extends: ''\n", r"child\.yaml: extends must be the path .* got ''$"),
    ("nested", "extends: base.yaml\nenv:\n  extends: base.yaml\n",
     r"child\.yaml: env\.extends: 'extends' is only allowed at the top level"),
    ("nested-without-top", "ppo:\n  extends: base.yaml\n",
     r"child\.yaml: ppo\.extends: 'extends' is only allowed at the top level"),
    ("itself", "extends: child.yaml\nn_envs: 4\n", r"child\.yaml: extends: 'child\.yaml' makes a cycle"),
]


@pytest.mark.parametrize("case, text, message", BAD_EXTENDS, ids=[c[0] for c in BAD_EXTENDS])
def test_bad_extends_is_one_line_naming_the_file_and_the_field(tmp_path, case, text, message):
    _base(tmp_path)
    child = _file(tmp_path / "child.yaml", text)
    for load in (TrainConfig.load, TorchPPOConfig.load, GraspLiftConfig.from_yaml, read_train_yaml):
        with pytest.raises(ConfigError, match=message) as exc:
            load(child)
        assert "\n" not in str(exc.value)


def test_a_cycle_through_two_files_names_the_chain(tmp_path):
    a = _file(tmp_path / "a.yaml", "extends: sub/b.yaml\nn_envs: 4\n")
    _file(tmp_path / "sub" / "b.yaml", "extends: ../a.yaml\nn_envs: 8\n")
    with pytest.raises(ConfigError, match=r"b\.yaml: extends: '\.\./a\.yaml' makes a cycle: .*a\.yaml -> .*b\.yaml "
                                          r"-> .*a\.yaml$"):
        TrainConfig.load(a)


def test_a_parent_that_is_not_a_config_is_an_error_naming_it(tmp_path):
    _file(tmp_path / "broken.yaml", "algo: [ppo\n")
    _file(tmp_path / "empty.yaml", "# nothing\n")
    for parent, message in (("broken.yaml", r"broken\.yaml is not valid YAML"),
                            ("empty.yaml", r"empty\.yaml is empty")):
        child = _file(tmp_path / "child.yaml", f"extends: {parent}\nn_envs: 4\n")
        with pytest.raises(ConfigError, match=message):
            TrainConfig.load(child)


@pytest.mark.parametrize("where, text, message", [
    ("child", "extends: base.yaml\ntotal_timestep: 1000\n", r"child\.yaml: unknown key 'total_timestep'"),
    ("child", "extends: base.yaml\nppo: {learning_rat: 0.1}\n", r"ppo: unknown key 'learning_rat'"),
    ("child", "extends: base.yaml\nenv: {reward: {peak_force_mu: 0.4}}\n", r"unknown key 'peak_force_mu'"),
    ("parent", "extends: base.yaml\nn_envs: 4\n", r"child\.yaml: unknown key 'bogus'"),
])
def test_unknown_keys_are_refused_after_merging(tmp_path, where, text, message):
    base = _base(tmp_path)
    if where == "parent":
        base.write_text(base.read_text() + "bogus: 1\n")
    child = _file(tmp_path / "child.yaml", text)
    with pytest.raises(ConfigError, match=message):
        TrainConfig.load(child)


def test_the_cli_refuses_a_bad_chain_in_one_line_before_any_output(tmp_path, capsys):
    from msdgrasp.cli.main import main

    _base(tmp_path)
    out = tmp_path / "run"
    for text, needle in (("extends: base.yaml\nppo: {n_step: 64}\n", "n_step"),
                         ("extends: nothere.yaml\n", "nothere.yaml")):
        child = _file(tmp_path / "child.yaml", text)
        assert main(["train", "--config", str(child), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "child.yaml" in err[0] and needle in err[0], err
        assert not out.exists()


def test_a_run_saves_the_merged_config(tmp_path, monkeypatch):
    """The run's config.yaml is the whole config: it loads the same with the files it was built from gone."""
    pytest.importorskip("stable_baselines3")
    import msdgrasp.envs.sb3
    from msdgrasp.agents.training import train

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop  # (the config is written before the training envs are built; nothing else is needed here)

    _base(tmp_path / "cfg")
    child = _file(tmp_path / "cfg" / "child.yaml", "extends: base.yaml\nn_envs: 2\nppo: {gamma: 0.99}\n")
    config = TrainConfig.load(child)
    monkeypatch.setattr(msdgrasp.envs.sb3, "GraspLiftSB3VecEnv", stop)
    with pytest.raises(Stop):
        train(config, tmp_path / "run", progress=False)
    for path in (tmp_path / "cfg").iterdir():
        path.unlink()
    saved = tmp_path / "run" / "config.yaml"
    assert "extends" not in read_yaml(saved)
    assert TrainConfig.load(saved) == config


# =================================================================================================
# the shipped experiment configs
# =================================================================================================


def _changed_keys(child: dict, parent: dict, where: str = "") -> tuple[list[str], list[str]]:
    """(the dotted keys ``child`` sets, those among them whose value is ``parent``'s already)."""
    keys, same = [], []
    for key, value in child.items():
        dotted = f"{where}{key}"
        if isinstance(value, dict) and isinstance(parent.get(key), dict):
            k, s = _changed_keys(value, parent[key], f"{dotted}.")
            keys += k
            same += s
        else:
            keys.append(dotted)
            if key in parent and parent[key] == value:
                same.append(dotted)
    return keys, same


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[p.name for p in EXPERIMENTS])
def test_an_experiment_config_states_only_what_it_changes(path):
    """An experiment that extends another config sets at least one key, each to a value its parent does not
    already give (a repeated value would hide what the experiment is about), and builds only on shipped configs."""
    own = read_yaml(path)
    if "extends" not in own:
        return
    parent = (path.parent / own.pop("extends")).resolve()
    assert parent.is_relative_to(CONFIG_DIR / "train"), f"{path.name} extends {parent}, outside configs/train"
    keys, same = _changed_keys(own, read_extending_yaml(parent))
    assert keys, f"{path.name} sets no key of its own: it is {parent.name}"
    assert not same, f"{path.name} repeats its parent's values of {same}"
    if path.name.startswith("recurrent"):  # (the recurrent learner's: the default training's task, no env of its own)
        from msdgrasp.agents.recurrent_training import RecurrentConfig

        RecurrentConfig.load(path)
        return
    cls = TorchPPOConfig if path.name.startswith("rsl") else TrainConfig
    assert GraspLiftConfig.from_yaml(path) == cls.load(path).env


def _extends_depth(path: Path) -> int:
    """How many files deep ``path``'s ``extends:`` chain goes (0: the file extends nothing)."""
    depth, seen = 0, {path.resolve()}
    data = read_yaml(path)
    while "extends" in data:
        path = (path.parent / data["extends"]).resolve()
        assert path not in seen, f"an extends cycle through {path}"
        seen.add(path)
        depth += 1
        data = read_yaml(path)
    return depth


def test_the_extends_depth_counts_every_file_of_a_chain(tmp_path):
    _base(tmp_path)
    middle = _file(tmp_path / "middle.yaml", "extends: base.yaml\nn_envs: 4\n")
    top = _file(tmp_path / "sub" / "top.yaml", "extends: ../middle.yaml\nn_envs: 8\n")
    assert [_extends_depth(p) for p in (tmp_path / "base.yaml", middle, top)] == [0, 1, 2]


def test_every_shipped_config_extends_at_most_one_shipped_default():
    """No chains: a shipped config is whole or extends one whole config that is not an experiment (a default such as
    configs/train/ppo_scratch.yaml), so the file itself states every field its run changes from that default."""
    shipped = sorted(CONFIG_DIR.rglob("*.yaml"))
    deep = [f"{p.relative_to(CONFIG_DIR)}: {_extends_depth(p)}" for p in shipped if _extends_depth(p) > 1]
    assert not deep, f"configs whose extends chain is deeper than one file: {deep}"
    on_experiments = []
    for path in shipped:
        data = read_yaml(path)
        if "extends" in data:
            parent = (path.parent / data["extends"]).resolve()
            if "experiments" in parent.relative_to(CONFIG_DIR).parts:
                on_experiments.append(f"{path.relative_to(CONFIG_DIR)} -> {parent.relative_to(CONFIG_DIR)}")
    assert not on_experiments, f"configs that extend an experiment instead of a default: {on_experiments}"


# =================================================================================================
# tissue configs extend too
# =================================================================================================

def test_a_tissue_config_builds_on_another_and_its_mesh_file_stays_beside_the_parent(tmp_path):
    from msdgrasp.experiments.compression import load_tissue_params
    from msdgrasp.physics.mesh_gen import sphere_mesh
    from msdgrasp.physics.mesh_io import mesh_spec, save_mesh

    import yaml

    (tmp_path / "a").mkdir()
    save_mesh(sphere_mesh(resolution="coarse"), tmp_path / "a" / "ball.vtu")
    parent = read_yaml(builtin_config("tissue/sphere.yaml"))
    parent["mesh"] = {"shape": "ball.vtu"}
    (tmp_path / "a" / "parent.yaml").write_text(yaml.safe_dump(parent))
    child = _file(tmp_path / "b" / "child.yaml", "extends: ../a/parent.yaml\ntissue: {youngs_modulus_pa: 9000.0}\n")
    assert mesh_spec(child).shape == str((tmp_path / "a" / "ball.vtu").resolve())
    mine, theirs = load_tissue_params(child), load_tissue_params(tmp_path / "a" / "parent.yaml")
    assert mine.youngs_modulus_pa == 9000.0 != theirs.youngs_modulus_pa
    assert mine.mass_kg == theirs.mass_kg and mine.stiffening == theirs.stiffening


def test_the_shipped_j1_spleen_is_the_spleen_s_material_and_nodes_on_other_tets():
    from msdgrasp.experiments.compression import load_tissue_params
    from msdgrasp.physics.mesh_io import mesh_from_config

    assert load_tissue_params(builtin_config("tissue/spleen-j1.yaml")) == load_tissue_params(
        builtin_config("tissue/spleen.yaml"))
    j1, octant = (mesh_from_config(builtin_config(f"tissue/{n}.yaml")) for n in ("spleen-j1", "spleen"))
    assert (j1.nodes == octant.nodes).all() and len(j1.tets) == len(octant.tets)
    assert not (j1.tets == octant.tets).all()


def test_a_parent_s_missing_mesh_file_is_named_beside_the_parent_not_found_beside_the_child(tmp_path):
    import yaml

    from msdgrasp.physics.mesh_io import mesh_spec

    parent = read_yaml(builtin_config("tissue/sphere.yaml"))
    parent["mesh"] = {"shape": "ball.vtu"}
    _file(tmp_path / "a" / "parent.yaml", yaml.safe_dump(parent))
    child = _file(tmp_path / "b" / "child.yaml", "extends: ../a/parent.yaml\n")
    (tmp_path / "b" / "ball.vtu").write_text("not the parent's mesh")  # (a file of that name beside the child)
    with pytest.raises(ConfigError, match=r"mesh file not found: .*/a/ball\.vtu"):
        mesh_spec(child)


def test_the_j1_spleen_takes_no_generator_option_and_a_grasper_config_extends_too(tmp_path):
    from msdgrasp.physics.config import GRASPER_FILE, read_config_file
    from msdgrasp.physics.mesh_io import mesh_spec

    parent = builtin_config("tissue/spleen-j1.yaml")
    child = _file(tmp_path / "t.yaml", f"extends: {parent}\nmesh: {{pattern: octant}}\n")
    with pytest.raises(ConfigError, match=r"unknown key 'pattern' for shape 'spleen-j1'; allowed keys: resolution, "):
        mesh_spec(child)
    grasper = _file(tmp_path / "g.yaml", f"extends: {builtin_config('grasper/default.yaml')}\ngrasper: {{mu: 0.45}}\n")
    merged, base = read_config_file(grasper, GRASPER_FILE), read_yaml(builtin_config("grasper/default.yaml"))
    assert merged["grasper"] == {**base["grasper"], "mu": 0.45}


def test_a_tissue_config_that_names_another_mesh_shape_inherits_none_of_the_parent_s_mesh_options(tmp_path):
    from msdgrasp.physics.mesh_gen import sphere_mesh
    from msdgrasp.physics.mesh_io import mesh_spec, save_mesh

    spleen = builtin_config("tissue/spleen.yaml")  # (its mesh: shape spleen, resolution coarse)
    save_mesh(sphere_mesh(resolution="coarse"), tmp_path / "ball.vtu")
    to_file = _file(tmp_path / "file.yaml", f"extends: {spleen}\nmesh: {{shape: ball.vtu}}\n")
    assert mesh_spec(to_file).shape == str((tmp_path / "ball.vtu").resolve())  # (a file takes no resolution)
    # the same shape merges key by key: the child's resolution, the parent's shape
    finer = _file(tmp_path / "fine.yaml", f"extends: {spleen}\nmesh: {{resolution: fine}}\n")
    assert mesh_spec(finer)[:2] == ("spleen", "fine")
