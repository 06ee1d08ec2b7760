"""Model selection again, on a finished run's saved checkpoints: ``msdgrasp select``.

Training validates every checkpoint as it goes and ships the best (:class:`~.training.BestModel`: success,
then the reward's force charge). The checkpoints stay on disk, so the choice can be made again with other
validation settings (more episodes per mu, other mu) without training again: validation costs minutes where
training costs half an hour per seed. The result is a run folder of its own, beside the original (which is
never touched), in the layout its learner writes:

* a torch PPO run (``train --learner rsl``: ``policy.json``, ``checkpoints/policy_<iteration>.pt``):
  ``policy.pt`` / ``policy.json``, ``validation.json`` and ``summary.json`` (the run's, with the new
  selection), so ``msdgrasp report`` and ``msdgrasp evaluate`` read it like a trained run;
* an SB3 run (``train``: ``config.yaml``, ``checkpoints/model_<steps>.zip``, ``final_model.zip``):
  ``best_model.zip`` / ``best_model.yaml``, ``validation.json`` and ``train_summary.json`` (the run's, with the
  new pick), so ``msdgrasp evaluate`` and ``msdgrasp report`` read it like a trained run.

Both also get ``selection.json``: where the checkpoints came from, the validation settings and the pick.
A folder of seeds (``seed_<k>/`` runs, what ``--seeds`` writes) is selected seed by seed into
``OUT/seed_<k>/``, each seed a job on a :class:`~.parallel.Runner`: local processes, or Ray tasks (``--ray`` /
``--address``). A Ray task may run on a node that cannot read the run's files, so on Ray each job gets the
files the selection reads (checkpoints, their configs, the training summary: a few MB) as an archive, and
its pick lands in ``OUT`` as a training run's does (:func:`~.parallel.run_in_folder`); the paths it records
name the run's own checkpoints either way.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..physics.config import ConfigError, atomic_write_text
from .learners.base import get_learner, learner_of_run, numbered_files
from .parallel import Runner, land, move_paths, pack, run_in_folder, unpack


@dataclass(frozen=True)
class SelectionPlan:
    """One run to select again: its learner's name (:func:`~.learners.get_learner`), the config with the new
    validation settings, its checkpoints in training order: (iteration or agent steps, path), and its
    training summary (written last: the run finished)."""

    run: Path
    learner: str
    config: Any
    checkpoints: tuple[tuple[int, Path], ...]
    summary: Path


def plan_selection(run: str | Path, validation_episodes: int | None = None,
                   validation_mu: Sequence[float] | None = None,
                   numbers: tuple[int, int] | None = None) -> SelectionPlan:
    """Read run folder ``run`` and check it can be selected again with the given validation settings (None:
    the run's own), among the checkpoints numbered ``numbers`` (first, last; None: all of them: e.g. a recurrent
    run's DAgger stage alone); raises :class:`ConfigError` naming what is wrong, before anything runs."""
    run = Path(run)
    if not run.is_dir():
        raise ConfigError(f"select: {run} is not a folder")
    overrides: dict[str, Any] = {}
    if validation_episodes is not None:
        if isinstance(validation_episodes, bool) or not isinstance(validation_episodes, int) or validation_episodes < 1:
            raise ConfigError(f"validation_episodes must be an integer >= 1, got {validation_episodes!r}")
        overrides["validation_episodes"] = validation_episodes
    if validation_mu is not None:
        if not validation_mu:
            raise ConfigError("validation_mu must name at least one friction coefficient")
        overrides["validation_mu"] = [float(m) for m in validation_mu]
    try:
        learner = learner_of_run(run)
    except ConfigError as exc:
        raise ConfigError(f"select: {exc}") from None
    layout = learner.layout
    if not (run / layout.config).is_file():  # (a pick of msdgrasp select has no training config of its own)
        raise ConfigError(f"select: {run} is not a training run (no {layout.config} of learner {learner.name})")
    config = learner.config_of_run(run, overrides)
    checkpoints = learner.checkpoints(run, config)
    if numbers is not None:
        checkpoints = [(k, p) for k, p in checkpoints if numbers[0] <= k <= numbers[1]]
    if not checkpoints:
        within = "" if numbers is None else f" numbered {numbers[0]}-{numbers[1]}"
        raise ConfigError(f"select: {run} has no {layout.checkpoint.format('<number>')}{within} to validate")
    if config.validation_episodes < 1:
        raise ConfigError(f"select: {run} was trained without validation; give validation_episodes >= 1")
    summary = run / layout.summary
    if not summary.is_file():
        raise ConfigError(f"select: {summary} is missing: the run did not finish "
                          "(its training summary is written last)")
    return SelectionPlan(run, learner.name, config, tuple(checkpoints), summary)


def _check_out(plan: SelectionPlan, out: Path) -> None:
    if out.resolve() == plan.run.resolve():
        raise ConfigError(f"select: --out {out} is the run itself; the run's own pick is kept, give another folder")
    if (out / "checkpoints").is_dir():  # (its pick would be overwritten by another run's)
        raise ConfigError(f"select: --out {out} is a training run of its own (it has checkpoints/); "
                          "give another folder")


def select_run(plan: SelectionPlan, out: str | Path) -> dict[str, Any]:
    """Validate every checkpoint of ``plan`` and write the pick into ``out`` (see the module docstring).
    Returns what ``selection.json`` holds."""
    out = Path(out)
    _check_out(plan, out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    picked = get_learner(plan.learner).select(plan.config, list(plan.checkpoints), out)
    summary = {**json.loads(plan.summary.read_text()), **picked}
    # the run's training summary (same file name) with the new pick, as report and evaluate read it
    atomic_write_text(out / plan.summary.name, json.dumps({**summary, "selected_from": str(plan.run)}, indent=2))
    best = json.loads((out / "validation.json").read_text())["best"]
    result = {"run": str(plan.run), "learner": plan.learner, "validation_episodes": plan.config.validation_episodes,
              "validation_mu": list(plan.config.validation_mu), "checkpoints_validated": len(plan.checkpoints),
              "best": best, "selection_s": round(time.perf_counter() - t0, 1)}
    atomic_write_text(out / "selection.json", json.dumps(result, indent=2))
    return result


def seed_runs(folder: Path) -> list[tuple[int, Path]]:
    """The ``seed_<k>/`` runs in ``folder`` (what ``train --seeds`` writes), by seed."""
    return numbered_files(folder, SEED_RUN) if folder.is_dir() else []


def _run_files(plan: SelectionPlan) -> list[Path]:
    """The files of ``plan.run`` that the selection reads: the run's config and summary, every checkpoint
    and the file that records its learner and config."""
    return get_learner(plan.learner).run_files(plan.run, list(plan.checkpoints))


def pack_run(plan: SelectionPlan) -> bytes:
    """:func:`_run_files` of ``plan`` as a tar.gz archive, paths relative to the run."""
    return pack(plan.run, _run_files(plan))


def _select_job(out: str, plan: SelectionPlan, archive: bytes | None) -> dict[str, Any]:
    """One run's selection as a job: from the run's own files, or (``archive``: :func:`pack_run`) from a copy
    unpacked here, with every path it records moved back to the run's."""
    if archive is None:
        return select_run(plan, out)
    with tempfile.TemporaryDirectory(prefix="msdgrasp-run-") as tmp:
        unpack(archive, tmp)
        here = Path(tmp)
        copy = dataclasses.replace(plan, run=here, summary=here / plan.summary.relative_to(plan.run),
                                   checkpoints=tuple((k, here / p.relative_to(plan.run)) for k, p in plan.checkpoints))
        result = select_run(copy, out)
    return move_paths(result, out, tmp, str(plan.run))


def select(run: str | Path, out: str | Path, validation_episodes: int | None = None,
           validation_mu: Sequence[float] | None = None, workers: int | None = None,
           runner: Runner | None = None, numbers: tuple[int, int] | None = None) -> list[dict[str, Any]]:
    """Select again in run folder ``run``, or in each ``seed_<k>/`` run of it (into ``out/seed_<k>``), each
    run a job on ``runner`` (default: ``workers`` local processes; one run without a runner: this process).
    Every run is checked before the first is validated."""
    run, out = Path(run), Path(out)
    mu = None if validation_mu is None else [float(m) for m in validation_mu]
    seeds = seed_runs(run) if learner_of_run(run, required=False) is None else []
    if seeds:
        if out.resolve() == run.resolve():
            raise ConfigError(f"select: --out {out} is the runs' own folder; give another folder")
        plans = [plan_selection(d, validation_episodes, mu, numbers) for _, d in seeds]  # all valid, or none runs
        outs = [out / f"seed_{k}" for k, _ in seeds]
    else:
        plans, outs = [plan_selection(run, validation_episodes, mu, numbers)], [out]
    for plan, folder in zip(plans, outs):
        _check_out(plan, folder)
    if runner is None and len(plans) == 1:
        return [select_run(plans[0], out)]
    with runner or Runner.processes(workers) as live:
        # a Ray task may land on a node without the run's files: it gets them with the job
        jobs = [(run_in_folder,
                 (_select_job, str(folder), live.driver_node, plan, pack_run(plan) if live.is_ray else None))
                for plan, folder in zip(plans, outs)]
        return [land(res, folder) for res, folder in zip(live.run(jobs), outs)]


#: the folder of one seed's run in a folder of seeds
SEED_RUN = "seed_{}"

__all__ = ["SelectionPlan", "pack_run", "plan_selection", "select", "select_run", "seed_runs"]
