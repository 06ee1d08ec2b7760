"""What the benchmarks share: the timer (:func:`time_per_unit`), the grasp they time (:func:`grasped`, copied into a
batch by :func:`clone`), the rounding of their JSON (:func:`round_sig`) and the paths of their files
(:func:`out_paths`). One place, so that ``bench``, ``profile`` and ``interleaved`` time the same set-up the same way.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..physics.reference import DT_OUTER


def round_sig(x: float, nd: int = 3) -> float:
    """Round to ``nd`` significant digits (JSON readability); None, 0 and non-finite values pass as they are."""
    if x is None or not math.isfinite(x) or x == 0:
        return x
    return round(x, -int(math.floor(math.log10(abs(x)))) + nd - 1)


def time_per_unit(run: Callable[[int], Any], min_time: float, repeats: int = 3, max_units: int = 10**8) -> dict:
    """Seconds per unit of ``run(n)`` (which does n units), measured over >= ``min_time`` s in total.

    The caller does the warm-up. Each of ``repeats`` timed calls runs >= min_time / repeats s (the unit
    count is grown from a probe); the median and the best wall-clock time are reported, and the median
    process CPU time (``cpu_s``: on a shared machine it excludes the time the process was descheduled).
    """
    chunk = min_time / max(1, repeats)
    n = 1
    t0 = time.perf_counter()
    run(n)
    el = time.perf_counter() - t0
    while el < 0.2 * chunk and n < max_units:  # probe until the estimate is reliable
        n = min(max_units, n * 4)
        t0 = time.perf_counter()
        run(n)
        el = time.perf_counter() - t0
    per = el / n
    n = max(1, min(max_units, math.ceil(chunk / max(per, 1e-12))))
    samples = []
    cpu = []
    total = 0.0
    units = 0
    while len(samples) < repeats or total < min_time:
        c0 = time.process_time()
        t0 = time.perf_counter()
        run(n)
        el = time.perf_counter() - t0
        cpu.append((time.process_time() - c0) / n)
        samples.append(el / n)
        total += el
        units += n
        # a probe slowed by a busy machine sizes the calls too small: re-size them from the fastest one
        n = max(1, min(max_units, math.ceil(chunk / max(min(samples), 1e-12))))
        if len(samples) > 8 * repeats:
            break
    return {"median_s": statistics.median(samples), "best_s": min(samples), "cpu_s": statistics.median(cpu),
            "best_cpu_s": min(cpu),
            "units": units, "seconds": total}


def grasped(resolution: str | int, settle_s: float, close_s: float):
    """(scene, one-tissue Simulation) of the settled spleen with the jaws closed for ``close_s`` s and then
    holding: contact stays active while the caller times it."""
    from ..physics.scenario import spleen_scene

    scene = spleen_scene(resolution=resolution, settle_s=settle_s)
    sim = scene.simulation(1, dt=DT_OUTER)
    sim.command(closing_speed=scene.grasper.max_closing_speed_m_s)
    sim.step(int(round(close_s / DT_OUTER)))
    sim.command(closing_speed=0.0)
    sim.step(10)
    return scene, sim


#: the Simulation arrays that :func:`clone` copies: a tissue's state, settings, grasper and contact memory
CLONED_FIELDS = ("x", "v", "t", "fv", "dl_prev", "kscale", "mscale", "f_ext", "g_tip", "g_axis", "g_e1", "g_radius",
                 "g_vradius", "g_vpull", "g_rmin", "g_rmax", "mu_s", "mu_k", "contact_state", "contact_force")


def clone(src, dst) -> None:
    """Copy the first tissue of the Simulation ``src`` into every tissue of ``dst`` (same model and grasper)."""
    for name in CLONED_FIELDS:
        getattr(dst, name)[:] = getattr(src, name)[0]


def out_paths(out: str | Path) -> tuple[Path, Path, Path]:
    """(JSON, markdown, PNG) paths of a report written to ``out``: a ``.json`` file, or a folder (``bench.json``
    in it); the markdown and the plot sit next to the JSON."""
    out = Path(out)
    if out.suffix.lower() != ".json":
        out = out / "bench.json"
    return out, out.with_suffix(".md"), out.with_name(out.stem + "_scaling.png")
