"""Demonstrations as Minari datasets (``msdgrasp collect``): a policy's episodes on the randomised task (the task its
training drew its episodes from; for a controller the benchmark task, or a training config's), written by
Minari itself (``minari.create_dataset_from_buffers`` with the registered env), so ``minari.load_dataset`` reads them
back and ``dataset.recover_environment()`` rebuilds the task they were collected on. The episodes are gathered into
Minari's ``EpisodeBuffer`` here rather than by its ``DataCollector`` wrapper, which needs JAX (``minari[create]``,
several hundred MB) to append steps; the dataset on disk is the same Minari format.

A dataset is written under ``out/<dataset id>/`` (Minari's layout; load it with ``MINARI_DATASETS_PATH=out``),
beside it ``card.md`` and ``card.json``: env id and version, the task config, the policy, the episodes, their seeds
(episode i is reset with ``seed + i``) and outcomes. It is made in a temporary folder and moved into place whole,
so an interrupted run leaves no partial dataset. Needs ``pip install 'msdgrasp[collect]'`` (Minari with Arrow).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import sys
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ..physics.config import ConfigError, atomic_write_text, to_dict
from .evaluation import build_policy, check_policy_spec, trained_task_of
from .protocol import check_not_sealed

#: the env the datasets are collected on (its version is part of every dataset's card)
ENV_ID = "msdgrasp/GraspLift-v0"
_ID = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*-v\d+$")


def import_minari() -> ModuleType:
    """The ``minari`` module; ConfigError naming the extra to install where it is missing."""
    try:
        import minari
    except ImportError as exc:
        raise ConfigError("msdgrasp collect needs Minari: pip install 'msdgrasp[collect]'") from exc
    return minari


def _version() -> str:
    from importlib.metadata import version

    return version("msdgrasp")


@contextlib.contextmanager
def datasets_path(folder: Path) -> Iterator[None]:
    """Minari's datasets folder (``MINARI_DATASETS_PATH``) set to ``folder`` inside the block, made absolute (Minari
    joins a relative one onto paths it has already joined it to), and restored after."""
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(folder).resolve())
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


def check_dataset_id(dataset_id: str) -> None:
    """ConfigError unless ``dataset_id`` is a Minari id, (namespace/)name-v<version> of letters, digits, '_', '.' and
    '-' (no path of its own: a dataset lives under the datasets folder)."""
    if not _ID.match(dataset_id) or ".." in dataset_id.split("/"):
        raise ConfigError(f"dataset id {dataset_id!r} is not a Minari id: (namespace/)name-v<version>, "
                          "letters, digits, '_', '.', '-'")


def default_dataset_id(policy_name: str) -> str:
    """``msdgrasp/grasplift/<policy>-v0``, the policy's name made safe for a Minari id."""
    slug = re.sub(r"[^A-Za-z0-9]+", "-", policy_name).strip("-").lower() or "policy"
    return f"msdgrasp/grasplift/{slug}-v0"


def collect(policy: str, episodes: int, out_dir: str | Path, dataset_id: str | None = None, seed: int = 0,
            progress: bool = True, train_config: str | Path | None = None) -> dict[str, Any]:
    """Record ``episodes`` episodes of ``policy`` (a spec as ``msdgrasp evaluate`` takes) into a Minari dataset
    under ``out_dir``; returns the card. The episodes are drawn from the task the policy's training drew from; for a
    controller, that of the training config file ``train_config`` (default: the benchmark task, ``TrainConfig().env``,
    with its own randomisation). Everything is
    checked before an episode runs."""
    minari = import_minari()
    import gymnasium as gym

    from ..envs.registration import register_envs

    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    # (a dataset is for training: never the sealed evaluation episodes)
    check_not_sealed(seed, int(episodes), "seed", via=f"episodes: seed + i, i < {int(episodes)}")
    check_policy_spec(policy)
    task, trained_on = trained_task_of([policy])
    if trained_on is None:  # a controller: the given training's task, or the benchmark task's own randomisation
        from .models import TrainConfig

        training = TrainConfig() if train_config is None else TrainConfig.load(train_config)
        task, config = training.env, training.training_task()
        task_from = f"{train_config}'s randomised task" if train_config is not None else "the benchmark task"
    elif train_config is not None:
        raise ConfigError(f"policy {policy!r} is a saved model: its episodes are drawn from its own training's task; "
                          "drop --config")
    else:
        from .learners.base import learner_of_model

        config, task_from = learner_of_model(Path(policy)).model_training_task(Path(policy)), trained_on
    # (the policy acts on its task; the episodes are drawn from its training's randomisation of it)
    pol = build_policy(policy, task)
    name = str(getattr(pol, "name", policy))
    dataset_id = dataset_id or default_dataset_id(name)
    check_dataset_id(dataset_id)
    out_dir = Path(out_dir)
    final = out_dir / dataset_id
    if final.exists():
        raise ConfigError(f"{final} exists: remove it or give another --dataset-id")
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output folder {out_dir} exists and is not a folder")
    register_envs()
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".collect-", dir=out_dir))
    try:
        with datasets_path(tmp):  # (Minari reads it when it creates the dataset)
            env = gym.make(ENV_ID, config=to_dict(config))
            buffers, outcomes = [], []
            for i in range(episodes):
                obs, info = env.reset(seed=int(seed) + i)
                pol.reset([info])
                observations, actions, rewards, terminations, truncations = [obs], [], [], [], []
                done = False
                while not done:
                    action = np.asarray(pol.act(obs[None]), dtype=np.float32).reshape(2)
                    obs, reward, terminated, truncated, info = env.step(action)
                    for seq, value in ((observations, obs), (actions, action), (rewards, float(reward)),
                                       (terminations, bool(terminated)), (truncations, bool(truncated))):
                        seq.append(value)
                    done = terminated or truncated
                buffers.append(minari.data_collector.EpisodeBuffer(
                    id=i, seed=int(seed) + i, observations=observations, actions=actions, rewards=rewards,
                    terminations=terminations, truncations=truncations, infos={}))
                outcomes.append({"seed": int(seed) + i, "mu": float(info["mu"]), "success": bool(info["is_success"]),
                                 "steps": len(actions), "peak_pinch_N": float(info["peak_pinch_N"]),
                                 "return": float(np.sum(rewards))})
                if progress:
                    print(f"  {name}: episode {i + 1}/{episodes} mu={outcomes[-1]['mu']:.3f} "
                          f"success={outcomes[-1]['success']}", file=sys.stderr)
            card = {
                "dataset_id": dataset_id, "env_id": ENV_ID, "env_version": int(ENV_ID.rsplit("-v", 1)[1]),
                "policy": name, "policy_spec": policy, "task_from": task_from, "env": to_dict(task),
                "episodes": int(episodes), "seeds": [o["seed"] for o in outcomes],
                "success_rate": float(np.mean([o["success"] for o in outcomes])),
                "steps": int(sum(o["steps"] for o in outcomes)), "per_episode": outcomes, "config": to_dict(config),
                "load": (f"MINARI_DATASETS_PATH={out_dir} python -c "
                         f"\"import minari; minari.load_dataset('{dataset_id}')\""),
            }
            with warnings.catch_warnings():  # (Minari asks for an author e-mail: a tool has none)
                warnings.filterwarnings("ignore", message="`author_email` is set to None")
                minari.create_dataset_from_buffers(
                    dataset_id, buffers, env=env, eval_env=env.spec, algorithm_name=name, author="msdgrasp collect",
                    code_permalink="msdgrasp/agents/demonstrations.py", description=card_markdown(card),
                    data_format="arrow", requirements=[f"msdgrasp=={_version()}"])
            env.close()
            made = tmp / dataset_id
            atomic_write_text(made / "card.json", json.dumps(card, indent=2) + "\n")
            atomic_write_text(made / "card.md", card_markdown(card))
            final.parent.mkdir(parents=True, exist_ok=True)
            os.replace(made, final)  # the whole dataset appears at once
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {**card, "path": str(final)}


def card_markdown(card: dict[str, Any]) -> str:
    """The dataset card: what was collected, on which env and task, by which policy, with what outcome."""
    rnd = card["config"]["randomization"]
    return "\n".join([
        f"# {card['dataset_id']}", "",
        f"Demonstrations of `{card['policy']}` on `{card['env_id']}` (env version {card['env_version']}), "
        f"task: {card['task_from']}.", "",
        f"- episodes: {card['episodes']}, seeds {card['seeds'][0]}..{card['seeds'][-1]} (episode i reset with seed "
        f"+ i), {card['steps']} steps",
        f"- success: {card['success_rate']:.0%}",
        f"- randomised per episode: mu {rnd['mu_range'][0]:g}-{rnd['mu_range'][1]:g} ({rnd['mu_distribution']}), "
        f"stiffness x{rnd['stiffness_scale_range'][0]:g}-{rnd['stiffness_scale_range'][1]:g}, mass "
        f"x{rnd['mass_scale_range'][0]:g}-{rnd['mass_scale_range'][1]:g}, grasp pose up to "
        f"{rnd['pose_offset_m'] * 1e3:g} mm / {rnd['pose_tilt_deg']:g} deg / {rnd['pose_azimuth_deg']:g} deg, "
        f"force noise {rnd['sensor_noise_N']:g} N",
        f"- load: `{card['load']}`", "",
    ])
