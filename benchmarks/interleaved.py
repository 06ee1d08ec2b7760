"""Two or more builds of the physics timed in one process, alternating: an A/B that a busy machine cannot skew.

On a shared machine the speed of a core drifts by tens of percent over minutes, so two builds timed one after
the other differ by the drift. Here every build steps its own copy of the bench's grasp (coarse spleen, jaws
closed on it: :func:`.bench._grasped`, one tissue and a batch of 64), and each round times every build once, in
a random order, so drift falls on all of them alike. Reported per build: the median, first quartile and minimum
over the rounds, in us of compute per simulated ms.

Each build is a copy of the package under its own name on ``sys.path`` (numba caches each copy apart)::

    mkdir -p /tmp/ab/msd_base && git archive <rev> | tar -x -C /tmp/ab/msd_base
    mkdir -p /tmp/ab/msd_new && git archive HEAD | tar -x -C /tmp/ab/msd_new
    PYTHONPATH=/tmp/ab python -m msdgrasp.benchmarks.interleaved msd_base,msd_new --rounds 200

(the name ``msdgrasp`` is the installed build itself). The first call of each build compiles its kernels.
"""

from __future__ import annotations

import argparse
import importlib
import random
import statistics
import sys
import time


def interleaved(packages: list[str], rounds: int, steps_one: int = 40, steps_batch: int = 2,
                batch: int = 64) -> dict[str, dict[str, float]]:
    """Per package: ``one_*`` (one tissue, ``steps_one`` ms per call) and ``batch_*`` (per tissue of ``batch``,
    ``steps_batch`` ms per call) median, first quartile and minimum, us per simulated ms, over ``rounds``."""
    if rounds < 4:
        raise ValueError(f"rounds must be >= 4 (quartiles), got {rounds}")
    sims = {}
    for name in packages:
        bench = importlib.import_module(name + ".benchmarks.bench")
        simulation = importlib.import_module(name + ".physics.simulation")
        scene, one = bench._grasped("coarse", 2.0, 2.0)
        many = simulation.Simulation(scene.model, batch, dt=bench.DT_OUTER, grasper=scene.grasper)
        bench._clone(one, many)
        one.step(1)  # compile or load the kernels
        many.step(1)
        sims[name] = (one, many)
    times: dict[str, tuple[list[float], list[float]]] = {name: ([], []) for name in packages}
    for _ in range(rounds):
        order = list(packages)
        random.shuffle(order)
        for name in order:
            one, many = sims[name]
            t0 = time.perf_counter()
            one.step(steps_one)
            t1 = time.perf_counter()
            many.step(steps_batch)
            t2 = time.perf_counter()
            times[name][0].append((t1 - t0) / steps_one * 1e6)
            times[name][1].append((t2 - t1) / steps_batch / batch * 1e6)
    out = {}
    for name, (a, b) in times.items():
        out[name] = {"one_median": statistics.median(a), "one_q1": statistics.quantiles(a)[0], "one_min": min(a),
                     "batch_median": statistics.median(b), "batch_q1": statistics.quantiles(b)[0],
                     "batch_min": min(b)}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m msdgrasp.benchmarks.interleaved",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("packages", help="comma-separated package names on sys.path (msdgrasp: this build)")
    parser.add_argument("--rounds", type=int, default=200)
    args = parser.parse_args(argv)
    names = [p for p in args.packages.split(",") if p]
    for name in names:  # every package, before the first one compiles its kernels
        try:
            importlib.import_module(name + ".physics.simulation")
        except ImportError as exc:
            parser.error(f"package {name!r} cannot be imported: {exc}")
    try:
        results = interleaved(names, args.rounds)
    except ValueError as exc:
        parser.error(f"--{exc}")
    print(f"{'build':14s} one tissue us/ms: median / q1 / min | per tissue of 64: median / q1 / min")
    for name, r in results.items():
        print(f"{name:14s} {r['one_median']:7.1f} {r['one_q1']:7.1f} {r['one_min']:7.1f} | "
              f"{r['batch_median']:6.1f} {r['batch_q1']:6.1f} {r['batch_min']:6.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
