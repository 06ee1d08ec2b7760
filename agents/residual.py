"""Residual policies: a learned correction added to a controller's action.

A model trained with ``residual_base`` (:class:`~.models.TrainConfig`) does not act alone: its output r in [-1, 1]
is added to the controller's action a_c, ``a = clip(a_c + residual_scale * r, -1, 1)`` (:func:`compose`; with
``residual_mode: raise`` only its positive part, ``max(r, 0)``: a correction that can raise the grip, never lower
it), in training (:func:`residual_venv`, around the SB3 vector env: PPO learns over r) and wherever the model runs
(:func:`with_residual`, around the loaded policy: evaluation, validation, the robustness suite, recording,
demonstrations). The controller keeps its own state per episode. With ``residual_start: pull`` the correction
acts only once the controller pulls (:func:`correction_mask`): a slip-feedback controller with a friction estimator
reads the closing at its probe grip, so the estimate sees the frames it was fitted on. An untrained network outputs
r ~ 0, so a residual training starts from the controller's behaviour and learns what it lacks (residual
reinforcement learning: Johannink et al., ICRA 2019; Silver et al., arXiv:1812.06298).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from .controllers import make_policy

def compose(base: np.ndarray, residual: np.ndarray, scale: float | Sequence[float], mode: str = "add") -> np.ndarray:
    """The action sent: the controller's ``base`` plus ``scale`` (one, or one per action) times the learned
    ``residual`` (``mode`` "raise": its positive part only), clipped to [-1, 1]."""
    if mode not in ("add", "raise"):
        raise ValueError(f"residual mode must be 'add' or 'raise', got {mode!r}")
    scale = np.asarray(scale, dtype=np.float64)
    residual = np.asarray(residual, dtype=np.float64)
    if mode == "raise":
        residual = np.maximum(residual, 0.0)
    return np.clip(np.asarray(base, dtype=np.float64) + scale * residual, -1.0, 1.0).astype(np.float32)


def correction_mask(base: Any, start: str) -> np.ndarray | None:
    """Per episode of the controller ``base``'s batch, whether the correction acts now (None: in every episode):
    ``start`` "reset" from the first step, "pull" from the step the controller starts pulling."""
    if start == "reset":
        return None
    if start != "pull":
        raise ValueError(f"residual start must be 'reset' or 'pull', got {start!r}")
    return np.asarray(base.pulling, dtype=bool)


def _masked(residual: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    return residual if mask is None else np.where(mask[:, None], residual, 0.0)


class ResidualPolicy:
    """A policy (``inner``, the trained model) acting as a correction on the controller ``base``."""

    def __init__(self, inner: Any, base: Any, scale: float | Sequence[float], mode: str = "add",
                 start: str = "reset") -> None:
        self.inner = inner
        self.base = base
        self.scale = scale
        self.mode = mode
        self.start = start
        self.name = inner.name

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        self.base.reset(infos)
        self.inner.reset(infos)

    def reset_one(self, index: int, info: dict[str, Any]) -> None:
        self.base.reset_one(index, info)

    def act(self, obs: np.ndarray) -> np.ndarray:
        action = self.base.act(obs)  # (first: the controller's state, and so the mask, follows this frame)
        return compose(action, _masked(self.inner.act(obs), correction_mask(self.base, self.start)), self.scale,
                       self.mode)


def with_residual(policy: Any, config: Any) -> Any:
    """``policy`` (a loaded model) as it acts: on its controller where its training ``config`` names one."""
    base = getattr(config, "residual_base", None)
    if base is None:
        return policy
    return ResidualPolicy(policy, make_policy(base, config.env), config.residual_scale, config.residual_mode,
                          config.residual_start)


def residual_venv(venv: Any, config: Any) -> Any:
    """The SB3 vector env ``venv`` with the policy's actions composed on ``config.residual_base`` (``venv`` itself
    without one); attributes (``core``, ...) read through."""
    if getattr(config, "residual_base", None) is None:
        return venv
    from stable_baselines3.common.vec_env import VecEnvWrapper

    class ResidualVecEnv(VecEnvWrapper):
        def __init__(self) -> None:
            super().__init__(venv)
            self.base = make_policy(config.residual_base, config.training_task())
            self.scale = config.residual_scale
            self.mode = config.residual_mode
            self.start = config.residual_start
            self._obs: np.ndarray | None = None

        def reset(self) -> np.ndarray:
            obs = self.venv.reset()
            self.base.reset([{}] * self.num_envs)
            self._obs = obs
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            action = self.base.act(self._obs)
            actions = _masked(actions, correction_mask(self.base, self.start))
            self.venv.step_async(compose(action, actions, self.scale, self.mode))

        def step_wait(self):
            obs, rewards, dones, infos = self.venv.step_wait()
            for i in np.flatnonzero(dones):  # (obs[i] is the next episode's first observation)
                self.base.reset_one(int(i), {})
            self._obs = obs
            return obs, rewards, dones, infos

    return ResidualVecEnv()
