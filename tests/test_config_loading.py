"""Strict loading of every YAML the project reads: tissue, grasper, training (and its env block), sweep.

A misspelt or missing section, an unknown key or a missing mesh file is one line on stderr naming the file and
the key, exit status 2, and nothing written; mesh paths are read from the folder of the YAML that names them; every
shipped config loads with the strict loaders.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from msdgrasp.physics.config import CONFIG_DIR, ConfigError, builtin_config, read_yaml
from msdgrasp.physics.grasper import GrasperParams
from msdgrasp.physics.mesh_io import build_mesh, mesh_from_config, mesh_spec, save_mesh
from msdgrasp.physics.scenario import check_scene_files, load_params, resolve_scene_paths
from msdgrasp.physics.tissue import TissueParams


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "msdgrasp.cli.main", *args], capture_output=True, text=True,
                          cwd=cwd, env=os.environ.copy(), timeout=300)


def _write(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _spleen() -> dict:
    return read_yaml(builtin_config("tissue/spleen.yaml"))


def _grasper() -> dict:
    return read_yaml(builtin_config("grasper/default.yaml"))


def _train() -> dict:
    return read_yaml(builtin_config("train/ppo_scratch.yaml"))


def _renamed(data: dict, old: str, new: str) -> dict:
    return {(new if k == old else k): v for k, v in data.items()}


def _without(data: dict, key: str) -> dict:
    return {k: v for k, v in data.items() if k != key}


def _with_key(data: dict, section: str | None, key: str, value) -> dict:
    if section is None:
        return {**data, key: value}
    return {**data, section: {**data[section], key: value}}


# (case id, which flag takes the file, the file's content, the key the message must name)
TISSUE_CASES = [
    ("tissue-misspelt-section", _renamed(_spleen(), "tissue", "tisue"), "tisue"),
    ("tissue-no-mesh-section", _without(_spleen(), "mesh"), "mesh"),
    ("tissue-no-tissue-section", _without(_spleen(), "tissue"), "tissue"),
    ("tissue-unknown-key", _with_key(_spleen(), "tissue", "youngs_modulus_kpa", 12.0), "youngs_modulus_kpa"),
    ("tissue-unknown-mesh-key", _with_key(_spleen(), "mesh", "lenght_m", 0.1), "lenght_m"),
    ("tissue-no-mesh-shape", {**_spleen(), "mesh": {"resolution": "coarse"}}, "shape"),
]
GRASPER_CASES = [
    ("grasper-misspelt-section", _renamed(_grasper(), "grasper", "grapser"), "grapser"),
    ("grasper-unknown-key", _with_key(_grasper(), "grasper", "jaw_widht_m", 0.014), "jaw_widht_m"),
]
TRAIN_CASES = [
    ("train-misspelt-section", _renamed(_train(), "env", "evn"), "evn"),
    ("train-unknown-key", _with_key(_train(), None, "total_timestep", 1000), "total_timestep"),
    ("train-unknown-env-key", _with_key(_train(), "env", "privileged_ob", True), "privileged_ob"),
    ("train-unknown-reward-key", {**_train(), "env": {**_train()["env"], "reward": {"peak_force_mu": 0.4}}},
     "peak_force_mu"),
]


def _assert_one_line_error(r: subprocess.CompletedProcess, file: Path, key: str, out: Path) -> None:
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert file.name in lines[0] and key in lines[0], lines[0]
    assert not out.exists() or not any(out.iterdir()), f"{out} was written: {list(out.iterdir())}"


#: (the command that loads the file, the flag that names it) x the bad files of each kind
BAD_FILES = ([(("experiment", "grasp", "--config"), *c) for c in TISSUE_CASES]
             + [(("experiment", "grasp", "--grasper"), *c) for c in GRASPER_CASES]
             + [(("train", "--config"), *c) for c in TRAIN_CASES])


@pytest.mark.parametrize("command, case, data, key", BAD_FILES, ids=[f"{c[0][-1]}-{c[1]}" for c in BAD_FILES])
def test_a_bad_tissue_grasper_or_training_config_is_one_line_exit_2_and_nothing_written(tmp_path, command, case,
                                                                                        data, key):
    cfg = _write(tmp_path / f"{case}.yaml", data)
    out = tmp_path / "out"
    r = _cli(*command, str(cfg), "--out", str(out), "--quiet")
    _assert_one_line_error(r, cfg, key, out)


def test_a_training_config_is_checked_before_the_learner_libraries_are_imported(tmp_path):
    """A typo in a training config is reported before torch and the learners' libraries load (seconds of imports):
    `msdgrasp train` checks the config first, the libraries after."""
    cfg = _write(tmp_path / "typo.yaml", _with_key(_train(), "ppo", "learning_rat", 1e-3))
    code = ("import sys\nfrom msdgrasp.cli.main import main\n"
            f"rc = main(['train', '--config', {str(cfg)!r}, '--out', {str(tmp_path / 'out')!r}, '--quiet'])\n"
            "print(rc, sorted(m for m in ('torch', 'stable_baselines3', 'rsl_rl') if m in sys.modules))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=os.environ.copy(), timeout=300)
    assert r.stdout.split("\n")[-2] == "2 []", (r.stdout, r.stderr)
    assert "unknown key 'learning_rat'" in r.stderr and not (tmp_path / "out").exists()


def test_errors_list_what_is_allowed(tmp_path):
    """The message says what to write instead: the allowed sections, the allowed keys, what a missing section holds."""
    with pytest.raises(ConfigError, match=r"unknown section 'tisue'.*allowed sections: mesh, tissue, calibration"):
        load_params(_write(tmp_path / "a.yaml", _renamed(_spleen(), "tissue", "tisue")), "tissue", TissueParams)
    with pytest.raises(ConfigError, match=r"no 'mesh:' section.*add e\.g\. mesh: \{shape:"):
        mesh_spec(_write(tmp_path / "b.yaml", _without(_spleen(), "mesh")))
    with pytest.raises(ConfigError, match=r"unknown key 'jaw_widht_m'; allowed keys: .*jaw_width_m"):
        load_params(_write(tmp_path / "c.yaml", _with_key(_grasper(), "grasper", "jaw_widht_m", 0.01)), "grasper",
                    GrasperParams)
    with pytest.raises(ConfigError, match=r"unknown key 'lenght_m' for shape 'spleen'; allowed keys: .*length_m"):
        mesh_spec(_write(tmp_path / "d.yaml", _with_key(_spleen(), "mesh", "lenght_m", 0.1)))
    with pytest.raises(ConfigError, match=r"e\.yaml:tissue must be a mapping"):
        load_params(_write(tmp_path / "e.yaml", {**_spleen(), "tissue": None}), "tissue", TissueParams)


def test_an_empty_config_file_is_an_error_not_the_defaults(tmp_path):
    empty = tmp_path / "empty.yaml"
    empty.write_text("# only a comment\n")
    for load in (lambda: load_params(empty, "grasper", GrasperParams), lambda: read_yaml(empty)):
        with pytest.raises(ConfigError, match=r"empty\.yaml is empty"):
            load()


@pytest.fixture()
def moved_config(tmp_path) -> Path:
    """A copy of the sphere config in tmp_path/cfg/ whose mesh is the file meshes/sphere.vtu beside it."""
    folder = tmp_path / "cfg"
    (folder / "meshes").mkdir(parents=True)
    save_mesh(build_mesh("sphere", "coarse"), folder / "meshes" / "sphere.vtu")
    data = read_yaml(builtin_config("tissue/sphere.yaml"))
    data["mesh"] = {"shape": "meshes/sphere.vtu"}
    return _write(folder / "sphere.yaml", data)


def test_a_relative_mesh_path_is_read_from_the_yaml_folder(moved_config, tmp_path, monkeypatch):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # no meshes/ here: the path must resolve against the YAML's folder
    spec = mesh_spec(os.path.relpath(moved_config, elsewhere))
    assert Path(spec.shape) == moved_config.parent / "meshes" / "sphere.vtu"
    mesh = mesh_from_config(moved_config)
    assert mesh.n_nodes == build_mesh("sphere", "coarse").n_nodes


def test_a_missing_mesh_file_is_one_line_exit_2_naming_yaml_and_path(moved_config, tmp_path):
    (moved_config.parent / "meshes" / "sphere.vtu").unlink()
    out = tmp_path / "out"
    r = _cli("experiment", "grasp-sphere", "--config", str(moved_config), "--out", str(out), "--quiet",
             cwd=tmp_path)
    _assert_one_line_error(r, moved_config, str(moved_config.parent / "meshes" / "sphere.vtu"), out)
    assert "mesh file not found" in r.stderr


def test_a_mesh_file_takes_no_generator_options(moved_config):
    data = read_yaml(moved_config)
    data["mesh"]["resolution"] = "fine"
    with pytest.raises(ConfigError, match=r"sphere\.yaml:mesh: unknown key 'resolution' for a mesh file"):
        mesh_spec(_write(moved_config, data))


def test_the_env_tissue_config_of_a_training_yaml_is_relative_to_it_and_checked_before_any_write(tmp_path):
    """A training YAML's env.tissue_config is read from the YAML's folder; a bad one fails before the run folder
    is made (the scene is built after the run's config.yaml is written)."""
    folder = tmp_path / "cfg"
    folder.mkdir()
    env = resolve_scene_paths({"tissue_config": "tissue.yaml", "grasper_config": None}, folder / "train.yaml")
    assert env == {"tissue_config": str(folder.resolve() / "tissue.yaml"), "grasper_config": None}
    with pytest.raises(ConfigError, match=r"env\.tissue_config: config file not found"):
        check_scene_files(env["tissue_config"], None)
    _write(folder / "tissue.yaml", _renamed(_spleen(), "tissue", "tisue"))
    cfg = _write(folder / "train.yaml", {**_train(), "env": {**_train()["env"], "tissue_config": "tissue.yaml"}})
    out = tmp_path / "out"
    r = _cli("train", "--config", str(cfg), "--out", str(out), "--quiet", cwd=tmp_path)
    _assert_one_line_error(r, folder / "tissue.yaml", "tisue", out)


# every shipped YAML, by the loader of its folder
SHIPPED = sorted(CONFIG_DIR.rglob("*.yaml"))


def _load_shipped(path: Path) -> None:
    kind = path.relative_to(CONFIG_DIR).parts[0]
    if kind == "tissue":
        load_params(path, "tissue", TissueParams)
        mesh_spec(path)
        check_scene_files(path, None)
    elif kind == "grasper":
        load_params(path, "grasper", GrasperParams)
    elif kind == "train":
        from msdgrasp.agents.models import TrainConfig
        from msdgrasp.agents.torch_ppo import TorchPPOConfig
        from msdgrasp.envs.core import GraspLiftConfig

        from msdgrasp.agents.models import default_training
        from msdgrasp.agents.recurrent_training import RecurrentConfig

        # the torch PPO's configs are the rsl_* ones (msdgrasp train --learner rsl), the recurrent learner's the
        # recurrent* ones, which take the default training's task (they state no env); every other is SB3's
        if path.name.startswith("recurrent"):
            assert RecurrentConfig.load(path).env == default_training().env
            return
        cls = TorchPPOConfig if path.name.startswith("rsl") else TrainConfig
        config = cls.load(path)
        assert GraspLiftConfig.from_yaml(path) == config.env
    elif kind == "sweep":
        from msdgrasp.agents.sweep import SweepConfig, sweep_points

        assert sweep_points(SweepConfig.load(path), path.name)
    else:
        raise AssertionError(f"{path}: a config folder this test does not know; add its loader here")


def test_shipped_configs_are_found():
    kinds = {p.relative_to(CONFIG_DIR).parts[0] for p in SHIPPED}
    assert {"tissue", "grasper", "train", "sweep"} <= kinds, kinds


@pytest.mark.parametrize("path", SHIPPED, ids=[str(p.relative_to(CONFIG_DIR)) for p in SHIPPED])
def test_every_shipped_config_loads_strictly(path):
    _load_shipped(path)


def test_the_env_grasper_is_the_experiments_grasper():
    """configs/grasper/env.yaml says its values are default.yaml's (the task's grasper must not drift silently)."""
    assert (load_params(builtin_config("grasper/env.yaml"), "grasper", GrasperParams)
            == load_params(builtin_config("grasper/default.yaml"), "grasper", GrasperParams))


def test_a_sweep_reads_its_base_config_beside_it_not_through_the_working_directory(tmp_path, monkeypatch):
    """A sweep and its base training config move together; a relative base is never looked up in the cwd."""
    from msdgrasp.agents.sweep import SweepConfig, sweep_points

    folder = tmp_path / "study"
    folder.mkdir()
    base = read_yaml(builtin_config("train/ppo_scratch.yaml"))
    (folder / "base.yaml").write_text(yaml.safe_dump({**base, "total_timesteps": 4096}))
    (folder / "sweep.yaml").write_text("base: base.yaml\ngrid: {ppo.learning_rate: [0.001]}\nseeds: '0'\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    ((_, config),) = sweep_points(SweepConfig.load(folder / "sweep.yaml"))
    assert config.total_timesteps == 4096
    (elsewhere / "base.yaml").write_text((folder / "base.yaml").read_text())  # found only through the cwd: refused
    (tmp_path / "other.yaml").write_text("base: base.yaml\ngrid: {ppo.learning_rate: [0.001]}\nseeds: '0'\n")
    with pytest.raises(ConfigError, match="base.yaml"):
        sweep_points(SweepConfig.load(tmp_path / "other.yaml"))
