"""``msdgrasp reference``: the reference forces of a task's force ratios (agents/reference.py), written as JSON.

    msdgrasp reference --out configs/reference/spleen.json              the benchmark task (spleen)
    msdgrasp reference --config TRAIN.yaml --out FILE --workers 8       the task of a training config's env: section
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from .rl import add_mu_grid_arg, add_runner_args, positive_mu_grid, runner_from_args, usage_error


def _pulls(text: str) -> list[float]:
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise usage_error(f"--pulls {text!r}: expected a comma list of fractions of the arm's top speed in (0, 1], "
                          "e.g. 0.25,0.3,0.5") from None
    for v in values:
        if not 0.0 < v <= 1.0:
            raise usage_error(f"--pulls: pull {v:g} is out of range; allowed (0, 1] (a fraction of the arm's top "
                              "speed)")
    return values


def _cmd_reference(args: argparse.Namespace) -> int:
    from ..agents.reference import (
        REFERENCE_SEEDS, compute_reference, format_reference, task_fingerprint, write_reference,
    )
    from ..envs.core import GraspLiftConfig, benchmark_config

    if args.out.suffix != ".json":
        raise usage_error(f"--out must be a .json file, got {args.out}")
    if args.out.is_dir():
        raise usage_error(f"--out {args.out} is a folder; give a file name such as {args.out / 'spleen.json'}")
    if args.config is not None and args.scene is not None:
        raise usage_error("give either --scene (the benchmark task of that scene) or --config (a training config's "
                          "task)")
    if args.episodes < 1:
        raise usage_error(f"--episodes must be >= 1, got {args.episodes}")
    last = REFERENCE_SEEDS.stop - args.episodes
    if not REFERENCE_SEEDS.start <= args.seed <= last:
        raise usage_error(f"--seed must keep the reference episodes in the reference seeds [{REFERENCE_SEEDS.start}, "
                          f"{REFERENCE_SEEDS.stop}); allowed {REFERENCE_SEEDS.start}..{last}, got {args.seed}")
    if not 0.0 < args.tolerance <= 0.1:
        raise usage_error(f"--tolerance must be in (0, 0.1] N, got {args.tolerance}")
    if args.config is not None:
        if not args.config.is_file():
            raise usage_error(f"--config: no such file: {args.config}")
        config = GraspLiftConfig.from_yaml(args.config)
    else:
        config = benchmark_config(args.scene or "spleen")
    mus = positive_mu_grid(args.mu_grid)
    pulls = _pulls(args.pulls)
    # (processes, one per core, unless --workers / --ray / --address)
    runner = runner_from_args(args, os.cpu_count() or 1)
    # every finished search is kept beside the table until it is written: a stopped run goes on where it stopped
    journal = args.out.with_name(args.out.name + ".cells.jsonl")
    with runner:
        record = compute_reference(config, mus, pulls, args.episodes, args.seed, args.tolerance, runner=runner,
                                   progress=not args.quiet, journal=journal)
    write_reference(record, args.out)
    journal.unlink(missing_ok=True)
    print(format_reference(record))
    print(json.dumps({"out": str(args.out), "task_digest": record["task_digest"], "seconds": record["seconds"],
                      "scene": task_fingerprint(config)["scene"]}, indent=2))
    return 0


def add_reference_command(sub) -> None:
    """Add ``reference`` to the ``msdgrasp`` subparsers ``sub``."""
    from ..agents.reference import DEFAULT_EPISODES, DEFAULT_MUS, DEFAULT_PULLS, REFERENCE_SEED, TOLERANCE_N

    p = sub.add_parser("reference", help="the reference forces of the force ratios: per mu, the least fixed grip that "
                                         "holds 95%% of the reference episodes at the pull speed that needs least")
    p.add_argument("--out", type=Path, required=True,
                   help="the table to write (.json), e.g. configs/reference/spleen.json; until it is written, each "
                        "finished search is kept in OUT.cells.jsonl, and a run started again takes them from there")
    p.add_argument("--scene", choices=("spleen", "sphere"), default=None,
                   help="the benchmark task of this scene (default spleen)")
    p.add_argument("--config", type=Path, default=None, metavar="TRAIN.yaml",
                   help="instead, the task of this config's env: section")
    add_mu_grid_arg(p, DEFAULT_MUS)
    p.add_argument("--pulls", default=",".join(f"{v:g}" for v in DEFAULT_PULLS),
                   help="pull speeds searched, fractions of the arm's top speed (default "
                        + ",".join(f"{v:g}" for v in DEFAULT_PULLS) + ")")
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES,
                   help=f"reference episodes per mu (default {DEFAULT_EPISODES})")
    p.add_argument("--seed", type=int, default=REFERENCE_SEED,
                   help=f"episode i is reset with seed + i (default {REFERENCE_SEED})")
    p.add_argument("--tolerance", type=float, default=TOLERANCE_N,
                   help=f"the bisection's tolerance on the grip, N (default {TOLERANCE_N:g})")
    add_runner_args(p, "every (mu, pull) search as its own job")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_reference)
