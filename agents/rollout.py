"""Running a policy's episodes and summarising them per mu (:func:`evaluate_policy`): what every evaluation runs,
wherever it runs (:mod:`.evaluation_jobs`).

The batch is stepped through the core (``env.core.step``) so that no sub-env is auto-reset mid-evaluation; each
episode's metrics are frozen at the step it ends, and its result depends on its seed and task alone, not on the batch
it runs in. The row of a mu: see :mod:`.evaluation`'s docstring.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..envs.core import DAMAGE_PRESSURE_PA, GraspLiftConfig
from ..physics.config import ConfigError
from .controllers import Policy, idle_action
from .stats import bootstrap_ci, wilson_interval

if TYPE_CHECKING:
    from ..envs.grasp_lift import GraspLiftVectorEnv


def config_for(config: GraspLiftConfig, options: dict[str, float]) -> GraspLiftConfig:
    """``config`` with its randomisation ranges widened to admit the pinned stiffness / mass scales (the
    env sizes its stability substeps from those ranges; the draws themselves are discarded when pinned)."""
    from dataclasses import replace

    rnd = config.randomization
    ks = options.get("stiffness_scale")
    ms = options.get("mass_scale")
    if ks is not None and ks > rnd.stiffness_scale_range[1]:
        rnd = replace(rnd, stiffness_scale_range=(rnd.stiffness_scale_range[0], float(ks)))
    if ms is not None and ms < rnd.mass_scale_range[0]:
        rnd = replace(rnd, mass_scale_range=(float(ms), rnd.mass_scale_range[1]))
    return config if rnd is config.randomization else replace(config, randomization=rnd)


#: the grasper's travel from which a pull counts as started (``peak_pinch_before_pull_N``), m
PULL_STARTED_M = 1e-3


def _outcome(inf: dict[str, np.ndarray], terminated: bool, i: int) -> str:
    """How episode ``i`` ended, from its last step's info."""
    if inf["is_success"][i]:
        return "success"
    if inf["numerical_failure"][i]:
        return "numerical_failure"
    if inf["lost_grasp"][i]:
        return "lost_grasp"
    if inf["slipped"][i]:
        return "slipped"  # more than lift_slip_tolerance_m after lifting began: ran out the clock
    if terminated and inf["damaged"][i]:
        return "damaged"
    return "timeout"


def run_batch(env: GraspLiftVectorEnv, policy: Policy, mus: Sequence[float], seeds: Sequence[int],
               options: dict[str, float] | None = None) -> dict[str, np.ndarray]:
    """Run ``len(seeds) <= env.num_envs`` episodes, episode k at friction ``mus[k]``; per-episode metrics
    (frozen at the end)."""
    B = env.num_envs
    n = len(seeds)
    # unused slots (a short last chunk) run too, with seeds continuing the sequence, and are ignored
    all_seeds = [int(s) for s in seeds] + [int(seeds[-1]) + 1 + k for k in range(B - n)]
    all_mus = [float(m) for m in mus] + [float(mus[-1])] * (B - n)
    obs, info = env.reset(seed=all_seeds, options={"mu": all_mus, **(options or {})})
    policy.reset([{k: (v[i].item() if hasattr(v[i], "item") else v[i]) for k, v in info.items()} for i in range(B)])
    core = env.core
    done = np.zeros(B, dtype=bool)
    out = {
        "success": np.zeros(B, dtype=bool),
        "peak_pinch_N": np.zeros(B),
        "peak_pinch_before_pull_N": np.zeros(B),
        "pinch_sum_N": np.zeros(B),
        "setpoint_change_sum_N": np.zeros(B),
        "return": np.zeros(B),
        "steps": np.zeros(B, dtype=np.int64),
        "slip_mm": np.zeros(B),
        "peak_stress_kPa": np.zeros(B),
        "time_above_damage_s": np.zeros(B),
        "time_to_lift_s": np.full(B, np.nan),
        "outcome": np.full(B, "timeout", dtype=object),
    }
    # the pinch-force set-point the policy commands (jaw_action = force), to measure how much it moves step to step
    force_setpoints = env.config.jaw_action == "force"
    previous_setpoint = np.full(B, np.nan)
    for _ in range(env.config.max_episode_steps + 1):
        act = np.asarray(policy.act(obs), dtype=np.float64).reshape(B, 2)
        if not np.all(np.isfinite(act[~done])):
            bad = int(np.flatnonzero(~np.all(np.isfinite(act), axis=1) & ~done)[0])
            raise ConfigError(f"policy {getattr(policy, 'name', 'policy')!r} returned a non-finite action at "
                              f"mu={all_mus[bad]:g}")
        act = np.where(done[:, None], idle_action(env.config), act)  # finished tissues just rest
        # ended episodes no longer count: their tissues stand still (each tissue's physics is the same in any
        # batch, so the others' are unchanged)
        obs, rew, term, trunc, inf = core.step(act, advance=np.flatnonzero(~done))
        live = ~done
        out["pinch_sum_N"][live] += inf["pinch_force_N"][live]
        if force_setpoints:
            setpoint = core.pinch_setpoint(np.clip(act[:, 0], -1.0, 1.0))
            moved = live & np.isfinite(previous_setpoint)
            out["setpoint_change_sum_N"][moved] += np.abs(setpoint - previous_setpoint)[moved]
            previous_setpoint = np.where(live, setpoint, previous_setpoint)
        # where the peak is set: the grip before the grasper has pulled PULL_STARTED_M (closing, squeezing)
        before = live & (inf["travel_m"] < PULL_STARTED_M)
        out["peak_pinch_before_pull_N"][before] = np.maximum(out["peak_pinch_before_pull_N"][before],
                                                             inf["pinch_force_N"][before])
        out["return"][live] += rew[live]
        out["steps"][live] += 1
        out["time_above_damage_s"][live & (inf["peak_stress_pa"] > DAMAGE_PRESSURE_PA)] += env.config.agent_dt_s
        ended = live & (term | trunc)
        if ended.any():
            out["success"][ended] = inf["is_success"][ended]
            out["peak_pinch_N"][ended] = core.peak_pinch[ended]
            out["slip_mm"][ended] = core.slip_total[ended] * 1e3
            out["peak_stress_kPa"][ended] = core.peak_stress[ended] * 1e-3
            out["time_to_lift_s"][ended] = core.time_to_lift[ended]
            for i in np.flatnonzero(ended):
                out["outcome"][i] = _outcome(inf, bool(term[i]), i)
            done |= ended
        if done.all():
            break
    out["mean_pinch_N"] = out.pop("pinch_sum_N") / np.maximum(out["steps"], 1)
    # mean |change| of the pinch set-point from one agent step to the next (NaN without a force set-point)
    change = out.pop("setpoint_change_sum_N") / np.maximum(out["steps"] - 1, 1)
    out["setpoint_change_N"] = change if force_setpoints else np.full(B, np.nan)
    return {k: v[:n] for k, v in out.items()}


def summarise(mu: float, ep: dict[str, np.ndarray]) -> dict[str, Any]:
    """The row of ``mu`` (success with its Wilson 95 % interval, pinch, slip, stress, time to lift; per-episode values
    under ``per_episode``) from the per-episode metrics ``ep`` of :func:`run_batch`."""
    ttl = ep["time_to_lift_s"]
    lifted = np.isfinite(ttl)
    outcomes = {o: int(np.sum(ep["outcome"] == o)) for o in sorted(set(ep["outcome"].tolist()))}
    n = int(len(ep["success"]))
    return {
        "mu": float(mu),
        "success_rate": float(np.mean(ep["success"])),
        "success_ci95": list(wilson_interval(int(np.sum(ep["success"])), n)),
        "mean_peak_pinch_N": float(np.mean(ep["peak_pinch_N"])),
        "peak_pinch_ci95_N": list(bootstrap_ci(ep["peak_pinch_N"])),
        "max_peak_pinch_N": float(np.max(ep["peak_pinch_N"])),
        "mean_peak_pinch_before_pull_N": float(np.mean(ep["peak_pinch_before_pull_N"])),
        "mean_pinch_N": float(np.mean(ep["mean_pinch_N"])),
        "mean_setpoint_change_N": float(np.mean(ep["setpoint_change_N"])),
        "mean_return": float(np.mean(ep["return"])),
        "mean_slip_mm": float(np.mean(ep["slip_mm"])),
        "mean_peak_stress_kPa": float(np.mean(ep["peak_stress_kPa"])),
        "max_peak_stress_kPa": float(np.max(ep["peak_stress_kPa"])),
        "mean_time_above_damage_s": float(np.mean(ep["time_above_damage_s"])),
        "mean_time_to_lift_s": float(np.mean(ttl[lifted])) if lifted.any() else float("nan"),
        "episodes": int(len(ep["success"])),
        "outcomes": outcomes,
        "per_episode": {
            "success": [bool(v) for v in ep["success"]],
            "peak_pinch_N": [float(v) for v in ep["peak_pinch_N"]],
            "peak_pinch_before_pull_N": [float(v) for v in ep["peak_pinch_before_pull_N"]],
            "mean_pinch_N": [float(v) for v in ep["mean_pinch_N"]],
            "setpoint_change_N": [float(v) for v in ep["setpoint_change_N"]],
            "return": [float(v) for v in ep["return"]],
            "slip_mm": [float(v) for v in ep["slip_mm"]],
            "peak_stress_kPa": [float(v) for v in ep["peak_stress_kPa"]],
            "time_above_damage_s": [float(v) for v in ep["time_above_damage_s"]],
            "time_to_lift_s": [float(v) for v in ttl],
            "steps": [int(v) for v in ep["steps"]],
            "outcome": [str(v) for v in ep["outcome"]],
        },
    }


def evaluate_policy(policy: Policy, mus: Sequence[float], episodes: int = 10, config: GraspLiftConfig | None = None,
                    seed: int = 0, n_envs: int | None = None, *, _envs: dict | None = None,
                    progress: bool = False, options: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """One row of metrics per mu (see the module docstring) for ``policy`` over ``episodes`` episodes each.

    Episode ``i`` (at every mu) is seeded ``seed + i`` with reset options ``{"mu": mu, **options}``
    (``options`` pins e.g. ``stiffness_scale`` beyond the training range: the env is then built for it,
    which changes only its stability substeps). ``n_envs`` caps the batch size (default: every episode at
    every mu in one batch; an episode's result does not depend on the batch).
    """
    options = dict(options or {})
    from ..envs.grasp_lift import GraspLiftVectorEnv

    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    if n_envs is not None and (isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or n_envs < 1):
        raise ConfigError(f"n_envs must be an integer >= 1 or None, got {n_envs!r}")
    config = config_for(config or GraspLiftConfig(), options)
    # every (mu, episode) pair in one batch unless n_envs caps it: one batched env runs the tissues in SIMD lanes
    # (from 16 up), and each episode's result is the same in any batch (its own seed and random stream)
    pairs = [(float(mu), seed + i) for mu in mus for i in range(episodes)]
    batch = int(min(n_envs or len(pairs), len(pairs)))
    envs = _envs if _envs is not None else {}
    key = (config, batch)
    if key not in envs:
        envs[key] = GraspLiftVectorEnv(batch, config)
    env = envs[key]
    t0 = time.perf_counter()
    chunks = [run_batch(env, policy, [mu for mu, _ in part], [s for _, s in part], options)
              for part in (pairs[k:k + batch] for k in range(0, len(pairs), batch))]
    ep_all = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    rows = []
    for m, mu in enumerate(mus):
        row = summarise(float(mu), {k: v[m * episodes:(m + 1) * episodes] for k, v in ep_all.items()})
        rows.append(row)
        if progress:
            print(f"  {getattr(policy, 'name', 'policy')}: mu={float(mu):g} success={row['success_rate']:.2f} "
                  f"peak pinch={row['mean_peak_pinch_N']:.2f} N", file=sys.stderr)
    if progress:
        print(f"  {getattr(policy, 'name', 'policy')}: {len(pairs)} episodes in {time.perf_counter() - t0:.1f} s",
              file=sys.stderr)
    return rows
