"""Behaviour cloning from a demonstration dataset (``msdgrasp clone``): the offline baseline of the leaderboard.

A Minari dataset made by ``msdgrasp collect`` (its ``card.json`` names the task the episodes were collected on) is
cloned into the default training's policy network: the PPO actor's mean action is fitted to the dataset's actions by
MSE (:func:`.training.fit_policy`, the step behaviour-cloning warm starts use), the actor seeing what a deployed policy
sees (the privileged entries are masked as in training). The result is saved in the SB3 layout (``best_model.zip``
and ``best_model.yaml`` beside it), so ``msdgrasp evaluate --policy DIR/best_model.zip`` and the robustness suite run
it on the benchmark task like any trained model. Needs the ``train`` and ``collect`` extras.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.core import GraspLiftConfig
from ..physics.config import ConfigError, atomic_write, atomic_write_text, from_dict, needs_extra, replace, to_dict
from ..physics.config import write_yaml
from .learners.sb3_layout import LAYOUT
from .models import TrainConfig
from .protocol import check_not_sealed

#: cloning passes over the dataset (the warm start's default)
CLONE_EPOCHS = 40


def _load(dataset_id: str, datasets_path_: Path):
    from .demonstrations import check_dataset_id, datasets_path, import_minari

    check_dataset_id(dataset_id)
    minari = import_minari()
    folder = datasets_path_ / dataset_id
    if not (folder / "card.json").is_file():
        raise ConfigError(f"dataset {dataset_id!r}: no {folder / 'card.json'} (datasets made by msdgrasp collect carry "
                          "one; give the folder they were written to with --datasets)")
    card = json.loads((folder / "card.json").read_text())
    with datasets_path(datasets_path_):
        dataset = minari.load_dataset(dataset_id)
        obs, actions = [], []
        for episode in dataset.iterate_episodes():
            obs.append(np.asarray(episode.observations[:-1], dtype=np.float32))  # (the last one has no action)
            actions.append(np.asarray(episode.actions, dtype=np.float32))
    return card, np.concatenate(obs), np.concatenate(actions)


def check_clone_seed(seed: int) -> None:
    """ConfigError where a clone's ``seed`` would draw sealed evaluation seeds (:mod:`.protocol`): its envs and
    validation episodes, the seeds a training with that seed draws."""
    for first, count, via in TrainConfig().seed_sets():  # (seed 0's: each shifts by the seed)
        check_not_sealed(seed + first, count, "seed", value=seed, via=via)


def clone_config(env: GraspLiftConfig, drawn: GraspLiftConfig, seed: int = 0) -> TrainConfig:
    """The training config a clone is saved with: the default training's, its task ``env`` (the one the teacher acts
    on, which evaluations run the clone on) and its training randomisation the one the episodes were drawn from
    (``drawn``'s; none where it is env's own); the asymmetric critic where the task has privileged entries."""
    if replace(drawn, randomization=env.randomization) != env:
        raise ConfigError("the dataset's card is inconsistent: its episodes were drawn from another task than its "
                          "'env' with another randomisation")
    rnd = None if drawn.randomization == env.randomization else drawn.randomization
    return replace(TrainConfig(seed=seed), env=env, train_randomization=rnd, randomization_ramp=None,
                   asymmetric_critic=env.privileged_obs)


def clone(dataset_id: str, out_dir: str | Path, datasets_path: str | Path = Path("logs") / "datasets",
          epochs: int = CLONE_EPOCHS, seed: int = 0) -> dict[str, Any]:
    """Clone the dataset ``dataset_id`` (under ``datasets_path``) into ``out_dir``; returns the summary it writes
    (``clone_summary.json``)."""
    with needs_extra("train", "behaviour cloning"):
        import torch

    from ..envs.sb3 import GraspLiftSB3VecEnv
    from .training import Demonstrations, fit_policy, new_model

    if isinstance(epochs, bool) or not isinstance(epochs, (int, np.integer)) or epochs < 1:
        raise ConfigError(f"epochs must be an integer >= 1, got {epochs!r}")
    check_clone_seed(seed)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder")
    card, obs, actions = _load(dataset_id, Path(datasets_path))
    if "env" not in card:
        raise ConfigError(f"dataset {dataset_id!r}: its card names no 'env' (the task its policy acts on); collect it "
                          "again with this version of msdgrasp collect")
    where = f"{dataset_id}/card.json"
    env = from_dict(GraspLiftConfig, card["env"], where=f"{where}:env")
    drawn = from_dict(GraspLiftConfig, card["config"], where=f"{where}:config")
    config = replace(clone_config(env, drawn, seed), bc_dataset=dataset_id, bc_epochs=int(epochs))
    torch.manual_seed(seed)
    venv = GraspLiftSB3VecEnv(config.n_envs, config.training_task(), seed=seed)
    if obs.shape[1] != venv.core.obs_dim:
        raise ConfigError(f"dataset {dataset_id!r}: observations of {obs.shape[1]} entries, its task's have "
                          f"{venv.core.obs_dim}")
    model = new_model(config, venv)
    demos = Demonstrations(obs, actions, np.full(len(obs), np.nan))
    fit = fit_policy(model.policy, demos, int(epochs), config.bc_log_std, seed=seed)
    venv.close()
    write_yaml(out / LAYOUT.config, to_dict(config))
    best = atomic_write(out / LAYOUT.model, lambda p: model.save(p))
    write_yaml(best.with_suffix(".yaml"), to_dict(config))
    summary = {"dataset_id": dataset_id, "teacher": card.get("policy"),
               "teacher_success_rate": card.get("success_rate"), "episodes": card.get("episodes"),
               "epochs": int(epochs), **fit, "model": str(best)}
    atomic_write_text(out / "clone_summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
