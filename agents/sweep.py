"""Hyper-parameter sweeps: a grid of training configs, every point trained over several seeds.

``msdgrasp sweep SWEEP.yaml`` (``--ray`` / ``--address`` to run the jobs on Ray, :mod:`.parallel`) reads a
:class:`SweepConfig`::

    base: train/ppo.yaml            # a built-in training config, or a file path relative to this sweep file
    set: {total_timesteps: 300000}  # dotted keys applied to every point
    grid:                           # dotted keys -> values; every combination is one point
      ppo.learning_rate: [1.0e-4, 3.0e-4]
      log_std_init: [-1.0, -2.0]
    seeds: 0-4                      # every point trains these seeds (>= 5 for a result)
    episodes: 10                    # evaluation episodes per mu and seed
    evaluation_seed: 0              # evaluation episode i is reset with evaluation_seed + i

Every point's config is built (and so validated) before any job starts: a bad key or value is a one-line
error naming the point. All points x seeds are independent jobs, run together; each point's seeds land in
``<out>/point_<k>/`` with the same report as ``msdgrasp train --seeds`` (seeds.json, seeds.md,
learning_curves.png), and the sweep's own ``sweep.json`` / ``sweep.md`` rank the points by the mean over
seeds of success over mu 0.3-0.9, then by peak pinch relative to the oracle's minimal force.

A sweep tunes on what it measures, so none of its seeds may reach the sealed evaluation seeds (:mod:`.protocol`):
neither a point's training seeds (its envs, validation and demonstrations) nor its evaluation's; every one is checked
before a job starts, and the reports record the evaluation's seeds as not sealed.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import time
from pathlib import Path
from typing import Annotated, Any

from annotated_types import Ge, Le, MinLen
from pydantic import Field

from ..physics.config import (ConfigError, Int, Real, Str, atomic_write_text, builtin_config, config_dataclass,
                              from_dict, read_yaml, to_dict)
from .evaluation import nan_to_none
from .learners.base import read_train_yaml
from .models import TrainConfig
from .parallel import Runner
from .protocol import check_not_sealed, seeds_record
from .seeds import (EVAL_MU, REFERENCE_MU, check_run_args, fmt_value, parse_seeds, seeds_line, train_points,
                    write_seed_report)

#: most grid points of one sweep (each trains every seed)
MAX_POINTS = 256


@config_dataclass
class SweepConfig:
    """A hyper-parameter sweep (see the module docstring)."""

    #: the training config every point starts from: a built-in one ("train/ppo.yaml") or a file path
    base: Str = "train/ppo.yaml"
    #: dotted keys set on every point (e.g. total_timesteps, env.reward.slip_per_mm)
    set: dict[Str, Any] = Field(default_factory=dict)
    #: dotted key -> list of values; the points are all combinations (in the order given)
    grid: Annotated[dict[Str, Annotated[list[Any], MinLen(1)]], MinLen(1)] = Field(default_factory=dict)
    #: the seeds every point trains: a range "0-4" or a list "0,3,7"
    seeds: Str = "0-4"
    #: evaluation episodes per mu and seed
    episodes: Annotated[Int, Ge(1)] = 10
    #: evaluation episode i of every point is reset with evaluation_seed + i: development seeds, never the sealed
    #: evaluation seeds (a sweep tunes on them)
    evaluation_seed: Annotated[Int, Ge(0)] = 0
    #: friction values of the evaluation (the headline averages mu 0.3-0.9 among them)
    mu_grid: Annotated[tuple[Annotated[Real, Ge(0), Le(10)], ...], MinLen(1)] = EVAL_MU

    def __post_init__(self) -> None:
        for key in (*self.set, *self.grid):
            if key == "seed" or key.startswith("seed."):
                raise ConfigError(f"sweep key {key!r}: seeds come from the sweep's 'seeds' field, not from a key")
            if not key or any(not part for part in key.split(".")):
                raise ConfigError(f"sweep key {key!r}: expected a dotted key such as 'ppo.learning_rate'")
        both = set(self.set) & set(self.grid)
        if both:
            raise ConfigError(f"sweep keys {sorted(both)} are both in 'set' and in 'grid'; give each once")
        n = 1
        for key, values in self.grid.items():
            twice = [v for i, v in enumerate(values) if v in values[:i]]
            if twice:  # (two identical points would train and rank the same config twice)
                raise ConfigError(f"sweep grid {key!r}: the value {twice[0]!r} is given twice; give each value once")
            n *= len(values)
        if n > MAX_POINTS:
            raise ConfigError(f"the grid has {n} points; allowed 1 ... {MAX_POINTS}")
        parse_seeds(self.seeds)
        check_not_sealed(self.evaluation_seed, self.episodes, "evaluation_seed",
                         via=f"evaluation episodes: evaluation_seed + i, i < episodes = {self.episodes}")

    @classmethod
    def load(cls, path: str | Path) -> "SweepConfig":
        """The sweep file at ``path``; a relative ``base`` that names a file beside it is read from there (a sweep
        and its base config move together), else it names a built-in config."""
        data = read_yaml(path)
        base = data.get("base")
        if isinstance(base, str) and base and not Path(base).is_absolute():
            beside = Path(path).resolve().parent / base
            if beside.is_file():
                data["base"] = str(beside)
        return from_dict(cls, data, where=str(path))


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    *parents, leaf = key.split(".")
    node = data
    for i, part in enumerate(parents):
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        elif not isinstance(child, dict):
            raise ConfigError(f"sweep key {key!r}: {'.'.join(parents[: i + 1])} is a value, not a section")
        node = child
    node[leaf] = value


def _base_path(base: str) -> Path:
    """An absolute base is that file; a relative one a built-in config (``SweepConfig.load`` has already made a
    base beside the sweep file absolute): never a file found through the current directory."""
    path = Path(base)
    if path.is_absolute():
        if not path.is_file():
            raise ConfigError(f"sweep base: config file not found: {path}")
        return path
    return builtin_config(base)


def sweep_points(sweep: SweepConfig, where: str = "sweep") -> list[tuple[dict[str, Any], TrainConfig]]:
    """Every grid point: (its values by dotted key, its validated TrainConfig); each point is valid with every seed of
    the sweep (none reaches the sealed evaluation seeds)."""
    base = read_train_yaml(_base_path(sweep.base))
    for key, value in sweep.set.items():
        _set_dotted(base, key, value)
    keys = list(sweep.grid)
    points = []
    for k, combo in enumerate(itertools.product(*(sweep.grid[key] for key in keys))):
        params = dict(zip(keys, combo))
        data = copy.deepcopy(base)
        for key, value in params.items():
            _set_dotted(data, key, value)
        label = ", ".join(f"{key}={value}" for key, value in params.items())
        config = from_dict(TrainConfig, data, where=f"{where} point {k} ({label})")
        for seed in parse_seeds(sweep.seeds):
            try:
                dataclasses.replace(config, seed=seed)
            except ConfigError as exc:
                raise ConfigError(f"{where} point {k} ({label}), seeds {sweep.seeds}: {exc}") from None
        points.append((params, config))
    return points


def run_sweep(sweep: SweepConfig, out_dir: str | Path, runner: Runner | None = None, *, progress: bool = True,
              where: str = "sweep") -> dict[str, Any]:
    """Train and evaluate every seed of every point; write the per-point reports and sweep.json / sweep.md."""
    out = Path(out_dir)
    seeds = parse_seeds(sweep.seeds)
    points = sweep_points(sweep, where)  # every point validated before anything runs or is written
    check_run_args(out, seeds, sweep.episodes, sweep.evaluation_seed)
    runner = runner or Runner.processes()
    folders = [out / f"point_{k}" for k in range(len(points))]
    t0 = time.perf_counter()
    with runner:
        results = train_points([cfg for _, cfg in points], folders, seeds, runner, episodes=sweep.episodes,
                               mus=sweep.mu_grid, progress=progress, evaluation_seed=sweep.evaluation_seed)
        capacity = runner.capacity()
    wall = round(time.perf_counter() - t0, 1)
    evaluated = seeds_record(sweep.evaluation_seed, sweep.episodes)
    records = []
    for k, ((params, cfg), res, folder) in enumerate(zip(points, results, folders)):
        report = {"config": to_dict(cfg), "training_seeds": seeds, "seeds": evaluated,
                  "episodes_per_mu": sweep.episodes,
                  "mu_grid": [float(m) for m in sweep.mu_grid], "reference_mu": list(REFERENCE_MU),
                  "workers": capacity, "runner": runner.label, "wall_s": wall, **res}
        files = write_seed_report(report, folder)
        records.append({"point": k, "params": params, "folder": str(folder), "files": files,
                        "aggregate": res["aggregate"], "baselines": res["baselines"],
                        "per_seed": [{key: val for key, val in r.items() if key not in ("rows", "validation")}
                                     for r in res["per_seed"]]})
    ranking = sorted(range(len(records)), key=lambda k: _rank_key(records[k]))
    result = {"sweep": to_dict(sweep), "training_seeds": seeds, "seeds": evaluated, "workers": capacity,
              "runner": runner.label, "wall_s": wall, "ranking": ranking, "points": records}
    files = {"json": out / "sweep.json", "md": out / "sweep.md"}
    atomic_write_text(files["json"], json.dumps(nan_to_none(result), indent=2) + "\n")
    atomic_write_text(files["md"], format_sweep_markdown(result))
    result["files"] = {k: str(v) for k, v in files.items()}
    return result


def _rank_key(record: dict[str, Any]) -> tuple[float, float]:
    """Higher mean success over mu 0.3-0.9 first, then lower peak pinch relative to the oracle minimum."""
    agg = record["aggregate"]
    success = agg["success_ref"]["mean"]
    ratio = agg["peak_pinch_over_oracle_min"]["mean"]
    nan_last = float("inf")
    return (-success if success == success else nan_last, ratio if ratio == ratio else nan_last)


def format_sweep_markdown(result: dict[str, Any]) -> str:
    """One row per point (best first): its values and the aggregate over seeds, with the baselines below."""
    points = result["points"]
    keys = list(points[0]["params"]) if points else []
    seeds = result.get("training_seeds", result["seeds"])
    lines = [f"# Sweep: {len(points)} points x {len(seeds)} seeds (seeds {', '.join(map(str, seeds))})", "",
             seeds_line(result.get("seeds")) + " A sweep tunes on these episodes.", "",
             "Mean over seeds [bootstrap 95% CI]; success over mu 0.3-0.9; ratio = mean peak pinch / the oracle's "
             "minimal slip-free force. Ranked by success, then ratio. Per-seed tables: point_<k>/seeds.md.", "",
             "| rank | point | " + " | ".join(keys) + " | success 0.3-0.9 | worst seed | success mu 0.2 "
             "| peak pinch (N) | ratio to oracle min |",
             "|---" * (len(keys) + 7) + "|"]
    for rank, k in enumerate(result["ranking"], 1):
        rec = points[k]
        agg = rec["aggregate"]

        def cell(name: str, digits: int = 3) -> str:
            a = agg[name]
            return (f"{fmt_value(a['mean'], digits)} "
                    f"[{fmt_value(a['ci95'][0], digits)}, {fmt_value(a['ci95'][1], digits)}]")

        lines.append(f"| {rank} | {k} | " + " | ".join(str(rec["params"][key]) for key in keys)
                     + f" | {cell('success_ref')} | {fmt_value(agg['success_ref']['min'])} | {cell('success_mu0.2')} "
                       f"| {cell('peak_pinch_ref_N', 2)} | {cell('peak_pinch_over_oracle_min', 2)} |")
    if points:
        base = points[0]["baselines"]
        lines += ["", "Baselines on the task (point 0's; points that change the task have their own in "
                      "point_<k>/seeds.md):",
                  "", "| policy | success 0.3-0.9 | peak pinch (N) | ratio to oracle min |", "|---|---|---|---|"]
        for name, b in base.items():  # (those the result was made with)
            lines.append(f"| {name} | {fmt_value(b['success_ref'])} | {fmt_value(b['peak_pinch_ref_N'], 2)} "
                         f"| {fmt_value(b['peak_pinch_over_oracle_min'], 2)} |")
    lines += ["", f"Wall time {result['wall_s']:.0f} s, {result['workers']} jobs at a time ({result['runner']})."]
    return "\n".join(lines) + "\n"

