"""Evaluate grasp policies across a grid of friction coefficients (``msdgrasp evaluate``).

For every policy and every mu of the grid, ``episodes`` episodes run as ONE batch of a
:class:`~msdgrasp.envs.grasp_lift.GraspLiftVectorEnv` (mu pinned through the reset options, every other
randomisation as configured, episode ``i`` seeded ``seed + i``). :func:`evaluate` starts at the sealed evaluation
seeds (:data:`~.protocol.EVALUATION_SEED`, which no training, validation, fit or sweep draws from) and records
``"seeds": {"first", "count", "sealed"}`` in ``evaluation.json``; another ``seed`` makes a result marked not sealed.
The batch is stepped through the core (``env.core.step``) so that no sub-env is auto-reset mid-evaluation; each
episode's metrics are frozen at the step it ends.

Per (policy, mu) row:

=========================  ======================================================================
``success_rate``           fraction of episodes ending with ``info["is_success"]`` (slip-free lift)
``mean_peak_pinch_N``      mean over episodes of the episode's peak pinch force, N
``max_peak_pinch_N``       largest peak pinch force of any episode, N
``mean_pinch_N``           mean over episodes of the episode's mean pinch force (all its steps), N
``mean_setpoint_change_N``  mean over episodes of the mean |change| of the commanded pinch-force set-point
                           from one agent step to the next, N (NaN without a force set-point): a policy that
                           drives the force loop bang-bang, 0 N and 5 N in turn, moves it by up to 5 N a step
``mean_slip_mm``           mean total slip distance between jaws and tissue, mm
``mean_peak_stress_kPa``   mean peak nodal contact stress, kPa
``mean_time_to_lift_s``    mean time until the lift target was first reached, over the episodes
                           that reached it, s (NaN -- ``null`` in the JSON -- when none did)
``episodes``               number of episodes
=========================  ======================================================================

:func:`evaluate` writes ``evaluation.json``, ``evaluation.csv``, ``success_vs_mu.png`` and
``pinch_vs_mu.png`` (atomically), and optionally one rerun recording per (policy, mu).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.core import DAMAGE_PRESSURE_PA, GraspLiftConfig, RandomizationConfig  # noqa: F401 (DAMAGE_PRESSURE_PA re-exported)
from ..physics.config import (  # noqa: F401 (nan_to_none re-exported)
    ConfigError, atomic_write_text, from_dict, nan_to_none, needs_extra, save_figure, to_dict,
)
from .controllers import (  # noqa: F401 (is_controller, display_name re-exported)
    OraclePolicy, baselines, check_controller_spec, display_name, idle_action, is_controller, make_policy,
    minimal_force, spec_forms,
)
from .reference import references_at
from .learners.base import learner_of_model, model_kinds
from .parallel import Runner
from .protocol import EVALUATION_SEED, check_evaluation_seeds, seeds_record
from .stats import bootstrap_ci, wilson_interval

#: the training range (0.3-0.9) and beyond it on both sides (0.15, 0.2, 1.0, 1.2: unseen in training)
DEFAULT_MU_GRID = "0.15,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0,1.2"
#: unseen tissue: stiffness and mass scales outside the training ranges (0.8-1.2, 0.9-1.1), at UNSEEN_MU
UNSEEN_CONDITIONS = ({"stiffness_scale": 0.6}, {"stiffness_scale": 1.5}, {"mass_scale": 0.8}, {"mass_scale": 1.25})
UNSEEN_MU = 0.5
MAX_GRID_VALUES = 101
MU_MAX = 10.0  # the env accepts mu in [0, 10]

CSV_COLUMNS = (
    "policy", "mu", "success_rate", "mean_peak_pinch_N", "force_ratio", "peak_pinch_over_oracle_min",
    "max_peak_pinch_N",
    "mean_pinch_N", "mean_slip_mm", "mean_peak_stress_kPa", "mean_time_to_lift_s", "mean_return", "episodes",
)
_GRID_HELP = "expected 'start:stop:step' (stop included, e.g. '0.2:1.0:0.1') or a comma list such as '0.3,0.5'"


# ------------------------------------------------------------------------------------------------
# mu grid
# ------------------------------------------------------------------------------------------------


def _grid_number(text: str, part: str, what: str) -> float:
    try:
        value = float(part)
    except ValueError:
        raise ConfigError(f"mu grid {text!r}: {what} {part.strip()!r} is not a number; {_GRID_HELP}") from None
    if not math.isfinite(value):
        raise ConfigError(f"mu grid {text!r}: {what} must be a finite number, got {part.strip()!r}; {_GRID_HELP}")
    return value


def _check_mu(text: str, value: float, what: str) -> None:
    if value < 0:
        raise ConfigError(f"mu grid {text!r}: {what} = {value:g} is negative; friction coefficients must be >= 0")
    if value > MU_MAX:
        raise ConfigError(f"mu grid {text!r}: {what} = {value:g} exceeds {MU_MAX:g}, the largest mu the env accepts")


def parse_mu_grid(text: str) -> np.ndarray:
    """``'start:stop:step'`` (stop included within float tolerance) or ``'0.3,0.5'`` -> sorted mu values.

    Raises :class:`ConfigError` naming the grid and the broken rule for non-numbers, ``step <= 0``,
    ``start > stop``, negative (or > 10) mu, or more than 101 values.
    """
    if not isinstance(text, str) or not text.strip():
        raise ConfigError(f"mu grid {text!r} is empty; {_GRID_HELP}")
    raw = text.strip()
    if ":" in raw:
        parts = raw.split(":")
        if len(parts) != 3:
            raise ConfigError(f"mu grid {text!r}: a range needs exactly three fields start:stop:step, got {len(parts)}")
        start, stop, step = (_grid_number(text, p, w) for p, w in zip(parts, ("start", "stop", "step")))
        if step <= 0:
            raise ConfigError(f"mu grid {text!r}: step must be > 0, got {step:g}")
        if start > stop:
            raise ConfigError(f"mu grid {text!r}: start ({start:g}) must be <= stop ({stop:g})")
        _check_mu(text, start, "start")
        _check_mu(text, stop, "stop")
        span = (stop - start) / step
        if span + 1 > MAX_GRID_VALUES + 1e-6:
            raise ConfigError(
                f"mu grid {text!r}: {int(math.floor(span + 1e-9)) + 1} values; at most {MAX_GRID_VALUES} are allowed "
                "(use a larger step)"
            )
        n = int(math.floor(span + 1e-9)) + 1
        values = start + step * np.arange(n)
        if abs(values[-1] - stop) <= 1e-9 * max(1.0, abs(stop)):
            values[-1] = stop
        values = np.minimum(values, stop)
    else:
        parts = raw.split(",")
        if any(not p.strip() for p in parts):
            raise ConfigError(f"mu grid {text!r}: empty entry in the comma list; {_GRID_HELP}")
        if len(parts) > MAX_GRID_VALUES:
            raise ConfigError(f"mu grid {text!r}: {len(parts)} values; at most {MAX_GRID_VALUES} are allowed")
        values = np.array([_grid_number(text, p, "value") for p in parts])
        for v in values:
            _check_mu(text, float(v), "mu")
    return np.unique(np.round(values, 10))


# ------------------------------------------------------------------------------------------------
# running episodes
# ------------------------------------------------------------------------------------------------


def _config_for(config: GraspLiftConfig, options: dict[str, float]) -> GraspLiftConfig:
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


def _run_batch(env, policy, mus: Sequence[float], seeds: Sequence[int],
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
                if inf["is_success"][i]:
                    o = "success"
                elif inf["numerical_failure"][i]:
                    o = "numerical_failure"
                elif inf["lost_grasp"][i]:
                    o = "lost_grasp"
                elif inf["slipped"][i]:
                    o = "slipped"  # more than lift_slip_tolerance_m after lifting began: ran out the clock
                elif term[i] and inf["damaged"][i]:
                    o = "damaged"
                else:
                    o = "timeout"
                out["outcome"][i] = o
            done |= ended
        if done.all():
            break
    out["mean_pinch_N"] = out.pop("pinch_sum_N") / np.maximum(out["steps"], 1)
    # mean |change| of the pinch set-point from one agent step to the next (NaN without a force set-point)
    change = out.pop("setpoint_change_sum_N") / np.maximum(out["steps"] - 1, 1)
    out["setpoint_change_N"] = change if force_setpoints else np.full(B, np.nan)
    return {k: v[:n] for k, v in out.items()}


def _summarise(mu: float, ep: dict[str, np.ndarray]) -> dict[str, Any]:
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


def evaluate_policy(policy, mus: Sequence[float], episodes: int = 10, config: GraspLiftConfig | None = None,
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
    config = _config_for(config or GraspLiftConfig(), options)
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
    chunks = [_run_batch(env, policy, [mu for mu, _ in part], [s for _, s in part], options)
              for part in (pairs[k:k + batch] for k in range(0, len(pairs), batch))]
    ep_all = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
    rows = []
    for m, mu in enumerate(mus):
        row = _summarise(float(mu), {k: v[m * episodes:(m + 1) * episodes] for k, v in ep_all.items()})
        rows.append(row)
        if progress:
            print(f"  {getattr(policy, 'name', 'policy')}: mu={float(mu):g} success={row['success_rate']:.2f} "
                  f"peak pinch={row['mean_peak_pinch_N']:.2f} N", file=sys.stderr)
    if progress:
        print(f"  {getattr(policy, 'name', 'policy')}: {len(pairs)} episodes in {time.perf_counter() - t0:.1f} s",
              file=sys.stderr)
    return rows


# ------------------------------------------------------------------------------------------------
# policy specs
# ------------------------------------------------------------------------------------------------


def check_policy_spec(spec: str) -> None:
    """Raise ConfigError for an unusable spec (a controller's bad options, unknown name, missing model file)."""
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(f"policy {spec!r}: empty policy spec; use one of {', '.join(spec_forms())} "
                          "or a model path")
    if is_controller(spec):
        check_controller_spec(spec)  # (a file its options name loads, or the spec is refused)
        return
    path = Path(spec)
    if path.is_dir():
        raise ConfigError(f"policy {spec!r}: {path} is a folder, not a saved model file ({model_kinds()})")
    if path.is_file():
        learner_of_model(path)  # a model records its learner and training config beside it, or it is refused
        return
    looks_like_path = path.suffix != "" or "/" in spec or "\\" in spec
    if looks_like_path:
        raise ConfigError(f"policy {spec!r}: model file not found: {path}")
    raise ConfigError(
        f"unknown policy {spec!r}: use one of {', '.join(spec_forms())} or the path of a saved model "
        f"({model_kinds()})"
    )


def build_policy(spec: str, config: GraspLiftConfig):
    """``make_policy`` after :func:`check_policy_spec`, with every failure as ConfigError."""

    check_policy_spec(spec)
    try:
        return make_policy(spec, config)
    except ConfigError:
        raise
    except (ValueError, OSError) as exc:
        raise ConfigError(f"policy {spec!r}: {exc}") from None


def _safe_name(name: str) -> str:
    """A display name as a file name: 'PPO (seed 3)' -> 'PPO_seed_3'."""
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", name).strip("_") or "policy"


def expand_policy_specs(specs: Sequence[str]) -> list[str]:
    """Model paths with a wildcard (``logs/train/seed_*/best_model.zip``) expand to the sorted matches; a
    pattern without a match is an error (never silently dropped)."""
    import glob

    out: list[str] = []
    for spec in specs:
        if isinstance(spec, str) and any(c in spec for c in "*?["):
            matches = sorted(glob.glob(spec))
            if not matches:
                raise ConfigError(f"policy {spec!r}: no saved model matches this pattern")
            out += matches
        else:
            out.append(spec)
    return out


def _mu_label(mu: float) -> str:
    return f"{mu:g}"


# ------------------------------------------------------------------------------------------------
# evaluate: run, write, plot
# ------------------------------------------------------------------------------------------------


def _csv_text(results: list[dict[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for pol in results:
        for r in pol["rows"]:
            vals = [pol["name"]]
            for col in CSV_COLUMNS[1:]:
                v = r[col]
                vals.append("nan" if v is None else v if isinstance(v, int) else f"{v:.6g}")
            w.writerow(vals)
    return buf.getvalue()


_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
_LINES = ("-", "--", "-.", ":")


def _style(k: int) -> dict[str, Any]:
    """Distinct marker and line style per policy (curves often coincide, e.g. at success rate 1)."""
    return {"marker": _MARKERS[k % len(_MARKERS)], "linestyle": _LINES[k % len(_LINES)],
            "markersize": 7 - 0.6 * (k % 4), "alpha": 0.9}


def _dodge(k: int, n: int) -> float:
    """Sideways offset of policy k of n, so that coinciding points of different policies stay visible."""
    return (k - (n - 1) / 2) * 0.006


def _errorbars(ax, results, key: str, ci_key: str, suffix: str = "") -> list[str]:
    """One error-bar curve per policy of ``row[key]`` with ``row[ci_key]`` as its interval (policies
    dodged sideways); returns the line colours."""
    colours = []
    for k, pol in enumerate(results):
        rows = pol["rows"]
        mus = np.array([r["mu"] for r in rows]) + _dodge(k, len(results))
        value = np.array([r[key] for r in rows])
        ci = np.array([r[ci_key] for r in rows])
        line = ax.errorbar(mus, value, yerr=[value - ci[:, 0], ci[:, 1] - value], capsize=2, elinewidth=0.8,
                           label=display_name(pol["name"]) + suffix, **_style(k))
        colours.append(line[0].get_color())
    return colours


def _finish(ax, fig, xlabel: str, ylabel: str, title: str, results, intervals: str, path: Path) -> Path:
    n = sorted({r["episodes"] for pol in results for r in pol["rows"]})
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title} (n = {'/'.join(map(str, n))} episodes per point, {intervals})", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)  # beside, not over, the data
    fig.tight_layout()
    return save_figure(fig, path)


def _plot_success(results, config: GraspLiftConfig, path: Path) -> Path:
    with needs_extra("train", "the evaluation's plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = config.randomization.mu_range
    fig, ax = plt.subplots(figsize=(10.0, 4.4))
    ax.axvspan(lo, hi, color="tab:gray", alpha=0.15, label=f"training range of mu [{lo:g}, {hi:g}]")
    _errorbars(ax, results, "success_rate", "success_ci95")
    ax.set_ylim(-0.05, 1.05)
    return _finish(ax, fig, "friction coefficient mu", "success rate (slip-free lift)",
                   "Grasp-and-lift success vs friction", results, "95% Wilson intervals", path)


def _plot_pinch(results, oracle_curve: dict[str, Any], path: Path) -> Path:
    with needs_extra("train", "the evaluation's plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10.0, 4.4))
    colours = _errorbars(ax, results, "mean_peak_pinch_N", "peak_pinch_ci95_N", " (mean peak, all episodes)")
    failed_label = "a failed episode's peak pinch"
    for k, (pol, colour) in enumerate(zip(results, colours)):
        dodge = _dodge(k, len(results))
        for r in pol["rows"]:  # failed episodes are in the mean: show them
            bad = [p for p, ok in zip(r["per_episode"]["peak_pinch_N"], r["per_episode"]["success"]) if not ok]
            if bad:
                ax.scatter([r["mu"] + dodge] * len(bad), bad, marker="x", s=14, color=colour, linewidths=0.8,
                           label=failed_label, zorder=3)
                failed_label = None
    limit = oracle_curve["search_limit_N"]
    held = [f if f < limit - 1e-9 else np.nan for f in oracle_curve["minimal_force_N"]]
    ax.plot(oracle_curve["mu"], held, color="black", linestyle="--", marker="+",
            label=f"minimal slip-free force (oracle bisection; none up to {limit:g} N where missing)")
    ax.set_ylim(bottom=0)
    return _finish(ax, fig, "friction coefficient mu", "peak pinch force (N)", "Peak pinch force vs friction",
                   results, "95% bootstrap intervals; x: failed episodes", path)


def _minimal_force_job(config: GraspLiftConfig | dict[str, Any], mu: float) -> float:
    if isinstance(config, dict):
        config = from_dict(GraspLiftConfig, config, where="env")
    ref = OraclePolicy(config)
    # the same rounding, pull and tolerance as OraclePolicy.reset: shares its cache
    return float(minimal_force(config, round(float(mu), 3), ref.pull, ref.tolerance))


def oracle_curve(config: GraspLiftConfig, mus: Sequence[float], progress: bool = False) -> dict[str, Any]:
    """The oracle's minimal slip-free fixed force at each mu (bisection in simulation, cached per mu)."""
    forces = []
    for mu in mus:
        t0 = time.perf_counter()
        forces.append(_minimal_force_job(config, float(mu)))
        if progress:
            print(f"  minimal force: mu={float(mu):g} -> {forces[-1]:.3f} N ({time.perf_counter() - t0:.1f} s)",
                  file=sys.stderr)
    return _curve_record(config, mus, forces)


def _curve_record(config: GraspLiftConfig, mus: Sequence[float], forces: Sequence[float]) -> dict[str, Any]:
    ref = OraclePolicy(config)
    return {"mu": [float(m) for m in mus], "minimal_force_N": [float(f) for f in forces], "oracle_margin": ref.margin,
            "pull": ref.pull, "tolerance_N": ref.tolerance,
            # the bisection's upper end: a minimal force equal to it means no force up to it holds
            "search_limit_N": 2.0 * config.reference_force_N}


def _model_paths(policies: Sequence[str]) -> list[Path]:
    """The saved models among policy specs (the controllers' names left out)."""
    return [Path(spec) for spec in policies if not is_controller(spec)]


def task_of(policies: Sequence[str], config: GraspLiftConfig | None) -> tuple[GraspLiftConfig, str | None]:
    """The task to evaluate on: the env config the model(s) were trained with (all models must agree, and
    agree with ``config`` where one is given), else ``config``, else (controllers only) the default task.
    Returns (config, the file it came from). A model is never run on a task it was not trained on."""
    found: dict[str, GraspLiftConfig] = {}
    for path in _model_paths(policies):
        learner = learner_of_model(path)
        found[str(learner.config_file(path))] = learner.model_task(path)
    if not found:
        return (config if config is not None else GraspLiftConfig()), None
    envs = list(found.values())
    if any(e != envs[0] for e in envs[1:]):
        raise ConfigError("the models were trained on different tasks (env configs differ: "
                          + ", ".join(found) + "); evaluate them separately")
    if config is not None and config != envs[0]:
        raise ConfigError(f"the given task is not the one the models were trained on ({next(iter(found))})")
    return envs[0], next(iter(found))


def trained_ranges_of(policies: Sequence[str]) -> RandomizationConfig:
    """The randomisation the first model among ``policies`` was trained under (its training's domain randomisation,
    else its task's); with controllers alone, the default training's."""
    for path in _model_paths(policies):
        return learner_of_model(path).model_training_task(path).randomization
    from .models import default_training

    return default_training().training_task().randomization


def trained_task_of(policies: Sequence[str]) -> tuple[GraspLiftConfig, str | None]:
    """:func:`task_of` without a given task, except that controllers alone run on the benchmark task
    (``TrainConfig().env``: the dynamics and observation the results are about; the default run's task differs from it
    only in its reward and its critic's inputs), not on the env's defaults."""
    config, trained_on = task_of(policies, None)
    if trained_on is None:
        from .models import TrainConfig

        config = TrainConfig().env
    return config, trained_on


def evaluate(policies: Sequence[str], mus: Sequence[float], episodes: int, out_dir: str | Path,
             config: GraspLiftConfig | None = None, seed: int = EVALUATION_SEED, record: bool = False,
             progress: bool = True, n_envs: int | None = None, video: bool = False,
             conditions: Sequence[dict[str, float]] = UNSEEN_CONDITIONS,
             runner: Runner | None = None) -> dict[str, Any]:
    """Evaluate every policy spec on every mu; write JSON, CSV, two PNGs (and recordings) into ``out_dir``.

    Every spec is validated (and every model loaded) before any episode runs or anything is written. Episode i (at
    every mu) is reset with ``seed + i``: by default the sealed evaluation seeds (:mod:`.protocol`); the result
    records ``"seeds": {"first", "count", "sealed"}``.
    The registry's baselines (:func:`.controllers.baselines`: slip-reactive and oracle) are always added. Without
    ``config`` the task is the one the model(s) were trained on (their saved config), else (controllers only) the
    default training's. Each policy also runs at ``UNSEEN_MU`` on every tissue of ``conditions`` (stiffness / mass
    outside the training ranges).
    With ``runner`` (:mod:`.parallel`: local processes or Ray) every (policy, mu) cell, unseen condition and
    minimal-force bisection is its own job, models travel to the jobs as bytes (no shared disk needed), and
    the numbers are the same as without (same episodes, same seeds); recordings are made here.
    Returns ``{"results": [...], "oracle_minimal_force": {...}, "files": {...}, "recordings": [...]}``.
    """
    out_dir = Path(out_dir)
    policies = expand_policy_specs(policies)
    if not policies:
        raise ConfigError("no policy to evaluate: give at least one --policy")
    for spec in policies:
        check_policy_spec(spec)
    # the baselines are always there: a learned policy is never shown alone
    policies += [b for b in baselines() if b not in policies]
    # controllers alone run on the default training's task, as in the suite (not on the env's version-0 defaults)
    config, trained_on = task_of(policies, config) if config is not None else trained_task_of(policies)
    mus = [float(m) for m in mus]
    if not mus:
        raise ConfigError("the mu grid is empty")
    for m in mus:
        if not (math.isfinite(m) and 0.0 <= m <= MU_MAX):
            raise ConfigError(f"mu = {m!r} is out of range; allowed [0, {MU_MAX:g}]")
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    check_evaluation_seeds(seed, int(episodes), "seed")
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output folder {out_dir} exists and is not a folder")
    built = [build_policy(spec, config) for spec in policies]

    names: list[str] = []
    for pol in built:
        base = str(getattr(pol, "name", "policy")) or "policy"
        name, k = base, 2
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.append(name)

    t_start = time.perf_counter()
    envs: dict = {}
    if runner is not None:
        results, curve, unseen = _evaluate_on(runner, policies, names, mus, episodes, config, seed, n_envs,
                                              conditions, progress)
    else:
        results = []
        for spec, name, pol in zip(policies, names, built):
            if progress:
                print(f"evaluating {name} ({spec}) on {len(mus)} mu x {episodes} episodes", file=sys.stderr)
            t0 = time.perf_counter()
            rows = evaluate_policy(pol, mus, episodes, config, seed, n_envs, _envs=envs, progress=progress)
            results.append({"spec": spec, "name": name, "rows": rows, "seconds": round(time.perf_counter() - t0, 2)})
        if progress:
            print("oracle minimal-force curve", file=sys.stderr)
        curve = oracle_curve(config, mus, progress=progress)
        unseen = []
        for spec, name, pol in zip(policies, names, built):
            for opts in conditions:
                row = evaluate_policy(pol, [UNSEEN_MU], episodes, config, seed, n_envs, _envs=envs, options=opts)[0]
                unseen.append({"policy": name, "conditions": {"mu": UNSEEN_MU, **opts}, **row})
                if progress:
                    print(f"  {name}: {opts} at mu={UNSEEN_MU:g}: success={row['success_rate']:.2f} "
                          f"peak pinch={row['mean_peak_pinch_N']:.2f} N", file=sys.stderr)
    minimal = dict(zip(curve["mu"], curve["minimal_force_N"]))
    # the force ratio: over the reference (a slower pull cannot lower it) where the task has a table and mu is on its
    # grid; the ratio to the nominal oracle at pull 0.5 stays beside it
    references, reference = references_at(config, [float(m) for m in mus])
    for pol in results:
        for r in pol["rows"]:
            r["peak_pinch_over_oracle_min"] = r["mean_peak_pinch_N"] / minimal[r["mu"]]
            ref = references.get(f"{r['mu']:g}")
            r["force_ratio"] = r["mean_peak_pinch_N"] / ref if ref else None  # (None: no reference at this mu)

    recordings: list[str] = []
    if record:
        recordings = _record_all(names, built, mus, config, seed, out_dir / "recordings", progress)
    if video:
        recordings += _record_all(names, built, mus, config, seed, out_dir / "videos", progress, suffix=".mp4")

    summary = {
        "seeds": seeds_record(seed, episodes),
        "config": to_dict(config),
        "evaluation": {
            "mu_grid": mus,
            "episodes": int(episodes),
            "seed": int(seed),
            "seeds": [int(seed) + i for i in range(int(episodes))],
            "reset_options": "{'mu': mu}; other randomisation as configured",
            "n_envs": n_envs,
            "runner": "this process" if runner is None else runner.label,
            "policies": policies,
            "training_mu_range": list(config.randomization.mu_range),
            "training_config_from": trained_on,
            "success": "info['is_success'] at the episode's end: lift_target_m reached and held hold_time_s "
                       "with less than hold_slip_tolerance_m slip",
            "seconds": round(time.perf_counter() - t_start, 2),
        },
        "results": results,
        "oracle_minimal_force": curve,
        "reference": reference,
        "reference_force_N": references,
        "unseen_conditions": unseen,
        "recordings": recordings,
    }
    files = {
        "json": out_dir / "evaluation.json",
        "csv": out_dir / "evaluation.csv",
        "success_png": out_dir / "success_vs_mu.png",
        "pinch_png": out_dir / "pinch_vs_mu.png",
    }
    atomic_write_text(files["json"], json.dumps(nan_to_none(summary), indent=2) + "\n")
    atomic_write_text(files["csv"], _csv_text(results))
    _plot_success(results, config, files["success_png"])
    _plot_pinch(results, curve, files["pinch_png"])
    return {"results": results, "oracle_minimal_force": curve, "files": {k: str(v) for k, v in files.items()},
            "recordings": recordings, "unseen_conditions": unseen, "config": config, "seeds": summary["seeds"]}


# ------------------------------------------------------------------------------------------------
# the evaluation as independent jobs (a Runner: local processes or Ray)
# ------------------------------------------------------------------------------------------------


#: spec or the model's file name, display name, the model's files by name (None: a built-in controller)
PolicyPayload = tuple[str, str, dict[str, bytes] | None]


def _payload(spec: str, name: str) -> PolicyPayload:
    """What a job needs to rebuild a policy on any machine: a built-in spec, or the model's files (the model
    and the file that records its learner and config, :meth:`~.learners.Learner.model_files`)."""
    if is_controller(spec):
        return spec, name, None
    path = Path(spec)
    files = learner_of_model(path).model_files(path)
    return path.name, name, {n: p.read_bytes() for n, p in files.items()}


def _policy_of(payload: PolicyPayload, config: GraspLiftConfig):
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


def _cell_job(payload: PolicyPayload, config_dict: dict[str, Any], mu: float, episodes: int, seed: int,
              n_envs: int | None, options: dict[str, float] | None) -> dict[str, Any]:
    config = from_dict(GraspLiftConfig, config_dict, where="env")
    return evaluate_policy(_policy_of(payload, config), [mu], episodes, config, seed, n_envs, options=options)[0]


def _evaluate_on(runner: Runner, policies, names, mus, episodes, config, seed, n_envs, conditions, progress):
    """(results, oracle curve, unseen rows) of :func:`evaluate`, every cell a job on ``runner``."""
    cfg = to_dict(config)
    payloads = [_payload(spec, name) for spec, name in zip(policies, names)]
    jobs: list = []
    where: list[tuple[str, int, Any]] = []
    for p, payload in enumerate(payloads):
        for mu in mus:
            jobs.append((_cell_job, (payload, cfg, float(mu), int(episodes), int(seed), n_envs, None)))
            where.append(("cell", p, mu))
        for opts in conditions:
            jobs.append((_cell_job, (payload, cfg, UNSEEN_MU, int(episodes), int(seed), n_envs, dict(opts))))
            where.append(("unseen", p, opts))
    for mu in mus:
        jobs.append((_minimal_force_job, (cfg, float(mu))))
        where.append(("oracle", -1, mu))

    def done(k: int, res: Any) -> None:
        kind, p, what = where[k]
        if progress and kind != "oracle":
            label = f"mu={what:g}" if kind == "cell" else f"{what} at mu={UNSEEN_MU:g}"
            print(f"  {names[p]}: {label} success={res['success_rate']:.2f} "
                  f"peak pinch={res['mean_peak_pinch_N']:.2f} N", file=sys.stderr)

    t0 = time.perf_counter()
    with runner:
        out = runner.run(jobs, on_done=done)
    seconds = round(time.perf_counter() - t0, 2)
    results = [{"spec": spec, "name": name, "seconds": seconds,
                "rows": [r for (kind, p, _), r in zip(where, out) if kind == "cell" and p == k]}
               for k, (spec, name) in enumerate(zip(policies, names))]
    unseen = [{"policy": names[p], "conditions": {"mu": UNSEEN_MU, **opts}, **r}
              for (kind, p, opts), r in zip(where, out) if kind == "unseen"]
    forces = [r for (kind, _, _), r in zip(where, out) if kind == "oracle"]
    return results, _curve_record(config, mus, forces), unseen


# ------------------------------------------------------------------------------------------------
# recordings
# ------------------------------------------------------------------------------------------------


def record_policy_episode(policy, env, path: str | Path, mu: float, seed: int = 0,
                          still: str | Path | None = None, video: str | Path | None = None) -> dict[str, Any]:
    """Record one episode of ``policy`` (batch interface) on the single env ``env`` at friction ``mu``:
    a rerun recording for a ``.rrd`` path, a video for ``.mp4`` / ``.gif``. ``video`` (with an ``.rrd``
    path): the same episode, run once, also rendered to that video (``still``: its last frame as a PNG)."""
    from ..envs.recording import RerunRecorder, record_episode
    from ..envs.video import VIDEO_SUFFIXES, record_video

    options = {"mu": float(mu)}
    # the reset info the recorder's reset will produce (same seed, same options): the policy needs it
    _, info = env.reset(seed=int(seed), options=options)
    policy.reset([dict(info)])

    def policy_fn(obs: np.ndarray) -> np.ndarray:
        return np.asarray(policy.act(np.asarray(obs)[None]), dtype=np.float64).reshape(-1, 2)[0]

    if Path(path).suffix.lower() in VIDEO_SUFFIXES:
        if video is not None:
            raise ValueError(f"video={video!r} needs an .rrd path, got {path}")
        return record_video(env, policy_fn, path, seed=int(seed), options=options, still=still)
    if video is None:
        return record_episode(env, policy_fn, path, seed=int(seed), options=options)
    recorder = RerunRecorder(env, path)  # logs every step of the episode the video renders
    try:
        summary = record_video(recorder, policy_fn, video, seed=int(seed), options=options, still=still)
        written = recorder.finish()
    except BaseException:
        recorder.abort()
        raise
    return {**summary, "path": str(written[0]), "video": summary["path"],
            "size_bytes": written[0].stat().st_size}


def _record_all(names, built, mus, config, seed, folder: Path, progress: bool, suffix: str = ".rrd") -> list[str]:
    from ..envs.grasp_lift import GraspLiftEnv

    env = GraspLiftEnv(config)
    paths = []
    try:
        for name, pol in zip(names, built):
            for mu in mus:
                path = folder / f"{_safe_name(name)}_mu{_mu_label(mu)}{suffix}"
                summary = record_policy_episode(pol, env, path, mu, seed)
                paths.append(summary["path"])
                if progress:
                    print(f"  recorded {path} ({summary['steps']} steps, success={summary['success']})",
                          file=sys.stderr)
    finally:
        env.close()
    return paths


def _seconds(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2f}"


def format_unseen(unseen: list[dict[str, Any]]) -> str:
    """A text table of the unseen-tissue rows (stiffness / mass outside the training ranges)."""
    lines = [f"{'policy':<16} {'conditions':<32} {'success':>7} {'peak N':>7} {'t_lift s':>8}", "-" * 74]
    for r in unseen:
        cond = ", ".join(f"{k}={v:g}" for k, v in r["conditions"].items())
        lines.append(f"{r['policy'][:16]:<16} {cond:<32} {r['success_rate']:>7.2f} {r['mean_peak_pinch_N']:>7.2f} "
                     f"{_seconds(r['mean_time_to_lift_s']):>8}")
    return "\n".join(lines)


def _ratio(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2f}"


def format_table(results: list[dict[str, Any]]) -> str:
    """A compact text table of the evaluation rows: success, the peak pinch, its ratio to the reference force (/ref:
    agents/reference.py, '-' without a table or off its grid) and to the oracle's minimal force at pull 0.5 (/oracle),
    beside them the mean time to lift (over the episodes that lifted), then the other metrics."""
    head = f"{'policy':<16} {'mu':>5} {'success':>7} {'peak N':>7} {'/ref':>6} {'/oracle':>7} {'t_lift s':>8} " \
           f"{'max N':>6} {'mean N':>6} {'slip mm':>7} {'stress kPa':>10} {'return':>7}"
    lines = [head, "-" * len(head)]
    for pol in results:
        for r in pol["rows"]:
            lines.append(
                f"{pol['name'][:16]:<16} {r['mu']:>5.2f} {r['success_rate']:>7.2f} {r['mean_peak_pinch_N']:>7.2f} "
                f"{_ratio(r.get('force_ratio')):>6} "
                f"{r.get('peak_pinch_over_oracle_min', float('nan')):>7.2f} {_seconds(r['mean_time_to_lift_s']):>8} "
                f"{r['max_peak_pinch_N']:>6.2f} {r['mean_pinch_N']:>6.2f} {r['mean_slip_mm']:>7.2f} "
                f"{r['mean_peak_stress_kPa']:>10.1f} {r['mean_return']:>7.2f}"
            )
    return "\n".join(lines)
