"""The Stable-Baselines3 learners' run layout and saved models (what :mod:`.sb3` and the SB3 training
(:mod:`msdgrasp.agents.training`) share; no training here).

A model's algorithm is the ``algo`` of the config saved beside it (``<model>.yaml``, else the run's
``config.yaml``): a model without one is an error, never a guess.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ...physics.config import ConfigError, needs_extra
from .base import RunLayout

if TYPE_CHECKING:
    from ..models import TrainConfig

LAYOUT = RunLayout(model="best_model.zip", fallback_model="final_model.zip", summary="train_summary.json",
                   config="config.yaml", checkpoint="checkpoints/model_{}.zip",
                   model_description="<name>.zip with <name>.yaml or the run's config.yaml beside it")
#: the final model of a run (validated last; shipped where the run kept no best)
FINAL_MODEL = LAYOUT.fallback_model
SUFFIX = Path(LAYOUT.model).suffix


def model_config_path(path: str | Path) -> Path | None:
    """The training config saved with a model: ``<model>.yaml`` or the run folder's ``config.yaml``."""
    path = Path(path)
    for cfg in (path.with_suffix(".yaml"), path.parent / LAYOUT.config, path.parent.parent / LAYOUT.config):
        if cfg.is_file():
            return cfg
    return None


def required_config_path(path: Path) -> Path:
    cfg = model_config_path(path)
    if cfg is None:
        raise ConfigError(f"model {path}: its training config is missing ({path.with_suffix('.yaml').name} beside it, "
                          f"or the run's {LAYOUT.config}); a model is only run on the task it was trained on")
    return cfg


def load_train_config(cfg: Path, what: str) -> "TrainConfig":
    from ..models import TrainConfig

    try:
        return TrainConfig.load(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{what}: its training config {cfg} is invalid: {exc}") from None


def model_train_config(path: str | Path) -> "TrainConfig":
    """The :class:`TrainConfig` a saved model was trained with (ConfigError: missing or invalid)."""
    path = Path(path)
    return load_train_config(required_config_path(path), f"model {path}")


def is_ppo(algo: str) -> bool:
    """Whether SB3 algorithm ``algo`` is PPO: a Gaussian policy with gSDE options and a log std, which
    behaviour cloning and the asymmetric critic need (SAC's actor has neither)."""
    return algo == "ppo"


def algo_class(name: str):
    with needs_extra("train", f"SB3 algorithm {name}"):
        from stable_baselines3 import PPO, SAC

    return {"ppo": PPO, "sac": SAC}[name]


def load_model(path: str | Path, env=None):
    """Load a saved SB3 model with the algorithm its saved training config names (ConfigError: the model or
    its config is missing, or the archive is not a model of that algorithm)."""
    import zipfile

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model file not found: {path}")
    if not zipfile.is_zipfile(path):
        raise ConfigError(f"model file {path} is not a Stable-Baselines3 {SUFFIX} archive (corrupt or wrong file)")
    algo = model_train_config(path).algo
    try:
        return algo_class(algo).load(path, env=env, device="cpu")
    except (ValueError, KeyError, RuntimeError, OSError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"cannot load model {path} as {algo}: {type(exc).__name__}: {exc}") from None


def read_summary(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"{path} is missing: the run did not finish (its training summary is written last)")
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ConfigError(f"{path} is not a training summary ({exc})") from None
