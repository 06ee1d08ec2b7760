"""``msdgrasp headroom``: how light a grip could be, by what it knows (agents/headroom.py), written as JSON.

    msdgrasp headroom --out logs/headroom.json                          the default training's task, 40 episodes per mu
    msdgrasp headroom --config TRAIN.yaml --episodes 60 --out FILE      another training's task

``msdgrasp frontier``: what choosing a policy per mu could do on a suite's development episodes (agents/frontier.py).

    msdgrasp frontier DEV/suite_in_range.json --family 'slipfeedback:*told=1*' --out DIR
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from .rl import add_mu_grid_arg, add_runner_args, positive_mu_grid, runner_from_args, usage_error


def _cmd_headroom(args: argparse.Namespace) -> int:
    from ..agents.headroom import (
        HEADROOM_SEEDS, estimating_controller, format_headroom, headroom_verdict, measure_headroom,
    )
    from ..agents.models import TrainConfig, default_training
    from ..physics.config import ConfigError, atomic_write_text

    if args.out.suffix != ".json" or args.out.is_dir():
        raise usage_error(f"--out must be a .json file, got {args.out}")
    if args.episodes < 3:
        raise usage_error(f"--episodes must be >= 3 (per mu; the regressions leave one out), got {args.episodes}")
    mus = positive_mu_grid(args.mu_grid)
    last = HEADROOM_SEEDS.stop - args.episodes * len(mus)
    if last < HEADROOM_SEEDS.start:
        raise usage_error(f"--episodes: {args.episodes} per mu x {len(mus)} mu do not fit in the headroom seeds "
                          f"[{HEADROOM_SEEDS.start}, {HEADROOM_SEEDS.stop}); allowed 3.."
                          f"{len(HEADROOM_SEEDS) // len(mus)}")
    if not HEADROOM_SEEDS.start <= args.seed <= last:
        raise usage_error(f"--seed must keep the episodes in the headroom seeds [{HEADROOM_SEEDS.start}, "
                          f"{HEADROOM_SEEDS.stop}); allowed {HEADROOM_SEEDS.start}..{last}, got {args.seed}")
    if args.config is not None and not args.config.is_file():
        raise usage_error(f"--config: no such file: {args.config}")
    config = (TrainConfig.load(args.config) if args.config else default_training()).training_task()
    try:
        estimating_controller(args.controller, config)
    except ConfigError as exc:
        raise usage_error(f"--controller: {exc}") from None
    runner = runner_from_args(args, os.cpu_count() or 1)
    try:  # (the folder now, not after a run of minutes)
        args.out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise usage_error(f"--out: cannot make the folder {args.out.parent}: {exc.strerror}") from None
    with runner:
        record = measure_headroom(config, mus, args.episodes, args.seed, args.controller, runner=runner)
    record["verdict"] = headroom_verdict(record)
    atomic_write_text(args.out, json.dumps(record, indent=2) + "\n")
    print(format_headroom(record))
    print(record["verdict"])
    print(json.dumps({"out": str(args.out), "seconds": record["seconds"]}))
    return 0


def _cmd_frontier(args: argparse.Namespace) -> int:
    from ..agents.frontier import family_specs, frontier_markdown, mu_frontier
    from ..agents.leaderboard import merge_results, read_result
    from ..physics.config import atomic_write_text, nan_to_none

    if args.out.exists() and not args.out.is_dir():
        raise usage_error(f"--out must be a folder, got the file {args.out}")
    result = merge_results([read_result(p) for p in args.suite_json])
    record = mu_frontier(result, args.against, family_specs(result, args.family or [], args.against), args.cap)
    text, data = frontier_markdown(record), json.dumps(nan_to_none(record), indent=2) + "\n"
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise usage_error(f"--out: cannot make the folder {args.out}: {exc.strerror}") from None
    atomic_write_text(args.out / "frontier.md", text)
    atomic_write_text(args.out / "frontier.json", data)
    print(text)
    return 0


def add_headroom_command(sub) -> None:
    """Add ``headroom`` to the ``msdgrasp`` subparsers ``sub``."""
    from ..agents.headroom import DEFAULT_CONTROLLER, DEFAULT_EPISODES, DEFAULT_MUS, HEADROOM_SEED

    p = sub.add_parser("headroom", help="how light a grip could be, by what it knows: each episode's holding grip "
                                        "against the true mu, the privileged draws, the controller's estimate and "
                                        "its closing features, and a fixed grip sized from each run on the episodes")
    p.add_argument("--out", type=Path, required=True, help="the record to write (.json)")
    p.add_argument("--config", type=Path, default=None, metavar="TRAIN.yaml",
                   help="the task of this training config (its env: with its train_randomization:); default the "
                        "default training's (configs/train/ppo.yaml)")
    add_mu_grid_arg(p, DEFAULT_MUS)
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES,
                   help=f"episodes per mu (default {DEFAULT_EPISODES})")
    p.add_argument("--seed", type=int, default=HEADROOM_SEED,
                   help=f"episode k is reset with seed + k (default {HEADROOM_SEED})")
    p.add_argument("--controller", default=DEFAULT_CONTROLLER,
                   help=f"the estimating controller compared (default {DEFAULT_CONTROLLER})")
    add_runner_args(p, "every chunk of episodes and every fixed-grip run as its own job")
    p.set_defaults(func=_cmd_headroom)

    from ..agents.frontier import DEFAULT_CAP

    f = sub.add_parser("frontier", help="what choosing one policy per mu could do on a suite's development episodes: "
                                        "each policy of a family against a reference per condition, the best "
                                        "schedule (one policy per mu) within a force cap, per-episode hindsight "
                                        "(agents/frontier.py)")
    f.add_argument("suite_json", type=Path, nargs="+", metavar="SUITE.json",
                   help="suite results on the same development episodes (msdgrasp evaluate --suite in_range "
                        "--no-baselines --seed S --policy ... --out DIR writes DIR/suite_in_range.json)")
    f.add_argument("--against", default=DEFAULT_CONTROLLER, metavar="SPEC",
                   help=f"the reference policy's spec in the result (default {DEFAULT_CONTROLLER})")
    f.add_argument("--family", action="append", metavar="PATTERN",
                   help="a glob of the specs picked from (repeat; default every policy but the reference)")
    f.add_argument("--cap", type=float, default=DEFAULT_CAP,
                   help=f"the most mean peak pinch over the reference's in any condition (default {DEFAULT_CAP})")
    f.add_argument("--out", type=Path, required=True, help="folder for frontier.json and frontier.md")
    f.set_defaults(func=_cmd_frontier)
