"""The torch-native PPO learner ``rsl`` (rsl-rl-lib; :mod:`msdgrasp.agents.torch_ppo`).

A run folder: ``checkpoints/policy_<iteration>.pt`` (TorchScript of the actor) each with
``policy_<iteration>.json`` (learner, observation columns, training config), the shipped ``policy.pt`` +
``policy.json`` (the validated best, or the last), ``validation.json``, ``summary.json`` (written last) and
``tb/`` (rsl-rl's own checkpoints and logs). A policy's learner is the ``learner`` of its ``.json``; a
``.json`` written before that field existed is recognised by its ``actor_columns`` and ``config``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ...physics.config import ConfigError
from .base import (
    Learner, TrainOverrides, check_env_files, get_learner, learner_names, numbered_files, read_train_yaml,
    register,
)
from .rsl_layout import CPU_CONFIG, GPU_CONFIG, LAYOUT, NAME, SUFFIX, config_path, meta_path, read_meta

if TYPE_CHECKING:
    from ...envs.core import GraspLiftConfig


class RslLearner(Learner):
    """rsl-rl's PPO on the batched core (the CUDA task or the CPU core): :func:`~..torch_ppo.train_torch`."""

    name = NAME
    backends = ("cpu", "cuda")
    default_out = Path("logs") / "train_torch"
    layout = LAYOUT
    can_resume = False
    #: one GPU: the seeds train one after the other
    parallel_seeds = False

    def check_available(self) -> None:
        from ..torch_ppo import rsl_vec_env

        rsl_vec_env()

    def owns_config(self, config: Any) -> bool:
        from ..torch_ppo import TorchPPOConfig

        return isinstance(config, TorchPPOConfig)

    def config_from_dict(self, data: Mapping[str, Any], where: str):
        from ...physics.config import from_dict
        from ..torch_ppo import TorchPPOConfig

        return from_dict(TorchPPOConfig, dict(data), where=where)

    def make_config(self, path: Path | None, overrides: TrainOverrides):
        if overrides.total_timesteps is not None:
            raise ConfigError("--total-timesteps is an option of the SB3 learners; the torch PPO's run length is "
                              f"'iterations' in its config ({GPU_CONFIG}, {CPU_CONFIG})")
        path = config_path(path, overrides.backend)
        data = read_train_yaml(path)
        for key, val in (("backend", overrides.backend), ("num_envs", overrides.n_envs), ("seed", overrides.seed)):
            if val is not None:  # (else the config's; rsl_ppo.yaml's backend: cuda)
                data[key] = val
        config = check_env_files(self.config_from_dict(data, where=str(path)), path)
        if config.backend == "cuda":
            from numba import cuda

            if not cuda.is_available():
                raise ConfigError("--backend cuda: no CUDA GPU found (numba.cuda.is_available() is False); run on a "
                                  "machine with an NVIDIA GPU and the gpu extra, or set NUMBA_ENABLE_CUDASIM=1 "
                                  "(numba's simulator: slow, for tests)")
        return config

    def config_dict_of_run(self, run: Path) -> dict[str, Any]:
        return read_meta(run / LAYOUT.model)["config"]

    def config_dict_of_model(self, model: Path) -> dict[str, Any]:
        return read_meta(model)["config"]

    def train(self, config: Any, out_dir: Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
        from ..torch_ppo import train_torch

        if resume:
            raise ConfigError(f"learner {NAME} cannot continue a run")
        return train_torch(config, out_dir, progress=progress)

    @staticmethod
    def recorded_learner(path: Path) -> str | None:
        path = Path(path)
        if path.is_dir():
            return read_meta(path / LAYOUT.model).get("learner", NAME) if (path / LAYOUT.config).is_file() else None
        if path.suffix != SUFFIX:
            return None
        try:  # (another learner whose models are .pt files records its own name beside them: not ours to claim)
            recorded = json.loads(meta_path(path).read_text()).get("learner", NAME)
        except (OSError, ValueError, AttributeError):
            recorded = NAME
        if recorded != NAME and recorded in learner_names() and Path(
                get_learner(recorded).layout.model).suffix == SUFFIX:
            return None
        return read_meta(path).get("learner", NAME)

    def load_policy(self, model: Path, name: str | None = None):
        from ..controllers import TorchScriptPolicy

        read_meta(model)
        return TorchScriptPolicy(model, name)

    def model_task(self, model: Path) -> "GraspLiftConfig":
        from ...envs.core import GraspLiftConfig
        from ...physics.config import from_dict

        meta = read_meta(model)
        return from_dict(GraspLiftConfig, meta["config"]["env"], where=f"{meta_path(model).name}:config.env")

    def model_files(self, model: Path) -> dict[str, Path]:
        model = Path(model)
        read_meta(model)
        return {model.name: model, meta_path(model).name: meta_path(model)}

    def checkpoints(self, run: Path, config: Any) -> list[tuple[int, Path]]:
        return numbered_files(run, LAYOUT.checkpoint)

    def select(self, config: Any, checkpoints: list[tuple[int, Path]], out: Path) -> dict[str, Any]:
        from ..torch_ppo import select_torch_checkpoints

        return select_torch_checkpoints(config, checkpoints, out)


RSL = register(RslLearner())
