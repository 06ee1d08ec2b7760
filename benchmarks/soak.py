"""Soak test of the GraspLift vector env (``msdgrasp soak``): many randomised episodes, nothing may break.

Episodes run on :class:`~msdgrasp.envs.grasp_lift.GraspLiftVectorEnv` with friction and stiffness drawn
across *and beyond* the training ranges (mu in [0, 1.5], stiffness scale in [0.5, 2.0] vs the default
0.3-0.9 and 0.8-1.2; wider mass and pose jitter too; the stiffest allowed tissue sets the substeps), with
a mix of controllers per episode: uniform random actions, the scripted :class:`FixedForcePolicy` (set
points up to 8 N) and :class:`SlipReactivePolicy`, bang-bang and "squeeze shut" actions, and occasional
out-of-range actions (up to +-5, which the env clips). Now and then every sub-env is reset with pinned
extreme options (mu 0 or 1.5, the softest or stiffest tissue, the lightest tissue, largest pose offsets).

Counted: episodes (and their outcomes), agent steps, numerical blow-ups (these must be terminations with
``info['error']`` and finite observations), *silent* NaNs (any non-finite observation or reward handed
out, including ``final_obs``), blow-ups reported without the error flag, exceptions (count and the first
traceback; the env is reset and the soak goes on), peak RSS and RSS growth after warm-up (sampled every
1 % of the run; growth = last sample / first sample after the warm-up 10 % - 1, target < 5 %).

``soak_cli`` prints the JSON report, writes ``report.json`` into ``--out`` atomically and exits 1 if any
silent NaN, unflagged blow-up or exception occurred, else 0.
"""

from __future__ import annotations

import json
import math
import os
import resource
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..physics.config import ConfigError

#: the soak's ranges (training defaults: mu 0.3-0.9, stiffness 0.8-1.2, mass 0.9-1.1)
MU_RANGE = (0.0, 1.5)
STIFFNESS_RANGE = (0.5, 2.0)
MASS_RANGE = (0.8, 1.25)
TRAIN_MU = (0.3, 0.9)
TRAIN_STIFFNESS = (0.8, 1.2)
MEMORY_GROWTH_TARGET = 0.05

MODES = ("random", "fixed", "reactive", "bang_bang", "squeeze", "sticky_random")
MODE_P = np.array([0.35, 0.2, 0.2, 0.1, 0.05, 0.1])

#: pinned extremes used by the occasional full reset
EXTREME_OPTIONS: tuple[dict[str, float], ...] = (
    {"mu": 0.0},
    {"mu": MU_RANGE[1]},
    {"stiffness_scale": STIFFNESS_RANGE[0]},
    {"stiffness_scale": STIFFNESS_RANGE[1]},
    {"mass_scale": MASS_RANGE[0], "stiffness_scale": STIFFNESS_RANGE[1]},
    {"mu": 0.0, "stiffness_scale": STIFFNESS_RANGE[1], "mass_scale": MASS_RANGE[0]},
    {"mu": MU_RANGE[1], "stiffness_scale": STIFFNESS_RANGE[0], "pose_offset_m": 0.006, "pose_tilt_deg": 8.0,
     "pose_azimuth_deg": 20.0},
)


def soak_config(resolution: str | int = "coarse"):
    """GraspLiftConfig whose randomisation spans the soak's (wider than training) ranges."""
    from ..envs.core import GraspLiftConfig, RandomizationConfig

    rnd = RandomizationConfig(mu_range=MU_RANGE, stiffness_scale_range=STIFFNESS_RANGE, mass_scale_range=MASS_RANGE,
                              pose_offset_m=0.003, pose_tilt_deg=3.0, pose_azimuth_deg=5.0, sensor_noise_N=0.05)
    return GraspLiftConfig(resolution=resolution, randomization=rnd)


def make_env(n_envs: int, config=None):
    from ..envs.grasp_lift import GraspLiftVectorEnv

    return GraspLiftVectorEnv(n_envs, config if config is not None else soak_config())


class MixedPolicy:
    """Per sub-env controller mode, redrawn every episode; scripted modes use the baseline controllers.

    Call :meth:`reset_all` after the env's reset and :meth:`new_episode` for each sub-env that autoresets.
    """

    def __init__(self, config, n_envs: int, rng: np.random.Generator) -> None:
        from ..agents.controllers import FixedForcePolicy, SlipReactivePolicy

        self.n = n_envs
        self.rng = rng
        self.fixed = FixedForcePolicy(config)
        self.reactive = SlipReactivePolicy(config)
        self.fixed.reset([{}] * n_envs)
        self.reactive.reset([{}] * n_envs)
        self.mode = np.zeros(n_envs, dtype=np.int64)
        self.held = np.zeros((n_envs, 2))
        self.hold_left = np.zeros(n_envs, dtype=np.int64)
        self.mode_counts = {m: 0 for m in MODES}
        self.extreme_actions = 0

    def new_episode(self, i: int) -> None:
        m = int(self.rng.choice(len(MODES), p=MODE_P))
        self.mode[i] = m
        self.mode_counts[MODES[m]] += 1
        self.hold_left[i] = 0
        # per-episode state of the batched baseline controllers; the fixed one gets a random set-point
        self.fixed.reset_one(i, {})
        self.fixed.force[i] = self.rng.uniform(0.5, 8.0)
        self.reactive.reset_one(i, {})

    def reset_all(self) -> None:
        for i in range(self.n):
            self.new_episode(i)

    def act(self, obs: np.ndarray) -> np.ndarray:
        n, rng = self.n, self.rng
        a = rng.uniform(-1.0, 1.0, (n, 2))
        a = np.where((self.mode == 1)[:, None], self.fixed.act(obs), a)
        a = np.where((self.mode == 2)[:, None], self.reactive.act(obs), a)
        bang = rng.choice([-1.0, 1.0], size=(n, 2))
        a = np.where((self.mode == 3)[:, None], bang, a)
        a = np.where((self.mode == 4)[:, None], np.array([1.0, 0.0]), a)  # close as hard as possible, never pull
        sticky = self.mode == 5
        renew = sticky & (self.hold_left <= 0)
        if np.any(renew):
            self.held[renew] = rng.uniform(-1.0, 1.0, (int(renew.sum()), 2))
            self.hold_left[renew] = rng.integers(5, 60, int(renew.sum()))
        self.hold_left[sticky] -= 1
        a = np.where(sticky[:, None], self.held, a)
        # occasionally an out-of-range action (the env clips it to [-1, 1])
        wild = rng.random(n) < 0.01
        if np.any(wild):
            k = int(wild.sum())
            a[wild] = rng.choice([-1.0, 1.0], size=(k, 2)) * rng.uniform(1.0, 5.0, (k, 2))
            self.extreme_actions += k
        return a.astype(np.float32)


def _rss_bytes() -> int:
    try:
        import psutil

        return int(psutil.Process(os.getpid()).memory_info().rss)
    except Exception:
        try:
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def _peak_rss_bytes() -> int:
    ru = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(ru) * (1 if sys.platform == "darwin" else 1024)


def _check_count(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")


def _flags(info: dict, key: str, n: int) -> np.ndarray:
    """info[key] as (n,) bools (all False where the env did not report it)."""
    return np.asarray(info.get(key, np.zeros(n, dtype=bool)), dtype=bool)


def _not_finite(a: Any, n: int) -> np.ndarray:
    """(n,) True where a sub-env's row of ``a`` holds a non-finite value."""
    return ~np.all(np.isfinite(np.asarray(a, dtype=np.float64).reshape(n, -1)), axis=1)


class SoakTally:
    """What the soak counts over its steps (``counts``) and the first failures' details."""

    OUTCOMES = ("success", "lost_grasp", "damaged", "numerical_failure", "truncated")
    #: the outcomes the env's info flags (outcome: info key)
    OUTCOME_FLAGS = {"success": "is_success", "lost_grasp": "lost_grasp", "damaged": "damaged"}
    #: info values that must stay finite wherever the physics has not failed
    INFO_VALUES = ("pinch_force_N", "slip_distance_m", "lifted_m", "peak_stress_pa", "contact_nodes")

    def __init__(self, n_envs: int) -> None:
        self.n = n_envs
        self.counts: dict[str, Any] = {
            "episodes": 0, "steps": 0, "vector_steps": 0, "silent_nan": 0, "silent_nan_obs": 0,
            "silent_nan_reward": 0, "silent_nan_final_obs": 0, "blowups": 0, "blowups_unflagged": 0,
            "nonfinite_info_values": 0, "exceptions": 0, "forced_resets": 0, "episodes_interrupted": 0,
            "outcomes": dict.fromkeys(self.OUTCOMES, 0),
        }
        self.first_traceback: str | None = None
        self.first_silent_nan: dict | None = None

    def exception(self) -> None:
        """Count the exception being handled (the first one's traceback is kept)."""
        self.counts["exceptions"] += 1
        self.first_traceback = self.first_traceback or traceback.format_exc()

    def step(self, k: int, env, obs, reward, term, trunc, info: dict) -> np.ndarray:
        """Count vector step ``k``'s results; the sub-envs whose episode ended."""
        c, n = self.counts, self.n
        c["vector_steps"] += 1
        c["steps"] += n
        bad = self._silent_nan(k, env, obs, reward, info)
        failed = _flags(info, "numerical_failure", n)
        self._blowups(failed, term, info, bad)
        for key in self.INFO_VALUES:
            if key in info:
                v = np.asarray(info[key], dtype=np.float64)
                c["nonfinite_info_values"] += int((~np.isfinite(v) & ~failed).sum())
        done = np.flatnonzero(np.asarray(term, dtype=bool) | np.asarray(trunc, dtype=bool))
        if done.size:
            self._episodes(done, failed, trunc, info)
        return done

    def _silent_nan(self, k: int, env, obs, reward, info: dict) -> np.ndarray:
        """Count non-finite observations, rewards and final observations handed out; (n,) where any was."""
        c, n = self.counts, self.n
        bad_obs = _not_finite(obs, n)
        bad_rew = ~np.isfinite(np.asarray(reward, dtype=np.float64))
        bad_final = _not_finite(info["final_obs"], n) if "final_obs" in info else np.zeros(n, dtype=bool)
        bad = bad_obs | bad_rew | bad_final
        if np.any(bad):
            c["silent_nan"] += int(bad.sum())
            c["silent_nan_obs"] += int(bad_obs.sum())
            c["silent_nan_reward"] += int(bad_rew.sum())
            c["silent_nan_final_obs"] += int(bad_final.sum())
            if self.first_silent_nan is None:
                i = int(np.flatnonzero(bad)[0])
                mu = float(env.core.mu[i]) if hasattr(env, "core") else None
                self.first_silent_nan = {"vector_step": k, "env": i, "mu": mu}
        return bad

    def _blowups(self, failed: np.ndarray, term, info: dict, bad: np.ndarray) -> None:
        """Count blow-ups, and those not reported as a termination with ``info['error']`` and finite output."""
        if not np.any(failed):
            return
        self.counts["blowups"] += int(failed.sum())
        err = info.get("error")
        for i in np.flatnonzero(failed):
            flagged = bool(term[i]) and err is not None and bool(str(np.asarray(err)[i])) and not bad[i]
            if not flagged:
                self.counts["blowups_unflagged"] += 1

    def _episodes(self, done: np.ndarray, failed: np.ndarray, trunc, info: dict) -> None:
        self.counts["episodes"] += len(done)
        out = self.counts["outcomes"]
        for name, key in self.OUTCOME_FLAGS.items():
            out[name] += int(_flags(info, key, self.n)[done].sum())
        out["numerical_failure"] += int(failed[done].sum())
        out["truncated"] += int(np.asarray(trunc, dtype=bool)[done].sum())


class _SoakEnv:
    """The soak's vector env with its controllers: resets (seeded apart), the episode parameters drawn so far
    (friction and stiffness scale) and the RSS samples."""

    def __init__(self, env, policy: MixedPolicy, seed: int) -> None:
        self.env, self.policy, self.n = env, policy, env.num_envs
        self.reset_seed = seed
        self.mus: list[float] = []
        self.kss: list[float] = []
        self.rss_samples: list[tuple[int, int]] = []
        self.rss_warm: int | None = None

    def record_episode_params(self, idx) -> None:
        core = getattr(self.env, "core", None)
        if core is not None:
            self.mus.extend(float(core.mu[i]) for i in idx)
            self.kss.extend(float(core.sim.kscale[i]) for i in idx)

    def full_reset(self, options: dict | None = None) -> np.ndarray:
        self.reset_seed += self.n
        obs, _ = self.env.reset(seed=self.reset_seed, options=options)
        self.policy.reset_all()
        self.record_episode_params(range(self.n))
        return obs

    def new_episodes(self, done: np.ndarray) -> None:
        for i in done:
            self.policy.new_episode(int(i))
        self.record_episode_params(done)

    def sample_rss(self, steps: int, warm: bool) -> None:
        rss = _rss_bytes()
        self.rss_samples.append((steps, rss))
        if self.rss_warm is None and warm:
            self.rss_warm = rss


def _progress_bar(total: int):
    from ..physics.config import needs_extra

    with needs_extra("viz", "the progress bar"):
        from tqdm import tqdm
    return tqdm(total=total, unit="step", desc="soak", file=sys.stderr, mininterval=1.0)


def _soak_loop(soak: _SoakEnv, tally: SoakTally, rng: np.random.Generator, vsteps: int, bar) -> str | None:
    """Run ``vsteps`` vector steps; why the run stopped early (None: it did not)."""
    n = soak.n
    warmup = max(1, vsteps // 10)
    sample_every = max(1, vsteps // 100)
    obs = soak.full_reset()
    for k in range(vsteps):
        if k > 0 and rng.random() < 0.002:  # pinned extremes for every sub-env (in-flight episodes dropped)
            opts = dict(EXTREME_OPTIONS[int(rng.integers(len(EXTREME_OPTIONS)))])
            try:
                obs = soak.full_reset(opts)
                tally.counts["forced_resets"] += 1
                tally.counts["episodes_interrupted"] += n
            except Exception:
                tally.exception()
        try:
            obs, reward, term, trunc, info = soak.env.step(soak.policy.act(obs))
        except Exception:
            tally.exception()
            try:
                obs = soak.full_reset()
            except Exception:
                tally.exception()
                return "reset after an exception failed too"
            continue
        soak.new_episodes(tally.step(k, soak.env, obs, reward, term, trunc, info))
        if k % sample_every == 0 or k == vsteps - 1:
            soak.sample_rss(tally.counts["steps"], k >= warmup)
        if bar is not None:
            bar.update(n)
    return None


def _frac_outside(a: np.ndarray, lo_hi: tuple[float, float]) -> float | None:
    return round(float(np.mean((a < lo_hi[0]) | (a > lo_hi[1]))), 4) if a.size else None


def _seen(a: np.ndarray) -> list[float] | None:
    return [round(float(a.min()), 4), round(float(a.max()), 4)] if a.size else None


def _randomization_report(soak: _SoakEnv) -> dict:
    mu_a, ks_a = np.array(soak.mus), np.array(soak.kss)
    return {
        "mu_range": list(MU_RANGE), "stiffness_scale_range": list(STIFFNESS_RANGE),
        "mass_scale_range": list(MASS_RANGE),
        "n_sub": int(soak.env.core.sim.n_sub) if hasattr(soak.env, "core") else None,
        "episodes_drawn": int(mu_a.size),
        "mu_seen": _seen(mu_a),
        "stiffness_seen": _seen(ks_a),
        "fraction_mu_outside_training": _frac_outside(mu_a, TRAIN_MU),
        "fraction_stiffness_outside_training": _frac_outside(ks_a, TRAIN_STIFFNESS),
    }


def _memory_report(soak: _SoakEnv) -> dict:
    samples = soak.rss_samples
    last = samples[-1][1] if samples else _rss_bytes()
    warm = soak.rss_warm
    if warm is None:  # a run too short for a warm-up: growth over the run
        warm = samples[0][1] if samples else last
    growth = last / warm - 1.0 if warm else 0.0
    return {
        "peak_rss_mb": round(_peak_rss_bytes() / 2**20, 1),
        "rss_after_warmup_mb": round(warm / 2**20, 1),
        "rss_last_mb": round(last / 2**20, 1),
        "growth_after_warmup": round(growth, 4),
        "growth_target": MEMORY_GROWTH_TARGET,
        "growth_ok": bool(growth < MEMORY_GROWTH_TARGET),
        "samples": [[s, round(r / 2**20, 1)] for s, r in samples],
    }


def run_soak(steps: int = 1_000_000, n_envs: int = 16, seed: int = 0, progress: bool = True,
             env_factory: Callable[[int], Any] | None = None) -> dict:
    """Run the soak for ``steps`` agent steps in total (summed over the ``n_envs`` sub-envs).

    ``env_factory(n_envs)`` builds the vector env (default :func:`make_env`, the soak's wide ranges).
    """
    _check_count("steps", steps)
    _check_count("n_envs", n_envs)
    seed = 0 if seed is None else int(seed)
    t_start = time.perf_counter()
    rng = np.random.default_rng(seed)
    env = (env_factory or make_env)(int(n_envs))
    n = env.num_envs
    soak = _SoakEnv(env, MixedPolicy(env.config, n, rng), seed)
    tally = SoakTally(n)
    vsteps = math.ceil(steps / n)
    bar = _progress_bar(vsteps * n) if progress else None
    aborted = _soak_loop(soak, tally, rng, vsteps, bar)
    if bar is not None:
        bar.close()
    env.close()
    elapsed = time.perf_counter() - t_start
    c = tally.counts
    report = {
        "steps_requested": int(steps),
        "n_envs": n,
        "seed": seed,
        **c,
        "first_traceback": tally.first_traceback,
        "first_silent_nan": tally.first_silent_nan,
        "aborted": aborted,
        "modes": soak.policy.mode_counts,
        "extreme_actions": soak.policy.extreme_actions,
        "randomization": _randomization_report(soak),
        "memory": _memory_report(soak),
        "elapsed_s": round(elapsed, 2),
        "steps_per_s": round(c["steps"] / elapsed, 1) if elapsed > 0 else None,
    }
    report["ok"] = bool(report["silent_nan"] == 0 and report["exceptions"] == 0 and report["blowups_unflagged"] == 0
                        and aborted is None)
    return report


def soak_cli(args) -> int:
    from ..physics.config import atomic_write_text

    raw = getattr(args, "steps", 1_000_000)
    try:
        steps_f = float(raw)
    except (TypeError, ValueError):
        raise ConfigError(f"steps must be a positive integer, got {raw!r}") from None
    if not math.isfinite(steps_f) or steps_f < 1 or steps_f != int(steps_f):
        raise ConfigError(f"steps must be a positive integer, got {raw!r}")
    n_envs = getattr(args, "n_envs", 16)
    if isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or n_envs < 1:
        raise ConfigError(f"n_envs must be an integer >= 1, got {n_envs!r}")
    seed = getattr(args, "seed", None)
    out = Path(getattr(args, "out", None) or Path("logs") / "soak")
    quiet = bool(getattr(args, "quiet", False))
    report = run_soak(int(steps_f), int(n_envs), 0 if seed is None else int(seed), progress=not quiet)
    path = out / "report.json" if out.suffix.lower() != ".json" else out
    report["report"] = str(path)
    atomic_write_text(path, json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    return 0 if report["ok"] else 1
