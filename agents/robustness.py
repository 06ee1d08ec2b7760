"""The robustness suite (``msdgrasp evaluate --suite robustness``): a fixed, versioned protocol that runs each policy
beside the baselines on the task with one thing changed at a time (sensing, actuation, placement, friction and tissue
outside training) and ranks them.

Protocol ``robustness`` version 1 (:data:`SUITE_VERSION`); a change of conditions, levels, mu, episodes or metrics
is a new version:

* every condition is the policy's own task (the one its model was trained on; for controllers alone the default
  training's task) with one change: a :class:`~..envs.core.RandomizationConfig` field set to the level
  (the perturbation is drawn per episode up to that level where the field is a range), a reset option pinned
  (stiffness, mass), or the friction grid replaced (friction outside training);
* :data:`MUS` (0.3, 0.5, 0.8) x :data:`EPISODES` (10) episodes per condition, episode i seeded ``seed + i``: the same
  episodes for every policy;
* per policy and condition: the success rate, the mean peak pinch over the oracle's minimal slip-free force at that
  mu on the nominal task (``force_ratio``; a condition that changes the tissue changes what is needed, the ratio still
  reads against the nominal need), the largest peak contact pressure of any episode and the mean time per episode
  above the published damage threshold (:data:`~.evaluation.DAMAGE_PRESSURE_PA`);
* the score of a policy: its success rate averaged over the conditions (each equally), then the mean force ratio;
  the worst condition beside it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..envs.core import GraspLiftConfig, RandomizationConfig, RewardConfig, setpoint_interface
from ..envs.task import config_record, peak_charge_points
from ..physics.config import ConfigError, atomic_write_text, from_dict, to_dict
from .evaluation import (
    ALWAYS, DAMAGE_PRESSURE_PA, _minimal_force_job, _payload, _policy_of, build_policy, check_policy_spec,
    evaluate_policy, expand_policy_specs, nan_to_none, trained_ranges_of, trained_task_of,
)
from .controllers import episode_minimal_forces
from .parallel import Runner

SUITE_VERSION = 1
MUS = (0.3, 0.5, 0.8)
EPISODES = 10
#: the suite's baselines (reactive and oracle are added to every evaluation; the fixed force beside them), and the
#: slip-feedback controller where the task has the interface it drives (a force set-point and a pull speed)
BASELINES = (*ALWAYS, "fixed")


@dataclasses.dataclass(frozen=True)
class Condition:
    """One condition: the nominal task with one change."""

    axis: str  # sensing, actuation, placement, friction, tissue (or nominal)
    name: str  # what changed, with its level
    randomization: dict[str, Any] = dataclasses.field(default_factory=dict)  # RandomizationConfig fields
    options: dict[str, float] = dataclasses.field(default_factory=dict)  # reset pins
    mus: tuple[float, ...] = MUS


def _placement(offset_mm: float, tilt_deg: float, azimuth_deg: float) -> Condition:
    return Condition("placement", f"grasp up to {offset_mm:g} mm off, {tilt_deg:g} deg tilt, {azimuth_deg:g} deg turn",
                     {"pose_offset_m": offset_mm * 1e-3, "pose_tilt_deg": tilt_deg, "pose_azimuth_deg": azimuth_deg})


#: the conditions of version 1
CONDITIONS: tuple[Condition, ...] = (
    Condition("nominal", "nominal"),
    *(Condition("sensing", f"force noise {n:g} N", {"sensor_noise_N": n}) for n in (0.05, 0.08, 0.1)),
    *(Condition("sensing", f"force bias up to {b:g} N", {"force_bias_N": b}) for b in (0.05, 0.1)),
    Condition("sensing", "slip sensed as a detector (binary)", {"slip_sensing": "binary"}),
    Condition("sensing", "slip not sensed", {"slip_sensing": "absent"}),
    Condition("sensing", "slip speed noise 0.1", {"slip_noise": 0.1}),
    *(Condition("actuation", f"latency {k} step{'s' if k > 1 else ''}", {"latency_steps": (k, k)}) for k in (1, 2, 3)),
    *(Condition("actuation", f"force-loop gain error up to {e:.0%}", {"force_loop_gain_error": e}) for e in (0.2, 0.4)),
    Condition("actuation", "pinch ceiling 3 N", {"pinch_ceiling_N": 3.0}),
    _placement(3.0, 5.0, 5.0),
    _placement(5.0, 10.0, 10.0),
    *(Condition("friction", f"mu {m:g}", mus=(m,)) for m in (0.1, 0.15, 1.2, 1.5)),
    *(Condition("tissue", f"stiffness x{k:g}", options={"stiffness_scale": k}) for k in (0.5, 2.0)),
    *(Condition("tissue", f"mass x{k:g}", options={"mass_scale": k}) for k in (0.7, 1.5)),
)
SUITES = {"robustness": CONDITIONS}
#: the hindsight oracle's axes: those inside a robust training's ranges whose conditions change the force a grasp
#: needs (the tissue's conditions change it too, but lie outside every training's ranges)
HINDSIGHT_AXES = ("nominal", "placement")
#: the share of a condition's episodes at each mu that the hindsight's fixed grip holds (the robust training's
#: success target, 95 %)
FIXED_GRIP_SHARE = 0.95


def condition_config(config: GraspLiftConfig, condition: Condition) -> GraspLiftConfig:
    """The task ``config`` with the condition's randomisation fields set."""
    if not condition.randomization:
        return config
    data = to_dict(config)
    data["randomization"] = {**data["randomization"], **condition.randomization}
    return from_dict(GraspLiftConfig, data, where="env")


def inside_ranges(condition: Condition, ranges: RandomizationConfig) -> bool:
    """Whether ``condition`` lies inside the randomisation a policy was trained on (``ranges``): every level it sets
    at most the training's (a latency within its steps, the same slip sensing, a pinch ceiling no lower than a
    trained one), its mu and tissue pins inside the training's ranges."""
    for key, value in condition.randomization.items():
        trained = getattr(ranges, key)
        if key == "latency_steps":
            ok = trained[0] <= value[0] and value[1] <= trained[1]
        elif key == "slip_sensing":
            ok = value == trained
        elif key == "pinch_ceiling_N":
            ok = trained is not None and value >= trained
        else:
            ok = value <= trained + 1e-12
        if not ok:
            return False
    for key, value in condition.options.items():
        lo, hi = getattr(ranges, f"{key}_range")
        if not lo <= value <= hi:
            return False
    return all(ranges.mu_range[0] <= m <= ranges.mu_range[1] for m in condition.mus)


def _suite_job(payload, config_dict: dict[str, Any], mus: Sequence[float], episodes: int, seed: int,
               options: dict[str, float]) -> list[dict[str, Any]]:
    config = from_dict(GraspLiftConfig, config_dict, where="env")
    return evaluate_policy(_policy_of(payload, config), list(mus), episodes, config, seed, options=options or None)


def _hindsight_job(config_dict: dict[str, Any], mus: Sequence[float], episodes: int, seed: int,
                   options: dict[str, float]) -> dict[str, list[float | None]]:
    """Each episode's minimal fixed force (the suite's episodes: episode i of every mu seeded seed + i), per mu."""
    config = from_dict(GraspLiftConfig, config_dict, where="env")
    forces = episode_minimal_forces(config, [m for m in mus for _ in range(episodes)],
                                    [seed + i for _ in mus for i in range(episodes)], options or None)
    return {str(m): [None if not math.isfinite(f) else float(f) for f in forces[k * episodes:(k + 1) * episodes]]
            for k, m in enumerate(mus)}


def fixed_grip_force(forces: Sequence[float | None], share: float = FIXED_GRIP_SHARE) -> float:
    """The smallest fixed pinch force that holds at least ``share`` of the episodes whose own minimal fixed forces are
    ``forces`` (None: no fixed force holds that episode): their ceil(share x n)-th smallest, as a grip that holds an
    episode holds it at any larger force too. NaN where no fixed force holds that share."""
    if not forces or not 0.0 < share <= 1.0:
        raise ValueError(f"need episodes and a share in (0, 1], got {len(forces)} episodes and share {share!r}")
    ordered = sorted(math.inf if f is None else float(f) for f in forces)
    f = ordered[math.ceil(share * len(ordered) - 1e-9) - 1]
    return f if math.isfinite(f) else math.nan


def fixed_grip_return(forces: Sequence[float | None], grip_N: float, mu: float, reward: RewardConfig,
                      reference_force_N: float) -> tuple[float, float]:
    """(held share, expected terminal return) of a grip of ``grip_N`` fixed for the episodes whose own minimal fixed
    forces are ``forces`` (None: none holds), at friction ``mu``, under ``reward``: the success bonus less the
    peak-force charge (friction-scaled, with its knee, as the task charges it) where the grip holds, the failure penalty
    where it does not. The shaping terms are left out: progress and hold pay about the same in a success and in a
    lift that slips."""
    held = float(np.mean([f is not None and f <= grip_N for f in forces]))
    # the task's own charge (envs/task.py), run as Python on the reward's record
    charge = peak_charge_points.py_func(config_record(reward), reference_force_N, grip_N, reward.peak_force_weight(mu))
    return held, held * (reward.success_bonus - charge) - (1.0 - held) * reward.failure_penalty


def reward_fixed_grip(forces: Sequence[float | None], mu: float, reward: RewardConfig,
                      reference_force_N: float) -> tuple[float, float, float]:
    """The fixed grip a reward prefers for the episodes whose own minimal fixed forces are ``forces``: (grip N, held
    share, expected terminal return) of the grip that maximises :func:`fixed_grip_return`. The return falls with the
    grip between two episodes' minimal forces, so the best grip is one of them, or none (0 N: every episode fails)."""
    candidates = [0.0] + sorted(float(f) for f in forces if f is not None)
    best = max(candidates, key=lambda g: fixed_grip_return(forces, g, mu, reward, reference_force_N)[1])
    return (best, *fixed_grip_return(forces, best, mu, reward, reference_force_N))


def reward_fixed_grip_table(suite: dict[str, Any], reward: RewardConfig, reference_force_N: float,
                            compare_ratio: float = 1.5) -> str:
    """A markdown table, per hindsight condition of a suite result (``suite_robustness.json``) and mu, of the fixed
    grip ``reward`` prefers for that condition's episodes (:func:`reward_fixed_grip`): its ratio to the nominal
    oracle's minimal force, the share it holds and its expected terminal return, beside the return of a grip of
    ``compare_ratio`` times the oracle's minimal force: how much the reward asks a policy to give up for a margin."""
    minimal, names = suite["oracle_minimal_force_N"], suite["conditions"]
    lines = [f"| condition | mu | reward's grip / oracle min | held | return | return at {compare_ratio:g}x |",
             "|---|---|---|---|---|---|"]
    for condition, cell in zip(names, suite["hindsight"]):
        name = condition["name"] if isinstance(condition, dict) else condition
        for mu, forces in (cell or {}).get("episode_minimal_force_N", {}).items():
            grip, held, ret = reward_fixed_grip(forces, float(mu), reward, reference_force_N)
            wide = fixed_grip_return(forces, compare_ratio * minimal[mu], float(mu), reward, reference_force_N)[1]
            lines.append(f"| {name} | {mu} | {grip / minimal[mu]:.2f} | {held:.2f} | {ret:.1f} | {wide:.1f} |")
    return "\n".join(lines) + "\n"


def _hindsight_cell(forces: dict[str, list[float | None]], minimal: dict[float, float]) -> dict[str, Any]:
    """What the hindsight oracle needs in one condition: the share of episodes some fixed force holds; the mean over
    mu of their mean minimal force over the nominal oracle's (the force ratio a policy that grips each episode with
    just enough could reach); and the mean over mu of :func:`fixed_grip_force` over the nominal oracle's (the force
    ratio of a grip fixed per mu that holds FIXED_GRIP_SHARE of the episodes: a policy that knows mu but cannot tell
    the condition's episodes apart)."""
    held = [f for fs in forces.values() for f in fs if f is not None]
    known = {m: fs for m, fs in forces.items() if math.isfinite(minimal.get(float(m), math.nan))}
    ratios = [np.mean([f for f in fs if f is not None]) / minimal[float(m)] for m, fs in known.items()
              if any(f is not None for f in fs)]
    fixed = [fixed_grip_force(fs) / minimal[float(m)] for m, fs in known.items()]
    return {"held_rate": len(held) / sum(len(fs) for fs in forces.values()),
            "force_ratio": float(np.mean(ratios)) if ratios else math.nan,
            "fixed_grip_ratio": float(np.mean(fixed)) if fixed else math.nan,
            "episode_minimal_force_N": forces}


def _cell(rows: list[dict[str, Any]], minimal: dict[float, float]) -> dict[str, Any]:
    """A policy's numbers in one condition, over its mu rows."""
    ratios = [r["mean_peak_pinch_N"] / minimal[r["mu"]] for r in rows
              if math.isfinite(minimal.get(r["mu"], math.nan))]
    return {"success_rate": float(np.mean([r["success_rate"] for r in rows])),
            "force_ratio": float(np.mean(ratios)) if ratios else math.nan,
            "max_peak_pressure_kPa": float(max(r["max_peak_stress_kPa"] for r in rows)),
            "mean_time_above_damage_s": float(np.mean([r["mean_time_above_damage_s"] for r in rows])),
            "outcomes": {k: sum(r["outcomes"].get(k, 0) for r in rows)
                         for k in sorted({k for r in rows for k in r["outcomes"]})},
            "rows": rows}


def select_conditions(suite: str, only: Sequence[str]) -> tuple[Condition, ...]:
    """The conditions of ``suite`` that ``only`` names, in the protocol's order: each entry an axis (every condition
    of it) or a condition's exact name. ConfigError naming the entry, the axes and the names, on one that matches
    nothing."""
    conditions = SUITES[suite]
    axes = list(dict.fromkeys(c.axis for c in conditions))
    wanted = set()
    for entry in only:
        hits = [k for k, c in enumerate(conditions) if entry in (c.axis, c.name)]
        if not hits:
            raise ConfigError(f"condition {entry!r} is not in suite {suite!r}: give an axis ({', '.join(axes)}) or a "
                              f"condition's name ({'; '.join(c.name for c in conditions)})")
        wanted.update(hits)
    return tuple(c for k, c in enumerate(conditions) if k in wanted)


def run_suite(policies: Sequence[str], out_dir: str | Path, suite: str = "robustness", episodes: int = EPISODES,
              seed: int = 0, runner: Runner | None = None, progress: bool = True,
              hindsight: bool = False, only: Sequence[str] | None = None) -> dict[str, Any]:
    """Run ``suite`` on every policy spec and the baselines; write ``suite_<suite>.json`` and
    ``leaderboard_<suite>.md`` into ``out_dir`` (atomically). Every spec is validated and every model loaded before any
    episode runs. ``runner``: each (policy, condition) a job (local processes or Ray), same numbers as without.
    ``hindsight``: also search each episode's minimal fixed force in the conditions of HINDSIGHT_AXES
    (:func:`.controllers.episode_minimal_forces`; about 3 CPU-minutes per condition and mu): what a policy that
    grips every episode with just enough force would reach there. ``only``: run these of the suite's conditions
    alone (:func:`select_conditions`: axes or condition names); the result says it is a subset, whose scores are
    not the suite's."""
    if suite not in SUITES:
        raise ConfigError(f"suite = {suite!r} is not known; choose one of {', '.join(map(repr, SUITES))}")
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output folder {out_dir} exists and is not a folder")
    conditions = SUITES[suite] if only is None else select_conditions(suite, only)
    specs = expand_policy_specs(policies)
    for spec in specs:
        check_policy_spec(spec)
    specs += [b for b in BASELINES if b not in specs]
    config, trained_on = trained_task_of(specs)
    if setpoint_interface(config) and "slipfeedback" not in specs:
        specs.append("slipfeedback")
    ranges = trained_ranges_of(specs)
    built = [build_policy(spec, config) for spec in specs]  # (loads every model: a bad one fails here)
    names = [str(getattr(p, "name", spec)) for p, spec in zip(built, specs)]
    payloads = [_payload(spec, name) for spec, name in zip(specs, names)]
    jobs, where = [], []
    for p, payload in enumerate(payloads):
        for c, cond in enumerate(conditions):
            cfg = to_dict(condition_config(config, cond))
            jobs.append((_suite_job, (payload, cfg, cond.mus, int(episodes), int(seed), dict(cond.options))))
            where.append((p, c))
    all_mus = sorted({m for cond in conditions for m in cond.mus})
    nominal = to_dict(config)
    jobs += [(_minimal_force_job, (nominal, m)) for m in all_mus]
    searched = [c for c, cond in enumerate(conditions) if hindsight and cond.axis in HINDSIGHT_AXES]
    jobs += [(_hindsight_job, (to_dict(condition_config(config, conditions[c])), conditions[c].mus, int(episodes),
                               int(seed), dict(conditions[c].options))) for c in searched]

    def done(k: int, res: Any) -> None:
        if progress and k < len(where):
            p, c = where[k]
            print(f"  {names[p]}: {conditions[c].name}: success "
                  f"{np.mean([r['success_rate'] for r in res]):.2f}", file=sys.stderr)

    t0 = time.perf_counter()
    if runner is None:
        out = []
        for k, (fn, args) in enumerate(jobs):
            out.append(fn(*args))
            done(k, out[-1])
    else:
        with runner:
            out = runner.run(jobs, on_done=done)
    # the bisection's cap (twice the reference force) means no fixed force up to it held: no minimal force known
    cap = 2.0 * config.reference_force_N
    minimal = {m: (float(f) if f < cap else math.nan)
               for m, f in zip(all_mus, out[len(where):len(where) + len(all_mus)])}
    inside = [inside_ranges(cond, ranges) for cond in conditions]
    hindsight_cells: list[dict[str, Any] | None] = [None] * len(conditions)
    for c, forces in zip(searched, out[len(where) + len(all_mus):]):
        hindsight_cells[c] = _hindsight_cell(forces, minimal)
    table = [[_cell(out[k], minimal) for k in range(p * len(conditions), (p + 1) * len(conditions))]
             for p in range(len(specs))]
    board = []
    for p, name in enumerate(names):
        cells = table[p]
        success = [c["success_rate"] for c in cells]
        ratios = [c["force_ratio"] for c in cells if math.isfinite(c["force_ratio"])]
        worst = int(np.argmin(success))
        in_range = [c for c, ok in zip(cells, inside) if ok]
        in_ratios = [c["force_ratio"] for c in in_range if math.isfinite(c["force_ratio"])]
        board.append({"policy": name, "spec": specs[p], "score": float(np.mean(success)),
                      "mean_force_ratio": float(np.mean(ratios)) if ratios else math.nan,
                      "worst_condition": conditions[worst].name, "worst_success_rate": success[worst],
                      "in_range_worst_success_rate": min((c["success_rate"] for c in in_range), default=math.nan),
                      "in_range_max_force_ratio": max(in_ratios, default=math.nan),
                      "max_peak_pressure_kPa": max(c["max_peak_pressure_kPa"] for c in cells)})
    order = sorted(range(len(board)), key=lambda p: (-board[p]["score"], board[p]["mean_force_ratio"]))
    result = {
        "suite": suite, "version": SUITE_VERSION, "episodes": int(episodes), "seed": int(seed),
        "subset": len(conditions) < len(SUITES[suite]),
        "seconds": round(time.perf_counter() - t0, 2), "runner": "this process" if runner is None else runner.label,
        "task_from": trained_on or "the benchmark task (TrainConfig().env)",
        "config": to_dict(config),
        "damage_pressure_kPa": DAMAGE_PRESSURE_PA * 1e-3,
        "oracle_minimal_force_N": {str(m): f for m, f in minimal.items()},
        "conditions": [dataclasses.asdict(c) for c in conditions],
        "inside_training_ranges": inside,
        "hindsight": hindsight_cells if hindsight else None,
        "leaderboard": [board[p] for p in order],
        "results": [{"policy": names[p], "spec": specs[p],
                     "cells": [{"axis": cond.axis, "condition": cond.name, **cell}
                               for cond, cell in zip(conditions, table[p])]} for p in range(len(specs))],
    }
    files = {"json": out_dir / f"suite_{suite}.json", "markdown": out_dir / f"leaderboard_{suite}.md"}
    atomic_write_text(files["json"], json.dumps(nan_to_none(result), indent=2) + "\n")
    atomic_write_text(files["markdown"], leaderboard_markdown(result))
    result["files"] = {k: str(v) for k, v in files.items()}
    return result


def _num(x: float, fmt: str) -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, fmt)


def leaderboard_markdown(result: dict[str, Any]) -> str:
    """The leaderboard and the per-condition table of a suite result."""
    subset = (f" (a subset of the protocol: {len(result['conditions'])} of {len(SUITES[result['suite']])} "
              "conditions; its scores are not the suite's)") if result.get("subset") else ""
    lines = [f"# Robustness suite `{result['suite']}` v{result['version']}{subset}", "",
             f"{len(result['conditions'])} conditions, {result['episodes']} episodes per mu "
             f"(mu {', '.join(f'{m:g}' for m in MUS)} unless the condition sets it), seeds {result['seed']}.."
             f"{result['seed'] + result['episodes'] - 1}; task: {result['task_from']}. "
             f"Score: success averaged over the conditions. Force ratio: mean peak pinch over the oracle's "
             f"minimal slip-free force at that mu on the nominal task. "
             f"Damage threshold: {result['damage_pressure_kPa']:g} kPa (published, human bowel, 10 s grasps).", "",
             f"In training ranges: the {sum(result['inside_training_ranges'])} conditions (marked *) inside the "
             "randomisation the task's model was trained on; each policy's worst success and largest force ratio "
             "there.", "",
             "| rank | policy | score | mean force ratio | in training ranges: worst success / max force ratio | "
             "worst condition (success) | max peak pressure kPa |",
             "|---|---|---|---|---|---|---|"]
    for k, row in enumerate(result["leaderboard"], 1):
        lines.append(f"| {k} | {row['policy']} | {row['score']:.3f} | {_num(row['mean_force_ratio'], '.2f')} | "
                     f"{_num(row['in_range_worst_success_rate'], '.2f')} / "
                     f"{_num(row['in_range_max_force_ratio'], '.2f')} | "
                     f"{row['worst_condition']} ({row['worst_success_rate']:.2f}) | "
                     f"{_num(row['max_peak_pressure_kPa'], '.1f')} |")
    names = [r["policy"] for r in result["results"]]
    hind = result.get("hindsight")
    lines += ["", "Success rate / force ratio per condition" + (
        "; hindsight: the share of episodes a fixed force holds / the ratio of their mean minimal fixed force "
        "(each episode's own, found by search) to the nominal oracle's, what a policy gripping every episode "
        "with just enough would reach / the ratio of the smallest grip fixed per mu that holds "
        f"{FIXED_GRIP_SHARE:.0%} of the episodes, what a policy that knows mu but cannot tell the episodes apart "
        "needs:" if hind else ":"), "",
              "| axis | condition | " + " | ".join(names) + (" | hindsight" if hind else "") + " |",
              "|---|---|" + "---|" * (len(names) + bool(hind))]
    for c, cond in enumerate(result["conditions"]):
        cells = [r["cells"][c] for r in result["results"]]
        extra = ""
        if hind:
            h = hind[c]
            extra = " | -" if h is None else (f" | {h['held_rate']:.2f} / {_num(h['force_ratio'], '.2f')} / "
                                              f"{_num(h.get('fixed_grip_ratio'), '.2f')}")
        mark = " *" if result["inside_training_ranges"][c] else ""
        lines.append(f"| {cond['axis']} | {cond['name']}{mark} | " + " | ".join(
            f"{x['success_rate']:.2f} / {_num(x['force_ratio'], '.2f')}" for x in cells) + extra + " |")
    return "\n".join(lines) + "\n"
