"""Seeds are the unit of a result: train several seeds in parallel processes, evaluate each, aggregate.

``msdgrasp train --seeds 0-4`` runs :func:`run_seeds`: every seed trains with the same config (only the
seed differs) into ``<out>/seed_<k>/`` (see :mod:`.training`), as its own job (``--workers`` local
processes, default one per CPU core, each with one torch thread; or Ray tasks with ``--ray`` / ``--address``,
:mod:`.parallel`); then every seed's ``best_model.zip`` runs
``episodes`` evaluation episodes at every mu of ``mu_grid``, episode i reset with ``evaluation_seed + i``
(default: the sealed evaluation seeds of ``msdgrasp evaluate``, :mod:`.protocol`, which no training or
validation draws from), beside the slip-reactive controller and the oracle. Written into ``<out>``:

* ``seeds.json``: per seed (success per mu, success over the reference range, mean peak pinch and its
  ratio to the oracle's minimal slip-free force, mean time to lift, training time and steps/s) and the aggregate
  over seeds (mean, interquartile mean, min, max and a bootstrap 95% interval of the mean) of each metric; the
  seeds trained (``training_seeds``) and the evaluation's (``seeds``: first, count and whether they are sealed);
* ``seeds.md``: the same as markdown tables;
* ``learning_curves.png``: validation success and mean peak pinch vs training steps, one line per seed.

The "reference range" is mu 0.3 ... 0.9 (the acceptance range of the task, inside the training range);
mu below it (0.2) is reported on its own.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.core import GraspLiftConfig
from ..physics.config import ConfigError, atomic_write_text, from_dict, needs_extra, save_figure, to_dict
from .controllers import baselines, make_policy
from .evaluation import display_name, evaluate_policy, nan_to_none, oracle_curve, task_of
from .learners.base import get_learner, learner_of_config, learner_of_run
from .parallel import Job, Runner, land, run_in_folder
from .reference import references_at
from .protocol import EVALUATION_SEED, check_evaluation_seeds, seeds_record
from .stats import bootstrap_ci, iqm  # noqa: F401  (re-exported)

#: friction values of the per-seed evaluation; REFERENCE_MU are the ones the headline numbers average
EVAL_MU = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
REFERENCE_MU = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
MAX_SEEDS = 64


def parse_seeds(text: str) -> list[int]:
    """'0-4' -> [0, 1, 2, 3, 4]; '0,3,7' -> [0, 3, 7]; '5' -> [5]. ConfigError on anything else."""
    raw = str(text).strip()
    try:
        if "-" in raw[1:]:
            lo_s, hi_s = raw.split("-", 1) if not raw.startswith("-") else (None, None)
            lo, hi = int(lo_s), int(hi_s)
            seeds = None
        else:
            seeds = [int(p) for p in raw.split(",")]
    except (TypeError, ValueError):
        raise ConfigError(f"--seeds {text!r}: expected a range such as '0-4' or a comma list such as '0,3,7' "
                          "of integers >= 0") from None
    if seeds is None:
        if hi - lo >= MAX_SEEDS:  # (before a list of them is built)
            raise ConfigError(f"--seeds {text!r}: between 1 and {MAX_SEEDS} seeds, got {hi - lo + 1}")
        seeds = list(range(lo, hi + 1))
    if "-" in raw[1:] and not seeds:
        raise ConfigError(f"--seeds {text!r}: the range end is below its start")
    if any(s < 0 for s in seeds):
        raise ConfigError(f"--seeds {text!r}: seeds must be integers >= 0")
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {text!r}: a seed is repeated")
    if not 1 <= len(seeds) <= MAX_SEEDS:
        raise ConfigError(f"--seeds {text!r}: between 1 and {MAX_SEEDS} seeds, got {len(seeds)}")
    return seeds


# ------------------------------------------------------------------------------------------------
# statistics (iqm, bootstrap_ci: agents/stats.py)
# ------------------------------------------------------------------------------------------------


def aggregate(values: Sequence[float]) -> dict[str, Any]:
    """mean, IQM, min, max and the bootstrap 95% interval of the mean of per-seed values; a value that is NaN or
    None (a seed with no episode to measure: no lift, no mu 0.2) is left out, and ``n`` counts the others."""
    x = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not x:
        nan = float("nan")
        return {"n": 0, "mean": nan, "iqm": nan, "min": nan, "max": nan, "ci95": [nan, nan]}
    lo, hi = bootstrap_ci(x)
    return {"n": len(x), "mean": float(np.mean(x)), "iqm": iqm(x), "min": float(np.min(x)),
            "max": float(np.max(x)), "ci95": [lo, hi]}


# ------------------------------------------------------------------------------------------------
# one seed (runs in a worker process or a Ray task)
# ------------------------------------------------------------------------------------------------


def _train_and_evaluate(run_dir: str, learner_name: str, config_dict: dict[str, Any], seed: int, episodes: int,
                        mus: Sequence[float], evaluation_seed: int) -> dict[str, Any]:
    learner = get_learner(learner_name)
    config = learner.config_from_dict({**config_dict, "seed": seed}, where="seeds")
    run = Path(run_dir)
    t0 = time.perf_counter()
    learner.train(config, run, progress=False)
    wall = time.perf_counter() - t0
    model = learner.shipped_model(run)  # the validated best, or the final model of a run without validation
    policy = learner.load_policy(model)  # (named by its learner: "PPO (seed 3)", "recurrent gru (seed 3)")
    rows = evaluate_policy(policy, mus, episodes, config.env, evaluation_seed)
    trained = learner.run_summary(run)
    return {"seed": seed, "policy": policy.name, "run": str(run), "model": str(model), "train_wall_s": round(wall, 1),
            "train": {"timesteps": trained.agent_steps, "steps_per_s": trained.agent_steps_per_s}, "rows": rows,
            "validation": _validation_history(run)}


def _validation_history(run: Path) -> list[dict[str, Any]]:
    """The run's validated checkpoints (``validation.json``, either learner), for the learning curves."""
    log = run / "validation.json"
    return json.loads(log.read_text())["history"] if log.is_file() else []


def _baselines(env_dict: dict[str, Any], episodes: int, mus: Sequence[float], evaluation_seed: int) -> dict[str, Any]:
    env = from_dict(GraspLiftConfig, env_dict, where="env")
    out = {name: evaluate_policy(make_policy(name, env), mus, episodes, env, evaluation_seed)
           for name in baselines()}
    out["oracle_minimal_force"] = oracle_curve(env, mus)
    out["reference_force_N"], out["reference"] = references_at(env, mus)
    return out


# ------------------------------------------------------------------------------------------------
# the whole run
# ------------------------------------------------------------------------------------------------


def _row_metrics(rows: list[dict[str, Any]], minimal: dict[float, float],
                 references: dict[str, float | None] | None = None) -> dict[str, Any]:
    ref = [r for r in rows if round(r["mu"], 6) in {round(m, 6) for m in REFERENCE_MU}]
    low = [r for r in rows if round(r["mu"], 6) == 0.2]
    ratio = [r["mean_peak_pinch_N"] / minimal[round(r["mu"], 6)] for r in ref]
    # over the reference force (a slower pull cannot lower it), where the task has a reference table
    force = [r["mean_peak_pinch_N"] / references[f"{r['mu']:g}"] for r in ref
             if (references or {}).get(f"{r['mu']:g}")]
    # (a row's mean over its lifted episodes; NaN, or null read back, where none lifted)
    lift = [r["mean_time_to_lift_s"] for r in ref
            if r["mean_time_to_lift_s"] is not None and math.isfinite(r["mean_time_to_lift_s"])]
    return {
        "success_by_mu": {f"{r['mu']:g}": r["success_rate"] for r in rows},
        "peak_pinch_by_mu": {f"{r['mu']:g}": round(r["mean_peak_pinch_N"], 4) for r in rows},
        "success_ref": float(np.mean([r["success_rate"] for r in ref])) if ref else float("nan"),
        "success_mu0.2": float(low[0]["success_rate"]) if low else float("nan"),
        "peak_pinch_ref_N": float(np.mean([r["mean_peak_pinch_N"] for r in ref])) if ref else float("nan"),
        "peak_pinch_over_oracle_min": float(np.mean(ratio)) if ratio else float("nan"),
        "force_ratio_ref": float(np.mean(force)) if force and len(force) == len(ref) else float("nan"),
        "time_to_lift_ref_s": float(np.mean(lift)) if lift else float("nan"),
    }


#: the per-seed metrics every multi-seed result aggregates
#: (timesteps: the agent steps each seed trained, fewer than total_timesteps where validation_patience stopped it)
AGGREGATED = ("success_ref", "success_mu0.2", "peak_pinch_ref_N", "force_ratio_ref", "peak_pinch_over_oracle_min",
              "time_to_lift_ref_s",
              "train_wall_s", "timesteps")


def check_run_args(out: Path, seeds: Sequence[int], episodes: int, evaluation_seed: int = EVALUATION_SEED) -> None:
    """ConfigError for an output path that is a file, no seed, episodes that are not an integer >= 1 or an
    evaluation seed that is not an integer >= 0."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder")
    if not seeds:
        raise ConfigError("give at least one seed")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    check_evaluation_seeds(evaluation_seed, episodes, "evaluation_seed")


def train_points(configs: Sequence[Any], folders: Sequence[Path], seeds: Sequence[int], runner: Runner,
                 *, episodes: int = 10, mus: Sequence[float] = EVAL_MU, progress: bool = True,
                 evaluation_seed: int = EVALUATION_SEED) -> list[dict[str, Any]]:
    """Train and evaluate every seed of every config (one job each, on ``runner``) into
    ``folders[p]/seed_<k>``, beside the baselines of each distinct task; evaluation episode i is reset with
    ``evaluation_seed + i``. One result per config: the per-seed records, their aggregate, the baselines and the
    oracle's minimal-force curve. Every seed's config is validated (none reaches the sealed evaluation seeds,
    :mod:`.protocol`) before the first job."""
    mus = [float(m) for m in mus]
    for c in configs:  # (every seed's inputs before the first job)
        for s in seeds:
            learner_of_config(c).check_inputs(replace(c, seed=s))
    learners = [learner_of_config(c).name for c in configs]
    # one core per job: the jobs are the parallelism
    cfg_dicts = [to_dict(learner_of_config(c).one_core(c)) for c in configs]
    tasks: list[str] = []  # distinct env configs (a sweep over training settings shares one baseline)
    task_of_point = []
    for c in cfg_dicts:
        key = json.dumps(c["env"], sort_keys=True)
        if key not in tasks:
            tasks.append(key)
        task_of_point.append(tasks.index(key))
    # the baselines first: they take the first slots, then the seeds
    jobs: list[Job] = [(_baselines, (json.loads(t), episodes, mus, evaluation_seed)) for t in tasks]
    where = []
    for p, (cfg, folder) in enumerate(zip(cfg_dicts, folders)):
        for s in seeds:
            run_dir = Path(folder) / f"seed_{s}"
            jobs.append((run_in_folder, (_train_and_evaluate, str(run_dir), runner.driver_node, learners[p], cfg, s,
                                         episodes, mus, evaluation_seed)))
            where.append((p, run_dir))

    def done(k: int, res: Any) -> None:
        if progress and k >= len(tasks):
            m = _row_metrics(res["rows"], {round(x, 6): 1.0 for x in mus})
            label = f"config {where[k - len(tasks)][0]} " if len(configs) > 1 else ""
            print(f"{label}seed {res['seed']}: success {m['success_ref']:.3f} over mu 0.3-0.9, "
                  f"{m['success_mu0.2']:.2f} at mu 0.2, mean peak pinch {m['peak_pinch_ref_N']:.2f} N "
                  f"({res['train_wall_s']:.0f} s training, {res['train']['timesteps']} steps)", file=sys.stderr)

    results = runner.run(jobs, on_done=done)
    bases, seed_results = results[: len(tasks)], results[len(tasks):]
    per_point: list[list[dict[str, Any]]] = [[] for _ in configs]
    for (p, run_dir), res in zip(where, seed_results):
        per_point[p].append(land(res, run_dir))
    return [_point_result(bases[task_of_point[p]], recs) for p, recs in enumerate(per_point)]


def _point_result(base: dict[str, Any], recs: list[dict[str, Any]]) -> dict[str, Any]:
    """One config's multi-seed result: the per-seed records (metrics of each seed's evaluation rows), their
    aggregate, and the baselines (``base``: :func:`_baselines`) with the same metrics."""
    minimal = {round(m, 6): f for m, f in zip(base["oracle_minimal_force"]["mu"],
                                              base["oracle_minimal_force"]["minimal_force_N"])}
    seed_recs = []
    for res in sorted(recs, key=lambda r: r["seed"]):
        tr = res["train"]
        seed_recs.append({"seed": res["seed"], "policy": res.get("policy"), "run": res["run"], "model": res["model"],
                          "train_wall_s": res["train_wall_s"], "timesteps": tr["timesteps"],
                          "steps_per_s": tr["steps_per_s"],
                          **_row_metrics(res["rows"], minimal, base.get("reference_force_N")),
                          "rows": res["rows"], "validation": res["validation"]})
    return {
        "per_seed": seed_recs,
        "aggregate": {k: aggregate([r[k] for r in seed_recs]) for k in AGGREGATED},
        "baselines": {name: _row_metrics(base[name], minimal, base.get("reference_force_N")) | {"rows": base[name]}
                      for name in baselines()},
        "oracle_minimal_force": base["oracle_minimal_force"],
        "reference": base.get("reference"), "reference_force_N": base.get("reference_force_N"),
    }


def _evaluate_trained(seed: int, model: str, train: dict[str, Any], env_dict: dict[str, Any], episodes: int,
                      mus: Sequence[float], evaluation_seed: int) -> dict[str, Any]:
    env = from_dict(GraspLiftConfig, env_dict, where="env")
    policy = make_policy(model, env)
    rows = evaluate_policy(policy, mus, episodes, env, evaluation_seed)
    return {"seed": seed, "policy": policy.name, "run": str(Path(model).parent), "model": model,
            "train_wall_s": train["train_s"],
            "train": {"timesteps": train["agent_steps"], "steps_per_s": train["agent_steps_per_s"]}, "rows": rows,
            "validation": _validation_history(Path(model).parent)}


def report_trained_seeds(models: Sequence[tuple[int, str | Path, dict[str, Any]]], env: GraspLiftConfig,
                         out_dir: str | Path, config: dict[str, Any], *, episodes: int = 10,
                         mus: Sequence[float] = EVAL_MU, runner: Runner | None = None,
                         progress: bool = True, evaluation_seed: int = EVALUATION_SEED) -> dict[str, Any]:
    """The multi-seed report of policies trained elsewhere (the torch PPO's ``policy.pt``), made as
    :func:`run_seeds` makes SB3's: every seed's policy at every mu of ``mus`` on the same evaluation episodes,
    beside the baselines; ``seeds.json``, ``seeds.md`` and ``learning_curves.png`` (from each run's
    ``validation.json``, where it has one) in ``out_dir``. ``models``: (seed, policy file, its training summary with
    ``train_s``, ``agent_steps`` and ``agent_steps_per_s``); ``config``: the training config, for the record.
    Evaluation episode i is reset with ``evaluation_seed + i`` (default: the sealed evaluation seeds)."""
    out = Path(out_dir)
    seeds = [int(s) for s, _, _ in models]
    check_run_args(out, seeds, episodes, evaluation_seed)
    mus = [float(m) for m in mus]
    if runner is None:
        runner = Runner.processes(min(len(seeds) + 1, os.cpu_count() or 1))
    env_dict = to_dict(env)
    jobs: list[Job] = [(_baselines, (env_dict, episodes, mus, evaluation_seed))]
    jobs += [(_evaluate_trained, (int(s), str(m), t, env_dict, episodes, mus, evaluation_seed)) for s, m, t in models]
    t0 = time.perf_counter()
    with runner:
        results = runner.run(jobs)
        capacity = runner.capacity()
    result = {"config": config, "training_seeds": seeds, "seeds": seeds_record(evaluation_seed, episodes),
              "episodes_per_mu": episodes, "mu_grid": mus,
              "reference_mu": list(REFERENCE_MU), "workers": capacity, "runner": runner.label,
              "wall_s": round(time.perf_counter() - t0, 1), **_point_result(results[0], results[1:])}
    result["files"] = write_seed_report(result, out)
    if progress:
        print(format_markdown(result), file=sys.stderr)
    return result


def report_seed_runs(folder: str | Path, *, seeds: Sequence[int] | None = None, episodes: int = 10,
                     runner: Runner | None = None, progress: bool = True,
                     evaluation_seed: int = EVALUATION_SEED) -> dict[str, Any]:
    """The multi-seed report (:func:`report_trained_seeds`) of the runs ``folder/seed_<k>/`` of any one
    learner (``seeds``: only these; default every run there that ships a model), each seed's model
    evaluated on the task it was trained on. ConfigError where there is none, the runs mix learners or
    tasks, or one did not finish."""
    from .selection import seed_runs

    folder = Path(folder)
    runs = []
    for k, d in seed_runs(folder):
        if seeds is not None and k not in set(seeds):
            continue  # (the folder may hold older runs)
        learner = learner_of_run(d, required=False)
        model = learner.shipped_model(d) if learner is not None else None
        if model is not None:
            runs.append((k, d, learner, model))
    if not runs:
        raise ConfigError(f"{folder}: no seed_<k>/ run with a trained model there (the runs of train --seeds)")
    names = sorted({learner.name for _, _, learner, _ in runs})
    if len(names) > 1:
        raise ConfigError(f"{folder}: the seed_<k>/ runs mix learners ({', '.join(names)}); report them apart")
    models = []
    for k, d, learner, model in runs:
        trained = learner.run_summary(d)  # (ConfigError: the run did not finish)
        models.append((k, str(model), trained._asdict()))
    env, _ = task_of([m for _, m, _ in models], None)  # (all from one task, or a one-line error)
    first_learner, first_model = runs[0][2], runs[0][3]
    config = first_learner.config_dict_of_model(first_model)
    config.pop("seed", None)
    return report_trained_seeds(models, env, folder, config, episodes=episodes, runner=runner, progress=progress,
                                evaluation_seed=evaluation_seed)


def run_seeds(config, seeds: Sequence[int], out_dir: str | Path, *, workers: int | None = None,
              episodes: int = 10, mus: Sequence[float] = EVAL_MU, progress: bool = True,
              runner: Runner | None = None, evaluation_seed: int = EVALUATION_SEED) -> dict[str, Any]:
    """Train and evaluate every seed (parallel jobs) and write seeds.json / seeds.md / learning_curves.png.

    ``runner`` says where the jobs run (default: ``workers`` local processes, one per core; see
    :mod:`.parallel` for Ray). Evaluation episode i is reset with ``evaluation_seed + i`` (default: the sealed
    evaluation seeds); a seed whose training would reach into them is refused before any job starts."""
    out = Path(out_dir)
    seeds = list(seeds)
    check_run_args(out, seeds, episodes, evaluation_seed)
    for s in seeds:  # (ConfigError: the seed's training or validation episodes reach the sealed seeds)
        replace(config, seed=s)
    if runner is None:
        runner = Runner.processes(workers if workers is not None else min(len(seeds), os.cpu_count() or 1))
    t0 = time.perf_counter()
    with runner:
        res = train_points([config], [out], seeds, runner, episodes=episodes, mus=mus, progress=progress,
                           evaluation_seed=evaluation_seed)[0]
        capacity = runner.capacity()
    result = {
        "config": to_dict(learner_of_config(config).one_core(config)),
        "training_seeds": seeds,
        "seeds": seeds_record(evaluation_seed, episodes),
        "episodes_per_mu": episodes,
        "mu_grid": [float(m) for m in mus],
        "reference_mu": list(REFERENCE_MU),
        "workers": capacity,
        "runner": runner.label,
        "wall_s": round(time.perf_counter() - t0, 1),
        **res,
    }
    result["files"] = write_seed_report(result, out)
    return result


def write_seed_report(result: dict[str, Any], out: Path) -> dict[str, str]:
    """seeds.json, seeds.md and learning_curves.png of a multi-seed result (atomically); their paths."""
    files = {"json": out / "seeds.json", "md": out / "seeds.md", "png": out / "learning_curves.png"}
    atomic_write_text(files["json"], json.dumps(nan_to_none(result), indent=2) + "\n")
    atomic_write_text(files["md"], format_markdown(result))
    plot_learning_curves(result["per_seed"], files["png"])
    return {k: str(v) for k, v in files.items()}


def fmt_value(x: float, digits: int = 3) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def seeds_line(record: dict[str, Any] | None) -> str:
    """What a result's ``seeds`` record (:func:`.protocol.seeds_record`) says, as a sentence for its markdown."""
    if not isinstance(record, dict):
        return "Evaluation seeds not recorded: not a sealed result."
    first, count = record["first"], record["count"]
    span = f"{first}..{first + count - 1}"
    if record.get("sealed"):
        return f"Evaluation episodes reset with seeds {span}: sealed (no training, validation or tuning drew them)."
    return (f"Evaluation episodes reset with seeds {span}: NOT sealed (outside the sealed evaluation seeds); a "
            "development result, not a certified one.")


def format_markdown(result: dict[str, Any]) -> str:
    """Per-seed and aggregate tables (markdown)."""
    mus = result["mu_grid"]
    trained = result.get("training_seeds", result["seeds"])
    lines = [f"# Multi-seed result: {len(trained)} seeds, {result['episodes_per_mu']} episodes per mu", "",
             seeds_line(result.get("seeds")), "",
             "Success = lifted and held without slip; peak pinch = mean over episodes of each episode's peak "
             "pinch force; force ratio = peak pinch / the reference force at that mu (the least fixed grip that holds "
             "95 % of the reference episodes at the pull speed that needs least, agents/reference.py; '-' without a "
             "table), averaged over mu 0.3-0.9; /oracle = peak pinch / the oracle's minimal slip-free force at pull "
             "0.5 on the nominal tissue (which a slower pull undercuts); time to lift = mean time until the lift "
             "target was first reached, over the episodes that reached it, averaged over mu 0.3-0.9.", "",
             "| policy | " + " | ".join(f"mu {m:g}" for m in mus) + " | success 0.3-0.9 | peak pinch 0.3-0.9 (N) "
             "| force ratio | /oracle | time to lift 0.3-0.9 (s) |",
             "|---" * (len(mus) + 6) + "|"]

    def row(name: str, rec: dict[str, Any]) -> str:
        cells = [f"{rec['success_by_mu'][f'{m:g}']:.1f} / {rec['peak_pinch_by_mu'][f'{m:g}']:.2f}" for m in mus]
        return (f"| {name} | " + " | ".join(cells) + f" | {fmt_value(rec['success_ref'])} | "
                f"{fmt_value(rec['peak_pinch_ref_N'], 2)} | {fmt_value(rec.get('force_ratio_ref', float('nan')), 2)} | "
                f"{fmt_value(rec['peak_pinch_over_oracle_min'], 2)} | "
                f"{fmt_value(rec.get('time_to_lift_ref_s', float('nan')), 2)} |")

    for rec in result["per_seed"]:
        lines.append(row(rec.get("policy") or f"PPO (seed {rec['seed']})", rec))
    for name, rec in result["baselines"].items():  # (those the result was made with)
        lines.append(row(display_name(name), rec))
    curve = result["oracle_minimal_force"]
    lines.append("| oracle minimal force (N) | " + " | ".join(f"{f:.2f}" for f in curve["minimal_force_N"])
                 + " | | | | | |")
    lines += ["", "Cells: success rate / mean peak pinch (N).", "",
              "## Aggregate over seeds", "",
              "| metric | mean | IQM | min | max | bootstrap 95% CI of the mean |", "|---|---|---|---|---|---|"]
    for key, agg in result["aggregate"].items():
        lines.append(f"| {key} | {fmt_value(agg['mean'])} | {fmt_value(agg['iqm'])} | {fmt_value(agg['min'])} "
                     f"| {fmt_value(agg['max'])} | [{fmt_value(agg['ci95'][0])}, {fmt_value(agg['ci95'][1])}] |")
    lines += ["", f"Wall time {result['wall_s']:.0f} s, {result['workers']} jobs at a time ({result['runner']})."]
    return "\n".join(lines) + "\n"


def plot_learning_curves(seed_recs: list[dict[str, Any]], path: Path) -> Path:
    """Validation success and mean peak pinch vs steps, one line per seed."""
    with needs_extra("train", "the learning-curve plot"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for rec in seed_recs:
        hist = sorted(rec["validation"], key=lambda h: h["timesteps"])
        steps = [h["timesteps"] for h in hist]
        a1.plot(steps, [h["success_rate"] for h in hist], marker="o", ms=3, label=f"seed {rec['seed']}")
        a2.plot(steps, [h["mean_peak_pinch_N"] for h in hist], marker="o", ms=3, label=f"seed {rec['seed']}")
    a1.set_xlabel("environment steps")
    a1.set_ylabel("validation success rate")
    a1.set_ylim(-0.05, 1.05)
    a2.set_xlabel("environment steps")
    a2.set_ylabel("validation mean peak pinch (N)")
    a2.set_ylim(bottom=0)
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    n = len(seed_recs)
    fig.suptitle(f"PPO from scratch, {n} seeds (validation episodes at every checkpoint)")
    return save_figure(fig, path)
