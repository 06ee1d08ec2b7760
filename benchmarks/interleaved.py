"""Two or more builds of the physics timed alternately, each in its own process: an A/B that a busy machine cannot
skew.

On a shared machine the speed of a core drifts by tens of percent over minutes, so two builds timed one after
the other differ by the drift. Here every build steps its own copy of the bench's grasp (coarse spleen, jaws
closed on it: :func:`.harness.grasped`, one tissue and a batch of 64) in a worker process of its own, and each
round times every build once, in a random order, one worker at a time, so drift falls on all of them alike.
Reported per build: the median, first quartile and minimum over the rounds, in us of compute per simulated ms.

Every worker runs on the same CPU (``--cpu``, by default the lowest this process may use): left to the OS, each
worker stays on a core of its own, and a difference between the cores' speeds would read as a difference between the
builds. The same build still differs from process to process in the batch row at its default 2 ms per call (medians
58-60 against 74-76 us per simulated ms per tissue in six processes of one build; at 33 ms per call 40-44 in
every process: the spread is in a call's set-up, not in the substeps), so ``--batch-ms 33`` (an agent step per
call) is the setting to judge a change of the batch's substeps by.

One process per build, because two copies of the package in one process are not independent: every build
imported after the first paid about 0.85 ms more per ``Simulation.step`` call (measured: the same build was
fast when imported first and slow when second, at equal cost per simulated ms), which at 40 ms per call read as
+21 us per simulated ms against whichever build came first.

Each build is a copy of the package under its own name on ``sys.path`` (numba caches each copy apart)::

    mkdir -p /tmp/ab/msd_base && git archive <rev> | tar -x -C /tmp/ab/msd_base
    mkdir -p /tmp/ab/msd_new && git archive HEAD | tar -x -C /tmp/ab/msd_new
    PYTHONPATH=/tmp/ab python -m msdgrasp.benchmarks.interleaved msd_base,msd_new --rounds 200

(the name ``msdgrasp`` is the installed build itself). Each worker compiles or loads its kernels before the
first round. ``--env`` times the envs the same way instead: the single env (``GraspLiftEnv``, as ``gym.make`` gives
it) and the native vector env of 64, random actions, us per agent step (per env). ``--sphere`` times the paper's
compression instead: the coarse sphere of ``tissue/sphere.yaml`` (Maxwell branch and spring dashpots) pressed 1 mm
between the plates, then pressed on at 6 mm/min, one tissue and a batch of two (the compression experiment's two
rates), us per simulated ms (per tissue).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import random
import statistics
import subprocess
import sys
import time


def _worker(name: str, steps_one: int, steps_batch: int, batch: int) -> None:
    """A build's worker: build the grasp, say ``ready``, then one timed round per line read from stdin; each
    reply is one line of JSON [us per simulated ms of one tissue, us per simulated ms per tissue of the batch]."""
    if name.startswith("env:"):
        _env_worker(name[4:], steps_one, steps_batch, batch)
        return
    if name.startswith("sphere:"):
        _sphere_worker(name[7:], steps_one, steps_batch, batch)
        return
    grasped, clone = _grasp_helpers(name)
    simulation = importlib.import_module(name + ".physics.simulation")
    scene, one = grasped("coarse", 2.0, 2.0)
    many = simulation.Simulation(scene.model, batch, dt=one.dt, grasper=scene.grasper)
    clone(one, many)
    one.step(1)  # compile or load the kernels
    many.step(1)
    _serve(one.step, many.step, steps_one, steps_batch, batch)


def _grasp_helpers(name: str) -> tuple:
    """(grasped, clone) of the build ``name``: each build times its own grasp."""
    try:
        harness = importlib.import_module(name + ".benchmarks.harness")
    except ModuleNotFoundError:  # a build from before benchmarks/harness.py: the same two, private to its bench
        bench = importlib.import_module(name + ".benchmarks.bench")
        return bench._grasped, bench._clone
    return harness.grasped, harness.clone


def _serve(run_one, run_many, steps_one: int, steps_batch: int, batch: int) -> None:
    """Say ``ready``, then per line read from stdin one timed round: ``run_one(steps_one)``, ``run_many(steps_batch)``;
    reply one line of JSON [us per step of the one, us per step per member of the ``batch``]."""
    print("ready", flush=True)
    for _ in sys.stdin:
        t0 = time.perf_counter()
        run_one(steps_one)
        t1 = time.perf_counter()
        run_many(steps_batch)
        t2 = time.perf_counter()
        print(json.dumps([(t1 - t0) / steps_one * 1e6, (t2 - t1) / steps_batch / batch * 1e6]), flush=True)


def _env_worker(name: str, steps_one: int, steps_batch: int, batch: int) -> None:
    """:func:`_worker` of the envs (``--env``): the Gymnasium env as ``gym.make`` gives it and the native vector env
    of ``batch`` envs, random actions in [-1, 1], autoreset; each reply [us per agent step of the single env, us per
    agent step per env of the vector env]."""
    import numpy as np

    module = importlib.import_module(name + ".envs.grasp_lift")
    single = module.GraspLiftEnv()
    vector = module.GraspLiftVectorEnv(batch)
    single.reset(seed=0)
    vector.reset(seed=0)
    rng = np.random.default_rng(0)

    def run_single(n: int) -> None:
        for _ in range(n):
            _, _, terminated, truncated, _ = single.step(rng.uniform(-1.0, 1.0, 2).astype(np.float32))
            if terminated or truncated:
                single.reset()

    def run_vector(n: int) -> None:
        for _ in range(n):
            vector.step(rng.uniform(-1.0, 1.0, (batch, 2)).astype(np.float32))

    run_single(5)  # compile or load the kernels
    run_vector(2)
    _serve(run_single, run_vector, steps_one, steps_batch, batch)


def _sphere_worker(name: str, steps_one: int, steps_batch: int, batch: int) -> None:
    """:func:`_worker` of the sphere's compression (``--sphere``): the coarse sphere of ``tissue/sphere.yaml``
    between two plates as :func:`~.experiments.compression.run_compression` builds it, one tissue and ``batch``
    tissues, pressed 1 mm at 60 mm/min, then the top plate moving at 6 mm/min through the rounds."""
    config = importlib.import_module(name + ".physics.config")
    compression = importlib.import_module(name + ".experiments.compression")
    mesh_gen = importlib.import_module(name + ".physics.mesh_gen")
    simulation = importlib.import_module(name + ".physics.simulation")
    mesh = mesh_gen.sphere_mesh(0.05, "coarse")
    model = compression.compression_model(mesh, compression.load_tissue_params(config.builtin_config(
        "tissue/sphere.yaml")))
    z, mu = mesh.nodes[:, 2], compression.CompressionConfig().plate_mu
    plates = [simulation.Plate((0.0, 0.0, float(z.min())), (0.0, 0.0, 1.0), mu=mu),
              simulation.Plate((0.0, 0.0, float(z.max())), (0.0, 0.0, -1.0), mu=mu)]
    sims = [simulation.Simulation(model, n, dt=1e-3, plates=plates) for n in (1, batch)]
    for sim in sims:  # 1 mm at 60 mm/min (compiles or loads the kernels), then 6 mm/min
        sim.pl_vel[:, 1, 2] = -1e-3
        sim.step(1000)
        sim.pl_vel[:, 1, 2] = -1e-4
    _serve(sims[0].step, sims[1].step, steps_one, steps_batch, batch)


def allowed_cpus() -> list[int] | None:
    """The CPUs this process may run on, lowest first (None where the OS cannot pin a process)."""
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None


def interleaved(packages: list[str], rounds: int, steps_one: int = 40, steps_batch: int = 2,
                batch: int = 64, cpu: int | None = None) -> dict[str, dict[str, float]]:
    """Per package: ``one_*`` (one tissue, ``steps_one`` ms per call) and ``batch_*`` (per tissue of ``batch``,
    ``steps_batch`` ms per call) median, first quartile and minimum, us per simulated ms, over ``rounds``. Every
    worker is pinned to ``cpu`` (None: not pinned)."""
    if rounds < 4:
        raise ValueError(f"rounds must be >= 4 (quartiles), got {rounds}")
    workers = {}
    try:
        for name in packages:  # one after the other: compiling builds do not compete for the cores
            steps = f"{steps_one},{steps_batch},{batch}"
            argv = [sys.executable, "-m", __spec__.name, "--worker", name, "--steps", steps]
            if cpu is not None:
                argv += ["--cpu", str(cpu)]
            proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            workers[name] = proc
            if proc.stdout.readline().strip() != "ready":
                raise RuntimeError(f"build {name!r}: its worker failed before the first round (rc {proc.wait()})")
        times: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in packages}
        for _ in range(rounds):
            order = list(packages)
            random.shuffle(order)
            for name in order:
                proc = workers[name]
                proc.stdin.write("\n")
                proc.stdin.flush()
                one_us, batch_us = json.loads(proc.stdout.readline())
                times[name][0].append(one_us)
                times[name][1].append(batch_us)
    finally:
        for proc in workers.values():
            proc.stdin.close()
            proc.wait()
    out = {}
    for name, (a, b) in times.items():
        out[name] = {"one_median": statistics.median(a), "one_q1": statistics.quantiles(a)[0], "one_min": min(a),
                     "batch_median": statistics.median(b), "batch_q1": statistics.quantiles(b)[0],
                     "batch_min": min(b)}
    return out


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m msdgrasp.benchmarks.interleaved",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("packages", nargs="?", help="comma-separated package names on sys.path (msdgrasp: this build)")
    parser.add_argument("--rounds", type=int, default=200)
    parser.add_argument("--env", action="store_true",
                        help="time the envs instead of the physics: the single env (20 agent steps per round) and the "
                             "vector env of 64 (2 steps per round), us per agent step (per env)")
    parser.add_argument("--sphere", action="store_true",
                        help="time the paper's sphere compression instead (tissue/sphere.yaml: Maxwell branch and "
                             "spring dashpots): one tissue and a batch of two, 40 simulated ms per round each, us per "
                             "simulated ms (per tissue)")
    parser.add_argument("--batch-ms", type=int, default=None,
                        help="simulated ms per timed call of the batch (default 2; 33 is an agent step)")
    parser.add_argument("--cpu", type=int, default=None,
                        help="the CPU every build's worker runs on (default: the lowest this process may use)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)  # (a build's worker process)
    parser.add_argument("--steps", default="40,2,64", help=argparse.SUPPRESS)
    return parser


def _pinned_cpu(parser: argparse.ArgumentParser, cpu: int | None) -> int | None:
    """The CPU every worker runs on: ``cpu`` checked against the ones this process may use, else the lowest."""
    cpus = allowed_cpus()
    if cpus is None and cpu is not None:
        parser.error("--cpu: this OS cannot pin a process to a CPU; leave --cpu out")
    if cpus is not None and cpu is not None and cpu not in cpus:
        parser.error(f"--cpu must be one of the CPUs this process may use, {cpus}; got {cpu}")
    return cpu if cpu is not None else (cpus[0] if cpus else None)


def _builds(parser: argparse.ArgumentParser, packages: str | None) -> list[str]:
    """The builds named by ``packages``, each imported (before any worker compiles its kernels)."""
    if not packages:
        parser.error("packages: give one or more comma-separated package names")
    names = [p for p in packages.split(",") if p]
    if len(set(names)) != len(names):
        parser.error(f"packages must differ, got {packages!r}")
    for name in names:
        try:
            importlib.import_module(name + ".physics.simulation")
        except ImportError as exc:
            parser.error(f"package {name!r} cannot be imported: {exc}")
    return names


def _check_workload(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.env and args.sphere:
        parser.error("--env and --sphere: give one of them")
    if args.batch_ms is not None and (args.env or args.sphere):
        parser.error("--batch-ms times the physics' batch: not with --env or --sphere")
    if args.batch_ms is not None and args.batch_ms < 1:
        parser.error(f"--batch-ms must be >= 1, got {args.batch_ms}")


def _timed(args: argparse.Namespace, names: list[str], cpu: int | None) -> dict[str, dict[str, float]]:
    """:func:`interleaved` of the workload ``args`` asks for, by build name."""
    if args.sphere:
        results = interleaved([f"sphere:{n}" for n in names], args.rounds, steps_one=40, steps_batch=40, batch=2,
                              cpu=cpu)
        return {name[7:]: r for name, r in results.items()}
    if args.env:
        results = interleaved([f"env:{n}" for n in names], args.rounds, steps_one=20, steps_batch=2, cpu=cpu)
        return {name[4:]: r for name, r in results.items()}
    return interleaved(names, args.rounds, steps_batch=args.batch_ms or 2, cpu=cpu)


def _print_results(args: argparse.Namespace, cpu: int | None, results: dict[str, dict[str, float]]) -> None:
    print("every build's worker on CPU " + (str(cpu) if cpu is not None else "the OS chose (not pinned)"))
    if args.env:
        print(f"{'build':14s} single env us per agent step: median / q1 / min | vector env of 64, per env: "
              "median / q1 / min")
    elif args.sphere:
        print(f"{'build':14s} one sphere us/ms: median / q1 / min | per tissue of 2: median / q1 / min")
    else:
        print(f"{'build':14s} one tissue us/ms: median / q1 / min | per tissue of 64: median / q1 / min")
    for name, r in results.items():
        print(f"{name:14s} {r['one_median']:7.1f} {r['one_q1']:7.1f} {r['one_min']:7.1f} | "
              f"{r['batch_median']:6.1f} {r['batch_q1']:6.1f} {r['batch_min']:6.1f}")


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.worker:
        if args.cpu is not None:
            os.sched_setaffinity(0, {args.cpu})
        _worker(args.worker, *(int(s) for s in args.steps.split(",")))
        return 0
    cpu = _pinned_cpu(parser, args.cpu)
    names = _builds(parser, args.packages)
    _check_workload(parser, args)
    try:
        results = _timed(args, names, cpu)
    except ValueError as exc:
        parser.error(f"--{exc}")
    _print_results(args, cpu, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
