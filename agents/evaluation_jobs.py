"""The evaluation driver: an evaluation's episodes as one list of jobs, run in this process, in local worker processes
or on Ray (:mod:`.parallel`), with the same numbers wherever they run.

``msdgrasp evaluate`` (:func:`.evaluation.evaluate`) and the robustness suite (:func:`.robustness.run_suite`) build a
:class:`JobList` and run it; what they do with the results (summaries, ratios, files, plots) is theirs. A job is a
module-level function and its arguments, so that it pickles: a policy travels as its :data:`PolicyPayload` (a
controller's spec, or a model's files as bytes: no shared disk needed) and is rebuilt in the job for the job's task;
a task travels as its config's dict. Each episode's result depends on its seed and task alone, never on the batch it
runs in or the process it runs on (:func:`.rollout.evaluate_policy`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import Any

from ..envs.core import GraspLiftConfig
from ..physics.config import from_dict, to_dict
from .controllers import OraclePolicy, is_controller, make_policy, minimal_force
from .learners.base import learner_of_model
from .parallel import Job, Runner, run_jobs
from .rollout import evaluate_policy

#: a policy as a job gets it: its spec or its model's file name, its display name, and its model's files by name
#: (None: a controller, rebuilt from its spec)
PolicyPayload = tuple[str, str, dict[str, bytes] | None]


def policy_payload(spec: str, name: str) -> PolicyPayload:
    """What a job needs to rebuild a policy on any machine: a controller's spec, or the model's files (the model
    and the file that records its learner and config, :meth:`~.learners.Learner.model_files`)."""
    if is_controller(spec):
        return spec, name, None
    path = Path(spec)
    files = learner_of_model(path).model_files(path)
    return path.name, name, {n: p.read_bytes() for n, p in files.items()}


def policy_of(payload: PolicyPayload, config: GraspLiftConfig) -> Any:
    """The policy of ``payload`` on the task ``config`` (a model from its files, loaded into memory)."""
    spec, name, files = payload
    if files is None:
        return make_policy(spec, config)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="msdgrasp-model-") as tmp:
        for file_name, data in files.items():
            (Path(tmp) / file_name).write_bytes(data)
        path = Path(tmp) / spec
        # loaded into memory: the folder may go
        return learner_of_model(path).load_policy(path, name)


def _config(config: GraspLiftConfig | dict[str, Any]) -> GraspLiftConfig:
    return from_dict(GraspLiftConfig, config, where="env") if isinstance(config, dict) else config


def rows_job(payload: PolicyPayload, config: GraspLiftConfig | dict[str, Any], mus: Sequence[float], episodes: int,
             seed: int, n_envs: int | None = None, options: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """One row per mu of ``mus`` (:func:`.rollout.evaluate_policy`) for the policy of ``payload``, built for the task
    ``config``, with reset ``options``."""
    config = _config(config)
    return evaluate_policy(policy_of(payload, config), list(mus), episodes, config, seed, n_envs,
                           options=options or None)


def minimal_force_job(config: GraspLiftConfig | dict[str, Any], mu: float) -> float:
    """The oracle's minimal slip-free fixed force at ``mu`` on the task ``config``, N (bisection, cached)."""
    config = _config(config)
    ref = OraclePolicy(config)
    # the same rounding, pull and tolerance as OraclePolicy.reset: shares its cache
    return float(minimal_force(config, round(float(mu), 3), ref.pull, ref.tolerance))


def curve_record(config: GraspLiftConfig, mus: Sequence[float], forces: Sequence[float]) -> dict[str, Any]:
    """The oracle's minimal-force curve as an evaluation records it: per mu its force, and the oracle's settings."""
    ref = OraclePolicy(config)
    return {"mu": [float(m) for m in mus], "minimal_force_N": [float(f) for f in forces], "oracle_margin": ref.margin,
            "pull": ref.pull, "tolerance_N": ref.tolerance,
            # the bisection's upper end: a minimal force equal to it means no force up to it holds
            "search_limit_N": 2.0 * config.reference_force_N}


def timed_call(fn: Callable[..., Any], *args: Any) -> tuple[float, Any]:
    """(seconds, ``fn(*args)``): a job's own run time, wherever it runs."""
    t0 = time.perf_counter()
    result = fn(*args)
    return time.perf_counter() - t0, result


@dataclasses.dataclass
class JobList:
    """Jobs, each with a tag saying what it is (a policy's cell, an oracle force, ...), run in their order's results.

    :meth:`run` runs them in this process one after the other (no runner) or on ``runner`` (local processes or Ray),
    and returns ``(tag, result)`` per job in the order they were added; :attr:`seconds` holds each job's run time."""

    jobs: list[Job] = dataclasses.field(default_factory=list)
    tags: list[Hashable] = dataclasses.field(default_factory=list)
    seconds: list[float] = dataclasses.field(default_factory=list)

    def add(self, tag: Hashable, fn: Callable[..., Any], *args: Any) -> None:
        """Add the job ``fn(*args)`` (``fn`` module-level, its arguments picklable) under ``tag``."""
        self.jobs.append((timed_call, (fn, *args)))
        self.tags.append(tag)

    def run(self, runner: Runner | None = None,
            on_done: Callable[[Hashable, Any], None] | None = None) -> list[tuple[Hashable, Any]]:
        """Run every job; ``on_done(tag, result)`` as each finishes (in completion order)."""

        def done(k: int, timed: tuple[float, Any]) -> None:
            if on_done is not None:
                on_done(self.tags[k], timed[1])

        with runner or contextlib.nullcontext():
            out = run_jobs(self.jobs, runner, done)
        self.seconds = [s for s, _ in out]
        return [(tag, result) for tag, (_, result) in zip(self.tags, out)]

    def add_rows(self, tag: Hashable, payload: PolicyPayload, config: GraspLiftConfig, mus: Sequence[float],
                 episodes: int, seed: int, n_envs: int | None = None, options: dict[str, float] | None = None) -> None:
        """Add a :func:`rows_job`: the policy of ``payload`` on ``mus`` of the task ``config``."""
        self.add(tag, rows_job, payload, to_dict(config), [float(m) for m in mus], int(episodes), int(seed), n_envs,
                 dict(options) if options else None)

    def add_minimal_forces(self, tag: Callable[[float], Hashable], config: GraspLiftConfig,
                           mus: Sequence[float]) -> None:
        """Add a :func:`minimal_force_job` per mu of ``mus`` on the task ``config``, tagged ``tag(mu)``."""
        data = to_dict(config)
        for mu in mus:
            self.add(tag(float(mu)), minimal_force_job, data, float(mu))
