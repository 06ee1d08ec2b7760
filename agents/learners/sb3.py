"""The Stable-Baselines3 learners: ``ppo`` and ``sac`` (one layout, one config class: :class:`TrainConfig`).

A run folder (:func:`~msdgrasp.agents.training.train`): ``config.yaml`` (the resolved training config,
written first), ``checkpoints/model_<steps>.zip``, ``final_model.zip`` + ``final_model.yaml``,
``best_model.zip`` + ``best_model.yaml`` (the validated best, the model a run ships), ``validation.json``,
``train_summary.json`` (written last). The learner of a model is the ``algo`` of the config saved beside it
(``<model>.yaml``, else the run's ``config.yaml``): a model without one is an error, never a guess.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .base import Learner, RunSummary, TrainOverrides, check_env_files, numbered_files, read_train_yaml, register
from .sb3_layout import (
    FINAL_MODEL, LAYOUT, SUFFIX, load_train_config, read_summary, required_config_path, load_model,
    model_train_config,
)

if TYPE_CHECKING:
    from ...envs.core import GraspLiftConfig
    from ..models import TrainConfig


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
        from ...physics.config import require_extra

        require_extra("train", f"learner {self.name}", "torch", "stable_baselines3")

    def owns_config(self, config: Any) -> bool:
        from ..models import TrainConfig

        return isinstance(config, TrainConfig) and config.algo == self.name

    def config_from_dict(self, data: Mapping[str, Any], where: str) -> "TrainConfig":
        from ...physics.config import from_dict
        from ..models import TrainConfig

        return from_dict(TrainConfig, dict(data), where=where)

    def make_config(self, path: Path | None, overrides: TrainOverrides) -> "TrainConfig":
        from ...physics.config import builtin_config
        from ..models import DEFAULT_TRAINING

        path = Path(path) if path is not None else builtin_config(DEFAULT_TRAINING)
        data = read_train_yaml(path)
        if overrides.learner is not None:  # the command line's choice over the config's algo
            data["algo"] = overrides.learner
            if overrides.learner != "ppo":  # the asymmetric critic is PPO's
                data["asymmetric_critic"] = False
        for key, val in (("total_timesteps", overrides.total_timesteps), ("n_envs", overrides.n_envs),
                         ("seed", overrides.seed)):
            if val is not None:
                data[key] = val
        return check_env_files(self.config_from_dict(data, where=str(path)), path)

    def check_inputs(self, config: "TrainConfig") -> None:
        config.check_inputs()

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

        return read_yaml(required_config_path(Path(model)))

    def train(self, config: Any, out_dir: Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
        from ..training import train

        return train(config, out_dir, resume=resume, progress=progress)

    def run_summary(self, run: Path) -> RunSummary:
        s = read_summary(run / LAYOUT.summary)
        return RunSummary(s["wall_time_s"], s["timesteps"], s["steps_per_s"])

    @staticmethod
    def recorded_learner(path: Path) -> str | None:
        path = Path(path)
        if path.is_dir():  # a run (config.yaml) or a selected pick (best_model.yaml)
            for name in (LAYOUT.config, LAYOUT.model, LAYOUT.fallback_model):
                cfg = path / Path(name).with_suffix(".yaml")
                if cfg.is_file():
                    return load_train_config(cfg, f"run {path}").algo
            return None
        if path.suffix != SUFFIX:
            return None
        return model_train_config(path).algo

    def load_policy(self, model: Path, name: str | None = None):
        from ..model_policy import ModelPolicy
        from ..residual import with_residual

        return with_residual(ModelPolicy(model, name), model_train_config(model))

    def model_task(self, model: Path) -> "GraspLiftConfig":
        return model_train_config(model).env

    def model_training_task(self, model: Path) -> "GraspLiftConfig":
        return model_train_config(model).training_task()

    def model_files(self, model: Path) -> dict[str, Path]:
        model = Path(model)
        return {model.name: model, model.with_suffix(".yaml").name: required_config_path(model)}

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


PPO = register(SB3Learner("ppo"))
SAC = register(SB3Learner("sac"))
