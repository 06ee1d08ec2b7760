"""A trained Stable-Baselines3 model behind the policy interface of :mod:`.controllers`.

Apart from the controllers: loading a model reads its training config (:mod:`.models`), and the training config asks
the controller registry (:mod:`.controllers`) what its ``residual_base`` is, so the import graph stays one-way.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


class ModelPolicy:
    """A trained Stable-Baselines3 model (deterministic actions)."""

    def __init__(self, path: str | Path, name: str | None = None) -> None:
        from .learners.sb3_layout import load_model, model_train_config

        self.model = load_model(path)
        if name is None:  # named by what it is: "PPO (seed 3)" when its training config is saved with it
            cfg = model_train_config(path)
            name = f"BC of {cfg.bc_dataset}" if cfg.bc_dataset else f"{cfg.algo.upper()} (seed {cfg.seed})"
        self.name = name

    @classmethod
    def from_model(cls, model, name: str = "model") -> "ModelPolicy":
        """Wrap an in-memory SB3 model (e.g. during training) without saving and reloading it."""
        self = cls.__new__(cls)
        self.model = model
        self.name = name
        return self

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        pass

    def act(self, obs: np.ndarray) -> np.ndarray:
        action, _ = self.model.predict(np.atleast_2d(obs), deterministic=True)
        return np.asarray(action, dtype=np.float32)
