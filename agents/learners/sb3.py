"""The Stable-Baselines3 learners: ``ppo`` and ``sac`` (one layout, one config class: :class:`TrainConfig`).

A run folder (:func:`~msdgrasp.agents.training.train`): ``config.yaml`` (the resolved training config,
written first), ``checkpoints/model_<steps>.zip``, ``final_model.zip`` + ``final_model.yaml``,
``best_model.zip`` + ``best_model.yaml`` (the validated best, the model a run ships), ``validation.json``,
``train_summary.json`` (written last). The learner of a model is the ``algo`` of the config saved beside it
(``<model>.yaml``, else the run's ``config.yaml``): a model without one is an error, never a guess.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ...physics.config import ConfigError
from . import Learner, RunLayout, RunSummary, TrainOverrides, numbered_files, register

if TYPE_CHECKING:
    from ...envs.core import GraspLiftConfig
    from ..models import TrainConfig

LAYOUT = RunLayout(model="best_model.zip", fallback_model="final_model.zip", summary="train_summary.json",
                   config="config.yaml", checkpoint="checkpoints/model_{}.zip",
                   model_description="<name>.zip with <name>.yaml or the run's config.yaml beside it")
#: the final model of a run (validated last; shipped where the run kept no best)
FINAL_MODEL = LAYOUT.fallback_model
#: the built-in training config (``msdgrasp train`` without ``--config``)
DEFAULT_CONFIG = "train/ppo.yaml"
_SUFFIX = Path(LAYOUT.model).suffix


def model_config_path(path: str | Path) -> Path | None:
    """The training config saved with a model: ``<model>.yaml`` or the run folder's ``config.yaml``."""
    path = Path(path)
    for cfg in (path.with_suffix(".yaml"), path.parent / LAYOUT.config, path.parent.parent / LAYOUT.config):
        if cfg.is_file():
            return cfg
    return None


def _required_config_path(path: Path) -> Path:
    cfg = model_config_path(path)
    if cfg is None:
        raise ConfigError(f"model {path}: its training config is missing ({path.with_suffix('.yaml').name} beside it, "
                          f"or the run's {LAYOUT.config}); a model is only run on the task it was trained on")
    return cfg


def _load_config(cfg: Path, what: str) -> "TrainConfig":
    from ..models import TrainConfig

    try:
        return TrainConfig.load(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{what}: its training config {cfg} is invalid: {exc}") from None


def model_train_config(path: str | Path) -> "TrainConfig":
    """The :class:`TrainConfig` a saved model was trained with (ConfigError: missing or invalid)."""
    path = Path(path)
    return _load_config(_required_config_path(path), f"model {path}")


def is_ppo(algo: str) -> bool:
    """Whether SB3 algorithm ``algo`` is PPO: a Gaussian policy with gSDE options and a log std, which
    behaviour cloning and the asymmetric critic need (SAC's actor has neither)."""
    return algo == "ppo"


def _algo_class(name: str):
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
        raise ConfigError(f"model file {path} is not a Stable-Baselines3 {_SUFFIX} archive (corrupt or wrong file)")
    algo = model_train_config(path).algo
    try:
        return _algo_class(algo).load(path, env=env, device="cpu")
    except (ValueError, KeyError, RuntimeError, OSError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"cannot load model {path} as {algo}: {type(exc).__name__}: {exc}") from None


class SB3Learner(Learner):
    """Stable-Baselines3's ``algo`` (PPO or SAC) on the batched CPU env (:mod:`msdgrasp.agents.training`)."""

    backends = ("cpu",)
    default_out = Path("logs") / "train"
    layout = LAYOUT
    can_resume = True
    parallel_seeds = True

    def __init__(self, algo: str) -> None:
        self.name = algo

    def check_available(self) -> None:
        import stable_baselines3  # noqa: F401

    def owns_config(self, config: Any) -> bool:
        from ..models import TrainConfig

        return isinstance(config, TrainConfig) and config.algo == self.name

    def one_core(self, config: Any) -> Any:
        from dataclasses import replace

        return replace(config, torch_threads=1)

    def config_from_dict(self, data: Mapping[str, Any], where: str) -> "TrainConfig":
        from ...physics.config import from_dict
        from ..models import TrainConfig

        return from_dict(TrainConfig, dict(data), where=where)

    def make_config(self, path: Path | None, overrides: TrainOverrides) -> "TrainConfig":
        from ...physics.config import builtin_config, read_yaml

        path = Path(path) if path is not None else builtin_config(DEFAULT_CONFIG)
        data = read_yaml(path)
        if overrides.learner is not None:  # the command line's choice over the config's algo
            data["algo"] = overrides.learner
            if overrides.learner != "ppo":  # the asymmetric critic is PPO's
                data["asymmetric_critic"] = False
        for key, val in (("total_timesteps", overrides.total_timesteps), ("n_envs", overrides.n_envs),
                         ("seed", overrides.seed)):
            if val is not None:
                data[key] = val
        return self.config_from_dict(data, where=path.name)

    def resume_config(self, run: Path, overrides: TrainOverrides) -> "TrainConfig":
        from ...physics.config import to_dict

        config = self.config_of_run(run)
        if overrides.total_timesteps:
            config = self.config_from_dict({**to_dict(config), "total_timesteps": overrides.total_timesteps},
                                           where=str(run / LAYOUT.config))
        return config

    def config_dict_of_run(self, run: Path) -> dict[str, Any]:
        from ...physics.config import read_yaml

        return read_yaml(run / LAYOUT.config)

    def config_dict_of_model(self, model: Path) -> dict[str, Any]:
        from ...physics.config import read_yaml

        return read_yaml(_required_config_path(Path(model)))

    def train(self, config: Any, out_dir: Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
        from ..training import train

        return train(config, out_dir, resume=resume, progress=progress)

    def run_summary(self, run: Path) -> RunSummary:
        s = _read_summary(run / LAYOUT.summary)
        return RunSummary(s["wall_time_s"], s["timesteps"], s["steps_per_s"])

    @staticmethod
    def recorded_learner(path: Path) -> str | None:
        path = Path(path)
        if path.is_dir():  # a run (config.yaml) or a selected pick (best_model.yaml)
            for name in (LAYOUT.config, LAYOUT.model, LAYOUT.fallback_model):
                cfg = path / Path(name).with_suffix(".yaml")
                if cfg.is_file():
                    return _load_config(cfg, f"run {path}").algo
            return None
        if path.suffix != _SUFFIX:
            return None
        return model_train_config(path).algo

    def load_policy(self, model: Path, name: str | None = None):
        from ..controllers import ModelPolicy

        return ModelPolicy(model, name)

    def model_task(self, model: Path) -> "GraspLiftConfig":
        return model_train_config(model).env

    def model_files(self, model: Path) -> dict[str, Path]:
        model = Path(model)
        return {model.name: model, model.with_suffix(".yaml").name: _required_config_path(model)}

    def checkpoints(self, run: Path, config: Any) -> list[tuple[int, Path]]:
        found = numbered_files(run, LAYOUT.checkpoint)
        if (run / FINAL_MODEL).is_file():
            found.append((config.total_timesteps, run / FINAL_MODEL))
        return found

    def select(self, config: Any, checkpoints: list[tuple[int, Path]], out: Path) -> dict[str, Any]:
        from ..training import BestModel

        selector = BestModel(config, out)
        for _, path in checkpoints:
            selector.consider(load_model(path), path)
        return {"best_model": str(out / LAYOUT.model), "best_validation": selector.best}


def _read_summary(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"{path} is missing: the run did not finish (its training summary is written last)")
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ConfigError(f"{path} is not a training summary ({exc})") from None


PPO = register(SB3Learner("ppo"))
SAC = register(SB3Learner("sac"))
