"""How light a grip could be, by what it knows: each episode's holding grip against what predicts it.

A policy that holds a share of the grasps with the least force must know each episode's holding grip. Which part of
that grip can any policy know? ``msdgrasp headroom`` measures it on development episodes of a task (the default
training's, in-range perturbations and all):

1. **The holding grip** h_k of each episode (the hindsight oracle, :func:`.controllers.episode_minimal_forces`: the
   least fixed pinch force, within 0.05 N, with which the fixed-force controller lifts and holds it at the
   controller's pull speed; none where no grip up to 5 N does: an episode no fixed grip holds).
2. **What predicts log h_k**, each a regression whose residuals are leave-one-out (ridge; the closed form
   r_i / (1 - H_ii), so no episode predicts itself), pooled over the friction grid (:data:`SOURCES`):
   the true mu; the true mu and every privileged draw (stiffness and mass scales, pose error, force biases, latency,
   force-loop gain error); the estimating controller's friction estimate; the closing features it estimates from.
3. **What it is worth**: for each source, the fixed grip exp(prediction) x M, M the :data:`HOLD_SHARE` quantile of
   exp(residual) over the other episodes (so that it would hold about that share of the episodes with a holding grip,
   no episode sizing its own margin), run on every episode by the fixed-force controller at the same pull: its success
   and mean peak pinch per mu beside the controller's. A source that knows mu sizes its margin per mu, so that it
   holds about that share at every mu; the others one margin for all mu.

The residual spread bounds what a source is worth to a fixed grip under this model (a ridge regression of log h):
whatever learns from it, a grip that knows no more needs about the margin M to hold the share. The episodes are reset
with seeds from :data:`HEADROOM_SEED` (inside :data:`HEADROOM_SEEDS`, apart from trainings, validations, the reference
and the sealed evaluation seeds).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from ..envs.core import GraspLiftConfig
from ..envs.perturbations import privileged_names
from ..physics.config import ConfigError, from_dict, to_dict
from .parallel import Runner, run_jobs

#: the seeds of the development episodes (half-open), apart from every other use
HEADROOM_SEEDS = range(5_000_000, 6_000_000)
HEADROOM_SEED = HEADROOM_SEEDS.start
#: the friction grid and the episodes per mu by default (the in-range suite's grid)
DEFAULT_MUS = (0.2, 0.3, 0.5, 0.8)
DEFAULT_EPISODES = 40
#: the estimating controller of the default training (agents.controller_registry spec)
DEFAULT_CONTROLLER = "slipfeedback:estimator=builtin,gate=0.9,gain=0.5,pull=0.3"
#: the share of the episodes with a holding grip that each source's fixed grip is sized to hold
HOLD_SHARE = 0.95
#: ridge weights of the standardised regressors: near zero for the few of mu, more for the 55 closing features
RIDGE = {"mu": 1e-6, "mu_draws": 1.0, "estimate": 1e-6, "closing": 10.0}
#: the sources that know mu, and so size their margin per mu (the others one margin for all)
KNOWS_MU = ("mu", "mu_draws")
#: what each source knows
SOURCES = {
    "mu": "the episode's true friction (log mu, log^2 mu)",
    "mu_draws": "the true friction and every privileged draw (scales, pose error, biases, latency, gain error)",
    "estimate": "the estimating controller's friction estimate (log, log^2)",
    "closing": "the closing features the controller estimates from (55, sensed)",
}


def privileged_draws(obs: np.ndarray, info: dict[str, Any]) -> np.ndarray:
    """Each episode's privileged draws at reset: log stiffness and mass scales (from the reset ``info``), then the
    perturbation block (:func:`.perturbations.privileged_names`), the last entries of an observation of a task with
    ``privileged_perturbations`` (its current frame's, frames being oldest first)."""
    n_pert = len(privileged_names())
    return np.column_stack([np.log(info["stiffness_scale"]), np.log(info["mass_scale"]), obs[:, -n_pert:]])


def _episodes_job(config_dict: dict[str, Any], mus: list[float], seeds: list[int], controller: str) -> dict[str, Any]:
    """One chunk of episodes, in a worker: each one's holding grip, privileged draws and the controller's run."""
    from ..envs.grasp_lift import GraspLiftVectorEnv
    from .controllers import episode_minimal_forces
    from .evaluation import build_policy
    from .rollout import run_batch

    config = from_dict(GraspLiftConfig, config_dict, where="env")
    policy = build_policy(controller, config)
    env = GraspLiftVectorEnv(len(seeds), config)
    draws = privileged_draws(*env.reset(seed=seeds, options={"mu": mus}))
    run = run_batch(env, policy, mus, seeds)  # (reset again with the same seeds: the same episodes)
    return {"hold_N": episode_minimal_forces(config, mus, seeds, pull=policy.pull).tolist(),
            "draws": draws.tolist(), "success": run["success"].tolist(), "peak_pinch_N": run["peak_pinch_N"].tolist(),
            "mu_estimate": policy.mu_estimate.tolist(), "features": policy.closing_features.tolist()}


def _fixed_grip_job(config_dict: dict[str, Any], mu: float, seeds: list[int], forces: list[float],
                    pull: float) -> dict[str, list]:
    from .reference import run_fixed_grips

    config = from_dict(GraspLiftConfig, config_dict, where="env")
    run = run_fixed_grips(config, mu, seeds, forces, pull)
    return {"success": run["success"].tolist(), "peak_pinch_N": run["peak_pinch_N"].tolist()}


def _ridge_system(x: np.ndarray, ridge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The design (standardised columns of ``x``, then the intercept), its column mean and scale, and the ridge's
    normal matrix (the intercept unpenalised)."""
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-12
    a = np.c_[(x - mean) / scale, np.ones(len(x))]
    return a, mean, scale, a.T @ a + np.diag([float(ridge)] * x.shape[1] + [0.0])


def loo_ridge_residuals(x: np.ndarray, y: np.ndarray, ridge: float) -> np.ndarray:
    """Leave-one-out residuals of a ridge regression of ``y`` on the standardised columns of ``x`` with an
    unpenalised intercept (the hat matrix's closed form r_i / (1 - H_ii))."""
    a, _, _, normal = _ridge_system(np.asarray(x, dtype=np.float64).reshape(len(y), -1), ridge)
    hat = a @ np.linalg.solve(normal, a.T)
    return (y - hat @ y) / (1.0 - np.diag(hat))


def _ridge_predict(x: np.ndarray, y: np.ndarray, ridge: float, new: np.ndarray) -> np.ndarray:
    """The same ridge regression fitted on every row of ``x``, predicting at the rows ``new``."""
    a, mean, scale, normal = _ridge_system(x, ridge)
    return np.c_[(new - mean) / scale, np.ones(len(new))] @ np.linalg.solve(normal, a.T @ y)


def leave_one_out_quantiles(values: np.ndarray, q: float) -> np.ndarray:
    """For each entry, the ``q`` quantile of the other entries (numpy's linear interpolation)."""
    values = np.asarray(values, dtype=np.float64)
    return np.array([np.quantile(np.delete(values, i), q) for i in range(len(values))])


def _regressors(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    log_mu, log_est = np.log(data["mu"]), np.log(data["mu_estimate"])
    return {"mu": np.c_[log_mu, log_mu ** 2], "mu_draws": np.c_[log_mu, log_mu ** 2, data["draws"]],
            "estimate": np.c_[log_est, log_est ** 2], "closing": data["features"]}


def _margined(pred: np.ndarray, resid: np.ndarray, fit: np.ndarray, groups: np.ndarray, share: float
              ) -> tuple[np.ndarray, dict[float, float]]:
    """Grips exp(pred) x the ``share`` quantile of exp(residual) within each group, for a fitted episode over the
    group's other fitted episodes; a group with fewer than 2 fitted episodes takes the pooled quantile."""
    e = np.exp(resid)
    pooled = float(np.quantile(e, share))
    grip, margins = np.exp(pred), {}
    rows = np.flatnonzero(fit)
    for g in np.unique(groups):
        mine = groups[fit] == g  # (over the fitted episodes)
        if mine.sum() >= 2:
            margins[float(g)] = float(np.quantile(e[mine], share))
            grip[rows[mine]] *= leave_one_out_quantiles(e[mine], share)
        else:
            margins[float(g)] = pooled
            grip[rows[mine]] *= pooled
        grip[~fit & (groups == g)] *= margins[float(g)]
    return grip, margins


def source_grips(data: dict[str, np.ndarray], share: float = HOLD_SHARE) -> dict[str, dict[str, Any]]:
    """Per source: its leave-one-out residual spread of log h and the fixed grip per episode (N) sized to hold
    ``share`` of the episodes with a holding grip, per mu for a source that knows mu (:data:`KNOWS_MU`), over all
    for the others. The regressions fit on those episodes; every episode gets a grip."""
    hold = data["hold_N"]
    out = {}
    for name, x in _regressors(data).items():
        x = np.asarray(x, dtype=np.float64).reshape(len(hold), -1)
        known = np.all(np.isfinite(x), axis=1)  # (an episode the controller made no estimate in: the mean grip)
        fit = np.isfinite(hold) & known
        x = np.where(known[:, None], x, np.nanmean(np.where(fit[:, None], x, np.nan), axis=0))
        if fit.sum() < 3:
            raise ConfigError(f"headroom: {int(fit.sum())} episodes with a holding grip and a {name} regressor; the "
                              "regression needs at least 3 (more episodes, or frictions a grip can hold)")
        y = np.log(hold[fit])
        resid = loo_ridge_residuals(x[fit], y, RIDGE[name])
        pred = np.empty(len(hold))
        pred[fit] = y - resid
        if (~fit).any():  # (episodes not fitted: the regression on every fitted one predicts them)
            pred[~fit] = _ridge_predict(x[fit], y, RIDGE[name], x[~fit])
        groups = data["mu"] if name in KNOWS_MU else np.zeros(len(hold))
        grip, margins = _margined(pred, resid, fit, groups, share)
        out[name] = {"what": SOURCES[name], "residual_sd": float(resid.std()), "r2": float(1 - resid.var() / y.var()),
                     "margins": list(margins.values()), "grip_N": grip, "fitted": int(fit.sum())}
    return out


def _chunks(mus: Sequence[float], episodes: int, seed: int, size: int) -> list[tuple[list[float], list[int]]]:
    mu = [float(m) for m in mus for _ in range(episodes)]
    seeds = [seed + k for k in range(len(mu))]
    return [(mu[i:i + size], seeds[i:i + size]) for i in range(0, len(mu), size)]


def _per_mu(mus: np.ndarray, grid: Sequence[float], success: np.ndarray, peak: np.ndarray,
            controller_peak: np.ndarray) -> list[dict[str, float]]:
    rows = []
    for m in grid:
        k = mus == m
        rows.append({"mu": float(m), "episodes": int(k.sum()), "success_rate": float(success[k].mean()),
                     "mean_peak_pinch_N": float(peak[k].mean()),
                     "force_vs_controller": float(peak[k].mean() / controller_peak[k].mean())})
    return rows


def estimating_controller(spec: str, config: GraspLiftConfig):
    """The controller ``spec`` names on ``config`` (ConfigError where it is none that estimates the friction)."""
    from .evaluation import build_policy

    policy = build_policy(spec, config)
    if getattr(policy, "estimator", None) is None or getattr(policy, "told_mu", False):
        raise ConfigError(f"the controller must be a slip-feedback controller with a friction estimator, not told mu "
                          f"(e.g. {DEFAULT_CONTROLLER}), got {spec!r}")
    return policy


def measure_headroom(config: GraspLiftConfig, mus: Sequence[float] = DEFAULT_MUS, episodes: int = DEFAULT_EPISODES,
                     seed: int = HEADROOM_SEED, controller: str = DEFAULT_CONTROLLER, runner: Runner | None = None,
                     chunk: int = 20) -> dict[str, Any]:
    """The headroom record of ``config`` (see the module docstring): ``episodes`` per mu of ``mus``."""
    if not (HEADROOM_SEEDS.start <= seed and seed + episodes * len(mus) <= HEADROOM_SEEDS.stop):
        raise ConfigError(f"seed must keep the episodes in [{HEADROOM_SEEDS.start}, {HEADROOM_SEEDS.stop}), got {seed}")
    policy = estimating_controller(controller, config)  # (a bad spec fails here, before anything runs)
    t0 = time.time()
    config = replace(config, privileged_obs=True, privileged_perturbations=True)
    cd = to_dict(config)
    parts = run_jobs([(_episodes_job, (cd, m, s, controller)) for m, s in _chunks(mus, episodes, seed, chunk)], runner)
    data = {k: np.concatenate([np.asarray(p[k], dtype=np.float64) for p in parts]) for k in parts[0]}
    data["mu"] = np.asarray([float(m) for m in mus for _ in range(episodes)])
    seeds = np.arange(seed, seed + len(data["mu"]))
    grips = source_grips(data)
    at = {float(m): data["mu"] == m for m in mus}
    jobs = [(_fixed_grip_job, (cd, m, seeds[k].tolist(), g["grip_N"][k].tolist(), policy.pull))
            for g in grips.values() for m, k in at.items()]
    runs = iter(run_jobs(jobs, runner))
    ctl_peak = data["peak_pinch_N"]
    sources = {}
    for name, g in grips.items():
        res = [next(runs) for _ in mus]
        success = np.concatenate([r["success"] for r in res])
        peak = np.concatenate([r["peak_pinch_N"] for r in res])
        sources[name] = {k: v for k, v in g.items() if k != "grip_N"} | {
            "per_mu": _per_mu(data["mu"], mus, success.astype(bool), peak, ctl_peak)}
    held = [data["hold_N"][(data["mu"] == m) & np.isfinite(data["hold_N"])] for m in mus]
    hindsight = [{"mu": float(m), "held_share": len(h) / episodes, "mean_hold_N": float(h.mean()) if len(h) else None}
                 for m, h in zip(mus, held)]
    return {"controller": controller, "pull": policy.pull, "mus": [float(m) for m in mus], "episodes": episodes,
            "seeds": f"{seed} + k, k < {len(seeds)} (episode k at mu grid[k // episodes])", "hold_share": HOLD_SHARE,
            "controller_per_mu": _per_mu(data["mu"], mus, data["success"].astype(bool), ctl_peak, ctl_peak),
            "hindsight": hindsight, "sources": sources, "per_episode": _per_episode(seeds, data),
            "seconds": round(time.time() - t0, 1)}


def _per_episode(seeds: np.ndarray, data: dict[str, np.ndarray]) -> dict[str, list]:
    """Each episode's seed, mu, holding grip (None: no grip up to 5 N holds it) and the controller's run, so that
    another policy can be run on the same episodes against their holding grips."""
    def plain(values: np.ndarray) -> list:
        return [float(v) if np.isfinite(v) else None for v in values]

    return {"seed": seeds.tolist(), "mu": data["mu"].tolist(), "hold_N": plain(data["hold_N"]),
            "controller_success": data["success"].astype(bool).tolist(),
            "controller_peak_pinch_N": plain(data["peak_pinch_N"]),
            "controller_mu_estimate": plain(data["mu_estimate"])}


def format_headroom(record: dict[str, Any]) -> str:
    """A markdown table of a headroom record: per source, its spread, margin, success and force per mu."""
    mus = " / ".join(f"{m:g}" for m in record["mus"])
    lines = [f"Holding grips of {record['episodes']} episodes per mu ({mus}), pull {record['pull']:g}; "
             f"a fixed grip sized to hold {record['hold_share']:.0%} of the holdable ones",
             "", "| what the grip knows | log sd (LOO) | margin | success per mu | peak pinch / controller's per mu |",
             "|---|---|---|---|---|"]

    def cells(rows: list[dict[str, float]], key: str) -> str:
        return " / ".join(f"{r[key]:.2f}" for r in rows)

    ctl = record["controller_per_mu"]
    lines.append(f"| the controller ({record['controller']}) | - | - | {cells(ctl, 'success_rate')} | "
                 f"{cells(ctl, 'mean_peak_pinch_N')} N |")
    for name, s in record["sources"].items():
        margin = "-".join(f"{m:.2f}" for m in sorted({min(s["margins"]), max(s["margins"])}))
        lines.append(f"| {name}: {s['what']} | {s['residual_sd']:.3f} | {margin} | "
                     f"{cells(s['per_mu'], 'success_rate')} | {cells(s['per_mu'], 'force_vs_controller')} |")
    held = " / ".join(f"{h['held_share']:.2f}" for h in record["hindsight"])
    lines += ["", f"Episodes some fixed grip up to 5 N holds, per mu: {held}."]
    return "\n".join(lines)


def headroom_verdict(record: dict[str, Any], target: float = 0.95) -> str:
    """One line: the lightest source whose fixed grip holds at least the controller's grasps at every mu, and its
    largest force ratio, against the learned-control target ``target`` x the controller's force."""
    ctl = [r["success_rate"] for r in record["controller_per_mu"]]
    fits = {name: max(r["force_vs_controller"] for r in s["per_mu"]) for name, s in record["sources"].items()
            if all(r["success_rate"] >= c - 1e-9 for r, c in zip(s["per_mu"], ctl))}
    if not fits:
        return "no source's fixed grip holds the controller's grasps at every mu"
    best = min(fits, key=fits.get)
    met = "within" if fits[best] <= target else "above"
    return (f"lightest fixed grip holding the controller's grasps at every mu: {best}, at most "
            f"{fits[best]:.2f}x the controller's force ({met} {target:g}x)")


__all__ = ["DEFAULT_CONTROLLER", "DEFAULT_EPISODES", "DEFAULT_MUS", "HEADROOM_SEED", "HEADROOM_SEEDS",
           "HOLD_SHARE", "KNOWS_MU", "SOURCES", "estimating_controller", "format_headroom", "headroom_verdict",
           "leave_one_out_quantiles", "loo_ridge_residuals", "measure_headroom", "privileged_draws", "source_grips"]
