"""The ``msdgrasp`` command line.

    msdgrasp experiment compress|grasp|grasp-sphere ...   the paper's experiments (CSV + PNG)
    msdgrasp experiment fem ...                            the MSD against a finite-element reference
    msdgrasp calibrate --data CSV ...                      fit the tissue's constants to compression curves
    msdgrasp bench [physics|grasp|env|gpu|learners|...]    speed benchmarks (JSON); precision: float32's error;
                                                          compile: a cold first run's compilation
    msdgrasp train / evaluate / record / replay / soak     RL (see --help of each)
    msdgrasp reference --out FILE                          the reference forces of the force ratios (JSON)
    msdgrasp headroom --out FILE                           how light a grip could be, by what it knows (JSON)
    msdgrasp frontier SUITE.json --out DIR                 what one policy per mu could do on development episodes
    msdgrasp meshes [--check]                              regenerate (or check) the shipped gmsh meshes

Every subcommand validates its inputs and exits with status 2 and a one-line message naming the bad
field on invalid input (no traceback); outputs are written atomically.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from .errors import UsageError

DEFAULT_LOGS = Path("logs")


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``msdgrasp train: error: ...``, exit 2), without the usage block;
    ``--help`` shows the usage. Its subparsers are of the same class."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


#: argument names that are output paths, checked before a command runs (:func:`check_output_path`)
OUTPUT_ARGS = ("out", "video", "still")
#: suffixes that make an output path a file; any other output path is a folder
FILE_SUFFIXES = (".json", ".yaml", ".yml", ".rrd", ".mp4", ".gif", ".png", ".csv", ".md", ".jsonl")


def check_output_path(path: Path, field: str) -> None:
    """UsageError (one line, naming ``field``) unless ``path`` can be written: a file (by its suffix) where no folder
    is, or a folder where no file is, under a folder this process can create files in. Probed with an unnamed
    temporary file, so nothing stays behind."""
    import tempfile

    is_file = path.suffix.lower() in FILE_SUFFIXES
    if path.exists():
        if is_file and path.is_dir():
            raise UsageError(f"{field} must be a file ({path.suffix}), got the folder {path}")
        if not is_file and not path.is_dir():
            raise UsageError(f"{field} must be a folder, got the file {path}")
    folder = path if (path.is_dir() or not is_file) else path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise UsageError(f"{field}: {path} lies under the file {folder}, not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise UsageError(f"{field}: cannot write under {folder}: {exc.strerror or exc}") from None


def _add_out(p: argparse.ArgumentParser, default: str) -> None:
    p.add_argument("--out", type=Path, default=DEFAULT_LOGS / default, help=f"output folder (default logs/{default})")


# ------------------------------------------------------------------------------------------------
# experiments
# ------------------------------------------------------------------------------------------------


def _cmd_compress(args: argparse.Namespace) -> int:
    from .experiments import compress_cli

    return compress_cli(args)


def _cmd_grasp(args: argparse.Namespace) -> int:
    from .experiments import grasp_cli

    return grasp_cli(args)


def _cmd_grasp_sphere(args: argparse.Namespace) -> int:
    from .experiments import grasp_sphere_cli

    return grasp_sphere_cli(args)


def _cmd_pinch_hold(args: argparse.Namespace) -> int:
    import json

    from ..experiments.pinch_hold import result_dict, run_pinch_hold
    from ..physics.config import ConfigError, check_range
    from .experiments import resolution_arg

    check_range("--mu", args.mu, 0.0, 10.0, lo_inclusive=False)  # (the env's mu range)
    check_range("--pinch", args.pinch, 0.0, 50.0, lo_inclusive=False)  # (the largest max_pinch_force_N a task has)
    if args.config is not None and not args.config.is_file():
        raise ConfigError(f"--config {args.config}: tissue config not found")
    result = run_pinch_hold(resolution_arg(args.resolution), mu=args.mu, pinch_N=args.pinch, tissue_config=args.config)
    print(json.dumps(result_dict(result), indent=2))
    return 0


def _cmd_fem(args: argparse.Namespace) -> int:
    from .experiments import fem_cli

    return fem_cli(args)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from .experiments import calibrate_cli

    return calibrate_cli(args)


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "profile":  # (its own module: it builds on bench.py's set-ups)
        from ..benchmarks.profile import profile_cli

        return profile_cli(bool(args.quick), args.out)
    if args.what == "compile":  # (a child process with an empty numba cache)
        from ..benchmarks.compile_time import compile_cli

        return compile_cli(args.out)
    from ..benchmarks.bench import bench_cli

    return bench_cli(args)


# ------------------------------------------------------------------------------------------------
# parser
# ------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="msdgrasp", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    exp = sub.add_parser("experiment", help="the paper's experiments")
    exp_sub = exp.add_subparsers(dest="experiment", required=True)

    c = exp_sub.add_parser("compress", help="unconstrained compression of the sphere between rigid plates")
    c.add_argument("--config", type=Path, default=None, help="tissue config (default configs/tissue/sphere.yaml)")
    c.add_argument("--rate", type=float, action="append", help="plate speed in mm/min (repeatable; default 6 and 60)")
    c.add_argument("--deformation", type=float, default=0.30, help="final deformation as a fraction of the diameter")
    c.add_argument("--samples", type=int, default=150, help="force samples per curve")
    c.add_argument("--resolution", default=None, help="coarse|medium|fine|xfine or a node count")
    c.add_argument("--diameter-mm", type=float, default=None, help="sphere diameter in mm (default 50)")
    c.add_argument("--plate-mu", type=float, default=None, help="plate/sample friction (default 0.5: the plates hold "
                   "the sample upright; 0: lubricated plates)")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_out(c, "compress")
    c.set_defaults(func=_cmd_compress)

    g = exp_sub.add_parser("grasp", help="the paper's spleen grasp protocol (close 5 s, hold 7 s, pull)")
    g.add_argument("--mu", type=float, action="append", help="friction coefficient (repeatable; default 0.4 0.6 0.8)")
    g.add_argument("--config", type=Path, default=None, help="tissue config (default configs/tissue/spleen.yaml)")
    g.add_argument("--grasper", type=Path, default=None, help="grasper config (default configs/grasper/default.yaml)")
    g.add_argument("--resolution", default=None, help="coarse|medium|fine or a node count")
    g.add_argument("--pull-time", type=float, default=None, help="time limit of the pull phase, s")
    g.add_argument("--quiet", action="store_true")
    _add_out(g, "grasp")
    g.set_defaults(func=_cmd_grasp)

    gs = exp_sub.add_parser("grasp-sphere", help="the sample grasped with increasing pinch (pinch force vs jaw travel)")
    gs.add_argument("--config", type=Path, default=None, help="tissue config (default configs/tissue/sphere.yaml)")
    gs.add_argument("--grasper", type=Path, default=None)
    gs.add_argument("--resolution", default=None)
    gs.add_argument("--quiet", action="store_true")
    _add_out(gs, "grasp_sphere")
    gs.set_defaults(func=_cmd_grasp_sphere)

    ph = exp_sub.add_parser("pinch-hold", help="5 N force-loop pinch, 15 mm/s pull, hold: pinch steadiness, friction "
                            "cone at every face-held node, smallest tet volume (JSON)")
    ph.add_argument("--resolution", default="coarse", help="coarse|medium|fine")
    ph.add_argument("--mu", type=float, default=0.3, help="jaw friction coefficient (default 0.3)")
    ph.add_argument("--pinch", type=float, default=5.0, help="pinch-force set-point, N (default 5)")
    ph.add_argument("--config", type=Path, default=None, help="tissue config (default configs/tissue/spleen.yaml)")
    ph.set_defaults(func=_cmd_pinch_hold)

    fe = exp_sub.add_parser("fem", help="the MSD against a finite-element reference on the same meshes (linear and "
                            "neo-Hookean; needs the extra fem)")
    fe.add_argument("--case", action="append", help="cube|cube-slip|sphere|spleen|sphere-pad|spleen-pad|spleen-even|"
                    "spleen-even-pad|cube-j1|cube-slip-j1|spleen-j1|spleen-j1-pad (repeatable; default all)")
    fe.add_argument("--resolution", action="append", help="coarse|medium|fine (repeatable; default coarse and fine)")
    fe.add_argument("--poisson", type=float, default=0.25,
                    help="the continuum's Poisson ratio in [0, 0.5) (default 0.25: the spring network's own)")
    fe.add_argument("--config", type=Path, default=None, help="tissue config (default configs/tissue/spleen.yaml)")
    fe.add_argument("--no-hertz", action="store_true",
                    help="skip the FEM's Hertz checks (a rigid sphere on a half-space, a sphere between plates; ~40 s)")
    fe.add_argument("--no-quadratic", action="store_true",
                    help="skip the quadratic (P2) FEM at small strain (the linear reference's own error; minutes)")
    fe.add_argument("--no-converge", action="store_true",
                    help="skip the refined, extrapolated FEM at small strain (the continuum's limit; minutes)")
    fe.add_argument("--small-strain-only", action="store_true",
                    help="only the small-strain (linear) comparison, not the neo-Hookean FEM and nonlinear MSD at "
                         "10 and 20 %%")
    _add_out(fe, "fem")
    fe.set_defaults(func=_cmd_fem)

    cal = sub.add_parser("calibrate", help="fit the tissue's constants to force-deformation curves at several rates")
    cal.add_argument("--data", type=Path, required=True,
                     help="CSV with rate_mm_per_min,deformation_mm,force_N[,time_s]")
    cal.add_argument("--config", type=Path, default=None,
                     help="config giving the mesh (default configs/tissue/sphere.yaml)")
    cal.add_argument("--out", type=Path, default=DEFAULT_LOGS / "calibrate" / "tissue.yaml",
                     help="tissue config to write")
    cal.add_argument("--max-evals", type=int, default=200, help="largest number of simulations of the fit")
    cal.add_argument("--fit", choices=("viscoelastic", "paper"), default="viscoelastic",
                     help="viscoelastic (default): K1, K2, dl_c and the springs' Maxwell branch (g, tau); "
                          "paper: K1, K2, dl_c and the nodal damping b0, b1 (Eq. 7)")
    cal.add_argument("--quiet", action="store_true")
    cal.set_defaults(func=_cmd_calibrate)

    b = sub.add_parser("bench", help="speed benchmarks, printed as JSON")
    b.add_argument("what", nargs="?", default="physics",
                   choices=["physics", "grasp", "env", "gpu", "precision", "learners", "profile", "compile", "all"])
    b.add_argument("--quick", action="store_true", help="fewer repetitions (for smoke tests)")
    b.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    b.set_defaults(func=_cmd_bench)

    _add_rl_commands(sub)
    from .headroom import add_headroom_command
    from .reference import add_reference_command

    add_reference_command(sub)
    add_headroom_command(sub)
    m = sub.add_parser("meshes", help="regenerate the shipped gmsh meshes (sphere-even, spleen-even; needs the extra "
                       "meshing), or --check them against a fresh generation")
    m.add_argument("--check", action="store_true", help="compare with the shipped files instead of writing (exit 1 "
                   "where one differs)")
    m.set_defaults(func=_cmd_meshes)
    return parser


def _cmd_meshes(args: argparse.Namespace) -> int:
    from .meshes import meshes_cli

    return meshes_cli(args)


def _add_rl_commands(sub) -> None:
    """train/evaluate/record/replay/soak live in modules (agents/, benchmarks/) that import torch lazily."""
    from .rl import add_rl_commands

    add_rl_commands(sub)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # (--help, or an argument's one-line error: the parser has printed it)
        return int(exc.code or 0)
    from ..physics.config import ConfigError, MissingExtraError
    from ..physics.mesh import MeshError
    from ..envs.recording import RecordingError

    try:
        for name in OUTPUT_ARGS:  # (before anything runs or is written)
            value = getattr(args, name, None)
            if isinstance(value, Path):
                check_output_path(value, f"--{name}")
        return int(args.func(args) or 0)
    except (UsageError, ConfigError, MissingExtraError, MeshError, RecordingError, OSError, UnicodeDecodeError) as exc:
        print(f"msdgrasp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError as exc:  # (a size asked for that the machine cannot hold: one line, not a traceback)
        print(f"msdgrasp {args.command}: error: not enough memory ({exc or 'allocation failed'}); ask for fewer envs, "
              "episodes or seeds", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
