"""The torch PPO learner's run layout and exported policies (what :mod:`.rsl`, the training
(:mod:`msdgrasp.agents.torch_ppo`) and the policy that runs them share; no training here)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .base import RunLayout, read_model_record

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
    return read_model_record(policy, NAME, ("config.env", "actor_columns"), "torch PPO policy", learner_optional=True)


def config_path(config: Path | None, backend: str | None) -> Path:
    """The torch PPO's config: the one given, else the CPU-sized one for ``--backend cpu``, else the GPU's."""
    from ...physics.config import builtin_config

    if config is not None:
        return Path(config)
    return builtin_config(CPU_CONFIG if backend == "cpu" else GPU_CONFIG)
