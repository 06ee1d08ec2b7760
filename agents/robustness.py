"""The robustness suite (``msdgrasp evaluate --suite robustness``): a fixed, versioned protocol that runs each policy
beside the baselines on the task with one thing changed at a time (sensing, actuation, placement, friction and tissue
outside training) and ranks them.

Protocol ``robustness`` version 2 (:data:`SUITE_VERSION`); a change of conditions, levels, mu, episodes, seeds or
metrics is a new version:

* every condition is the policy's own task (the one its model was trained on; for controllers alone the default
  training's task) with one change: a :class:`~..envs.core.RandomizationConfig` field set to the level
  (the perturbation is drawn per episode up to that level where the field is a range), a reset option pinned
  (stiffness, mass), or the friction grid replaced (friction outside training);
* the conditions :data:`CONDITIONS`: the levels each perturbation declares (:mod:`..envs.perturbations`), by axis;
  version 2 added the lift tracker's (v2 reads the lift from it): a noisier one (1 mm), a later one (3 frames), none;
* the in-range friction grid :data:`MUS` (0.2, 0.3, 0.5, 0.8: mu 0.2, the training range's low end, joined in
  version 2) x :data:`EPISODES` (19) episodes per mu, so that every condition pools :data:`POOLED_EPISODES` (76); a
  condition at fewer mu (friction outside training: one mu each) runs more episodes per mu, 76 at its one mu. 76
  is the least multiple of the grid's four mu that reaches 73, the fewest episodes whose all-success Wilson 95 %
  lower bound reaches 0.95 (:func:`~.stats.episodes_for_lower_bound`): only then can a condition show a success
  rate of at least 95 % at all (76 of 76: 0.952);
* episode i at every mu is reset with ``seed + i``, the seed by default the first of the sealed evaluation seeds
  (:data:`~.protocol.EVALUATION_SEED`, which no training, validation, fit or sweep draws from): the same episodes for
  every policy; the result records ``"seeds": {"first", "count", "sealed"}``;
* per policy and condition, over the pooled episodes: the success rate with its Wilson 95 % interval and lower bound;
  the mean peak pinch over the oracle's minimal slip-free force at that mu on the nominal task (``force_ratio``, the
  mean over mu; a condition that changes the tissue changes what is needed, the ratio still reads against the
  nominal need); the mean time to lift (s, over the episodes that reached the lift target); the largest peak contact
  pressure of any episode and the mean time per episode above the published damage threshold
  (:data:`~.evaluation.DAMAGE_PRESSURE_PA`);
* the score of a policy: its success rate averaged over the conditions (each equally), then the mean force ratio;
  the worst condition and the lowest lower bound beside it.

Fewer episodes than the protocol's (``--episodes``) or a subset of its conditions (``--condition``) run, but the
result says ``"protocol": false`` and its leaderboard "not the protocol". Version 1 (:data:`PROTOCOLS`) ran the grid
0.3, 0.5, 0.8 x 10 episodes per mu (30 per condition, 10 for a friction condition) from seed 0; its conditions stay
defined (:data:`CONDITIONS_V1`) and its results readable (:func:`leaderboard_markdown`).
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

from ..envs.core import GraspLiftConfig, RandomizationConfig, RewardConfig
from ..envs.perturbations import Condition, rule_of, suite_conditions
from ..envs.task import config_record, peak_charge_points
from ..physics.config import ConfigError, atomic_write_text, from_dict, to_dict
from .evaluation import (
    DAMAGE_PRESSURE_PA, build_policy, check_policy_spec, expand_policy_specs, nan_to_none, trained_ranges_of,
    trained_task_of,
)
from .evaluation_jobs import JobList, PolicyPayload, policy_payload
from .controllers import episode_minimal_forces, suite_baselines
from .parallel import Runner
from .protocol import EVALUATION_SEED, check_evaluation_seeds, seeds_record
from .reference import references_at
from .stats import mean_of_runs, stratified_bootstrap_ci, wilson_interval, wilson_lower_bound

#: the protocol version that runs
SUITE_VERSION = 2
#: the in-range friction grid of version 2
MUS = (0.2, 0.3, 0.5, 0.8)
#: episodes per mu of a condition on the whole grid (version 2)
EPISODES = 19
#: the episodes every condition of version 2 pools: 19 x 4 = 76 >= 73, the fewest with an all-success Wilson 95 %
#: lower bound >= 0.95
POOLED_EPISODES = EPISODES * len(MUS)
#: version 1's grid and episodes per mu
MUS_V1 = (0.3, 0.5, 0.8)
EPISODES_V1 = 10


#: the conditions of version 2 (those of version 1 on the grid MUS)
CONDITIONS: tuple[Condition, ...] = suite_conditions(MUS, 2)
#: the conditions of version 1 (on the grid MUS_V1), kept so that its results stay readable
CONDITIONS_V1: tuple[Condition, ...] = suite_conditions(MUS_V1, 1)


def _in_range(conditions: tuple[Condition, ...]) -> tuple[Condition, ...]:
    """The conditions inside the benchmark's robustness ranges: the randomisation the default training draws from
    (``configs/train/ppo.yaml``'s ``train_randomization``), the ranges a benchmark policy is asked to hold."""
    from .models import default_training

    ranges = default_training().train_randomization
    return tuple(c for c in conditions if inside_ranges(c, ranges))


#: the conditions a suite runs (its current version's): ``robustness`` all of them, ``in_range`` those inside the
#: benchmark's robustness ranges (the leaderboard's: nominal, force noise and bias, a step of latency, a force loop
#: 20 % off, grasps placed up to 5 mm / 10 deg off), filled in below
SUITES: dict[str, tuple[Condition, ...]] = {"robustness": CONDITIONS}


@dataclasses.dataclass(frozen=True)
class SuiteProtocol:
    """One version of a suite's protocol: its friction grid, episodes per mu, conditions, and whether a condition at
    fewer mu than the grid runs more episodes per mu so that every condition pools the same number."""

    version: int
    mus: tuple[float, ...]
    episodes: int
    conditions: tuple[Condition, ...]
    pooled: bool

    def episodes_per_mu(self, condition: Condition, episodes: int | None = None) -> int:
        """Episodes per mu of ``condition`` when a run asks for ``episodes`` per mu of the grid (default the
        protocol's): the same, or, pooled, enough that the condition pools ``episodes`` x the grid's mu count."""
        n = self.episodes if episodes is None else int(episodes)
        return math.ceil(n * len(self.mus) / len(condition.mus)) if self.pooled else n

    def pooled_episodes(self, condition: Condition, episodes: int | None = None) -> int:
        """The episodes ``condition`` pools over its mu."""
        return self.episodes_per_mu(condition, episodes) * len(condition.mus)


#: every version of each suite, by (suite, version)
PROTOCOLS: dict[tuple[str, int], SuiteProtocol] = {
    ("robustness", 1): SuiteProtocol(1, MUS_V1, EPISODES_V1, CONDITIONS_V1, pooled=False),
    ("robustness", 2): SuiteProtocol(2, MUS, EPISODES, CONDITIONS, pooled=True),
}


def protocol_of(suite: str, version: int = SUITE_VERSION) -> SuiteProtocol:
    """The protocol of ``suite`` at ``version`` (ConfigError naming the known ones for another)."""
    if (suite, version) not in PROTOCOLS:
        raise ConfigError(f"suite {suite!r} version {version!r} is not known; known: "
                          + ", ".join(f"{s} v{v}" for s, v in PROTOCOLS))
    return PROTOCOLS[suite, version]
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
    at most the training's (a latency within its steps, the same slip and lift sensing, a pinch ceiling no lower than a
    trained one), its mu and tissue pins inside the training's ranges."""
    for key, value in condition.randomization.items():  # (each field's rule: its perturbation's declaration)
        if not rule_of(key)(value, getattr(ranges, key)):
            return False
    for key, value in condition.options.items():
        lo, hi = getattr(ranges, f"{key}_range")
        if not lo <= value <= hi:
            return False
    return all(ranges.mu_range[0] <= m <= ranges.mu_range[1] for m in condition.mus)


SUITES["in_range"] = _in_range(CONDITIONS)
PROTOCOLS["in_range", 2] = SuiteProtocol(2, MUS, EPISODES, SUITES["in_range"], pooled=True)


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
    """A policy's numbers in one condition, over its mu rows: the success rate of the pooled episodes with its Wilson
    95 % interval and lower bound, the mean force ratio over mu, the mean time to lift over the pooled episodes that
    lifted (s; NaN where none did)."""
    ratios = [r["mean_peak_pinch_N"] / minimal[r["mu"]] for r in rows
              if math.isfinite(minimal.get(r["mu"], math.nan))]
    successes = int(sum(sum(bool(v) for v in r["per_episode"]["success"]) for r in rows))
    n = int(sum(r["episodes"] for r in rows))
    lifts = [float(t) for r in rows for t in r["per_episode"]["time_to_lift_s"] if t is not None and math.isfinite(t)]
    return {"success_rate": successes / n, "successes": successes, "episodes": n,
            "success_ci95": list(wilson_interval(successes, n)),
            "success_lower_bound": wilson_lower_bound(successes, n),
            "force_ratio": float(np.mean(ratios)) if ratios else math.nan,
            "mean_time_to_lift_s": float(np.mean(lifts)) if lifts else math.nan,
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


@dataclasses.dataclass(frozen=True)
class SuiteRun:
    """A suite run's inputs, checked: its suite and protocol, episodes per mu of the grid, conditions (with each one's
    episodes per mu), policy specs (the baselines added) and task."""

    suite: str
    protocol: SuiteProtocol
    episodes: int
    conditions: tuple[Condition, ...]
    per_mu: list[int]
    specs: list[str]
    config: GraspLiftConfig
    trained_on: str | None

    @property
    def subset(self) -> bool:
        """Whether it runs fewer conditions than its suite has."""
        return len(self.conditions) < len(SUITES[self.suite])


def suite_run(policies: Sequence[str], out_dir: Path, suite: str, episodes: int | None, seed: int,
              only: Sequence[str] | None, baselines: bool, task: GraspLiftConfig | None) -> SuiteRun:
    """The checked inputs of :func:`run_suite` (its arguments' meanings); ConfigError naming a bad one, before any
    episode runs or anything is written."""
    if suite not in SUITES:
        raise ConfigError(f"suite = {suite!r} is not known; choose one of {', '.join(map(repr, SUITES))}")
    # the protocol's grid and episodes; its conditions are SUITES[suite]
    protocol = dataclasses.replace(protocol_of(suite), conditions=SUITES[suite])
    if episodes is None:
        episodes = protocol.episodes
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output folder {out_dir} exists and is not a folder")
    conditions = SUITES[suite] if only is None else select_conditions(suite, only)
    per_mu = [protocol.episodes_per_mu(cond, int(episodes)) for cond in conditions]
    check_evaluation_seeds(seed, max(per_mu), "seed")
    specs = expand_policy_specs(policies)
    for spec in specs:
        check_policy_spec(spec)
    config, trained_on = trained_task_of(specs)
    if task is not None:
        if trained_on is not None:
            raise ConfigError(f"task: a model runs on the task it was trained on ({trained_on}); give controllers "
                              "alone with a task")
        config, trained_on = task, "the task given"
    if baselines:  # (the registry's: every evaluation's and the suite's own, where the task has their interface)
        specs += [b for b in suite_baselines(config) if b not in specs]
    return SuiteRun(suite, protocol, int(episodes), tuple(conditions), per_mu, specs, config, trained_on)


def _suite_jobs(run: SuiteRun, payloads: Sequence[PolicyPayload], seed: int, hindsight: bool) -> JobList:
    """The suite's jobs: every (policy, condition) cell on the condition's task, the oracle's force at every mu of
    the nominal task, and (``hindsight``) each episode's minimal fixed force in the conditions of HINDSIGHT_AXES."""
    jobs = JobList()
    tasks = [condition_config(run.config, cond) for cond in run.conditions]
    for p, payload in enumerate(payloads):
        for c, cond in enumerate(run.conditions):
            jobs.add_rows(("cell", p, c), payload, tasks[c], cond.mus, run.per_mu[c], seed, None, cond.options)
    jobs.add_minimal_forces(lambda mu: ("oracle", mu), run.config, sorted({m for c in run.conditions for m in c.mus}))
    for c, cond in enumerate(run.conditions):
        if hindsight and cond.axis in HINDSIGHT_AXES:
            jobs.add(("hindsight", c), _hindsight_job, to_dict(tasks[c]), cond.mus, run.per_mu[c], seed,
                     dict(cond.options))
    return jobs


def _suite_printer(names: Sequence[str], conditions: Sequence[Condition]):
    """``on_done`` of the suite's jobs: a line per (policy, condition) cell as it finishes."""

    def done(tag: tuple, res: Any) -> None:
        if tag[0] == "cell":
            print(f"  {names[tag[1]]}: {conditions[tag[2]].name}: success "
                  f"{np.mean([r['success_rate'] for r in res]):.3f} of {sum(r['episodes'] for r in res)} episodes",
                  file=sys.stderr)

    return done


def _board_row(name: str, spec: str, cells: list[dict[str, Any]], conditions: Sequence[Condition],
               inside: Sequence[bool]) -> dict[str, Any]:
    """A policy's leaderboard row from its cells: the score (success averaged over the conditions) with its
    stratified bootstrap interval, the mean force ratio and time to lift, the worst condition, and the same inside
    the training ranges."""
    success = [c["success_rate"] for c in cells]
    ratios = [c["force_ratio"] for c in cells if math.isfinite(c["force_ratio"])]
    lifts = [c["mean_time_to_lift_s"] for c in cells if math.isfinite(c["mean_time_to_lift_s"])]
    worst = int(np.argmin(success))
    in_range = [c for c, ok in zip(cells, inside) if ok]
    in_ratios = [c["force_ratio"] for c in in_range if math.isfinite(c["force_ratio"])]
    # the score's interval: episodes resampled within each condition (a stratified bootstrap, conditions fixed)
    outcomes = [np.array([[float(v) for r in c["rows"] for v in r["per_episode"]["success"]]]) for c in cells]
    _, lo, hi = stratified_bootstrap_ci(outcomes, mean_of_runs)
    return {"policy": name, "spec": spec, "score": float(np.mean(success)), "score_ci95": [float(lo), float(hi)],
            "mean_force_ratio": float(np.mean(ratios)) if ratios else math.nan,
            "mean_time_to_lift_s": float(np.mean(lifts)) if lifts else math.nan,
            "worst_condition": conditions[worst].name, "worst_success_rate": success[worst],
            "worst_lower_bound": min(c["success_lower_bound"] for c in cells),
            "in_range_worst_success_rate": min((c["success_rate"] for c in in_range), default=math.nan),
            "in_range_worst_lower_bound": min((c["success_lower_bound"] for c in in_range), default=math.nan),
            "in_range_max_force_ratio": max(in_ratios, default=math.nan),
            "max_peak_pressure_kPa": max(c["max_peak_pressure_kPa"] for c in cells)}


def _ratio_denominators(config: GraspLiftConfig, minimal: dict[float, float]) -> tuple[dict, dict, dict]:
    """(what each mu's force ratios divide by, the reference forces, what they are): the reference (a slower pull
    cannot lower it) where the task has a table; a task without one reads against the nominal oracle at pull 0.5, and
    the result says so."""
    references, reference = references_at(config, list(minimal))
    if reference["kind"] != "reference":
        return minimal, references, reference
    return {m: (references[f"{m:g}"] or math.nan) for m in minimal}, references, reference


def run_suite(policies: Sequence[str], out_dir: str | Path, suite: str = "robustness", episodes: int | None = None,
              seed: int = EVALUATION_SEED, runner: Runner | None = None, progress: bool = True,
              hindsight: bool = False, only: Sequence[str] | None = None, baselines: bool = True,
              task: GraspLiftConfig | None = None) -> dict[str, Any]:
    """Run ``suite`` (its current version, :data:`SUITE_VERSION`) on every policy spec and the baselines; write
    ``suite_<suite>.json`` and ``leaderboard_<suite>.md`` into ``out_dir`` (atomically). Every spec is validated and
    every model loaded before any episode runs. ``episodes``: per mu of a condition on the whole grid (default the
    protocol's, :data:`EPISODES`; fewer run, marked ``"protocol": false``); a condition at fewer mu runs more per mu,
    so each pools ``episodes`` x the grid's mu count. ``seed``: episode i at every mu is reset with ``seed + i``
    (default the sealed evaluation seeds; another is recorded as not sealed). Each (policy, condition) is a job of one
    job list (:mod:`.evaluation_jobs`, the driver ``msdgrasp evaluate`` runs too), run in this process or on
    ``runner`` (local processes or Ray), with the same numbers.
    ``hindsight``: also search each episode's minimal fixed force in the conditions of HINDSIGHT_AXES
    (:func:`.controllers.episode_minimal_forces`; about 3 CPU-minutes per condition and mu): what a policy that
    grips every episode with just enough force would reach there. ``only``: run these of the suite's conditions
    alone (:func:`select_conditions`: axes or condition names); the result says it is a subset, whose scores are
    not the suite's. ``baselines``: add the baselines (False: the policies given alone, e.g. a second run on the same
    episodes whose baselines an earlier run has). ``task``: the task for controllers alone (default: the default
    training's, TrainConfig().env); a model always runs on its own."""
    out_dir = Path(out_dir)
    run = suite_run(policies, out_dir, suite, episodes, seed, only, baselines, task)
    conditions, config, specs = run.conditions, run.config, run.specs
    ranges = trained_ranges_of(specs)
    built = [build_policy(spec, config) for spec in specs]  # (loads every model: a bad one fails here)
    names = [str(getattr(p, "name", spec)) for p, spec in zip(built, specs)]
    jobs = _suite_jobs(run, [policy_payload(spec, name) for spec, name in zip(specs, names)], int(seed), hindsight)
    t0 = time.perf_counter()
    out = dict(jobs.run(runner, _suite_printer(names, conditions) if progress else None))
    # the bisection's cap (twice the reference force) means no fixed force up to it held: no minimal force known
    cap = 2.0 * config.reference_force_N
    minimal = {tag[1]: (float(f) if f < cap else math.nan) for tag, f in out.items() if tag[0] == "oracle"}
    denominators, references, reference = _ratio_denominators(config, minimal)
    inside = [inside_ranges(cond, ranges) for cond in conditions]
    table = [[_cell(out["cell", p, c], denominators) for c in range(len(conditions))] for p in range(len(specs))]
    board = [_board_row(name, spec, cells, conditions, inside) for name, spec, cells in zip(names, specs, table)]
    order = sorted(range(len(board)), key=lambda p: (-board[p]["score"], board[p]["mean_force_ratio"]))
    protocol = run.protocol
    result = {
        "suite": suite, "version": protocol.version, "episodes": run.episodes,
        "protocol_episodes": protocol.episodes, "mu_grid": list(protocol.mus),
        # the protocol as it stands: its episodes (or more) on every condition
        "protocol": run.episodes >= protocol.episodes and not run.subset,
        "seed": int(seed), "seeds": seeds_record(int(seed), max(run.per_mu)),
        "subset": run.subset,
        "seconds": round(time.perf_counter() - t0, 2), "runner": "this process" if runner is None else runner.label,
        "task_from": run.trained_on or "the benchmark task (TrainConfig().env)",
        "config": to_dict(config),
        "damage_pressure_kPa": DAMAGE_PRESSURE_PA * 1e-3,
        "oracle_minimal_force_N": {str(m): f for m, f in minimal.items()},
        "reference": reference,
        "reference_force_N": references,
        "conditions": [{**dataclasses.asdict(c), "episodes_per_mu": n, "pooled_episodes": n * len(c.mus)}
                       for c, n in zip(conditions, run.per_mu)],
        "inside_training_ranges": inside,
        "hindsight": [_hindsight_cell(out["hindsight", c], minimal) if ("hindsight", c) in out else None
                      for c in range(len(conditions))] if hindsight else None,
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


def _success_text(cell: dict[str, Any]) -> str:
    """A cell's success rate with its Wilson 95 % interval (version 2), or alone (version 1's cells have none)."""
    ci = cell.get("success_ci95")
    if not ci:
        return f"{cell['success_rate']:.2f}"
    return f"{cell['success_rate']:.2f} [{ci[0]:.2f}, {ci[1]:.2f}]"


def _seconds(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2f} s"


def _protocol_notes(result: dict[str, Any], protocol: SuiteProtocol | None) -> list[str]:
    """What keeps a result from being the protocol's, and whether its seeds are sealed, as lines of markdown."""
    notes = []
    if result.get("protocol") is False or result.get("subset"):
        why = []
        if result.get("subset"):
            current = result["version"] == SUITE_VERSION or protocol is None
            total = len(SUITES[result["suite"]]) if current else len(protocol.conditions)
            why.append(f"a subset of the protocol: {len(result['conditions'])} of {total} conditions; its scores are "
                       "not the suite's")
        wanted = result.get("protocol_episodes", protocol.episodes if protocol is not None else None)
        if wanted is not None and result["episodes"] < wanted:
            why.append(f"{result['episodes']} episodes per mu where the protocol runs {wanted}")
        notes.append("**Not the protocol**: " + "; ".join(why) + ".")
    seeds = result.get("seeds")
    if not isinstance(seeds, dict) or not seeds.get("sealed"):
        notes.append("**Seeds not sealed**: the episodes are not drawn from the sealed evaluation seeds "
                     "(agents/protocol.py); a development result, not a certified one.")
    return notes


def _ratio_reference(result: dict[str, Any]) -> str:
    """What a suite result's force ratios divide by, in words."""
    ref = result.get("reference") or {}
    if ref.get("kind") == "reference":
        return ("the reference force at that mu (the least fixed grip that holds 95 % of the reference episodes, at "
                "the pull speed that needs least: a slower pull cannot lower it; agents/reference.py)")
    return ("the oracle's minimal slip-free force at that mu on the nominal task, at pull 0.5 (a policy that pulls "
            "slower needs less: ratios of policies at other pull speeds do not compare"
            + (f"; no reference table: {ref['why']}" if ref.get("why") else "") + ")")


def leaderboard_markdown(result: dict[str, Any]) -> str:
    """The leaderboard and the per-condition table of a suite result, of any version (:data:`PROTOCOLS`)."""
    protocol = PROTOCOLS.get((result["suite"], result["version"]))
    mus = result.get("mu_grid") or (list(protocol.mus) if protocol is not None else list(MUS))
    subset = " (a subset of the protocol)" if result.get("subset") else ""
    per_mu = [c.get("episodes_per_mu", result["episodes"]) for c in result["conditions"]]
    pooled = sorted({c.get("pooled_episodes", n * len(c["mus"])) for c, n in zip(result["conditions"], per_mu)})
    seed = result["seed"]
    lines = [f"# Robustness suite `{result['suite']}` v{result['version']}{subset}", "",
             *(note for n in _protocol_notes(result, protocol) for note in (n, "")),
             f"{len(result['conditions'])} conditions, {result['episodes']} episodes per mu "
             f"(mu {', '.join(f'{m:g}' for m in mus)} unless the condition sets it; a condition at fewer mu runs "
             f"more per mu), {' or '.join(map(str, pooled))} per condition, seeds {seed}..{seed + max(per_mu) - 1}; "
             f"task: {result['task_from']}. "
             "Score: success averaged over the conditions, with a 95% interval from a bootstrap of the episodes "
             "within each condition. Success: the share of a condition's pooled episodes "
             f"with its Wilson 95% interval; lower bound: the interval's low end. Force ratio: mean peak pinch over "
             f"{_ratio_reference(result)}. Time to lift: mean time until "
             f"the lift target was first reached, over the episodes that reached it. "
             f"Damage threshold: {result['damage_pressure_kPa']:g} kPa (published, human bowel, 10 s grasps).", "",
             f"In training ranges: the {sum(result['inside_training_ranges'])} conditions (marked *) inside the "
             "randomisation the task's model was trained on; each policy's worst success (and lowest lower bound) "
             "and largest force ratio there.", "",
             "| rank | policy | score | lowest lower bound | mean force ratio | mean time to lift | "
             "in training ranges: worst success (lower bound) / max force ratio | "
             "worst condition (success) | max peak pressure kPa |",
             "|---|---|---|---|---|---|---|---|---|"]
    for k, row in enumerate(result["leaderboard"], 1):
        ci = row.get("score_ci95")
        score = f"{row['score']:.3f}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else "")
        lines.append(f"| {k} | {row['policy']} | {score} | {_num(row.get('worst_lower_bound'), '.3f')} | "
                     f"{_num(row['mean_force_ratio'], '.2f')} | {_seconds(row.get('mean_time_to_lift_s'))} | "
                     f"{_num(row['in_range_worst_success_rate'], '.2f')} "
                     f"({_num(row.get('in_range_worst_lower_bound'), '.2f')}) / "
                     f"{_num(row['in_range_max_force_ratio'], '.2f')} | "
                     f"{row['worst_condition']} ({row['worst_success_rate']:.2f}) | "
                     f"{_num(row['max_peak_pressure_kPa'], '.1f')} |")
    names = [r["policy"] for r in result["results"]]
    hind = result.get("hindsight")
    lines += ["", "Success [Wilson 95% interval] / force ratio / time to lift per condition" + (
        "; hindsight: the share of episodes a fixed force holds / the ratio of their mean minimal fixed force "
        "(each episode's own, found by search) to the nominal oracle's, what a policy gripping every episode "
        "with just enough would reach / the ratio of the smallest grip fixed per mu that holds "
        f"{FIXED_GRIP_SHARE:.0%} of the episodes, what a policy that knows mu but cannot tell the episodes apart "
        "needs:" if hind else ":"), "",
              "| axis | condition | episodes | " + " | ".join(names) + (" | hindsight" if hind else "") + " |",
              "|---|---|---|" + "---|" * (len(names) + bool(hind))]
    for c, cond in enumerate(result["conditions"]):
        cells = [r["cells"][c] for r in result["results"]]
        extra = ""
        if hind:
            h = hind[c]
            extra = " | -" if h is None else (f" | {h['held_rate']:.2f} / {_num(h['force_ratio'], '.2f')} / "
                                              f"{_num(h.get('fixed_grip_ratio'), '.2f')}")
        mark = " *" if result["inside_training_ranges"][c] else ""
        n = cond.get("pooled_episodes", per_mu[c] * len(cond["mus"]))
        lines.append(f"| {cond['axis']} | {cond['name']}{mark} | {n} | " + " | ".join(
            f"{_success_text(x)} / {_num(x['force_ratio'], '.2f')} / {_seconds(x.get('mean_time_to_lift_s'))}"
            for x in cells) + extra + " |")
    return "\n".join(lines) + "\n"
