"""Stable-Baselines3 adapter: the natively batched GraspLift core as an SB3 ``VecEnv``.

SB3 (PPO, SAC, ...) does not accept Gymnasium vector envs; wrapping N single envs in a ``DummyVecEnv``
would step N tissues in N numba calls. :class:`GraspLiftSB3VecEnv` drives one
:class:`~msdgrasp.envs.core.GraspLiftCore` with ``num_envs`` tissues instead (ONE numba call per step)
and speaks SB3's VecEnv API:

* ``reset()`` returns the observations only; seeds and options set with ``seed()`` / ``set_options()``
  are used at the next ``reset()`` only (SB3 2.x convention); sub-env i seeded with s behaves exactly
  like a single :class:`~msdgrasp.envs.grasp_lift.GraspLiftEnv` reset with seed s (``seed(s)`` gives
  sub-env i the seed s + i, as SB3 does);
* ``step_wait()`` returns ``(obs, rewards, dones, infos)`` with a list of per-env info dicts; a finished
  sub-env is reset in the same call, its last observation in ``info["terminal_observation"]``, and
  ``info["TimeLimit.truncated"]`` = truncated and not terminated (SB3 bootstraps from it).
  ``info["is_success"]`` feeds SB3's success-rate logging and ``info["episode"]`` = {r, l, t} its
  episode reward/length logging (what ``Monitor``/``VecMonitor`` would add; wrapping in ``VecMonitor``
  still works and overwrites it).

:class:`CudaSB3VecEnv` puts the GPU task (:class:`~msdgrasp.envs.cuda_core.CudaGraspLiftCore`) behind the
same API, host copies included: what ``msdgrasp bench learners`` times against the torch-native learner.

Example::

    from stable_baselines3 import PPO
    from msdgrasp.envs.sb3 import make_sb3_env

    venv = make_sb3_env(16, seed=0)
    PPO("MlpPolicy", venv).learn(100_000)
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..physics.config import needs_extra
from ..physics.device_layout import Precision
from .core import GraspLiftConfig, GraspLiftCore
from .grasp_lift import check_render_mode, checked_action, env_config

with needs_extra("train", "the Stable-Baselines3 adapter"):
    from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvObs, VecEnvStepReturn

#: core attributes that hold one entry per sub-env (``get_attr``/``set_attr`` address entry i)
PER_ENV_ATTRS = (
    "rngs", "mu", "pull_dir", "tip0", "region0", "steps", "prev_action", "lift", "best_lift", "slip_total",
    "lift_slip", "hold_time", "hold_slip", "hold_progress", "travel_target", "peak_pinch", "peak_stress",
    "lift_started", "time_to_lift", "obs",
)
ERROR_MESSAGE = "numerical failure: the tissue state became non-finite (blow-up); episode terminated"


class GraspLiftSB3VecEnv(VecEnv):
    """``num_envs`` GraspLift tissues as one SB3 VecEnv (one numba call per step, same-step autoreset).

    Parameters
    ----------
    num_envs : int
    config : GraspLiftConfig | dict | None
        The task (default: the spleen task); ``overrides`` replace single fields (e.g. ``scene="sphere"``).
    seed : int | None
        Seeds of the first ``reset()``: sub-env i gets ``seed + i`` (None: fresh entropy).
    render_mode : "rgb_array" | None
        ``render()`` tiles the frames of all sub-envs (``get_images()`` gives them one by one).
    precision : "float64" | "float32"
        The tissue arrays' storage (:class:`~msdgrasp.envs.core.GraspLiftCore`): float32 is a training's option
        for the speed of its rollouts, float64 the physics of every result.
    """

    @property
    def config(self) -> GraspLiftConfig:
        """The task (the core's: a training curriculum moves its randomisation)."""
        return self.core.config

    def __init__(self, num_envs: int, config: GraspLiftConfig | dict | None = None, seed: int | None = None,
                 render_mode: str | None = "rgb_array", precision: Precision = "float64", **overrides: Any) -> None:
        check_render_mode(render_mode, type(self).__name__)
        self.core = GraspLiftCore(env_config(config, **overrides), int(num_envs), precision)
        self._render_mode = render_mode
        obs_space = spaces.Box(-np.inf, np.inf, (self.core.obs_dim,), np.float32)
        act_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        super().__init__(self.core.num_envs, obs_space, act_space)
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.config.agent_dt_s))}
        self._actions: np.ndarray | None = None
        self._ever_reset = False
        self._ep_return = np.zeros(self.num_envs)
        self._ep_len = np.zeros(self.num_envs, dtype=np.int64)
        self._t0 = time.time()
        if seed is not None:
            self.seed(int(seed))

    # -- reset / step ------------------------------------------------------------------------------
    def reset(self) -> VecEnvObs:
        core = self.core
        for i in range(self.num_envs):
            s = self._seeds[i]
            if s is not None:
                core.seed(i, int(s))
            elif not self._ever_reset:
                core.seed(i, int(np.random.SeedSequence().entropy % (2**63)))
            draws = core.reset(i, self._options[i] or None)
            self.reset_infos[i] = core.info_at_reset(i, draws)
        self._ever_reset = True
        self._reset_seeds()
        self._reset_options()
        self._ep_return[:] = 0.0
        self._ep_len[:] = 0
        self._actions = None
        return core.obs.astype(np.float32)

    def step_async(self, actions: np.ndarray) -> None:
        """Store (num_envs, 2) actions in [-1, 1] (clipped); NaN/inf or a wrong shape raise ValueError."""
        self._actions = checked_action(actions, self.num_envs)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() called without a pending step_async(actions)")
        if not self._ever_reset:
            raise RuntimeError("reset() must be called before stepping")
        core = self.core
        obs, reward, terminated, truncated, infos = core.step(self._actions)
        self._actions = None
        dones = terminated | truncated
        self._ep_return += reward
        self._ep_len += 1
        terms = infos["reward_terms"]
        scalar_keys = [k for k in infos if k != "reward_terms"]
        info_list: list[dict[str, Any]] = []
        for i in range(self.num_envs):
            info = {k: infos[k][i].item() for k in scalar_keys}
            info["reward_terms"] = {k: float(v[i]) for k, v in terms.items()}
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            if info["numerical_failure"]:
                info["error"] = ERROR_MESSAGE
            if dones[i]:
                info["terminal_observation"] = obs[i].copy()
                info["episode"] = {"r": float(self._ep_return[i]), "l": int(self._ep_len[i]),
                                   "t": round(time.time() - self._t0, 6)}
            info_list.append(info)
        for i in np.flatnonzero(dones):
            # an autoreset draws from the sub-env's own generator (as a single env's plain reset() does)
            draws = core.reset(int(i))
            self.reset_infos[i] = core.info_at_reset(int(i), draws)
            self._ep_return[i] = 0.0
            self._ep_len[i] = 0
        return core.obs.astype(np.float32), reward.astype(np.float32), dones.copy(), info_list

    def close(self) -> None:
        cache = getattr(self.core, "_render_cache", None)
        if cache:
            cache.clear()

    # -- rendering ----------------------------------------------------------------------------------
    def get_images(self) -> Sequence[np.ndarray | None]:
        from .render import render_rgb

        return [render_rgb(self.core, i) for i in range(self.num_envs)]

    def render(self, mode: str | None = None) -> np.ndarray | None:
        """Tiled RGB frame of all sub-envs (SB3 convention), (H, W, 3) uint8."""
        return super().render(mode=mode)

    # -- attribute access ---------------------------------------------------------------------------
    def _indices(self, indices: VecEnvIndices) -> list[int]:
        idx = list(self._get_indices(indices))
        for i in idx:
            if not 0 <= int(i) < self.num_envs:
                raise IndexError(f"env index {i} out of range [0, {self.num_envs - 1}]")
        return [int(i) for i in idx]

    def _target(self, attr_name: str) -> Any:
        if attr_name == "render_mode":
            return self._render_mode
        for owner in (self, self.core):
            try:
                return getattr(owner, attr_name)
            except AttributeError:
                continue
        raise AttributeError(f"GraspLiftSB3VecEnv: no attribute {attr_name!r} (neither on the adapter nor on the core)")

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of each sub-env. Per-env core arrays (``mu``, ``lift``, ...) give entry i; the rest
        (``config``, ``render_mode``, spaces, ...) is shared by all sub-envs."""
        idx = self._indices(indices)
        value = self._target(attr_name)
        if attr_name in PER_ENV_ATTRS:
            return [value[i] for i in idx]
        return [value for _ in idx]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        """Set a per-env core array entry (e.g. ``mu``) for the given sub-envs; shared attributes can only be
        set for all sub-envs at once."""
        idx = self._indices(indices)
        if attr_name in PER_ENV_ATTRS:
            arr = getattr(self.core, attr_name)
            for i in idx:
                arr[i] = value
            return
        if sorted(idx) != list(range(self.num_envs)):
            raise ValueError(f"{attr_name!r} is shared by all sub-envs; set it with indices=None")
        if attr_name == "render_mode":
            self._render_mode = value
            self.render_mode = value
        elif hasattr(self, attr_name):
            setattr(self, attr_name, value)
        else:
            setattr(self.core, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        """Call a method per sub-env: ``reset(seed=, options=)`` -> [(obs, info)], ``render()`` -> [frame];
        other adapter/core methods once per index, with the index as first argument when the method's first
        parameter is ``index`` (e.g. ``env_method("seed", 7, indices=[2])`` calls ``core.seed(2, 7)``)."""
        idx = self._indices(indices)
        if method_name == "render":
            from .render import render_rgb

            return [render_rgb(self.core, i, *method_args, **method_kwargs) for i in idx]
        if method_name == "reset":
            out = []
            for i in idx:
                seed = method_kwargs.get("seed")
                if seed is not None:
                    self.core.seed(i, int(seed))
                draws = self.core.reset(i, method_kwargs.get("options"))
                self.reset_infos[i] = self.core.info_at_reset(i, draws)
                self._ep_return[i] = 0.0
                self._ep_len[i] = 0
                out.append((self.core.obs[i].astype(np.float32), self.reset_infos[i]))
            return out
        method = self._target(method_name)
        if not callable(method):
            raise AttributeError(f"{method_name!r} is not a method")
        try:
            params = list(inspect.signature(method).parameters)
        except (TypeError, ValueError):
            params = []
        if params and params[0] == "index":  # a per-env core method, e.g. seed(index, seed)
            return [method(i, *method_args, **method_kwargs) for i in idx]
        return [method(*method_args, **method_kwargs) for _ in idx]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        """No sub-env is a wrapped Gymnasium env (episode stats come natively in ``info["episode"]``)."""
        return [False for _ in self._indices(indices)]

    def __repr__(self) -> str:
        return f"GraspLiftSB3VecEnv(num_envs={self.num_envs}, scene={self.config.scene!r})"


def make_sb3_env(num_envs: int = 8, config: GraspLiftConfig | dict | None = None, seed: int | None = None,
                 **overrides: Any) -> GraspLiftSB3VecEnv:
    """A :class:`GraspLiftSB3VecEnv` ready for ``PPO("MlpPolicy", venv)`` / ``SAC(...)``.

    Wrap it in ``stable_baselines3.common.vec_env.VecNormalize`` for observation/reward normalisation if
    wanted; episode statistics and success rates are logged without a ``VecMonitor``.
    """
    return GraspLiftSB3VecEnv(num_envs, config, seed=seed, **overrides)


class CudaSB3VecEnv(VecEnv):
    """The GPU task (:class:`~msdgrasp.envs.cuda_core.CudaGraspLiftCore`) as an SB3 ``VecEnv``.

    SB3 steps NumPy arrays: every step uploads the actions and downloads the observations, rewards and
    flags, and builds one info dict per env; where episodes ended, their terminal observation, success,
    return and length are downloaded too (``info["terminal_observation"]``, ``"is_success"``, ``"episode"``,
    ``"TimeLimit.truncated"``, as :class:`GraspLiftSB3VecEnv` gives them). This host round trip is what a
    torch-native learner avoids; ``msdgrasp bench learners`` measures it. The GPU core resets ended envs in
    the same step and pins nothing through ``reset()`` here; ``seed`` is the core's.
    """

    def __init__(self, core) -> None:
        self.core = core
        obs_space = spaces.Box(-np.inf, np.inf, (core.obs_dim,), np.float32)
        super().__init__(core.num_envs, obs_space, spaces.Box(-1.0, 1.0, (2,), np.float32))
        self._actions: np.ndarray | None = None
        self._t0 = time.time()

    def reset(self) -> VecEnvObs:
        return self.core.reset().copy_to_host()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = checked_action(actions, self.num_envs)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() called without a pending step_async(actions)")
        obs, reward, terminated, truncated = (a.copy_to_host() for a in self.core.step(self._actions))
        self._actions = None
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if dones.any():
            ended = self.core.download("terminal_obs", "is_success", "episode_return", "episode_length")
            for i in np.flatnonzero(dones):
                infos[i] = {"terminal_observation": ended["terminal_obs"][i],
                            "TimeLimit.truncated": bool(truncated[i] and not terminated[i]),
                            "is_success": bool(ended["is_success"][i]),
                            "episode": {"r": float(ended["episode_return"][i]), "l": int(ended["episode_length"][i]),
                                        "t": round(time.time() - self._t0, 6)}}
        return obs, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self.core, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise AttributeError(f"CudaSB3VecEnv: the GPU task's {attr_name!r} is set through its config, not per env")

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        raise AttributeError(f"CudaSB3VecEnv: no per-env method {method_name!r} on the GPU task")

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]
