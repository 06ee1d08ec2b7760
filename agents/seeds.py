"""Seeds are the unit of a result: train several seeds in parallel processes, evaluate each, aggregate.

``msdgrasp train --seeds 0-4`` runs :func:`run_seeds`: every seed trains with the same config (only the
seed differs) into ``<out>/seed_<k>/`` (see :mod:`.training`), in its own process (``--workers``, default:
one per CPU core, each with one torch thread); then every seed's ``best_model.zip`` runs
``episodes`` evaluation episodes at every mu of ``mu_grid`` (the seeds of ``msdgrasp evaluate``, disjoint
from the validation seeds), beside the slip-reactive controller and the oracle. Written into ``<out>``:

* ``seeds.json``: per seed (success per mu, success over the reference range, mean peak pinch and its
  ratio to the oracle's minimal slip-free force, training time and steps/s) and the aggregate over seeds
  (mean, interquartile mean, min, max and a bootstrap 95% interval of the mean) of each metric;
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
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.core import GraspLiftConfig
from ..physics.config import ConfigError, atomic_write_text, from_dict, save_figure, to_dict
from .controllers import ModelPolicy, make_policy
from .evaluation import display_name, evaluate_policy, nan_to_none, oracle_curve
from .models import TrainConfig
from .stats import bootstrap_ci, iqm  # noqa: F401  (re-exported)
from .training import train

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
            seeds = list(range(lo, hi + 1))
        else:
            seeds = [int(p) for p in raw.split(",")]
    except (TypeError, ValueError):
        raise ConfigError(f"--seeds {text!r}: expected a range such as '0-4' or a comma list such as '0,3,7' "
                          "of integers >= 0") from None
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
    """mean, IQM, min, max and the bootstrap 95% interval of the mean of per-seed values."""
    x = [float(v) for v in values]
    lo, hi = bootstrap_ci(x)
    return {"n": len(x), "mean": float(np.mean(x)), "iqm": iqm(x), "min": float(np.min(x)),
            "max": float(np.max(x)), "ci95": [lo, hi]}


# ------------------------------------------------------------------------------------------------
# one seed (runs in a worker process)
# ------------------------------------------------------------------------------------------------


def _train_and_evaluate(config_dict: dict[str, Any], seed: int, out: str, episodes: int,
                        mus: Sequence[float]) -> dict[str, Any]:
    config = from_dict(TrainConfig, {**config_dict, "seed": seed}, where="seeds")
    run = Path(out) / f"seed_{seed}"
    t0 = time.perf_counter()
    summary = train(config, run, progress=False)
    wall = time.perf_counter() - t0
    model = Path(summary["best_model"] or summary["final_model"])
    rows = evaluate_policy(ModelPolicy(model, f"PPO seed {seed}"), mus, episodes, config.env)
    history = json.loads((run / "validation.json").read_text())["history"] if (run / "validation.json").is_file() else []
    return {"seed": seed, "run": str(run), "model": str(model), "train_wall_s": round(wall, 1),
            "train": summary, "rows": rows, "validation": history}


def _baselines(env_dict: dict[str, Any], episodes: int, mus: Sequence[float]) -> dict[str, Any]:
    env = from_dict(GraspLiftConfig, env_dict, where="env")
    out = {name: evaluate_policy(make_policy(name, env), mus, episodes, env) for name in ("reactive", "oracle")}
    out["oracle_minimal_force"] = oracle_curve(env, mus)
    return out


# ------------------------------------------------------------------------------------------------
# the whole run
# ------------------------------------------------------------------------------------------------


def _row_metrics(rows: list[dict[str, Any]], minimal: dict[float, float]) -> dict[str, Any]:
    ref = [r for r in rows if round(r["mu"], 6) in {round(m, 6) for m in REFERENCE_MU}]
    low = [r for r in rows if round(r["mu"], 6) == 0.2]
    ratio = [r["mean_peak_pinch_N"] / minimal[round(r["mu"], 6)] for r in ref]
    return {
        "success_by_mu": {f"{r['mu']:g}": r["success_rate"] for r in rows},
        "peak_pinch_by_mu": {f"{r['mu']:g}": round(r["mean_peak_pinch_N"], 4) for r in rows},
        "success_ref": float(np.mean([r["success_rate"] for r in ref])) if ref else float("nan"),
        "success_mu0.2": float(low[0]["success_rate"]) if low else float("nan"),
        "peak_pinch_ref_N": float(np.mean([r["mean_peak_pinch_N"] for r in ref])) if ref else float("nan"),
        "peak_pinch_over_oracle_min": float(np.mean(ratio)) if ratio else float("nan"),
    }


def run_seeds(config, seeds: Sequence[int], out_dir: str | Path, *, workers: int | None = None,
              episodes: int = 10, mus: Sequence[float] = EVAL_MU, progress: bool = True) -> dict[str, Any]:
    """Train and evaluate every seed (parallel processes) and write seeds.json / seeds.md / learning_curves.png."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output folder {out} exists and is not a folder")
    seeds = list(seeds)
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ConfigError(f"--workers must be an integer >= 1, got {workers!r}")
    workers = workers or min(len(seeds), os.cpu_count() or 1)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    config = replace(config, torch_threads=1)  # one core per process: processes are the parallelism
    cfg_dict = to_dict(config)
    t0 = time.perf_counter()
    ctx = get_context("spawn")  # fork would copy torch/numba thread pools into the workers
    # the baselines take the first slot, then the seeds: never more than `workers` processes at a time
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        base_future = pool.submit(_baselines, to_dict(config.env), episodes, list(mus))
        futures = {s: pool.submit(_train_and_evaluate, cfg_dict, s, str(out), episodes, list(mus)) for s in seeds}
        per_seed = []
        for s, fut in futures.items():
            res = fut.result()
            per_seed.append(res)
            if progress:
                m = _row_metrics(res["rows"], {round(x, 6): 1.0 for x in mus})
                print(f"seed {s}: success {m['success_ref']:.3f} over mu 0.3-0.9, {m['success_mu0.2']:.2f} at mu 0.2, "
                      f"mean peak pinch {m['peak_pinch_ref_N']:.2f} N ({res['train_wall_s']:.0f} s training)",
                      file=sys.stderr)
        base = base_future.result()
    minimal = {round(m, 6): f for m, f in zip(base["oracle_minimal_force"]["mu"],
                                              base["oracle_minimal_force"]["minimal_force_N"])}
    seed_recs = []
    for res in sorted(per_seed, key=lambda r: r["seed"]):
        tr = res["train"]
        seed_recs.append({"seed": res["seed"], "run": res["run"], "model": res["model"],
                          "train_wall_s": res["train_wall_s"], "timesteps": tr["timesteps"],
                          "steps_per_s": tr["steps_per_s"], **_row_metrics(res["rows"], minimal),
                          "rows": res["rows"], "validation": res["validation"]})
    baselines = {name: _row_metrics(base[name], minimal) | {"rows": base[name]} for name in ("reactive", "oracle")}
    keys = ("success_ref", "success_mu0.2", "peak_pinch_ref_N", "peak_pinch_over_oracle_min", "train_wall_s")
    agg = {k: aggregate([r[k] for r in seed_recs]) for k in keys}
    result = {
        "config": cfg_dict,
        "seeds": seeds,
        "episodes_per_mu": episodes,
        "mu_grid": [float(m) for m in mus],
        "reference_mu": list(REFERENCE_MU),
        "workers": workers,
        "wall_s": round(time.perf_counter() - t0, 1),
        "oracle_minimal_force": base["oracle_minimal_force"],
        "per_seed": seed_recs,
        "aggregate": agg,
        "baselines": baselines,
    }
    files = {"json": out / "seeds.json", "md": out / "seeds.md", "png": out / "learning_curves.png"}
    atomic_write_text(files["json"], json.dumps(nan_to_none(result), indent=2) + "\n")
    atomic_write_text(files["md"], format_markdown(result))
    plot_learning_curves(seed_recs, files["png"])
    result["files"] = {k: str(v) for k, v in files.items()}
    return result


def _fmt(x: float, digits: int = 3) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def format_markdown(result: dict[str, Any]) -> str:
    """Per-seed and aggregate tables (markdown)."""
    mus = result["mu_grid"]
    lines = [f"# Multi-seed result: {len(result['seeds'])} seeds, {result['episodes_per_mu']} episodes per mu", "",
             "Success = lifted and held without slip; peak pinch = mean over episodes of each episode's peak "
             "pinch force; ratio = peak pinch / the oracle's minimal slip-free force at that mu, averaged over "
             "mu 0.3-0.9.", "",
             "| policy | " + " | ".join(f"mu {m:g}" for m in mus) + " | success 0.3-0.9 | peak pinch 0.3-0.9 (N) "
             "| ratio to oracle min |",
             "|---" * (len(mus) + 4) + "|"]

    def row(name: str, rec: dict[str, Any]) -> str:
        cells = [f"{rec['success_by_mu'][f'{m:g}']:.1f} / {rec['peak_pinch_by_mu'][f'{m:g}']:.2f}" for m in mus]
        return (f"| {name} | " + " | ".join(cells) + f" | {_fmt(rec['success_ref'])} | "
                f"{_fmt(rec['peak_pinch_ref_N'], 2)} | {_fmt(rec['peak_pinch_over_oracle_min'], 2)} |")

    for rec in result["per_seed"]:
        lines.append(row(f"PPO (seed {rec['seed']})", rec))
    lines.append(row(display_name("reactive"), result["baselines"]["reactive"]))
    lines.append(row(display_name("oracle"), result["baselines"]["oracle"]))
    curve = result["oracle_minimal_force"]
    lines.append("| oracle minimal force (N) | " + " | ".join(f"{f:.2f}" for f in curve["minimal_force_N"])
                 + " | | | |")
    lines += ["", "Cells: success rate / mean peak pinch (N).", "",
              "## Aggregate over seeds", "",
              "| metric | mean | IQM | min | max | bootstrap 95% CI of the mean |", "|---|---|---|---|---|---|"]
    for key, agg in result["aggregate"].items():
        lines.append(f"| {key} | {_fmt(agg['mean'])} | {_fmt(agg['iqm'])} | {_fmt(agg['min'])} | {_fmt(agg['max'])} "
                     f"| [{_fmt(agg['ci95'][0])}, {_fmt(agg['ci95'][1])}] |")
    lines += ["", f"Wall time {result['wall_s']:.0f} s with {result['workers']} worker processes."]
    return "\n".join(lines) + "\n"


def plot_learning_curves(seed_recs: list[dict[str, Any]], path: Path) -> Path:
    """Validation success and mean peak pinch vs steps, one line per seed."""
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
