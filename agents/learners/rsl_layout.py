"""The torch PPO learner's run layout and exported policies (what :mod:`.rsl`, the training
(:mod:`msdgrasp.agents.torch_ppo`) and the policy that runs them share; no training here)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ...physics.config import ConfigError
from .base import RunLayout

NAME = "rsl"
LAYOUT = RunLayout(model="policy.pt", fallback_model=None, summary="summary.json", config="policy.json",
                   checkpoint="checkpoints/policy_{}.pt", model_description="<name>.pt with <name>.json beside it")
SUFFIX = Path(LAYOUT.model).suffix
#: where rsl-rl's runner saves its own checkpoints (log_dir "tb"), which the run exports to LAYOUT.checkpoint
RUNNER_CHECKPOINT = "tb/model_{}.pt"
#: the built-in configs: the GPU's (4,096 envs, backend cuda) and the CPU-sized one (64 envs)
GPU_CONFIG, CPU_CONFIG = "train/rsl_ppo.yaml", "train/rsl_ppo_cpu.yaml"


def meta_path(policy: str | Path) -> Path:
    """The ``.json`` that describes an exported policy (``policy.pt`` -> ``policy.json``)."""
    return Path(policy).with_suffix(".json")


def read_meta(policy: str | Path) -> dict[str, Any]:
    """The description of an exported policy (ConfigError naming the missing or broken file)."""
    policy = Path(policy)
    meta = meta_path(policy)
    if not meta.is_file():
        raise ConfigError(f"model {policy}: {meta.name} is missing beside it (the policy's learner, observation "
                          "layout and training config); a model is only run on the task it was trained on")
    try:
        data = json.loads(meta.read_text())
        data["config"]["env"], data["actor_columns"]  # noqa: B018 (both must be there)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"model {policy}: {meta.name} is not a torch PPO policy's description ({exc!r})") from None
    if data.get("learner", NAME) != NAME:
        raise ConfigError(f"model {policy}: {meta.name} records learner {data['learner']!r}, not {NAME!r}")
    return data


def config_path(config: Path | None, backend: str | None) -> Path:
    """The torch PPO's config: the one given, else the CPU-sized one for ``--backend cpu``, else the GPU's."""
    from ...physics.config import builtin_config

    if config is not None:
        return Path(config)
    return builtin_config(CPU_CONFIG if backend == "cpu" else GPU_CONFIG)
