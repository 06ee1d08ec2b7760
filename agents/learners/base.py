"""The learner interface and the registry (no learner here: :mod:`.sb3` and :mod:`.rsl` register theirs
when the package :mod:`msdgrasp.agents.learners` is imported, which importing this module does first)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

from ...physics.config import ConfigError

if TYPE_CHECKING:
    import numpy as np

    from ...envs.core import GraspLiftConfig


class Policy(Protocol):
    """What evaluation and recording run: a batch of observations in, a batch of actions out."""

    name: str

    def reset(self, infos: Any) -> None: ...

    def act(self, obs: "np.ndarray") -> "np.ndarray": ...


class RunLayout(NamedTuple):
    """The files a learner writes into a run folder (names relative to the run)."""

    #: the model a finished run ships (what evaluate, record and report use)
    model: str
    #: the model shipped where the run kept no best one (training without validation); None: ``model`` always
    fallback_model: str | None
    #: the training summary, written last (its presence means the run finished)
    summary: str
    #: the file that records the run's learner and config
    config: str
    #: how a checkpoint is named, ``{}`` for its step or iteration number (relative to the run)
    checkpoint: str
    #: a saved model's file suffix and the file beside it that records its learner and config, for messages
    model_description: str


class RunSummary(NamedTuple):
    """The learner-independent part of a training summary (what the multi-seed report shows)."""

    train_s: float
    agent_steps: int
    agent_steps_per_s: float | None


class TrainOverrides(NamedTuple):
    """Command-line settings over a training config (None: the config's)."""

    #: the learner named on the command line (None: the one the config names, where a config names one)
    learner: str | None = None
    seed: int | None = None
    n_envs: int | None = None
    total_timesteps: int | None = None
    backend: str | None = None


class Learner(ABC):
    """One learner. Subclasses fill the class attributes and the methods; :func:`register` makes it known."""

    #: the name the CLI and the run's files use
    name: str
    #: where the task may run: "cpu" (numba, host arrays), "cuda" (the GPU task)
    backends: tuple[str, ...]
    #: where ``msdgrasp train`` writes without ``--out``
    default_out: Path
    layout: RunLayout
    #: whether ``train --resume`` can continue one of its runs
    can_resume: bool = False
    #: whether its seeds train as parallel jobs (False: one after the other, e.g. on the one GPU)
    parallel_seeds: bool = True

    # ---- training -------------------------------------------------------------------------------

    @abstractmethod
    def owns_config(self, config: Any) -> bool:
        """Whether ``config`` is a training config of this learner."""

    def one_core(self, config: Any) -> Any:
        """``config`` for a job that gets one CPU core (parallel seeds: the jobs are the parallelism): a config with a
        ``torch_threads`` field runs torch on one thread, which a larger setting would otherwise override."""
        import dataclasses

        if dataclasses.is_dataclass(config) and "torch_threads" in {f.name for f in dataclasses.fields(config)}:
            return dataclasses.replace(config, torch_threads=1)
        return config

    def resume_config(self, run: Path, overrides: TrainOverrides) -> Any:
        """The config to continue run ``run`` with (only where ``can_resume``)."""
        raise ConfigError(f"--resume {run}: learner {self.name} cannot continue a run; train a new one")

    def check_inputs(self, config: Any) -> None:
        """ConfigError for a file that the run of ``config`` reads and that is missing (checked for every seed of a
        multi-seed run before its first job, so that no seed trains when another cannot start)."""

    def check_available(self) -> None:
        """Raise ImportError naming the missing package where the learner's dependencies are not installed."""

    @abstractmethod
    def make_config(self, path: Path | None, overrides: TrainOverrides) -> Any:
        """The validated training config: the file at ``path`` (None: the learner's built-in default) with
        ``overrides``; ConfigError for an override this learner does not take, before anything is written."""

    @abstractmethod
    def config_from_dict(self, data: Mapping[str, Any], where: str) -> Any:
        """A training config from plain data (as a job receives it); ConfigError naming ``where``."""

    def config_of_run(self, run: Path, overrides: Mapping[str, Any] | None = None) -> Any:
        """The training config recorded in run folder ``run`` with ``overrides`` (plain keys)."""
        return self.config_from_dict({**self.config_dict_of_run(run), **(overrides or {})},
                                     where=str(run / self.layout.config))

    @abstractmethod
    def config_dict_of_run(self, run: Path) -> dict[str, Any]:
        """The training config recorded in run folder ``run`` (the one it trained with), as plain data."""

    @abstractmethod
    def config_dict_of_model(self, model: Path) -> dict[str, Any]:
        """The training config recorded beside a saved model (after ``msdgrasp select``: with the validation
        settings that picked it), as plain data."""

    @abstractmethod
    def train(self, config: Any, out_dir: Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
        """Train (``resume``: continue the run in ``out_dir``); returns the run's summary (also written to
        ``layout.summary``)."""

    def run_summary(self, run: Path) -> RunSummary:
        """Training time and steps of the finished run ``run`` (ConfigError: it did not finish): by default its
        summary's ``train_s``, ``agent_steps`` and ``agent_steps_per_s``."""
        import json

        path = run / self.layout.summary
        if not path.is_file():
            raise ConfigError(f"{path} is missing: the run did not finish (its training summary is written last)")
        s = json.loads(path.read_text())
        return RunSummary(s["train_s"], s["agent_steps"], s["agent_steps_per_s"])

    # ---- models -----------------------------------------------------------------------------------

    @staticmethod
    @abstractmethod
    def recorded_learner(path: Path) -> str | None:
        """The learner name recorded beside model or in run folder ``path`` by this learner's layout; None
        where ``path`` is not of this layout. ConfigError where it is, but the record is missing or broken
        (the message names the missing file). Reads small text files only, never the model."""

    @abstractmethod
    def load_policy(self, model: Path, name: str | None = None) -> Policy:
        """The saved model as a deterministic policy (ConfigError: missing or corrupt)."""

    @abstractmethod
    def model_task(self, model: Path) -> "GraspLiftConfig":
        """The task (env config) the model was trained on."""

    def model_training_task(self, model: Path) -> "GraspLiftConfig":
        """The task the training drew its episodes from (its domain randomisation in place of the task's own); the
        model's task where the learner has no randomisation of its own."""
        return self.model_task(model)

    @abstractmethod
    def model_files(self, model: Path) -> dict[str, Path]:
        """The files a copy of the model needs elsewhere (a job on another machine), by the file name each
        must have there: the model and the file recording its learner and config."""

    def config_file(self, model: Path) -> Path:
        """The file recording the model's learner and training config."""
        return next(p for n, p in self.model_files(model).items() if n != Path(model).name)

    def shipped_model(self, run: Path) -> Path | None:
        """The model run folder ``run`` ships, or None where it has none."""
        for name in (self.layout.model, self.layout.fallback_model):
            if name is not None and (run / name).is_file():
                return run / name
        return None

    # ---- selection --------------------------------------------------------------------------------

    @abstractmethod
    def checkpoints(self, run: Path, config: Any) -> list[tuple[int, Path]]:
        """The run's validatable models in training order: (step or iteration, path)."""

    @abstractmethod
    def select(self, config: Any, checkpoints: list[tuple[int, Path]], out: Path) -> dict[str, Any]:
        """Validate ``checkpoints`` with ``config``'s validation settings, ship the best into ``out`` as the
        run's model (``layout.model`` and its config file, ``validation.json``); returns the entries the
        run's summary gets for the new pick."""

    def run_files(self, run: Path, checkpoints: list[tuple[int, Path]]) -> list[Path]:
        """The files of ``run`` that a selection reads (its config, summary, every checkpoint and its record)."""
        files = [run / self.layout.config, run / self.layout.summary]
        for _, path in checkpoints:
            files += [path, self.config_file(path)]
        return list(dict.fromkeys(files))


def read_model_record(model: str | Path, learner: str | None, required: tuple[str, ...], what: str,
                      learner_optional: bool = False) -> dict[str, Any]:
    """The ``.json`` beside a saved model (``<name>.pt`` -> ``<name>.json``): ConfigError naming the model and the file
    where it is missing, lacks an entry of ``required`` (``"config.env"``: a nested one), or records a learner other
    than ``learner`` (None: any; ``learner_optional``: a record without one is ``learner``'s). ``what``: the model's
    kind, for messages."""
    import json

    model = Path(model)
    meta = model.with_suffix(".json")
    if not meta.is_file():
        raise ConfigError(f"model {model}: {meta.name} is missing beside it (the {what}'s learner, observation layout "
                          "and training config); a model is only run on the task it was trained on")
    try:
        data = json.loads(meta.read_text())
        for key in required:
            node = data
            for part in key.split("."):
                node = node[part]
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"model {model}: {meta.name} is not a {what}'s description ({exc!r})") from None
    recorded = data.get("learner", learner if learner_optional else None)
    if learner is not None and recorded != learner:
        raise ConfigError(f"model {model}: {meta.name} records learner {recorded!r}, not {learner!r}")
    return data


def read_train_yaml(path: Path) -> dict[str, Any]:
    """A training YAML's data, its ``extends:`` chain merged, each file's ``env:`` tissue / grasper files resolved
    against that file's folder (a config and the files it names move together)."""
    from ...physics.config import read_extending_yaml
    from ...physics.scenario import resolve_scene_paths

    def resolve(data: dict[str, Any], file: Path) -> dict[str, Any]:
        if "env" in data:
            data["env"] = resolve_scene_paths(data["env"], file)
        return data

    return read_extending_yaml(path, prepare=resolve)


def check_env_files(config: Any, path: Path) -> Any:
    """``config`` after its env's tissue and grasper files are loaded strictly (one ConfigError line naming
    ``path``), so a bad file fails before a run writes anything."""
    from ...physics.scenario import check_scene_files

    check_scene_files(config.env.tissue_config, config.env.grasper_config, f"{path}:env")
    return config


def numbered_files(run: Path, template: str) -> list[tuple[int, Path]]:
    """The files of ``run`` named by ``template`` (a layout's ``checkpoint``), by their number."""
    import re

    rel = Path(template)
    pattern = re.escape(rel.name).replace(re.escape("{}"), r"(\d+)")
    found = []
    for p in (run / rel.parent).glob("*"):
        m = re.fullmatch(pattern, p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


_REGISTRY: dict[str, Learner] = {}


def register(learner: Learner) -> Learner:
    """Make ``learner`` known by its name (a second learner of one name is an error)."""
    if learner.name in _REGISTRY:
        raise ValueError(f"learner {learner.name!r} is registered twice")
    _REGISTRY[learner.name] = learner
    return learner


def learner_names() -> tuple[str, ...]:
    """The registered learners' names, in registration order."""
    return tuple(_REGISTRY)


def get_learner(name: str) -> Learner:
    """The learner called ``name``; ConfigError listing the known ones otherwise."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown learner {name!r}; known learners: {', '.join(_REGISTRY)}") from None


#: the learner of ``msdgrasp train`` without --learner, where the config names none and the backend allows it
DEFAULT = "ppo"


def default_learner(backend: str | None, preferred: str = DEFAULT) -> Learner:
    """``preferred`` where it runs on ``backend`` (None: any), else the first registered learner that does."""
    if backend is None or backend in get_learner(preferred).backends:
        return get_learner(preferred)
    for learner in _REGISTRY.values():
        if backend in learner.backends:
            return learner
    raise ConfigError(f"no learner runs on backend {backend!r}")


def _families() -> list[Learner]:
    """One learner per layout (learners sharing a class share how they record themselves)."""
    seen: dict[type, Learner] = {}
    for learner in _REGISTRY.values():
        seen.setdefault(type(learner), learner)
    return list(seen.values())


def _recorded(path: Path) -> str | None:
    names = {n for fam in _families() if (n := fam.recorded_learner(path)) is not None}
    if len(names) > 1:  # (layouts are disjoint; two claims would be a bug in a learner module)
        raise ConfigError(f"{path}: claimed by several learners ({', '.join(sorted(names))})")
    return names.pop() if names else None


def model_kinds() -> str:
    """What a saved model of each learner looks like, for messages."""
    return "; ".join(f"{', '.join(n for n, learner in _REGISTRY.items() if type(learner) is type(fam))}: "
                     f"{fam.layout.model_description}" for fam in _families())


def learner_of_model(path: str | Path) -> Learner:
    """The learner that wrote model file ``path``, by the learner name recorded beside it (ConfigError naming
    the model and the missing file where nothing is recorded)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"model file not found: {path}")
    name = _recorded(path)
    if name is None:
        raise ConfigError(f"model {path}: not a saved model of a known learner ({model_kinds()})")
    return get_learner(name)


def learner_of_run(path: str | Path, required: bool = True) -> Learner | None:
    """The learner of run folder ``path``, by the learner name its files record (ConfigError otherwise;
    ``required=False``: None where no learner's record is there)."""
    path = Path(path)
    if not path.is_dir():
        raise ConfigError(f"{path} is not a folder")
    name = _recorded(path)
    if name is None and not required:
        return None
    if name is None:
        raise ConfigError(f"{path} is not a training run (no "
                          + " or ".join(fam.layout.config for fam in _families()) + " of a known learner there)")
    return get_learner(name)


def learner_of_config(config: Any) -> Learner:
    """The learner a training config belongs to."""
    for learner in _REGISTRY.values():
        if learner.owns_config(config):
            return learner
    raise ConfigError(f"no learner trains a {type(config).__name__}")
