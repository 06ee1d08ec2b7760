"""The RL subcommands of ``msdgrasp``: train, sweep, evaluate, report, select, record, replay, soak.

Only argparse wiring lives here; every handler imports its (torch-, rerun- or numba-heavy) module lazily,
so ``msdgrasp --help`` stays fast and an unavailable optional module only breaks its own subcommand.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any, Sequence


def _default_models() -> list[str]:
    """The model the default learner's run in its default folder (logs/train) ships, else the models of its
    seed runs there (a multi-seed run)."""
    from ..agents.learners import default_learner
    from ..agents.selection import seed_runs

    learner = default_learner(None)
    one = learner.default_out / learner.layout.model
    if one.is_file():
        return [str(one)]
    return [str(d / learner.layout.model) for _, d in seed_runs(learner.default_out)
            if (d / learner.layout.model).is_file()]


def seed_int(text: str) -> int:
    """An argparse type: a seed, an integer >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value


def env_count(text: str) -> int:
    """An argparse type: a number of parallel envs, 1..MAX_ENVS."""
    from ..physics.config import MAX_ENVS

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer in 1..{MAX_ENVS}, got {text!r}") from None
    if not 1 <= value <= MAX_ENVS:
        raise argparse.ArgumentTypeError(f"allowed 1..{MAX_ENVS}, got {value}")
    return value


def usage_error(message: str) -> Exception:
    """A one-line input error (exit status 2)."""
    from .errors import UsageError

    return UsageError(message)


def _missing_module(command: str, exc: ImportError) -> Exception:
    return usage_error(f"the {command} command is unavailable: {exc}")


def _require_plots(command: str) -> None:
    """Plots are drawn at the end of a run: a missing matplotlib stops the command before the run starts."""
    from ..physics.config import require_extra

    require_extra("train", f"msdgrasp {command} (its plots)", "matplotlib")


def add_mu_grid_arg(p: argparse.ArgumentParser, default: Sequence[float]) -> None:
    """--mu-grid with the grid ``default`` (read back by :func:`positive_mu_grid`)."""
    text = ",".join(f"{m:g}" for m in default)
    p.add_argument("--mu-grid", default=text,
                   help=f"friction coefficients: a comma list or start:stop:step (default {text})")


def positive_mu_grid(text: str) -> list[float]:
    """The frictions of a --mu-grid value, each > 0 (a usage error naming --mu-grid otherwise)."""
    from ..agents.evaluation import parse_mu_grid
    from ..physics.config import ConfigError

    try:
        mus = [float(m) for m in parse_mu_grid(text)]
    except ConfigError as exc:
        raise usage_error(f"--mu-grid: {exc}") from None
    if mus[0] <= 0.0:
        raise usage_error(f"--mu-grid: mu must be > 0, got {mus[0]:g}")
    return mus


def add_runner_args(p: argparse.ArgumentParser, what: str) -> None:
    """--ray, --address and --workers: where ``what`` runs (:func:`runner_from_args`)."""
    p.add_argument("--ray", action="store_true",
                   help=f"run {what} as Ray tasks on a local Ray instance (pip install 'msdgrasp[ray]')")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help=f"run {what} on this Ray cluster ('auto', host:port or ray://host:10001; implies --ray)")
    p.add_argument("--workers", type=int, default=None,
                   help="jobs at a time on the local machine (default: one per CPU core); with --address the "
                        "cluster's CPUs decide")


def _runner_asked(args: argparse.Namespace) -> bool:
    """Whether the command line names a runner (--ray, --address or --workers)."""
    return args.ray or args.address is not None or args.workers is not None


def runner_from_args(args: argparse.Namespace, default_workers: int | None = None):
    """The job runner the arguments ask for (agents.parallel.Runner); validated before anything runs."""
    from ..agents.parallel import Runner

    if args.workers is not None and args.workers < 1:
        raise usage_error(f"--workers must be >= 1, got {args.workers}")
    if args.address is not None:
        if args.workers is not None:
            raise usage_error("--workers sizes a local run; with --address the cluster's CPUs decide")
        return Runner.ray(address=args.address)
    if args.ray:
        return Runner.ray(workers=args.workers)
    return Runner.processes(args.workers if args.workers is not None else default_workers)


# ------------------------------------------------------------------------------------------------
# handlers
# ------------------------------------------------------------------------------------------------


def _report_seeds(folder: Path, quiet: bool, episodes: int = 10, runner=None, seeds=None,
                  evaluation_seed: int | None = None) -> int:
    """The multi-seed report of the runs folder/seed_<k>/ of any learner (agents.seeds.report_seed_runs); its
    evaluation on the sealed evaluation seeds unless ``evaluation_seed`` says otherwise."""
    from ..agents.protocol import EVALUATION_SEED
    from ..agents.seeds import report_seed_runs

    first = EVALUATION_SEED if evaluation_seed is None else evaluation_seed
    result = report_seed_runs(folder, seeds=seeds, episodes=episodes, runner=runner, progress=not quiet,
                              evaluation_seed=first)
    print(json.dumps({"files": result["files"], "aggregate": result["aggregate"]}, indent=2))
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    """``msdgrasp report DIR``: the multi-seed report of seed runs (what ``train --seeds`` writes at its end),
    for runs made elsewhere, re-selected (``msdgrasp select``) or made before it wrote one."""
    if args.episodes < 1:
        raise usage_error(f"--episodes must be >= 1, got {args.episodes}")
    if not Path(args.folder).is_dir():
        raise usage_error(f"{args.folder}: not a folder")
    runner = runner_from_args(args, os.cpu_count() or 1) if _runner_asked(args) else None
    _require_plots("report")
    return _report_seeds(Path(args.folder), args.quiet, args.episodes, runner, evaluation_seed=args.seed)


def _check_train_flags(args: argparse.Namespace) -> None:
    """The train flags that exclude or need each other."""
    if args.seed is not None and args.seeds is not None:
        raise usage_error("give either --seed or --seeds, not both")
    if args.seeds is None and _runner_asked(args):
        raise usage_error("--ray, --address and --workers run the seeds of --seeds; give --seeds")
    if args.resume is not None and args.seeds is not None:
        raise usage_error("--resume continues one run; it cannot be combined with --seeds")


def _resumed_learner(args: argparse.Namespace):
    """The learner of the run --resume names (recorded in its files), able to continue it."""
    from ..agents.learners import learner_of_run
    from ..physics.config import ConfigError

    try:
        learner = learner_of_run(args.resume)
    except ConfigError as exc:
        raise usage_error(f"--resume: {exc}") from None
    if args.learner is not None and args.learner != learner.name:
        raise usage_error(f"--resume {args.resume}: a run of learner {learner.name}, not {args.learner}")
    if not learner.can_resume:
        raise usage_error(f"--resume {args.resume}: learner {learner.name} cannot continue a run; train a new one")
    return learner


def _train_learner(args: argparse.Namespace):
    """The learner train runs: the resumed run's, --learner's, or the default on --backend; checked against
    --backend and --seeds with a runner."""
    from ..agents.learners import default_learner, get_learner

    if args.resume is not None:
        learner = _resumed_learner(args)
    else:
        learner = get_learner(args.learner) if args.learner is not None else default_learner(args.backend)
    if args.backend is not None and args.backend not in learner.backends:
        able = [n for n in _learner_names() if args.backend in get_learner(n).backends]
        raise usage_error(f"--backend {args.backend}: learner {learner.name} runs on {', '.join(learner.backends)}; "
                          f"on {args.backend} train with --learner {' or '.join(able)}")
    if args.seeds is not None and not learner.parallel_seeds and _runner_asked(args):
        raise usage_error(f"--ray, --address and --workers run seeds in parallel; learner {learner.name} trains its "
                          "seeds one after the other (on the one GPU)")
    return learner


def _checked_seeds(args: argparse.Namespace, config) -> list[int] | None:
    """--seeds as a list (None without it), every seed's config valid (none reaches the sealed evaluation seeds)
    before one trains."""
    if args.seeds is None:
        return None
    from dataclasses import replace

    from ..agents.seeds import parse_seeds

    seeds = parse_seeds(args.seeds)
    for seed in seeds:
        replace(config, seed=seed)
    return seeds


def _train_seed_runs(args: argparse.Namespace, learner, config, seeds: list[int]) -> int:
    """train --seeds: every seed's run in OUT/seed_<k>/ (in parallel where the learner allows), then the report."""
    from dataclasses import replace

    from ..agents.seeds import run_seeds

    _require_plots("train --seeds")
    out = args.out if args.out is not None else learner.default_out
    if not learner.parallel_seeds:  # one after the other, then the report of exactly these seeds
        for seed in seeds:
            learner.train(replace(config, seed=seed), out / f"seed_{seed}", progress=not args.quiet)
        return _report_seeds(out, args.quiet, seeds=seeds)
    result = run_seeds(config, seeds, out, runner=runner_from_args(args, min(len(seeds), os.cpu_count() or 1)),
                       progress=not args.quiet)
    print(json.dumps({"files": result["files"], "aggregate": result["aggregate"]}, indent=2))
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    """``msdgrasp train``: any learner by name (agents.learners); one run, a resumed run, or --seeds."""
    from ..agents.learners import TrainOverrides, learner_of_config

    _check_train_flags(args)
    overrides = TrainOverrides(learner=args.learner, seed=args.seed, n_envs=args.n_envs,
                               total_timesteps=args.total_timesteps, backend=args.backend)
    learner = _train_learner(args)
    # the config first (its loading imports no learner library: a typo is reported in about a second), then the
    # learner's libraries, which take seconds to import, before anything is trained or written
    if args.resume is not None:
        config = learner.resume_config(args.resume, overrides)
    else:
        config = learner.make_config(args.config, overrides)
        learner = learner_of_config(config)  # (the config's algo where --learner named none)
    seeds = _checked_seeds(args, config)
    try:
        learner.check_available()
    except ImportError as exc:
        raise _missing_module(f"train --learner {learner.name}", exc) from None
    if seeds is not None:
        return _train_seed_runs(args, learner, config, seeds)
    if args.resume is not None:
        summary = learner.train(config, args.resume, resume=True, progress=not args.quiet)
    else:
        out = args.out if args.out is not None else learner.default_out
        summary = learner.train(config, out, progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0


def _learner_names() -> tuple[str, ...]:
    from ..agents.learners import learner_names

    return learner_names()


def _cmd_sweep(args: argparse.Namespace) -> int:
    try:
        from ..agents.sweep import SweepConfig, run_sweep, sweep_points
    except ImportError as exc:
        raise _missing_module("sweep", exc) from None
    sweep = SweepConfig.load(args.config)
    runner = runner_from_args(args)
    if args.dry_run:  # every point built and validated, nothing run or written
        points = sweep_points(sweep, Path(args.config).name)
        print(json.dumps({"points": [p for p, _ in points], "seeds": sweep.seeds}, indent=2))
        return 0
    result = run_sweep(sweep, args.out, runner, progress=not args.quiet, where=Path(args.config).name)
    best = result["points"][result["ranking"][0]]
    print(json.dumps({"files": result["files"], "best": {"point": best["point"], "params": best["params"],
                                                         "aggregate": best["aggregate"]}}, indent=2))
    return 0


def _default_policies() -> list[str]:
    """Without --policy: the trained models of the default run folder; none there is an error, not a controller
    evaluated in their place."""
    from ..agents.controllers import controller_names
    from ..agents.learners import default_learner

    models = _default_models()
    if not models:
        raise usage_error(f"evaluate: no --policy given and no trained model in {default_learner(None).default_out} "
                          f"(or its seed_<k>/); give --policy PATH|{'|'.join(controller_names())}")
    return models


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from ..agents.evaluation import UNSEEN_CONDITIONS, evaluate, format_table, format_unseen, parse_mu_grid

    from ..agents.evaluation import DEFAULT_MU_GRID

    if args.suite is not None:
        return _cmd_suite(args)
    if args.hindsight:
        raise usage_error("--hindsight needs --suite robustness (it searches the suite's episodes)")
    if args.condition:
        raise usage_error("--condition needs --suite robustness (it picks the suite's conditions)")
    if args.no_baselines or args.task_version is not None:
        raise usage_error("--no-baselines and --task-version need --suite (they shape a suite run)")
    mus = parse_mu_grid(DEFAULT_MU_GRID if args.mu_grid is None else args.mu_grid)
    if args.episodes is None:
        args.episodes = 10
    if args.episodes < 1:
        raise usage_error(f"--episodes must be >= 1, got {args.episodes}")
    policies = args.policy or _default_policies()
    task = _training_task(args.training_task, policies) if args.training_task is not None else None
    _require_plots("evaluate")
    # without --ray / --address / --workers the evaluation runs in this process, as it always did
    runner = runner_from_args(args) if _runner_asked(args) else None
    result = evaluate(policies, mus, args.episodes, args.out, config=task, seed=args.seed, record=args.record,
                      progress=not args.quiet, n_envs=args.n_envs, video=args.video,
                      conditions=() if args.no_unseen else UNSEEN_CONDITIONS, runner=runner)
    print(format_table(result["results"]))
    if result["unseen_conditions"]:
        print(format_unseen(result["unseen_conditions"]))
    curve = result["oracle_minimal_force"]
    print("oracle minimal force (N): " + ", ".join(
        f"mu={m:g}: {f:.2f}" for m, f in zip(curve["mu"], curve["minimal_force_N"])))
    print(_seeds_sentence(result["seeds"]))
    print(json.dumps({**result["files"], "recordings": result["recordings"]}, indent=2))
    return 0


def _seeds_sentence(record: dict) -> str:
    """One line on an evaluation's seeds: sealed, or not (agents/protocol.py)."""
    span = f"{record['first']}..{record['first'] + record['count'] - 1}"
    from ..agents.protocol import sealed_range_text

    if record["sealed"]:
        return f"evaluation seeds {span}: sealed"
    return f"evaluation seeds {span}: NOT sealed, outside {sealed_range_text()} (a development result)"


def _training_task(path: Path, policies: list[str]):
    """``--training-task CONFIG``: the episodes that training config draws (its task with its perturbations at
    their full ranges, as its validation runs). Controllers only: a model runs on the task it was trained on."""
    from ..agents.controllers import is_controller
    from ..agents.learners.sb3_layout import load_train_config

    models = [spec for spec in policies if not is_controller(spec)]
    if models:
        raise usage_error("--training-task runs controllers only (a model runs on the task it was trained on); "
                          f"got {models[0]}")
    if not path.is_file():
        raise usage_error(f"--training-task: no such file: {path}")
    return load_train_config(path, "--training-task").training_task()


def _cmd_suite(args: argparse.Namespace) -> int:
    """``evaluate --suite NAME``: the versioned protocol fixes its conditions, mu and episodes."""
    from ..agents.robustness import run_suite

    fixed = [flag for flag, given in (("--mu-grid", args.mu_grid), ("--no-unseen", args.no_unseen),
                                      ("--n-envs", args.n_envs), ("--record", args.record), ("--video", args.video),
                                      ("--training-task", args.training_task))
             if given]
    if fixed:
        raise usage_error(f"evaluate --suite {args.suite}: the suite fixes its conditions, mu and batches; drop "
                          + ", ".join(fixed))
    if args.episodes is not None and args.episodes < 1:
        raise usage_error(f"--episodes must be >= 1, got {args.episodes}")
    policies = args.policy or _default_policies()
    runner = runner_from_args(args) if _runner_asked(args) else None
    task = None
    if args.task_version is not None:  # controllers on another version of the benchmark task (the critic's entries too)
        from dataclasses import replace

        from ..agents.models import TrainConfig
        from ..envs.core import benchmark_config

        task = replace(benchmark_config(TrainConfig().env.scene, args.task_version), privileged_obs=True)
    result = run_suite(policies, args.out, args.suite, episodes=args.episodes, seed=args.seed, runner=runner,
                       progress=not args.quiet, hindsight=args.hindsight, only=args.condition,
                       baselines=not args.no_baselines, task=task)
    print(Path(result["files"]["markdown"]).read_text())
    print(json.dumps(result["files"], indent=2))
    return 0


def _cmd_collect(args: argparse.Namespace) -> int:
    from ..agents.demonstrations import collect
    from ..agents.protocol import check_not_sealed

    if args.episodes < 1:
        raise usage_error(f"--episodes must be >= 1, got {args.episodes}")
    check_not_sealed(args.seed, args.episodes, "--seed", via=f"episodes: seed + i, i < {args.episodes}")
    card = collect(args.policy, args.episodes, args.out, dataset_id=args.dataset_id, seed=args.seed,
                   progress=not args.quiet, train_config=args.config)
    print(json.dumps({k: card[k] for k in ("dataset_id", "path", "policy", "episodes", "success_rate", "steps",
                                           "load")}, indent=2))
    return 0


def _cmd_clone(args: argparse.Namespace) -> int:
    from ..agents.offline import CLONE_EPOCHS, check_clone_seed, clone

    epochs = CLONE_EPOCHS if args.epochs is None else args.epochs
    if epochs < 1:
        raise usage_error(f"--epochs must be >= 1, got {epochs}")
    check_clone_seed(args.seed)
    print(json.dumps(clone(args.dataset_id, args.out, args.datasets, epochs=epochs, seed=args.seed), indent=2))
    return 0


def _cmd_fit_friction(args: argparse.Namespace) -> int:
    from ..agents.friction_fit import fit_friction_estimator
    from ..agents.models import TrainConfig
    from ..agents.protocol import check_not_sealed

    if args.episodes < 2:
        raise usage_error(f"--episodes must be >= 2, got {args.episodes}")
    if not 0 < args.probe <= 5:
        raise usage_error(f"--probe must be in (0, 5] N, got {args.probe}")
    if not 0 < args.pull <= 1:
        raise usage_error(f"--pull must be in (0, 1], got {args.pull}")
    if args.out.suffix != ".json":
        raise usage_error(f"--out must be a .json file, got {args.out}")
    check_not_sealed(args.seed, args.episodes, "--seed", via=f"fitting episodes: seed + i, i < {args.episodes}")
    config = TrainConfig.load(args.config)
    what = f"{args.config}: {args.episodes} episodes of its training task, reset seeds from {args.seed}"
    est, report = fit_friction_estimator(config.training_task(), args.episodes, args.seed, args.probe, args.pull,
                                         table_task=config.env, fitted_on=what)
    est.save(args.out)
    print(json.dumps({"out": str(args.out), **report}, indent=2))
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from ..envs.grasp_lift import GraspLiftEnv
    from ..agents.evaluation import build_policy, check_policy_spec, record_policy_episode, trained_task_of

    if not (math.isfinite(args.mu) and 0.0 <= args.mu <= 10.0):
        raise usage_error(f"--mu must be in [0, 10], got {args.mu}")
    out = Path(args.out)
    if "{episode" in str(out):
        raise usage_error(f"--out {out}: give one file name (no {{episode}} template)")
    if out.is_dir():
        raise usage_error(f"--out {out} is a folder; give a file name such as {out / 'episode.rrd'}")
    from ..envs.video import check_still_path, check_video_path

    if args.video is not None:
        check_video_path(args.video)
    if args.still is not None:
        if args.video is None:
            raise usage_error(f"--still {args.still}: needs --video (the still is the video's last frame)")
        check_still_path(args.still)
    spec = args.policy
    check_policy_spec(spec)
    config, _ = trained_task_of([spec])  # a model runs on the task it was trained on, a controller on the default's
    policy = build_policy(spec, config)
    env = GraspLiftEnv(config)
    try:
        # one episode: logged to the recording and, with --video, rendered as it runs
        summary = record_policy_episode(policy, env, out, args.mu, args.seed, still=args.still, video=args.video)
    finally:
        env.close()
    print(json.dumps({"policy": spec, "mu": args.mu, "seed": args.seed, **summary}, indent=2))
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from .replay import replay_cli

    return replay_cli(args)


def _cmd_soak(args: argparse.Namespace) -> int:
    try:
        from ..benchmarks.soak import soak_cli
    except ImportError as exc:
        raise _missing_module("soak", exc) from None
    return soak_cli(args)


# ------------------------------------------------------------------------------------------------
# parser
# ------------------------------------------------------------------------------------------------


def _cmd_leaderboard(args: argparse.Namespace) -> int:
    """``msdgrasp leaderboard SUITE.json --track NAME=PATTERN ... --out DIR`` (agents.leaderboard)."""
    from ..agents.leaderboard import leaderboard_markdown, write_leaderboard

    board = write_leaderboard(args.suite_json, args.track, args.baseline, args.out, against=args.against)
    print(leaderboard_markdown(board))
    return 0


def _cmd_select(args: argparse.Namespace) -> int:
    """``msdgrasp select RUN --out DIR``: validate a finished run's checkpoints again (other episodes or mu)
    and write the pick into DIR, the run untouched (agents.selection)."""
    from ..agents.evaluation import parse_mu_grid
    from ..agents.selection import select

    runner = runner_from_args(args) if _runner_asked(args) else None
    mu = None if args.validation_mu is None else [float(m) for m in parse_mu_grid(args.validation_mu)]
    shown = []
    numbers = None
    if args.checkpoints is not None:
        first, sep, last = args.checkpoints.partition("-")
        try:
            numbers = (int(first), int(last if sep else first))
        except ValueError:
            raise usage_error(f"--checkpoints {args.checkpoints!r}: expected FIRST-LAST or N (checkpoint "
                              "numbers)") from None
        if not 0 <= numbers[0] <= numbers[1]:
            raise usage_error(f"--checkpoints {args.checkpoints!r}: expected 0 <= FIRST <= LAST")
    for r in select(args.run, args.out, args.validation_episodes, mu, runner=runner, numbers=numbers):
        best = r["best"]
        shown.append({"run": r["run"], "learner": r["learner"], "validation_episodes": r["validation_episodes"],
                      "checkpoints_validated": r["checkpoints_validated"], "selection_s": r["selection_s"],
                      "best": best["model"], "success_rate": best["success_rate"],
                      "force_cost_N": best["force_cost_N"]})
    print(json.dumps(shown, indent=2))
    return 0


@dataclasses.dataclass(frozen=True)
class _HelpTexts:
    """What several subcommands' help says: the learners, the sealed seeds, the controllers a --policy may name."""

    learners: tuple[str, ...]
    sealed: str  # the sealed evaluation seeds' range
    refused: str  # what happens to a training seed that would reach them
    evaluation_seed: int
    policy_usage: str  # the controller specs, from their registry
    controllers: dict[str, Any]  # add_parser keywords: the registry's controllers listed below a command's options

    @classmethod
    def now(cls) -> "_HelpTexts":
        from ..agents.controllers import controllers_help, policy_usage
        from ..agents.protocol import EVALUATION_SEED, sealed_range_text

        sealed = sealed_range_text()
        return cls(_learner_names(), sealed,
                   f"seeds that would reach the sealed evaluation seeds {sealed} are refused (exit 2)",
                   EVALUATION_SEED, policy_usage(),
                   {"epilog": f"controllers (--policy NAME[:OPTIONS]):\n{controllers_help()}",
                    "formatter_class": argparse.RawDescriptionHelpFormatter})


def _add_train(sub, h: _HelpTexts) -> None:
    """train: any learner, one run, a resumed run or --seeds."""
    t = sub.add_parser("train", help=f"train a grasp policy (learners: {', '.join(h.learners)}; docs/learners.md)")
    t.add_argument("--config", type=Path, default=None,
                   help="training config (default: the learner's built-in one, configs/train/ppo.yaml for SB3)")
    t.add_argument("--learner", "--algo", dest="learner", choices=h.learners, default=None,
                   help="the learner (default: the config's algo, ppo; rsl with --backend cuda). ppo and sac are "
                        "Stable-Baselines3's (sac trains with a symmetric critic, asymmetric_critic: false); rsl is "
                        "rsl-rl's torch-native PPO (config configs/train/rsl_ppo.yaml, whose backend is cuda, or with "
                        "--backend cpu configs/train/rsl_ppo_cpu.yaml); recurrent trains an actor with memory, "
                        "taught by a privileged teacher, then fine-tuned by PPO (configs/train/recurrent.yaml)")
    t.add_argument("--total-timesteps", type=int, default=None, help="environment steps to train for")
    t.add_argument("--n-envs", type=env_count, default=None, help="parallel environments")
    t.add_argument("--seed", type=seed_int, default=None,
                   help="random seed (one run): its training envs are reset with seed + i, its validation episodes "
                        f"with seed + 100000 + i; {h.refused}")
    t.add_argument("--seeds", default=None, metavar="RANGE",
                   help="train several seeds in parallel processes and evaluate each, e.g. 0-4 or 0,3,7: "
                        "writes seed_<k>/ runs and seeds.json, seeds.md, learning_curves.png (aggregate over seeds); "
                        "the evaluation's episodes are reset with the sealed evaluation seeds from "
                        f"{h.evaluation_seed}; training {h.refused}")
    add_runner_args(t, "the seeds of --seeds")
    t.add_argument("--out", type=Path, default=None,
                   help="output folder (default logs/train; logs/train_torch for --learner rsl)")
    t.add_argument("--resume", type=Path, default=None, help="continue the run saved in this folder")
    t.add_argument("--quiet", action="store_true", help="no progress output")
    t.add_argument("--backend", choices=["cpu", "cuda"], default=None,
                   help="where the task runs: cpu (numba; SB3's default) or cuda (the whole agent step on the GPU; "
                        "trains with --learner rsl; pip install 'msdgrasp[gpu]'); default: the config's")
    t.set_defaults(func=_cmd_train)


def _add_sweep(sub, h: _HelpTexts) -> None:
    """sweep: a grid of training configs over seeds."""
    sw = sub.add_parser("sweep", help="hyper-parameter sweep: a grid of training configs, each over several seeds")
    sw.add_argument("config", type=Path,
                    help="sweep file (base, set, grid, seeds, episodes, evaluation_seed; see agents/sweep.py); a sweep "
                         f"tunes on what it measures: {h.refused}")
    sw.add_argument("--out", type=Path, default=Path("logs") / "sweep", help="output folder (default logs/sweep)")
    sw.add_argument("--dry-run", action="store_true", help="validate and list the points, run nothing")
    add_runner_args(sw, "the points' seeds")
    sw.add_argument("--quiet", action="store_true", help="no progress output")
    sw.set_defaults(func=_cmd_sweep)


def _add_evaluate(sub, h: _HelpTexts) -> None:
    """evaluate: policies over a mu grid, or a versioned suite."""
    from ..agents.controllers import baselines

    e = sub.add_parser("evaluate", help="success and pinch force of policies across a grid of friction mu",
                       **h.controllers)
    e.add_argument("--policy", action="append", default=None, metavar="SPEC",
                   help="PATH (a saved model of any learner; it runs on the task it was trained on) | "
                        f"{h.policy_usage} (repeatable; default: the model of the default learner's run in logs/train, "
                        "else of every logs/train/seed_*/; none there is an error). "
                        f"{' and '.join(baselines())} are always added")
    e.add_argument("--mu-grid", default=None,
                   help="start:stop:step (stop included) or a comma list (default: the training range 0.3-0.9 "
                        "and the unseen 0.15, 0.2, 1.0, 1.2)")
    e.add_argument("--no-baselines", action="store_true",
                   help="with --suite: the policies given alone, no baselines (a second run on the same episodes)")
    e.add_argument("--task-version", type=int, choices=(1, 2), default=None,
                   help="with --suite, controllers only: run on that version of the benchmark task (default: the "
                        "default training's, v2)")
    e.add_argument("--suite", choices=("robustness", "in_range"), default=None,
                   help="run a versioned protocol instead of the mu grid: robustness v2 (sensing, actuation, "
                        "placement, friction and tissue outside training; mu 0.2, 0.3, 0.5, 0.8 x 19 episodes, 76 "
                        "per condition, each with its success's Wilson 95%% interval; agents/robustness.py), or "
                        "in_range, its 8 conditions inside the benchmark's robustness ranges (the leaderboard's): "
                        "suite_<name>.json and leaderboard_<name>.md in --out")
    e.add_argument("--condition", action="append", default=None, metavar="AXIS|NAME",
                   help="with --suite: run only these conditions (repeatable): an axis (nominal, sensing, actuation, "
                        "placement, friction, tissue) or a condition's name as the leaderboard writes it; the "
                        "result is marked a subset")
    e.add_argument("--hindsight", action="store_true",
                   help="with --suite: also search each episode's minimal fixed force in the nominal and placement "
                        "conditions (the hindsight oracle: what gripping every episode with just enough would "
                        "reach; about 3 CPU-minutes per condition and mu)")
    e.add_argument("--training-task", type=Path, default=None, metavar="CONFIG",
                   help="run the controllers on the episodes this training config draws: its task with its "
                        "perturbations at their full ranges, where its validation runs (mean return in "
                        "evaluation.json and the table: what that training's reward makes of each controller)")
    e.add_argument("--no-unseen", action="store_true",
                   help="skip the unseen tissues (stiffness 0.6 / 1.5, mass 0.8 / 1.25 at mu 0.5)")
    e.add_argument("--episodes", type=int, default=None,
                   help="episodes per policy and mu (default 10; with --suite the protocol's 19 per mu of the "
                        "grid, 76 per condition: fewer run, marked not the protocol)")
    e.add_argument("--n-envs", type=env_count, default=None,
                   help="batch size (default: all episodes of one mu at once)")
    e.add_argument("--seed", type=seed_int, default=h.evaluation_seed,
                   help=f"episode i is reset with seed + i (default {h.evaluation_seed}, the first of the sealed "
                        f"evaluation seeds {h.sealed}, which no training, validation, fit or sweep may use; the result "
                        "records its seeds and whether they are sealed: another seed makes a development result)")
    e.add_argument("--out", type=Path, default=Path("logs") / "evaluate", help="output folder (default logs/evaluate)")
    e.add_argument("--record", action="store_true", help="also record one episode per policy and mu (.rrd)")
    e.add_argument("--video", action="store_true", help="also write one video per policy and mu (videos/*.mp4)")
    add_runner_args(e, "every (policy, mu) cell as its own job")
    e.add_argument("--quiet", action="store_true", help="no progress output")
    e.set_defaults(func=_cmd_evaluate)


def _add_collect(sub, h: _HelpTexts) -> None:
    """collect: a policy's episodes as a Minari dataset."""
    co = sub.add_parser("collect", help="record a policy's episodes as a Minari dataset (demonstrations)",
                        **h.controllers)
    co.add_argument("--policy", required=True, metavar="SPEC",
                    help=f"PATH (a saved model: its own task) | {h.policy_usage} (the benchmark task)")
    co.add_argument("--config", type=Path, default=None, metavar="TRAIN.yaml",
                    help="a controller's episodes are drawn from this training's randomised task (default: the "
                         "benchmark task's own randomisation)")
    co.add_argument("--episodes", type=int, default=100, help="episodes (default 100)")
    co.add_argument("--seed", type=seed_int, default=0,
                    help=f"episode i is reset with seed + i (default 0); a dataset is for training: {h.refused}")
    co.add_argument("--dataset-id", default=None,
                    help="Minari id, (namespace/)name-v<version> (default msdgrasp/grasplift/<policy>-v0)")
    co.add_argument("--out", type=Path, default=Path("logs") / "datasets",
                    help="datasets folder (default logs/datasets; load with MINARI_DATASETS_PATH=<it>)")
    co.add_argument("--quiet", action="store_true", help="no progress output")
    co.set_defaults(func=_cmd_collect)


def _add_fit_friction(sub, h: _HelpTexts) -> None:
    """fit-friction: a friction estimator for the slip-feedback controller."""
    ff = sub.add_parser("fit-friction", help="fit a friction estimator (the closing's sensing -> mu) for "
                                             "slipfeedback:estimator=PATH")
    ff.add_argument("--config", type=Path, required=True, metavar="TRAIN.yaml",
                    help="its training task gives the episodes (their sensing and placement errors); its env the "
                         "minimal-force table")
    ff.add_argument("--episodes", type=int, default=768, help="episodes to fit on (default 768)")
    ff.add_argument("--seed", type=seed_int, default=20000,
                    help=f"episode i is reset with seed + i (default 20000); {h.refused}")
    ff.add_argument("--probe", type=float, default=0.7, help="the grip the jaws close to, N (default 0.7)")
    ff.add_argument("--pull", type=float, default=0.3,
                    help="the controller's pull speed, a fraction of the top speed, for the force table (default 0.3)")
    ff.add_argument("--out", type=Path, required=True, help="the estimator's file (.json)")
    ff.set_defaults(func=_cmd_fit_friction)


def _add_clone(sub, h: _HelpTexts) -> None:
    """clone: behaviour cloning of a collected dataset."""
    cl = sub.add_parser("clone", help="behaviour cloning of a Minari dataset made by collect (the offline baseline)")
    cl.add_argument("dataset_id", metavar="DATASET_ID", help="the dataset's Minari id (collect prints it)")
    cl.add_argument("--datasets", type=Path, default=Path("logs") / "datasets",
                    help="the folder collect wrote it to (default logs/datasets)")
    cl.add_argument("--out", type=Path, required=True,
                    help="output folder: best_model.zip + .yaml (evaluate it as --policy OUT/best_model.zip)")
    cl.add_argument("--epochs", type=int, default=None,
                    help="passes over the dataset (default: agents.offline.CLONE_EPOCHS, 40)")
    cl.add_argument("--seed", type=seed_int, default=0,
                    help="network initialisation and minibatch order (default 0); the clone's config seeds envs "
                         f"and validation from it as a training does: {h.refused}")
    cl.set_defaults(func=_cmd_clone)


def _add_report(sub, h: _HelpTexts) -> None:
    """report: the multi-seed report of seed runs."""
    rp = sub.add_parser("report", help="the multi-seed report (seeds.json / seeds.md) of the runs DIR/seed_<k>/")
    rp.add_argument("folder", type=Path, metavar="DIR",
                    help="a folder of train --seeds runs (seed_<k>/ of any one learner), "
                         "or of msdgrasp select's picks; the report is written there")
    rp.add_argument("--episodes", type=int, default=10, help="episodes per seed and mu (default 10)")
    rp.add_argument("--seed", type=seed_int, default=h.evaluation_seed,
                    help=f"evaluation episode i is reset with seed + i (default {h.evaluation_seed}, the first of the "
                         f"sealed evaluation seeds {h.sealed}; seeds.json records whether they are sealed)")
    add_runner_args(rp, "every seed's evaluation")
    rp.add_argument("--quiet", action="store_true", help="no progress output")
    rp.set_defaults(func=_cmd_report)


def _add_leaderboard(sub) -> None:
    """leaderboard: a suite result's policies grouped into tracks."""
    lb = sub.add_parser("leaderboard", help="group a suite result's policies into tracks (a training's seeds, a "
                        "controller) and compare them: success with its Wilson lower bound, force ratio and time to "
                        "lift per condition; IQM with stratified bootstrap intervals, probability of improvement over "
                        "a baseline, performance profiles (agents/leaderboard.py)")
    lb.add_argument("suite_json", type=Path, nargs="+", metavar="SUITE.json",
                    help="suite results on the same episodes (msdgrasp evaluate --suite in_range --out DIR writes "
                         "DIR/suite_in_range.json; a second run with --no-baselines adds policies)")
    lb.add_argument("--track", action="append", required=True, metavar="NAME=PATTERN",
                    help="a track: its name and a glob of the policy specs it groups (repeat), e.g. "
                         "'default training=logs/train/seed_*/best_model.zip' or 'slip-reactive=reactive'; several "
                         "patterns joined by |")
    lb.add_argument("--baseline", default=None, metavar="NAME",
                    help="the track the probability of improvement compares every other with")
    lb.add_argument("--against", default=None, metavar="NAME",
                    help="a track every run (seed) of the others is compared with per condition: its successes "
                         "against that track's success rate, its mean peak pinch over that track's")
    lb.add_argument("--out", type=Path, required=True, help="folder for leaderboard.json and leaderboard.md")
    lb.set_defaults(func=_cmd_leaderboard)


def _add_select(sub, h: _HelpTexts) -> None:
    """select: a finished run's checkpoints validated again."""
    sl = sub.add_parser("select", help="validate a finished run's checkpoints again (more episodes, other mu) "
                                       "and write the best into a new folder; its validation episodes are the run's "
                                       f"(seed + 100000 + i): {h.refused}")
    sl.add_argument("run", type=Path, metavar="RUN",
                    help="a run folder of train (any learner), or a folder of their seed_<k>/ runs")
    sl.add_argument("--out", type=Path, required=True,
                    help="where the pick goes (OUT/seed_<k>/ for a folder of seeds); the run itself is not changed")
    sl.add_argument("--validation-episodes", type=int, default=None,
                    help="episodes per mu and checkpoint (default: the run's own, 6 in the shipped configs)")
    sl.add_argument("--validation-mu", default=None,
                    help="friction coefficients to validate at: a comma list or start:stop:step "
                         "(default: the run's own)")
    sl.add_argument("--checkpoints", default=None, metavar="FIRST-LAST",
                    help="select among the checkpoints numbered FIRST to LAST only (default: all), e.g. 0-3: a "
                         "recurrent run's DAgger iterations without its PPO stage")
    add_runner_args(sl, "the seeds' selections")
    sl.set_defaults(func=_cmd_select)


def _add_record(sub, h: _HelpTexts) -> None:
    """record: one episode of a policy to a rerun file."""
    r = sub.add_parser("record", help="record one episode of a policy to a rerun file (.rrd)", **h.controllers)
    r.add_argument("--policy", required=True, metavar="SPEC",
                   help=f"PATH (a saved model: it runs on the task it was trained on) | {h.policy_usage}")
    r.add_argument("--mu", type=float, default=0.5, help="friction coefficient (default 0.5)")
    r.add_argument("--seed", type=seed_int, default=0, help="episode seed (default 0)")
    r.add_argument("--out", type=Path, default=Path("logs") / "record" / "episode.rrd",
                   help="recording to write (default logs/record/episode.rrd)")
    r.add_argument("--video", type=Path, default=None, metavar="PATH",
                   help="also write the episode as a video: PATH ending in .mp4 or .gif")
    r.add_argument("--still", type=Path, default=None, metavar="PNG",
                   help="with --video: also save the video's last frame (the outcome) as a PNG")
    r.set_defaults(func=_cmd_record)


def _add_replay(sub) -> None:
    """replay: a recording in the rerun viewer."""
    from .replay import add_replay_arguments

    p = sub.add_parser("replay", help="open a recording (.rrd) in the rerun viewer")
    add_replay_arguments(p)
    p.set_defaults(func=_cmd_replay)


def _add_soak(sub) -> None:
    """soak: a long random-action run of the vector env."""
    s = sub.add_parser("soak", help="long random-action run of the vector env (stability soak test)")
    s.add_argument("--steps", type=int, default=1_000_000, help="total environment steps (default 1000000)")
    s.add_argument("--n-envs", type=env_count, default=16, help="parallel environments (default 16)")
    s.add_argument("--seed", type=seed_int, default=0, help="random seed (default 0)")
    s.add_argument("--out", type=Path, default=Path("logs") / "soak", help="output folder (default logs/soak)")
    s.add_argument("--quiet", action="store_true", help="no progress output")
    s.set_defaults(func=_cmd_soak)


def add_rl_commands(sub) -> None:
    """Add train / sweep / evaluate / collect / fit-friction / clone / report / leaderboard / select / record / replay /
    soak to the ``msdgrasp`` subparsers ``sub``."""
    h = _HelpTexts.now()
    _add_train(sub, h)
    _add_sweep(sub, h)
    _add_evaluate(sub, h)
    _add_collect(sub, h)
    _add_fit_friction(sub, h)
    _add_clone(sub, h)
    _add_report(sub, h)
    _add_leaderboard(sub)
    _add_select(sub, h)
    _add_record(sub, h)
    _add_replay(sub)
    _add_soak(sub)
