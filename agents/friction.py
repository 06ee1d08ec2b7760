"""A friction estimate from the jaws' closing: what a controller needs to set its grip before the pull.

Told mu, the slip-feedback controller with a pinch-gated pull meets the robustness suite's force target in every
condition inside the robust training's ranges (docs/robustness.md). :class:`FrictionEstimator` replaces the telling:
a ridge regression of log mu on features of the observation frames a controller sees while its jaws close to a probe
grip (the sensing of the task, noise and all), fitted on episodes of a training's randomised task, where mu is known
(:func:`.friction_fit.fit_friction_estimator`). It carries the minimal fixed force per mu at the controller's pull
speed, so a controller turns its estimate into a grip without a search. ``msdgrasp fit-friction`` fits and saves one.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.task import N_OBS, obs_group
from ..physics.config import ConfigError, atomic_write_text, builtin_config

#: the per-jaw observation groups the features read
FEATURE_GROUPS = ("normal_force", "tangential_force", "contact_fraction", "slip_speed", "slipping_fraction",
                  "friction_use")
#: the last frames of the closing whose mean and max enter the features (a third of a second at 30 Hz)
RECENT_FRAMES = 10
#: features: per group and jaw the mean and the max over the recent frames and the mean over the closing, and the
#: closing's length in agent steps
N_FEATURES = 3 * 3 * len(FEATURE_GROUPS) + 1
#: the friction values at which a fit tabulates the minimal fixed force (log-log interpolation between them)
MU_GRID = (0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.65, 0.8, 1.0, 1.5)
FORMAT = "msdgrasp-friction-estimator-1"

#: the name of the estimator shipped with the package (``configs/friction/estimator.json``, fitted by
#: ``msdgrasp fit-friction --config configs/train/ppo.yaml``, the default training's task) in a policy spec
BUILTIN_ESTIMATOR = "builtin"


def estimator_path(value: str) -> Path:
    """The file an ``estimator=`` value names: ``builtin``, the package's estimator, or a path."""
    return builtin_config("friction/estimator.json") if value == BUILTIN_ESTIMATOR else Path(value)


def with_estimator(options: dict[str, Any]) -> dict[str, Any]:
    """The slip-feedback options ``options`` (a spec's, ``controller_registry.parse_controller_spec``) with the friction
    estimator they name loaded in place of its name (ConfigError naming the file where it is missing or not one) and the
    initial grip, unless given, its probe grip; ``options`` unchanged where they name none."""
    if "friction_estimator" not in options:
        return options
    est = FrictionEstimator.load(estimator_path(str(options["friction_estimator"])))
    return {"initial_force_N": est.probe_force_N, **options, "friction_estimator": est}


def closing_features(frames: np.ndarray) -> np.ndarray:
    """The features (N_FEATURES,) of the observation frames ``frames`` (T, N_OBS), T >= 1, seen while the jaws
    closed (the last one when the estimate is made)."""
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim != 2 or frames.shape[1] != N_OBS or len(frames) < 1:
        raise ValueError(f"frames must be (T >= 1, {N_OBS}), got {frames.shape}")
    recent = frames[-RECENT_FRAMES:]
    out = []
    for name in FEATURE_GROUPS:
        g = obs_group(name)
        out += [recent[:, g].mean(axis=0), recent[:, g].max(axis=0), frames[:, g].mean(axis=0)]
    return np.concatenate([*out, [float(len(frames))]])


def fit_ridge(features: np.ndarray, mu: np.ndarray, ridge: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ridge regression of log mu on standardised features: (mean, scale, weights with the intercept last)."""
    x = np.asarray(features, dtype=np.float64)
    y = np.log(np.asarray(mu, dtype=np.float64))
    if x.ndim != 2 or len(x) != len(y) or len(y) < 2:
        raise ValueError(f"need (n >= 2, F) features and n values of mu, got {x.shape} and {y.shape}")
    if not ridge > 0:
        raise ValueError(f"ridge must be > 0, got {ridge!r}")
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-9
    a = np.c_[(x - mean) / scale, np.ones(len(y))]
    weights = np.linalg.solve(a.T @ a + ridge * np.eye(a.shape[1]), a.T @ y)
    return mean, scale, weights


@dataclasses.dataclass(frozen=True)
class FrictionEstimator:
    """A fitted friction estimate and the minimal fixed force per mu at its pull speed."""

    feature_mean: tuple[float, ...]
    feature_scale: tuple[float, ...]
    weights: tuple[float, ...]  # one per feature, then the intercept (log mu)
    probe_force_N: float  # the grip the jaws close to while the features are seen, N
    pull: float  # the pull speed the force table is for (a fraction of the arm's top speed)
    mu_grid: tuple[float, ...]
    minimal_force_N: tuple[float, ...]  # the oracle's minimal fixed force at each mu of mu_grid and this pull, N
    fitted_on: str = ""  # what it was fitted on (the training config, episodes, seeds)

    def __post_init__(self) -> None:
        n = len(self.feature_mean)
        if n != N_FEATURES or len(self.feature_scale) != n or len(self.weights) != n + 1:
            raise ConfigError(f"friction estimator: feature_mean, feature_scale and weights must have {N_FEATURES}, "
                              f"{N_FEATURES} and {N_FEATURES + 1} entries, got {n}, {len(self.feature_scale)} and "
                              f"{len(self.weights)}")
        if len(self.mu_grid) < 2 or len(self.minimal_force_N) != len(self.mu_grid) or list(self.mu_grid) != sorted(
                set(self.mu_grid)) or min(self.mu_grid) <= 0 or min(self.minimal_force_N) <= 0:
            raise ConfigError("friction estimator: mu_grid must rise strictly from > 0, with one minimal_force_N > 0 "
                              "per entry")
        if not self.probe_force_N > 0 or not 0 < self.pull <= 1:
            raise ConfigError(f"friction estimator: probe_force_N must be > 0 and pull in (0, 1], got "
                              f"{self.probe_force_N!r} and {self.pull!r}")

    def mu(self, features: np.ndarray) -> float:
        """The friction estimated from ``closing_features``, held inside mu_grid."""
        x = (np.asarray(features, dtype=np.float64) - self.feature_mean) / np.asarray(self.feature_scale)
        log_mu = float(x @ np.asarray(self.weights[:-1]) + self.weights[-1])
        return float(np.clip(math.exp(log_mu), self.mu_grid[0], self.mu_grid[-1]))

    def grip_N(self, mu: float) -> float:
        """The minimal fixed force at ``mu`` (log-log interpolation of the table), N."""
        return float(np.exp(np.interp(np.log(mu), np.log(self.mu_grid), np.log(self.minimal_force_N))))

    def save(self, path: str | Path) -> Path:
        data = {"format": FORMAT, **dataclasses.asdict(self)}
        return atomic_write_text(path, json.dumps(data, indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> FrictionEstimator:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"friction estimator {path}: no such file (make one with msdgrasp fit-friction)")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ConfigError(f"friction estimator {path}: not JSON ({exc})") from None
        if not isinstance(data, dict) or data.pop("format", None) != FORMAT:
            raise ConfigError(f"friction estimator {path}: format must be {FORMAT!r}")
        fields = {f.name for f in dataclasses.fields(cls)}
        if set(data) - fields or {f for f in fields if f != "fitted_on"} - set(data):
            raise ConfigError(f"friction estimator {path}: fields must be {sorted(fields)}, got {sorted(data)}")
        try:
            return cls(**{k: (tuple(float(v) for v in data[k]) if isinstance(data[k], list) else data[k])
                          for k in data})
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
