"""Evaluate grasp policies across a grid of friction coefficients (``msdgrasp evaluate``).

For every policy and every mu of the grid, ``episodes`` episodes run in a batch of a
:class:`~msdgrasp.envs.grasp_lift.GraspLiftVectorEnv` (mu pinned through the reset options, every other
randomisation as configured, episode ``i`` seeded ``seed + i``; :mod:`.rollout`). :func:`evaluate` starts at the
sealed evaluation seeds (:data:`~.protocol.EVALUATION_SEED`, which no training, validation, fit or sweep draws from)
and records ``"seeds": {"first", "count", "sealed"}`` in ``evaluation.json``; another ``seed`` makes a result marked
not sealed. The episodes run as one job list (:mod:`.evaluation_jobs`, the driver the robustness suite runs too), in
this process or on a runner; the plots are :mod:`.evaluation_plots`'.

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
from ..physics.config import ConfigError, atomic_write_text, nan_to_none, to_dict  # noqa: F401 (nan_to_none re-exported)
from .controllers import (  # noqa: F401 (display_name re-exported)
    baselines, check_controller_spec, display_name, is_controller, make_policy, spec_forms,
)
from .evaluation_jobs import JobList, PolicyPayload, curve_record, policy_payload
from .evaluation_plots import plot_pinch, plot_success
from .reference import references_at
from .learners.base import learner_of_model, model_kinds
from .parallel import Runner
from .protocol import EVALUATION_SEED, check_evaluation_seeds, seeds_record
from .rollout import PULL_STARTED_M, evaluate_policy  # noqa: F401 (re-exported: the per-policy evaluation)

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
        if len(np.unique(np.round(values, 10))) != len(values):
            raise ConfigError(f"mu grid {text!r}: a value is given twice; give each mu once")
    return np.unique(np.round(values, 10))


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
# evaluate: check, run, summarise, write
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


def oracle_curve(config: GraspLiftConfig, mus: Sequence[float], progress: bool = False) -> dict[str, Any]:
    """The oracle's minimal slip-free fixed force at each mu (bisection in simulation, cached per mu)."""
    jobs = JobList()
    jobs.add_minimal_forces(lambda mu: ("oracle", mu), config, mus)
    forces = [f for _, f in jobs.run(on_done=_print_minimal_force if progress else None)]
    return curve_record(config, mus, forces)


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


def _checked_run(policies: Sequence[str], mus: Sequence[float], episodes: int, seed: int, out_dir: Path,
                 config: GraspLiftConfig | None) -> tuple[list[str], list[float], GraspLiftConfig, str | None]:
    """An evaluation's inputs checked before anything runs: (specs with the baselines, mu, task, where the task came
    from); ConfigError naming the input otherwise."""
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
    return policies, mus, config, trained_on


def _unique_names(built: Sequence[Any]) -> list[str]:
    """The policies' display names, a repeated one numbered (``fixed2.5N``, ``fixed2.5N_2``)."""
    names: list[str] = []
    for pol in built:
        base = str(getattr(pol, "name", "policy")) or "policy"
        name, k = base, 2
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.append(name)
    return names


def _evaluation_jobs(payloads: Sequence[PolicyPayload], mus: Sequence[float], episodes: int, config: GraspLiftConfig,
                     seed: int, n_envs: int | None, conditions: Sequence[dict[str, float]], split: bool) -> JobList:
    """The evaluation's jobs: each policy on the grid (``split``: one job per mu, to spread them over a runner's
    workers; else one job, the whole grid in one batch), on every unseen tissue, and the oracle's force per mu."""
    jobs = JobList()
    parts = [[m] for m in mus] if split else [list(mus)]
    for p, payload in enumerate(payloads):
        for part in parts:
            jobs.add_rows(("grid", p), payload, config, part, episodes, seed, n_envs)
        for c, opts in enumerate(conditions):
            jobs.add_rows(("unseen", p, c), payload, config, [UNSEEN_MU], episodes, seed, n_envs, opts)
    jobs.add_minimal_forces(lambda mu: ("oracle", mu), config, mus)
    return jobs


def _print_minimal_force(tag: tuple, force: float) -> None:
    print(f"  minimal force: mu={tag[-1]:g} -> {force:.3f} N", file=sys.stderr)


def _progress_printer(names: Sequence[str], conditions: Sequence[dict[str, float]]):
    """``on_done`` of the evaluation's jobs: a line per row as its job finishes."""

    def done(tag: tuple, res: Any) -> None:
        if tag[0] == "oracle":
            return _print_minimal_force(tag, res)
        where = [f"mu={r['mu']:g}" for r in res] if tag[0] == "grid" else [f"{conditions[tag[2]]} at mu={UNSEEN_MU:g}"]
        for label, row in zip(where, res):
            print(f"  {names[tag[1]]}: {label} success={row['success_rate']:.2f} "
                  f"peak pinch={row['mean_peak_pinch_N']:.2f} N", file=sys.stderr)

    return done


def _run_evaluation(policies: Sequence[str], names: Sequence[str], mus: Sequence[float], episodes: int,
                    config: GraspLiftConfig, seed: int, n_envs: int | None, conditions: Sequence[dict[str, float]],
                    runner: Runner | None, progress: bool) -> tuple[list[dict], dict[str, Any], list[dict]]:
    """(results per policy, the oracle's curve, the unseen-tissue rows) of :func:`evaluate`, from one job list run in
    this process or on ``runner``."""
    payloads = [policy_payload(spec, name) for spec, name in zip(policies, names)]
    jobs = _evaluation_jobs(payloads, mus, episodes, config, seed, n_envs, conditions, split=runner is not None)
    if progress:
        print(f"evaluating {', '.join(names)} on {len(mus)} mu x {episodes} episodes: {len(jobs.jobs)} jobs in "
              f"{'this process' if runner is None else runner.label}", file=sys.stderr)
    out = jobs.run(runner, _progress_printer(names, conditions) if progress else None)
    results = [{"spec": spec, "name": name, "rows": [], "seconds": 0.0} for spec, name in zip(policies, names)]
    unseen, forces = [], []
    for (tag, res), seconds in zip(out, jobs.seconds):
        if tag[0] == "grid":
            results[tag[1]]["rows"] += res
            results[tag[1]]["seconds"] += seconds
        elif tag[0] == "unseen":
            unseen.append({"policy": names[tag[1]], "conditions": {"mu": UNSEEN_MU, **conditions[tag[2]]}, **res[0]})
        else:
            forces.append(res)
    for pol in results:
        pol["seconds"] = round(pol["seconds"], 2)
    return results, curve_record(config, mus, forces), unseen


def _add_force_ratios(results: list[dict[str, Any]], curve: dict[str, Any],
                      config: GraspLiftConfig) -> tuple[dict[str, float | None], dict[str, Any]]:
    """Each row's force ratio: over the reference (a slower pull cannot lower it) where the task has a table and mu is
    on its grid, and over the nominal oracle at pull 0.5 beside it. Returns the references and what they are."""
    minimal = dict(zip(curve["mu"], curve["minimal_force_N"]))
    references, reference = references_at(config, [float(m) for m in curve["mu"]])
    for pol in results:
        for r in pol["rows"]:
            r["peak_pinch_over_oracle_min"] = r["mean_peak_pinch_N"] / minimal[r["mu"]]
            ref = references.get(f"{r['mu']:g}")
            r["force_ratio"] = r["mean_peak_pinch_N"] / ref if ref else None  # (None: no reference at this mu)
    return references, reference


def _evaluation_record(policies: Sequence[str], mus: Sequence[float], episodes: int, seed: int, n_envs: int | None,
                       config: GraspLiftConfig, trained_on: str | None, runner: Runner | None,
                       seconds: float) -> dict[str, Any]:
    """How the evaluation ran, as ``evaluation.json`` records it."""
    return {
        "mu_grid": list(mus),
        "episodes": int(episodes),
        "seed": int(seed),
        "seeds": [int(seed) + i for i in range(int(episodes))],
        "reset_options": "{'mu': mu}; other randomisation as configured",
        "n_envs": n_envs,
        "runner": "this process" if runner is None else runner.label,
        "policies": list(policies),
        "training_mu_range": list(config.randomization.mu_range),
        "training_config_from": trained_on,
        "success": "info['is_success'] at the episode's end: lift_target_m reached and held hold_time_s "
                   "with less than hold_slip_tolerance_m slip",
        "seconds": round(seconds, 2),
    }


def _write_outputs(out_dir: Path, summary: dict[str, Any], config: GraspLiftConfig) -> dict[str, str]:
    """``evaluation.json``, ``evaluation.csv`` and the two plots in ``out_dir`` (atomically); their paths."""
    files = {
        "json": out_dir / "evaluation.json",
        "csv": out_dir / "evaluation.csv",
        "success_png": out_dir / "success_vs_mu.png",
        "pinch_png": out_dir / "pinch_vs_mu.png",
    }
    atomic_write_text(files["json"], json.dumps(nan_to_none(summary), indent=2) + "\n")
    atomic_write_text(files["csv"], _csv_text(summary["results"]))
    plot_success(summary["results"], config, files["success_png"])
    plot_pinch(summary["results"], summary["oracle_minimal_force"], files["pinch_png"])
    return {k: str(v) for k, v in files.items()}


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
    The episodes run as one job list (:mod:`.evaluation_jobs`): in this process, or with ``runner`` (:mod:`.parallel`:
    local processes or Ray) every (policy, mu) cell, unseen condition and minimal-force bisection a job of its own,
    models travelling to the jobs as bytes (no shared disk needed); the numbers are the same either way (same
    episodes, same seeds). Recordings are made here.
    Returns ``{"results": [...], "oracle_minimal_force": {...}, "files": {...}, "recordings": [...]}``.
    """
    out_dir = Path(out_dir)
    policies, mus, config, trained_on = _checked_run(policies, mus, episodes, seed, out_dir, config)
    built = [build_policy(spec, config) for spec in policies]
    names = _unique_names(built)
    t_start = time.perf_counter()
    results, curve, unseen = _run_evaluation(policies, names, mus, episodes, config, seed, n_envs, conditions,
                                             runner, progress)
    references, reference = _add_force_ratios(results, curve, config)
    recordings: list[str] = []
    if record:
        recordings = _record_all(names, built, mus, config, seed, out_dir / "recordings", progress)
    if video:
        recordings += _record_all(names, built, mus, config, seed, out_dir / "videos", progress, suffix=".mp4")
    summary = {
        "seeds": seeds_record(seed, episodes),
        "config": to_dict(config),
        "evaluation": _evaluation_record(policies, mus, episodes, seed, n_envs, config, trained_on, runner,
                                         time.perf_counter() - t_start),
        "results": results,
        "oracle_minimal_force": curve,
        "reference": reference,
        "reference_force_N": references,
        "unseen_conditions": unseen,
        "recordings": recordings,
    }
    files = _write_outputs(out_dir, summary, config)
    return {"results": results, "oracle_minimal_force": curve, "files": files, "recordings": recordings,
            "unseen_conditions": unseen, "config": config, "seeds": summary["seeds"]}


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
