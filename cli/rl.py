"""The RL subcommands of ``msdgrasp``: train, sweep, evaluate, report, select, record, replay, soak.

Only argparse wiring lives here; every handler imports its (torch-, rerun- or numba-heavy) module lazily,
so ``msdgrasp --help`` stays fast and an unavailable optional module only breaks its own subcommand.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

DEFAULT_MODEL = Path("logs") / "train" / "best_model.zip"
#: the models of ``msdgrasp train --seeds`` with the default output folder
DEFAULT_SEED_MODELS = Path("logs") / "train" / "seed_*" / "best_model.zip"


def _default_models() -> list[str]:
    """logs/train/best_model.zip (one run) or every logs/train/seed_*/best_model.zip (a multi-seed run)."""
    if DEFAULT_MODEL.is_file():
        return [str(DEFAULT_MODEL)]
    return sorted(str(p) for p in Path().glob(str(DEFAULT_SEED_MODELS)))


def _usage(message: str) -> Exception:
    """A one-line input error (exit status 2)."""
    from .errors import UsageError

    return UsageError(message)


def _missing_module(command: str, exc: ImportError) -> Exception:
    return _usage(f"the {command} command is unavailable: {exc}")


def _add_runner_args(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--ray", action="store_true",
                   help=f"run {what} as Ray tasks on a local Ray instance (pip install 'msdgrasp[ray]')")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help=f"run {what} on this Ray cluster ('auto', host:port or ray://host:10001; implies --ray)")
    p.add_argument("--workers", type=int, default=None,
                   help="jobs at a time on this machine (default: one per CPU core); with --address the "
                        "cluster's CPUs decide")


def _runner_asked(args: argparse.Namespace) -> bool:
    """Whether the command line names a runner (--ray, --address or --workers)."""
    return args.ray or args.address is not None or args.workers is not None


def _runner(args: argparse.Namespace, default_workers: int | None = None):
    """The job runner the arguments ask for (agents.parallel.Runner); validated before anything runs."""
    from ..agents.parallel import Runner

    if args.workers is not None and args.workers < 1:
        raise _usage(f"--workers must be >= 1, got {args.workers}")
    if args.address is not None:
        if args.workers is not None:
            raise _usage("--workers sizes a local run; with --address the cluster's CPUs decide")
        return Runner.ray(address=args.address)
    if args.ray:
        return Runner.ray(workers=args.workers)
    return Runner.processes(args.workers if args.workers is not None else default_workers)


# ------------------------------------------------------------------------------------------------
# handlers
# ------------------------------------------------------------------------------------------------


def torch_config_path(config: Path | None, backend: str | None) -> Path:
    """The torch PPO's config: the one given, else the CPU-sized one for ``--backend cpu``
    (configs/train/rsl_ppo_cpu.yaml: 64 envs), else configs/train/rsl_ppo.yaml (the GPU's 4,096 envs)."""
    from ..physics.config import builtin_config

    if config is not None:
        return Path(config)
    return builtin_config("train/rsl_ppo_cpu.yaml" if backend == "cpu" else "train/rsl_ppo.yaml")


def _cmd_train_torch(args: argparse.Namespace) -> int:
    """``train --learner rsl`` (the default of ``--backend cuda``): rsl-rl's PPO on the batched core."""
    from ..physics.config import from_dict, read_yaml
    from ..physics.scenario import check_scene_files, resolve_scene_paths

    for flag, given in (("--algo", args.algo), ("--total-timesteps", args.total_timesteps), ("--resume", args.resume)):
        if given is not None:
            raise _usage(f"{flag} is an option of the SB3 learner; the torch PPO's run length is 'iterations' in its "
                         "config (configs/train/rsl_ppo.yaml, rsl_ppo_cpu.yaml)")
    if _runner_asked(args):
        raise _usage("--ray, --address and --workers run SB3 seeds in parallel; the torch PPO runs its seeds one "
                     "after the other on the one GPU")
    if args.seed is not None and args.seeds is not None:
        raise _usage("give either --seed or --seeds, not both")
    if args.n_envs is not None and args.n_envs < 1:
        raise _usage(f"--n-envs must be >= 1, got {args.n_envs}")
    try:
        from ..agents.torch_ppo import TorchPPOConfig, _rsl, train_torch

        _rsl()
    except ImportError as exc:
        raise _missing_module("train --learner rsl", exc) from None
    path = torch_config_path(args.config, args.backend)
    data = read_yaml(path)
    if "env" in data:  # the env's tissue / grasper configs: relative to this YAML
        data["env"] = resolve_scene_paths(data["env"], path)
    if args.backend is not None:  # else the config's (rsl_ppo.yaml: cuda)
        data["backend"] = args.backend
    if args.n_envs is not None:
        data["num_envs"] = args.n_envs
    config = from_dict(TorchPPOConfig, data, where=Path(path).name)
    check_scene_files(config.env.tissue_config, config.env.grasper_config, f"{path}:env")  # before any write
    if config.backend == "cuda":
        from numba import cuda

        if not cuda.is_available():
            raise _usage("--backend cuda: no CUDA GPU found (numba.cuda.is_available() is False); run on a machine "
                         "with an NVIDIA GPU and the gpu extra, or set NUMBA_ENABLE_CUDASIM=1 (numba's simulator: "
                         "slow, for tests)")
    if args.seeds is None:
        seeds = [config.seed if args.seed is None else args.seed]
    else:
        from ..agents.seeds import parse_seeds

        seeds = parse_seeds(args.seeds)
    results = []
    for seed in seeds:
        run = from_dict(TorchPPOConfig, {**data, "seed": seed}, where=Path(path).name)
        out = args.out if args.seeds is None else args.out / f"seed_{seed}"
        results.append(train_torch(run, out, progress=not args.quiet))
    if args.seeds is None:
        print(json.dumps(results[0], indent=2))
        return 0
    return _report_seeds(args.out, args.quiet, seeds=seeds)  # (only these: the folder may hold older runs)


def _seed_run(d: Path) -> tuple[str, Path, Path] | None:
    """A finished-or-not seed run's learner, policy and training summary: torch PPO (policy.pt, summary.json)
    or SB3 (best_model.zip, or final_model.zip of a run without validation, as ``train --seeds`` evaluates;
    train_summary.json); None where no policy is there."""
    if (d / "policy.pt").is_file():
        return "rsl", d / "policy.pt", d / "summary.json"
    for name in ("best_model.zip", "final_model.zip"):
        if (d / name).is_file():
            return "sb3", d / name, d / "train_summary.json"
    return None


def _report_seeds(folder: Path, quiet: bool, episodes: int = 10, runner=None, seeds=None) -> int:
    """The multi-seed report of the runs folder/seed_<k>/ of either learner (torch PPO: policy.pt and
    summary.json; SB3: best_model.zip and train_summary.json), of ``seeds`` (default: every run there):
    seeds.json / seeds.md as ``train --seeds`` writes them (agents.seeds.report_trained_seeds)."""
    from ..agents.evaluation import task_of
    from ..agents.models import model_config_path
    from ..agents.seeds import report_trained_seeds
    from ..agents.selection import seed_runs
    from ..physics.config import read_yaml

    runs = [(k, d, found) for k, d in seed_runs(Path(folder)) if (found := _seed_run(d)) is not None]
    if seeds is not None:
        runs = [r for r in runs if r[0] in set(seeds)]
    if not runs:
        raise _usage(f"{folder}: no seed_<k>/policy.pt or seed_<k>/best_model.zip there (the runs of train --seeds)")
    if len({learner for _, _, (learner, _, _) in runs}) > 1:
        raise _usage(f"{folder}: the seed_<k>/ runs mix learners (policy.pt and best_model.zip); report them apart")
    missing = [str(summary) for _, _, (_, _, summary) in runs if not summary.is_file()]
    if missing:
        raise _usage(f"{missing[0]} is missing: the run did not finish (its training summary is written last)")
    models = []
    for k, _, (learner, policy, summary_path) in runs:
        summary = json.loads(summary_path.read_text())
        if learner == "sb3":  # (SB3's summary, in the torch PPO's names)
            summary = {"train_s": summary["wall_time_s"], "agent_steps": summary["timesteps"],
                       "agent_steps_per_s": summary["steps_per_s"]}
        models.append((k, str(policy), summary))
    env, _ = task_of([m for _, m, _ in models], None)  # (all from one task, or a one-line error)
    first = runs[0][2]
    if first[0] == "rsl":
        config = json.loads((first[1].with_suffix(".json")).read_text())["config"]
    else:
        config = read_yaml(model_config_path(first[1]))
    config.pop("seed", None)
    result = report_trained_seeds(models, env, folder, config, episodes=episodes, runner=runner, progress=not quiet)
    print(json.dumps({"files": result["files"], "aggregate": result["aggregate"]}, indent=2))
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    """``msdgrasp report DIR``: the multi-seed report of seed runs (what ``train --seeds`` writes at its end),
    for runs made elsewhere, re-selected (``msdgrasp select``) or made before it wrote one."""
    if args.episodes < 1:
        raise _usage(f"--episodes must be >= 1, got {args.episodes}")
    if not Path(args.folder).is_dir():
        raise _usage(f"{args.folder}: not a folder")
    runner = _runner(args, os.cpu_count() or 1) if _runner_asked(args) else None
    return _report_seeds(Path(args.folder), args.quiet, args.episodes, runner)


def _cmd_train(args: argparse.Namespace) -> int:
    from ..physics.config import builtin_config, from_dict, read_yaml, to_dict
    from ..physics.scenario import check_scene_files, resolve_scene_paths
    from ..agents.models import TrainConfig

    learner = args.learner or ("rsl" if args.backend == "cuda" else "sb3")
    if args.out is None:  # the learners' runs are kept apart (evaluate's default reads logs/train)
        args.out = Path("logs") / ("train_torch" if learner == "rsl" else "train")
    if learner == "rsl":
        return _cmd_train_torch(args)
    if args.backend == "cuda":
        raise _usage("--backend cuda trains with the torch-native PPO (--learner rsl); SB3 steps host arrays")

    try:
        from ..agents.seeds import parse_seeds, run_seeds
        from ..agents.training import train
    except ImportError as exc:
        raise _missing_module("train", exc) from None
    if args.seeds is None and _runner_asked(args):
        raise _usage("--ray, --address and --workers run the seeds of --seeds; give --seeds")
    if args.resume is not None:
        if args.seeds is not None:
            raise _usage("--resume continues one run; it cannot be combined with --seeds")
        run_dir = Path(args.resume)
        if not (run_dir / "config.yaml").is_file():
            raise _usage(f"--resume {run_dir}: no config.yaml there (not a training run folder)")
        config = TrainConfig.load(run_dir / "config.yaml")
        if args.total_timesteps:
            config = from_dict(TrainConfig, {**to_dict(config), "total_timesteps": args.total_timesteps})
        summary = train(config, run_dir, resume=True, progress=not args.quiet)
    else:
        path = args.config or builtin_config("train/ppo.yaml")
        data = read_yaml(path)
        if "env" in data:  # the env's tissue / grasper configs: relative to this YAML
            data["env"] = resolve_scene_paths(data["env"], path)
        for key, val in (("algo", args.algo), ("total_timesteps", args.total_timesteps), ("n_envs", args.n_envs),
                         ("seed", args.seed)):
            if val is not None:
                data[key] = val
        if args.algo == "sac":  # the asymmetric critic is PPO's (documented in --algo's help)
            data["asymmetric_critic"] = False
        config = from_dict(TrainConfig, data, where=Path(path).name)
        check_scene_files(config.env.tissue_config, config.env.grasper_config, f"{path}:env")  # before any write
        if args.seeds is not None:
            if args.seed is not None:
                raise _usage("give either --seed or --seeds, not both")
            seeds = parse_seeds(args.seeds)
            result = run_seeds(config, seeds, args.out, runner=_runner(args, min(len(seeds), os.cpu_count() or 1)),
                               progress=not args.quiet)
            print(json.dumps({"files": result["files"], "aggregate": result["aggregate"]}, indent=2))
            return 0
        summary = train(config, args.out, progress=not args.quiet)
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
    try:
        from ..agents.sweep import SweepConfig, run_sweep, sweep_points
    except ImportError as exc:
        raise _missing_module("sweep", exc) from None
    sweep = SweepConfig.load(args.config)
    runner = _runner(args)
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
    return _default_models() or ["fixed"]


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from ..agents.evaluation import UNSEEN_CONDITIONS, evaluate, format_table, format_unseen, parse_mu_grid

    from ..agents.evaluation import DEFAULT_MU_GRID

    mus = parse_mu_grid(args.mu_grid or DEFAULT_MU_GRID)
    if args.episodes < 1:
        raise _usage(f"--episodes must be >= 1, got {args.episodes}")
    if args.n_envs is not None and args.n_envs < 1:
        raise _usage(f"--n-envs must be >= 1, got {args.n_envs}")
    policies = args.policy or _default_policies()
    # without --ray / --address / --workers the evaluation runs in this process, as it always did
    runner = _runner(args) if _runner_asked(args) else None
    result = evaluate(policies, mus, args.episodes, args.out, seed=args.seed, record=args.record,
                      progress=not args.quiet, n_envs=args.n_envs, video=args.video,
                      conditions=() if args.no_unseen else UNSEEN_CONDITIONS, runner=runner)
    print(format_table(result["results"]))
    if result["unseen_conditions"]:
        print(format_unseen(result["unseen_conditions"]))
    curve = result["oracle_minimal_force"]
    print("oracle minimal force (N): " + ", ".join(
        f"mu={m:g}: {f:.2f}" for m, f in zip(curve["mu"], curve["minimal_force_N"])))
    print(json.dumps({**result["files"], "recordings": result["recordings"]}, indent=2))
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from ..envs.grasp_lift import GraspLiftEnv
    from ..agents.evaluation import build_policy, check_policy_spec, record_policy_episode, task_of

    if not (math.isfinite(args.mu) and 0.0 <= args.mu <= 10.0):
        raise _usage(f"--mu must be in [0, 10], got {args.mu}")
    out = Path(args.out)
    if "{episode" in str(out):
        raise _usage(f"--out {out}: give one file name (no {{episode}} template)")
    if out.is_dir():
        raise _usage(f"--out {out} is a folder; give a file name such as {out / 'episode.rrd'}")
    from ..envs.video import check_still_path, check_video_path

    if args.video is not None:
        check_video_path(args.video)
    if args.still is not None:
        if args.video is None:
            raise _usage(f"--still {args.still}: needs --video (the still is the video's last frame)")
        check_still_path(args.still)
    spec = args.policy or next(iter(_default_models()), "fixed")
    check_policy_spec(spec)
    config, _ = task_of([spec], None)  # a model runs on the task it was trained on
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


def _cmd_select(args: argparse.Namespace) -> int:
    """``msdgrasp select RUN --out DIR``: validate a finished run's checkpoints again (other episodes or mu)
    and write the pick into DIR, the run untouched (agents.selection)."""
    from ..agents.evaluation import parse_mu_grid
    from ..agents.selection import select

    runner = _runner(args) if _runner_asked(args) else None
    mu = None if args.validation_mu is None else [float(m) for m in parse_mu_grid(args.validation_mu)]
    shown = []
    for r in select(args.run, args.out, args.validation_episodes, mu, runner=runner):
        best = r["best"]
        shown.append({"run": r["run"], "learner": r["learner"], "validation_episodes": r["validation_episodes"],
                      "checkpoints_validated": r["checkpoints_validated"], "selection_s": r["selection_s"],
                      "best": best["model"], "success_rate": best["success_rate"], "force_cost_N": best["force_cost_N"]})
    print(json.dumps(shown, indent=2))
    return 0


def add_rl_commands(sub) -> None:
    """Add train / evaluate / record / replay / soak to the ``msdgrasp`` subparsers ``sub``."""
    t = sub.add_parser("train", help="train a PPO/SAC grasp policy (Stable-Baselines3)")
    t.add_argument("--config", type=Path, default=None, help="training config (default configs/train/ppo.yaml)")
    t.add_argument("--algo", choices=["ppo", "sac"], default=None,
                   help="algorithm (default: from the config); sac trains with a symmetric critic (asymmetric_critic: false)")
    t.add_argument("--total-timesteps", type=int, default=None, help="environment steps to train for")
    t.add_argument("--n-envs", type=int, default=None, help="parallel environments")
    t.add_argument("--seed", type=int, default=None, help="random seed (one run)")
    t.add_argument("--seeds", default=None, metavar="RANGE",
                   help="train several seeds in parallel processes and evaluate each, e.g. 0-4 or 0,3,7: "
                        "writes seed_<k>/ runs and seeds.json, seeds.md, learning_curves.png (aggregate over seeds)")
    _add_runner_args(t, "the seeds of --seeds")
    t.add_argument("--out", type=Path, default=None,
                   help="output folder (default logs/train; logs/train_torch for --learner rsl)")
    t.add_argument("--resume", type=Path, default=None, help="continue the run saved in this folder")
    t.add_argument("--quiet", action="store_true", help="no progress output")
    t.add_argument("--backend", choices=["cpu", "cuda"], default=None,
                   help="where the task runs: cpu (numba; SB3's default) or cuda (the whole agent step on the GPU; "
                        "trains with --learner rsl; pip install 'msdgrasp[gpu]'); default: the config's")
    t.add_argument("--learner", choices=["sb3", "rsl"], default=None,
                   help="sb3 (Stable-Baselines3, the default) or rsl (rsl-rl's torch-native PPO, the default with "
                        "--backend cuda; config configs/train/rsl_ppo.yaml, whose backend is cuda, or with --backend "
                        "cpu configs/train/rsl_ppo_cpu.yaml)")
    t.set_defaults(func=_cmd_train)

    sw = sub.add_parser("sweep", help="hyper-parameter sweep: a grid of training configs, each over several seeds")
    sw.add_argument("config", type=Path, help="sweep file (base, set, grid, seeds, episodes; see agents/sweep.py)")
    sw.add_argument("--out", type=Path, default=Path("logs") / "sweep", help="output folder (default logs/sweep)")
    sw.add_argument("--dry-run", action="store_true", help="validate and list the points, run nothing")
    _add_runner_args(sw, "the points' seeds")
    sw.add_argument("--quiet", action="store_true", help="no progress output")
    sw.set_defaults(func=_cmd_sweep)

    e = sub.add_parser("evaluate", help="success and pinch force of policies across a grid of friction mu")
    e.add_argument("--policy", action="append", default=None, metavar="SPEC",
                   help="PATH (saved model .zip) | fixed | fixed:<N> | reactive | oracle (repeatable; default "
                        "logs/train/best_model.zip, else every logs/train/seed_*/best_model.zip, else fixed). "
                        "reactive and oracle are always added")
    e.add_argument("--mu-grid", default=None,
                   help="start:stop:step (stop included) or a comma list (default: the training range 0.3-0.9 "
                        "and the unseen 0.15, 0.2, 1.0, 1.2)")
    e.add_argument("--no-unseen", action="store_true",
                   help="skip the unseen tissues (stiffness 0.6 / 1.5, mass 0.8 / 1.25 at mu 0.5)")
    e.add_argument("--episodes", type=int, default=10, help="episodes per policy and mu (default 10)")
    e.add_argument("--n-envs", type=int, default=None, help="batch size (default: all episodes of one mu at once)")
    e.add_argument("--seed", type=int, default=0, help="episode i is seeded seed + i (default 0)")
    e.add_argument("--out", type=Path, default=Path("logs") / "evaluate", help="output folder (default logs/evaluate)")
    e.add_argument("--record", action="store_true", help="also record one episode per policy and mu (.rrd)")
    e.add_argument("--video", action="store_true", help="also write one video per policy and mu (videos/*.mp4)")
    _add_runner_args(e, "every (policy, mu) cell as its own job")
    e.add_argument("--quiet", action="store_true", help="no progress output")
    e.set_defaults(func=_cmd_evaluate)

    rp = sub.add_parser("report", help="the multi-seed report (seeds.json / seeds.md) of the runs DIR/seed_<k>/")
    rp.add_argument("folder", type=Path, metavar="DIR",
                    help="a folder of train --seeds runs (seed_<k>/best_model.zip, or policy.pt of --learner rsl), "
                         "or of msdgrasp select's picks; the report is written there")
    rp.add_argument("--episodes", type=int, default=10, help="episodes per seed and mu (default 10)")
    _add_runner_args(rp, "every seed's evaluation")
    rp.add_argument("--quiet", action="store_true", help="no progress output")
    rp.set_defaults(func=_cmd_report)

    sl = sub.add_parser("select", help="validate a finished run's checkpoints again (more episodes, other mu) "
                                       "and write the best into a new folder")
    sl.add_argument("run", type=Path, metavar="RUN",
                    help="a run folder of train (SB3) or train --learner rsl, or a folder of their seed_<k>/ runs")
    sl.add_argument("--out", type=Path, required=True,
                    help="where the pick goes (OUT/seed_<k>/ for a folder of seeds); the run itself is not changed")
    sl.add_argument("--validation-episodes", type=int, default=None,
                    help="episodes per mu and checkpoint (default: the run's own, 6 in the shipped configs)")
    sl.add_argument("--validation-mu", default=None,
                    help="friction coefficients to validate at: a comma list or start:stop:step (default: the run's own)")
    _add_runner_args(sl, "the seeds' selections")
    sl.set_defaults(func=_cmd_select)

    r = sub.add_parser("record", help="record one episode of a policy to a rerun file (.rrd)")
    r.add_argument("--policy", default=None, metavar="SPEC",
                   help="PATH | fixed | fixed:<N> | reactive | oracle | zero | idle (default "
                        "logs/train/best_model.zip, else logs/train/seed_0's, else fixed)")
    r.add_argument("--mu", type=float, default=0.5, help="friction coefficient (default 0.5)")
    r.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    r.add_argument("--out", type=Path, default=Path("logs") / "record" / "episode.rrd",
                   help="recording to write (default logs/record/episode.rrd)")
    r.add_argument("--video", type=Path, default=None, metavar="PATH",
                   help="also write the episode as a video: PATH ending in .mp4 or .gif")
    r.add_argument("--still", type=Path, default=None, metavar="PNG",
                   help="with --video: also save the video's last frame (the outcome) as a PNG")
    r.set_defaults(func=_cmd_record)

    from .replay import add_replay_arguments

    p = sub.add_parser("replay", help="open a recording (.rrd) in the rerun viewer")
    add_replay_arguments(p)
    p.set_defaults(func=_cmd_replay)

    s = sub.add_parser("soak", help="long random-action run of the vector env (stability soak test)")
    s.add_argument("--steps", type=int, default=1_000_000, help="total environment steps (default 1000000)")
    s.add_argument("--n-envs", type=int, default=16, help="parallel environments (default 16)")
    s.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    s.add_argument("--out", type=Path, default=Path("logs") / "soak", help="output folder (default logs/soak)")
    s.add_argument("--quiet", action="store_true", help="no progress output")
    s.set_defaults(func=_cmd_soak)
