"""The learner ``recurrent`` (:mod:`msdgrasp.agents.recurrent_training`): an actor with memory (a GRU over the sensed
entries) beside a privileged critic, taught by DAgger from a privileged teacher, then fine-tuned by PPO (either stage
may be off: PPO alone is recurrent PPO from scratch).

A run folder: ``config.json`` (written first), ``checkpoints/student_<iteration>.pt`` each with
``student_<iteration>.json`` (learner, architecture, observation columns, training config), the shipped
``student.pt`` + ``student.json`` (the validated best), ``validation.json`` and ``summary.json`` (written last).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ...physics.config import ConfigError
from .base import Learner, TrainOverrides, check_env_files, numbered_files, read_train_yaml, register
from .recurrent_layout import CONFIG, LAYOUT, NAME

if TYPE_CHECKING:
    from ...envs.core import GraspLiftConfig


def _meta(path: Path) -> dict[str, Any]:
    from ..recurrent import read_student_meta

    return read_student_meta(path, NAME)


def _run_record(run: Path) -> dict[str, Any]:
    """A run's ``config.json``: ``{"learner": "recurrent", "config": {...}}`` (ConfigError where it is broken)."""
    path = Path(run) / LAYOUT.config
    try:
        data = json.loads(path.read_text())
        data["config"]  # noqa: B018
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path}: not a training run's record ({exc!r})") from None
    return data


class RecurrentLearner(Learner):
    """A recurrent actor: DAgger from a privileged teacher, then PPO with a privileged critic, on the CPU env."""

    name = NAME
    backends = ("cpu",)
    default_out = Path("logs") / "train_recurrent"
    layout = LAYOUT

    def check_available(self) -> None:
        from ...physics.config import require_extra

        require_extra("train", f"learner {NAME}", "torch")

    def owns_config(self, config: Any) -> bool:
        from ..recurrent_training import RecurrentConfig

        return isinstance(config, RecurrentConfig)

    def config_from_dict(self, data: Mapping[str, Any], where: str):
        from ...physics.config import from_dict
        from ..recurrent_training import RecurrentConfig

        return from_dict(RecurrentConfig, dict(data), where=where)

    def make_config(self, path: Path | None, overrides: TrainOverrides):
        from ...physics.config import builtin_config

        if overrides.total_timesteps is not None:
            raise ConfigError("--total-timesteps is an option of the SB3 learners; a recurrent run's length is "
                              "its DAgger iterations and PPO waves in its config")
        path = Path(path) if path is not None else builtin_config(CONFIG)
        data = read_train_yaml(path)
        for key, val in (("n_envs", overrides.n_envs), ("seed", overrides.seed)):
            if val is not None:
                data[key] = val
        return check_env_files(self.config_from_dict(data, where=str(path)), path)

    def config_dict_of_run(self, run: Path) -> dict[str, Any]:
        return _run_record(run)["config"]

    def config_dict_of_model(self, model: Path) -> dict[str, Any]:
        return _meta(model)["config"]

    def train(self, config: Any, out_dir: Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
        from ..recurrent_training import train_recurrent

        if resume:
            raise ConfigError(f"learner {NAME} cannot continue a run")
        return train_recurrent(config, out_dir, progress=progress)

    @staticmethod
    def recorded_learner(path: Path) -> str | None:
        path = Path(path)
        if path.is_dir():
            return NAME if (path / LAYOUT.config).is_file() and _run_record(path).get("learner") == NAME else None
        meta = path.with_suffix(".json")
        if path.suffix != Path(LAYOUT.model).suffix or not meta.is_file():
            return None
        try:
            recorded = json.loads(meta.read_text()).get("learner")
        except (ValueError, AttributeError):
            return None
        return NAME if recorded == NAME else None

    def load_policy(self, model: Path, name: str | None = None):
        from ..recurrent import StudentPolicy

        _meta(model)
        return StudentPolicy.load(model, name)

    def model_task(self, model: Path) -> "GraspLiftConfig":
        from ...envs.core import GraspLiftConfig
        from ...physics.config import from_dict

        return from_dict(GraspLiftConfig, _meta(model)["config"]["env"], where=f"{Path(model).stem}.json:config.env")

    def model_training_task(self, model: Path) -> "GraspLiftConfig":
        return self.config_from_dict(_meta(model)["config"], where=f"{Path(model).stem}.json:config").training_task()

    def model_files(self, model: Path) -> dict[str, Path]:
        model = Path(model)
        _meta(model)
        meta = model.with_suffix(".json")
        return {model.name: model, meta.name: meta}

    def checkpoints(self, run: Path, config: Any) -> list[tuple[int, Path]]:
        return numbered_files(run, LAYOUT.checkpoint)

    def select(self, config: Any, checkpoints: list[tuple[int, Path]], out: Path) -> dict[str, Any]:
        from ..recurrent_training import select_students

        return select_students(config, checkpoints, out)


RECURRENT = register(RecurrentLearner())
