"""Speed benchmarks of the physics and the GraspLift envs (``msdgrasp bench physics|grasp|env|all``).

Everything is reported as JSON (printed; with ``--out`` also written, with a markdown table and a PNG of
the scaling curve next to it, all atomically).

physics
    Compute time per 1 ms of simulated time (``us_per_ms``, all substeps included; ``n_sub`` is reported)
    of the spleen at coarse/medium/fine (and xfine unless ``--quick``): one tissue and a batch of 16
    (total and per tissue), without contact (the spleen anchored at its hilum, sagging under gravity)
    and with contact (the grasp scene with the jaws closed onto the inferior pole for ~2 s first, then
    held, so contact is active while timing). Timed with ``time.perf_counter`` over >= 0.5 s per
    measurement (``--quick``: 0.1 s) after a warm-up call, so numba compilation is excluded. Also: the
    fitted log-log exponent of cost vs node count; a plain NumPy implementation of the same MSD step
    (:class:`~msdgrasp.physics.reference.NumpyMSD`, the reference) with its speed and a force/state cross-check
    against the numba kernel; and MuJoCo's flex soft body on the same tet mesh at 1 kHz when ``mujoco`` is importable.
grasp
    Only the with-contact part of ``physics``.
env
    Agent steps per second of :class:`~msdgrasp.envs.grasp_lift.GraspLiftEnv` and of
    :class:`~msdgrasp.envs.grasp_lift.GraspLiftVectorEnv` with N = 1, 16, 64 (per env and in total),
    random actions from a fixed seed, coarse spleen.

``targets`` holds pass/fail flags against the bench's targets (benchmarks/report.py: TARGETS; coarse
<= 10 us per simulated ms, fine <= 200 us per ms, contact overhead <= 50 % and coarse-with-contact >= 70x
real time, env >= 1000 steps/s single and >= 2000 aggregate batched). Machines are noisy: the flags
describe this run on the machine it ran on.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..physics.contact import J_CONTACT
from ..physics.reference import DT_OUTER, NumpyMSD, cross_check, spleen_model
from .harness import clone, grasped, out_paths, round_sig, time_per_unit
from .report import BATCH, ENV_SIZES, evaluate_targets, machine_info, markdown, plot_gpu, plot_scaling

# ------------------------------------------------------------------------------------------------
# physics benchmarks
# ------------------------------------------------------------------------------------------------


def _sim_time(sim, min_time: float, repeats: int) -> dict:
    sim.step(1)  # warm-up (compilation, or loading the numba cache)
    return time_per_unit(sim.step, min_time, repeats)


def bench_no_contact(resolution, min_time: float, repeats: int, batch: int = BATCH) -> dict:
    from ..physics.simulation import Simulation

    model = spleen_model(resolution)
    t0 = time.perf_counter()
    sim1 = Simulation(model, 1, dt=DT_OUTER)
    setup = time.perf_counter() - t0
    single = _sim_time(sim1, min_time, repeats)
    simb = Simulation(model, batch, dt=DT_OUTER)
    batched = _sim_time(simb, min_time, repeats)
    us1 = single["median_s"] * 1e6
    usb = batched["median_s"] * 1e6
    return {
        "resolution": resolution,
        "nodes": model.n_nodes,
        "springs": int(len(model.edges)),
        "n_sub": sim1.n_sub,
        "single_us_per_ms": round_sig(us1),
        "single_best_us_per_ms": round_sig(single["best_s"] * 1e6),
        "single_cpu_us_per_ms": round_sig(single["cpu_s"] * 1e6),
        "single_us_per_substep": round_sig(us1 / sim1.n_sub),
        # whole substep (springs, tets, nodes) per spring: comparable across mesh sizes
        "single_ns_per_spring_substep": round_sig(us1 / sim1.n_sub / len(model.edges) * 1e3),
        f"batch{batch}_ns_per_spring_substep": round_sig(usb / batch / simb.n_sub / len(model.edges) * 1e3),
        "single_realtime_factor": round_sig(1000.0 / us1),
        f"batch{batch}_total_us_per_ms": round_sig(usb),
        f"batch{batch}_per_tissue_us_per_ms": round_sig(usb / batch),
        f"batch{batch}_realtime_factor_per_tissue": round_sig(1000.0 * batch / usb),
        "finite": bool(sim1.finite().all() and simb.finite().all()),
        "simulated_s_timed": round_sig(single["units"] * DT_OUTER + batched["units"] * DT_OUTER),
        "setup_s": round_sig(setup),
    }


def bench_contact(resolution, min_time: float, repeats: int, settle_s: float, close_s: float,
                  batch: int = BATCH) -> dict:
    from ..physics.simulation import Simulation

    t0 = time.perf_counter()
    scene, sim1 = grasped(resolution, settle_s, close_s)
    setup = time.perf_counter() - t0
    contacts_before = int(sim1.jaw_contact_counts[0, :, 0].sum())
    single = _sim_time(sim1, min_time, repeats)
    contacts_single = int(sim1.jaw_contact_counts[0, :, 0].sum())
    simb = Simulation(scene.model, batch, dt=DT_OUTER, grasper=scene.grasper)
    clone(sim1, simb)
    float32 = bench_float32(scene, sim1, min_time, repeats, batch) if resolution == "coarse" else None
    batched = _sim_time(simb, min_time, repeats)
    us1 = single["median_s"] * 1e6
    usb = batched["median_s"] * 1e6
    return {
        "resolution": resolution,
        "nodes": scene.model.n_nodes,
        "surface_nodes": int(len(scene.mesh.surface_nodes)),
        "n_sub": sim1.n_sub,
        "contact_nodes": contacts_before,
        "contact_nodes_after_timing": contacts_single,
        f"contact_nodes_batch{batch}_mean": round_sig(float(simb.jaw_contact_counts[:, :, 0].sum(axis=1).mean())),
        "pinch_force_N": round_sig(float(sim1.pinch_force[0])),
        "single_us_per_ms": round_sig(us1),
        "single_best_us_per_ms": round_sig(single["best_s"] * 1e6),
        "single_cpu_us_per_ms": round_sig(single["cpu_s"] * 1e6),
        "single_realtime_factor": round_sig(1000.0 / us1),
        f"batch{batch}_total_us_per_ms": round_sig(usb),
        f"batch{batch}_per_tissue_us_per_ms": round_sig(usb / batch),
        f"batch{batch}_realtime_factor_per_tissue": round_sig(1000.0 * batch / usb),
        "finite": bool(sim1.finite().all() and simb.finite().all()),
        "float32": float32,
        "settle_s": settle_s,
        "close_s": close_s,
        "setup_s": round_sig(setup),
    }


#: simulated time over which ``bench_float32`` compares float32 with float64 from the same grasp, ms
FLOAT32_COMPARE_MS = 200


def bench_float32(scene, held, min_time: float, repeats: int, batch: int = BATCH) -> dict:
    """``Simulation(precision="float32")`` on the grasp ``held`` holds: us per simulated ms for one tissue and per
    tissue of a batch (timed from clones of the grasp), and its error against float64 from the same state over
    :data:`FLOAT32_COMPARE_MS` ms of the hold: the largest position difference (m), the pinch's relative difference,
    and the share of nodes in the same contact state (free / stick / slip)."""
    from ..physics.simulation import Simulation

    def copy_of(b: int, precision: str) -> Simulation:
        sim = Simulation(scene.model, b, dt=DT_OUTER, grasper=scene.grasper, precision=precision)
        clone(held, sim)
        return sim

    one, many = copy_of(1, "float32"), copy_of(batch, "float32")
    single, batched = _sim_time(one, min_time, repeats), _sim_time(many, min_time, repeats)
    a, b = copy_of(1, "float64"), copy_of(1, "float32")
    a.step(FLOAT32_COMPARE_MS)
    b.step(FLOAT32_COMPARE_MS)
    return {"single_us_per_ms": round_sig(single["median_s"] * 1e6),
            f"batch{batch}_per_tissue_us_per_ms": round_sig(batched["median_s"] * 1e6 / batch),
            "compare_ms": FLOAT32_COMPARE_MS,
            "max_position_error_m": float(f"{np.abs(b.x - a.x).max():.3g}"),
            "pinch_rel_error": float(f"{abs(b.pinch_force[0] / a.pinch_force[0] - 1.0):.3g}"),
            "same_contact_state": round_sig(float(np.mean(a.contact_state == b.contact_state)))}


def bench_numpy(resolution, min_time: float, repeats: int, numba_us_per_ms: float | None) -> dict:
    from ..physics.simulation import Simulation

    model = spleen_model(resolution)
    n_sub = Simulation(model, 1, dt=DT_OUTER).n_sub
    ref = NumpyMSD(model, n_sub)
    ref.step(1)
    t = time_per_unit(ref.step, min_time, repeats)
    us = t["median_s"] * 1e6
    return {
        "resolution": resolution,
        "nodes": model.n_nodes,
        "n_sub": n_sub,
        "numpy_us_per_ms": round_sig(us),
        "numpy_cpu_us_per_ms": round_sig(t["cpu_s"] * 1e6),
        "numba_us_per_ms": numba_us_per_ms,
        "ratio_ours_over_numpy": round_sig(numba_us_per_ms / us) if numba_us_per_ms else None,
        "speedup_vs_numpy": round_sig(us / numba_us_per_ms) if numba_us_per_ms else None,
    }


def mujoco_flex_xml(model, timestep: float = DT_OUTER, poisson: float = 0.3) -> str:
    """MJCF of a MuJoCo flex soft body on ``model``'s tet mesh: same nodes, tets, mass, E, anchors, gravity."""
    mesh = model.mesh
    p = model.params
    pts = " ".join(f"{c:.9g}" for c in mesh.nodes.ravel())
    elem = " ".join(str(int(i)) for i in mesh.tets.ravel())
    pins = " ".join(str(int(i)) for i in np.flatnonzero(model.fixed))
    g = " ".join(f"{c:g}" for c in model.gravity)
    pin = f'<pin id="{pins}"/>' if pins else ""
    # mass-proportional nodal damping ~ the MSD's b0 = damping_rate * m (MuJoCo: joint damping per dof)
    damping = (p.damping_rate_per_s * model.total_mass / model.n_nodes if p.stiffness_mode == "modulus"
               else p.b0_n_s_per_m)
    return f"""<mujoco model="spleen_flex">
  <option timestep="{timestep:g}" gravity="{g}"/>
  <worldbody>
    <flexcomp name="spleen" type="direct" dim="3" point="{pts}" element="{elem}" mass="{model.total_mass:.9g}"
              radius="0.0005">
      <edge equality="false" damping="{damping:.6g}"/>
      <elasticity young="{p.youngs_modulus_pa:g}" poisson="{poisson:g}" damping="0"/>
      <contact selfcollide="none" contype="0" conaffinity="0"/>
      {pin}
    </flexcomp>
  </worldbody>
</mujoco>"""


def bench_mujoco(resolutions, min_time: float, repeats: int, ours: dict, ours_batched: dict | None = None) -> dict:
    try:
        import mujoco
    except Exception as exc:  # ImportError, or a broken install (missing GL libraries, ...)
        return {"available": False, "reason": f"import mujoco failed: {type(exc).__name__}: {exc} "
                                              f"(optional: pip install 'msdgrasp[bench]')"}
    # MuJoCo's warnings (compiler notes, instabilities) go into the report, not into MUJOCO_LOG.TXT in the cwd
    warnings: list[str] = []
    previous = mujoco.get_mju_user_warning() if hasattr(mujoco, "get_mju_user_warning") else None
    if hasattr(mujoco, "set_mju_user_warning"):
        mujoco.set_mju_user_warning(lambda msg: warnings.append(str(msg).strip()))
    try:
        rows = _mujoco_rows(mujoco, resolutions, min_time, repeats, ours, ours_batched)
    finally:
        if hasattr(mujoco, "set_mju_user_warning"):
            mujoco.set_mju_user_warning(previous)
    return {
        "available": True,
        "version": mujoco.__version__,
        "model": "flexcomp type=direct dim=3 on the same tet mesh (linear elasticity, E and mass of the spleen, "
                 "hilum pinned, no contact), default integrator, 1 kHz, single thread",
        "rows": rows,
        "warnings": sorted(set(warnings))[:10],
    }


def _mujoco_rows(mujoco, resolutions, min_time: float, repeats: int, ours: dict,
                 ours_batched: dict | None = None) -> list[dict]:
    rows = []
    for res in resolutions:
        model = spleen_model(res)
        try:
            mj = mujoco.MjModel.from_xml_string(mujoco_flex_xml(model))
            data = mujoco.MjData(mj)
        except Exception as exc:
            rows.append({"resolution": res, "error": f"{type(exc).__name__}: {exc}"})
            continue

        def run(n: int, mj=mj, data=data) -> None:
            for _ in range(n):
                mujoco.mj_step(mj, data)

        run(1)
        t = time_per_unit(run, min_time, repeats)
        us = t["median_s"] * 1e6
        ours_us = ours.get(res)
        ours_batch = (ours_batched or {}).get(res)
        vert = data.flexvert_xpos if hasattr(data, "flexvert_xpos") else None
        sag = (float(np.max(np.abs(vert - model.rest_positions)))
               if vert is not None and vert.shape == model.rest_positions.shape else None)
        rows.append({
            "resolution": res,
            "nodes": int(mj.flex_vertnum[0]),
            "elements": int(mj.nflexelem),
            "dofs": int(mj.nv),
            "timestep_s": float(mj.opt.timestep),
            "mujoco_us_per_ms": round_sig(us),
            "mujoco_cpu_us_per_ms": round_sig(t["cpu_s"] * 1e6),
            "ours_us_per_ms": ours_us,
            "ratio_ours_over_mujoco": round_sig(ours_us / us) if ours_us else None,
            "speedup_vs_mujoco": round_sig(us / ours_us) if ours_us else None,
            f"ours_batch{BATCH}_per_tissue_us_per_ms": ours_batch,
            "speedup_batch_per_tissue": round_sig(us / ours_batch) if ours_batch else None,
            "finite": bool(np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))),
            "simulated_s": round_sig(float(data.time)),
            "max_displacement_m": round_sig(sag) if sag is not None else None,
        })
    return rows


def fit_exponent(nodes, cost) -> float | None:
    """Slope of log(cost) vs log(nodes) (least squares); None with fewer than two points."""
    pts = [(n, c) for n, c in zip(nodes, cost) if n and c and c > 0]
    if len(pts) < 2:
        return None
    n, c = np.log(np.array(pts, dtype=float)).T
    return float(np.polyfit(n, c, 1)[0])


def bench_physics(quick: bool, include_contact: bool = True, include_no_contact: bool = True,
                  progress: Callable[[str], None] = lambda s: None) -> dict:
    resolutions = ["coarse", "medium", "fine"] + ([] if quick else ["xfine"])
    min_time = 0.1 if quick else 0.5
    repeats = 1 if quick else 3
    settle_s, close_s = (0.5, 1.0) if quick else (2.0, 2.0)
    from ..physics.integrator import LANE_BLOCK, LANE_MIN

    out: dict[str, Any] = {"min_time_per_measurement_s": min_time, "dt_outer_s": DT_OUTER, "batch": BATCH,
                           "lane_min": LANE_MIN, "lane_block": LANE_BLOCK}
    if include_no_contact:
        rows = []
        for res in resolutions:
            progress(f"physics without contact: {res}")
            rows.append(bench_no_contact(res, min_time, repeats))
        out["no_contact"] = rows
        nodes = [r["nodes"] for r in rows]
        out["scaling"] = {
            "exponent_us_per_ms_vs_nodes": round_sig(fit_exponent(nodes, [r["single_us_per_ms"] for r in rows])),
            "exponent_us_per_substep_vs_nodes": round_sig(
                fit_exponent(nodes, [r["single_us_per_substep"] for r in rows])),
            "exponent_batch_per_tissue_vs_nodes": round_sig(
                fit_exponent(nodes, [r[f"batch{BATCH}_per_tissue_us_per_ms"] for r in rows])),
            "n_sub_by_resolution": {r["resolution"]: r["n_sub"] for r in rows},
        }
    if include_contact:
        rows = []
        for res in resolutions:
            progress(f"physics with contact: {res}")
            rows.append(bench_contact(res, min_time, repeats, settle_s, close_s))
        if include_no_contact:
            base = {r["resolution"]: r for r in out["no_contact"]}
            for r in rows:
                b = base[r["resolution"]]
                r["overhead_single"] = round_sig(r["single_us_per_ms"] / b["single_us_per_ms"] - 1.0)
                r[f"overhead_batch{BATCH}"] = round_sig(r[f"batch{BATCH}_total_us_per_ms"]
                                                 / b[f"batch{BATCH}_total_us_per_ms"] - 1.0)
        out["contact"] = rows
        if "scaling" in out:
            out["scaling"]["exponent_contact_us_per_ms_vs_nodes"] = round_sig(
                fit_exponent([r["nodes"] for r in rows], [r["single_us_per_ms"] for r in rows]))
    if include_no_contact:
        ours = {r["resolution"]: r["single_us_per_ms"] for r in out["no_contact"]}
        progress("NumPy reference")
        out["numpy_reference"] = {
            "cross_check": cross_check("coarse"),
            "rows": [bench_numpy(res, min_time, repeats, ours.get(res)) for res in ("coarse", "medium")],
        }
        progress("MuJoCo flex")
        batched = {r["resolution"]: r[f"batch{BATCH}_per_tissue_us_per_ms"] for r in out["no_contact"]}
        out["mujoco"] = bench_mujoco(["coarse"] if quick else ["coarse", "medium"], min_time, repeats, ours, batched)
    return out


# ------------------------------------------------------------------------------------------------
# env benchmarks
# ------------------------------------------------------------------------------------------------


def bench_env(quick: bool, seed: int = 0, progress: Callable[[str], None] = lambda s: None) -> dict:
    from ..envs.grasp_lift import GraspLiftEnv, GraspLiftVectorEnv

    min_time = 0.2 if quick else 1.0
    repeats = 1 if quick else 3
    progress("env: single")
    env = GraspLiftEnv()
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    episodes = [0]

    def run_single(n: int) -> None:
        for _ in range(n):
            _, _, term, trunc, _ = env.step(rng.uniform(-1.0, 1.0, 2).astype(np.float32))
            if term or trunc:
                episodes[0] += 1
                env.reset()

    run_single(5)
    t = time_per_unit(run_single, min_time, repeats)
    single = {
        "steps_per_s": round_sig(1.0 / t["median_s"]),
        "us_per_step": round_sig(t["median_s"] * 1e6),
        "cpu_steps_per_s": round_sig(1.0 / t["cpu_s"]) if t["cpu_s"] > 0 else None,
        "physics_ms_per_step": env.config.physics_steps_per_action,
        "n_sub": env.core.sim.n_sub,
        "nodes": env.core.sim.model.n_nodes,
        "steps_timed": t["units"],
        "episodes_finished": episodes[0],
    }
    env.close()
    vec = []
    for n_envs in ENV_SIZES[:-1] if quick else ENV_SIZES:
        progress(f"env: vector N={n_envs}")
        venv = GraspLiftVectorEnv(n_envs)
        venv.reset(seed=seed)
        rng = np.random.default_rng(seed)

        def run_vec(n: int, venv=venv, rng=rng, n_envs=n_envs) -> None:
            for _ in range(n):
                venv.step(rng.uniform(-1.0, 1.0, (n_envs, 2)).astype(np.float32))

        run_vec(2)
        t = time_per_unit(run_vec, min_time, repeats)
        vec.append({
            "n_envs": n_envs,
            "vector_steps_per_s": round_sig(1.0 / t["median_s"]),
            "total_steps_per_s": round_sig(n_envs / t["median_s"]),
            "per_env_steps_per_s": round_sig(1.0 / t["median_s"]),
            "us_per_env_step": round_sig(t["median_s"] * 1e6 / n_envs),
            "cpu_total_steps_per_s": round_sig(n_envs / t["cpu_s"]) if t["cpu_s"] > 0 else None,
        })
        venv.close()
    return {"min_time_per_measurement_s": min_time, "seed": seed, "resolution": "coarse", "single": single,
            "vector": vec}


# ------------------------------------------------------------------------------------------------
# GPU: agent steps/s of a device-resident batch vs batch size, with and without contact
# ------------------------------------------------------------------------------------------------

#: batch sizes of the GPU rows (quick: the first two)
GPU_BATCHES = (1, 64, 1024, 4096, 16384)
STEPS_PER_AGENT_STEP = 33  # 1 ms physics steps per 30 Hz agent step
#: the task rows' action: a 2.5 N pinch set-point, no pull (the jaws close and hold)
PINCH_ONLY_ACTION = (0.0, -1.0)


def _rate_row(batch: int, timing: dict, **fields: Any) -> dict:
    """A throughput row: ``batch`` agent steps per timed unit (:func:`time_per_unit`'s median) and ``fields``."""
    return {"batch": batch, **fields, "agent_steps_per_s": round_sig(batch / timing["median_s"]),
            "ms_per_agent_step": round_sig(timing["median_s"] * 1e3)}


def _warmup_steps(config, warmup_s: float) -> int:
    """Agent steps of a task row's warm-up (compile, close the jaws): at least one."""
    return max(1, int(round(warmup_s / config.agent_dt_s)))


def gpu_unavailable_reason() -> str | None:
    """Why GPU rows cannot be measured here (None: they can)."""
    from numba import config as numba_config

    if numba_config.ENABLE_CUDASIM:
        return "NUMBA_ENABLE_CUDASIM=1: numba's CUDA simulator runs on the CPU, its timings mean nothing"
    try:
        from numba import cuda

        if not cuda.is_available():
            return "no CUDA GPU or driver found (numba.cuda.is_available() is False)"
    except ImportError as exc:  # pragma: no cover - numba without its CUDA target
        return f"numba's CUDA target is unavailable ({exc})"
    return None


def bench_gpu(quick: bool, resolution="coarse", batches: tuple[int, ...] = GPU_BATCHES, settle_s: float = 2.0,
              close_s: float = 1.5, steps: int = STEPS_PER_AGENT_STEP, min_time: float | None = None,
              force: bool = False, task_warmup_s: float = 0.5, threads: int | None = None,
              precisions: tuple[str, ...] = ("float64", "float32")) -> dict:
    """Agent steps/s (``steps`` physics ms each) of a :class:`~..physics.cuda_step.CudaBatch` per batch size,
    jaws closed on the tissue (contact) and open (none), in each of ``precisions``. Without a GPU: the reason,
    no numbers (``force=True`` runs the harness anyway, e.g. in the simulator for tests; its numbers are not
    timings)."""
    reason = gpu_unavailable_reason()
    if reason is not None and not force:
        return {"available": False, "reason": reason, "rows": []}
    from numba import cuda

    from ..physics.cuda_step import THREADS_PER_BLOCK, CudaBatch
    from ..physics.simulation import Simulation

    batches = tuple(batches[:2]) if quick else tuple(batches)
    min_time = min_time if min_time is not None else (0.5 if quick else 2.0)
    scene, sim1 = grasped(resolution, settle_s, close_s)
    rows = []
    for precision in precisions:
        for contact in (True, False):
            for batch in batches:
                sim = Simulation(scene.model, batch, dt=DT_OUTER, grasper=scene.grasper)
                if contact:
                    clone(sim1, sim)  # every tissue grasped: the contact pass runs on every step
                else:
                    scene.reset(sim)  # settled tissue, jaws open at the start radius: no contact
                dev = CudaBatch(sim.kernel_model(), sim.kernel_state(), sim.kernel_readout(),
                                threads=threads or THREADS_PER_BLOCK, precision=precision)

                def run(n: int) -> None:
                    for _ in range(n):
                        dev.step(steps)
                    cuda.synchronize()

                run(1)  # compile / load
                timing = time_per_unit(run, min_time, repeats=3, max_units=10_000)
                dev.download(out=sim.kernel_readout(), fields=("jaw_out",))
                contact_nodes = float(sim.jaw_out[:, :, J_CONTACT].sum(axis=1).mean())
                rows.append(_rate_row(batch, timing, contact=contact, dtype=precision, n_sub=sim.n_sub,
                                      contact_nodes_mean=round_sig(contact_nodes)))
    task_rows = bench_gpu_task(batches, resolution, steps, min_time, task_warmup_s, threads, precisions)
    return {"available": reason is None, "reason": reason, "resolution": resolution,
            "nodes": scene.model.n_nodes, "steps_per_agent_step": steps, "rows": rows, "task_rows": task_rows}


def bench_gpu_task(batches: tuple[int, ...], resolution="coarse", steps: int = STEPS_PER_AGENT_STEP,
                   min_time: float = 2.0, warmup_s: float = 0.5, threads: int | None = None,
                   precisions: tuple[str, ...] = ("float64",)) -> list[dict]:
    """Agent steps/s of the whole GPU task step (:class:`~..envs.cuda_core.CudaGraspLiftCore`: commands, physics,
    observation, reward, flags, autoreset; actions already on the device) per precision and batch size: the
    jaws pinch at 2.5 N without a pull, so after ``warmup_s`` nearly every env holds the tissue
    (``contact_fraction``: the share of envs with contact over 10 steps after the timing)."""
    from numba import cuda

    from ..envs.core import GraspLiftConfig
    from ..envs.cuda_core import CudaGraspLiftCore
    from ..physics.cuda_step import THREADS_PER_BLOCK

    config = GraspLiftConfig(resolution=resolution, physics_steps_per_action=steps)
    rows = []
    for precision in precisions:
        for batch in batches:
            core = CudaGraspLiftCore(config, batch, seed=0, threads=threads or THREADS_PER_BLOCK, precision=precision)
            core.reset()
            actions = cuda.to_device(np.tile(PINCH_ONLY_ACTION, (batch, 1)))

            def run(n: int) -> None:
                for _ in range(n):
                    core.step(actions)
                cuda.synchronize()

            run(_warmup_steps(config, warmup_s))
            timing = time_per_unit(run, min_time, repeats=3, max_units=10_000)
            held = []
            for _ in range(10):
                core.step(actions)
                held.append(float(np.mean(core.download("contact")["contact"] > 0)))
            rows.append(_rate_row(batch, timing, contact=True, dtype=precision, what="task",
                                  contact_fraction=round_sig(float(np.mean(held)))))
    return rows


#: batch sizes of the CPU reference rows (quick: the first two); one core steps a batch in time linear in its size
CPU_REFERENCE_BATCHES = (1, 64, 1024)


def bench_cpu_reference(quick: bool, resolution="coarse", batches: tuple[int, ...] = CPU_REFERENCE_BATCHES,
                        settle_s: float = 2.0, close_s: float = 1.5, steps: int = STEPS_PER_AGENT_STEP,
                        min_time: float | None = None, task_warmup_s: float = 0.5) -> dict:
    """The CPU side of the GPU rows, measured the same way on the same machine: agent steps/s (``steps`` physics
    ms each) of the numba kernel on one core for the same grasped tissues (``rows``), and of the CPU task step
    (:class:`~..envs.core.GraspLiftCore`, the bench's 2.5 N pinch without a pull: ``task_rows``)."""
    from ..envs.core import GraspLiftConfig, GraspLiftCore
    from ..physics.simulation import Simulation

    batches = tuple(batches[:2]) if quick else tuple(batches)
    min_time = min_time if min_time is not None else (0.5 if quick else 2.0)
    scene, sim1 = grasped(resolution, settle_s, close_s)
    rows = []
    for batch in batches:
        sim = Simulation(scene.model, batch, dt=DT_OUTER, grasper=scene.grasper)
        clone(sim1, sim)  # every tissue grasped, as the GPU rows with contact
        sim.step(1)  # compile / load the numba cache
        timing = time_per_unit(lambda n, sim=sim: sim.step(n * steps), min_time, repeats=3, max_units=10_000)
        rows.append(_rate_row(batch, timing, contact=True, dtype="float64", n_sub=sim.n_sub,
                              contact_nodes_mean=round_sig(float(sim.jaw_out[:, :, J_CONTACT].sum(axis=1).mean()))))
    config = GraspLiftConfig(resolution=resolution, physics_steps_per_action=steps)
    task_rows = []
    for batch in batches:
        core = GraspLiftCore(config, batch)
        for i in range(batch):
            core.seed(i, i)
            core.reset(i)
        actions = np.tile(PINCH_ONLY_ACTION, (batch, 1))

        def run(n: int, core=core, actions=actions) -> None:
            for _ in range(n):
                core.step(actions)

        run(_warmup_steps(config, task_warmup_s))
        timing = time_per_unit(run, min_time, repeats=3, max_units=10_000)
        held = [float(np.mean(core.step(actions)[4]["contact_nodes"] > 0)) for _ in range(10)]
        task_rows.append(_rate_row(batch, timing, contact=True, dtype="float64", what="task",
                                   contact_fraction=round_sig(float(np.mean(held)))))
    return {"device": "one CPU core (numba)", "resolution": resolution, "nodes": scene.model.n_nodes,
            "steps_per_agent_step": steps, "rows": rows, "task_rows": task_rows}


def precision_actions(num_envs: int, step: int, steps_per_s: float) -> np.ndarray:
    """The scripted grasp of :func:`bench_precision`: env b pinches at its own set-point (action 0 spread over
    -0.4..0.6, 0.9-3.1 N) from the start and pulls forward at half speed after 0.3 s."""
    pinch = np.linspace(-0.4, 0.6, num_envs) if num_envs > 1 else np.array([0.2])
    pull = 0.0 if step >= 0.3 * steps_per_s else -1.0
    return np.stack([pinch, np.full(num_envs, pull)], axis=1)


def bench_precision(config=None, num_envs: int = 256, seed: int = 0, threads: int | None = None,
                    jaws_in_m: float = 0.0) -> dict:
    """The float32 option's error: the GPU task in float32 against float64, same seed (same friction, scales
    and poses), same scripted grasp-and-pull (:func:`precision_actions`) for one episode length.

    Per agent step, while both precisions are in the same episode: the largest position difference (m),
    the share of surface nodes in the same contact state (free / stick / slip), the largest reward and
    observation differences and the largest relative pinch difference; at the ends: how many envs ended on a
    different step or with a different outcome (success, lost grasp, slip, time limit). On a GPU these are
    the GPU's numbers; in numba's simulator (an error is no timing: it runs there too) NumPy's promotion rules
    apply, which keep more of the arithmetic in float32 than numba's compiled typing does. ``jaws_in_m``: the jaws
    start this much closer than the task's start radius (contact within a short episode)."""
    from numba import config as numba_config

    reason = gpu_unavailable_reason()
    if reason is not None and not numba_config.ENABLE_CUDASIM:
        return {"available": False, "reason": reason}
    from ..envs.core import GraspLiftConfig
    from ..envs.cuda_core import CudaGraspLiftCore
    from ..physics.cuda_step import THREADS_PER_BLOCK

    config = config or GraspLiftConfig()
    cores = [CudaGraspLiftCore(config, num_envs, seed=seed, threads=threads or THREADS_PER_BLOCK, precision=p)
             for p in ("float64", "float32")]
    for core in cores:
        core.reset()
        radius = core.arrays()["g_radius"]
        radius.copy_to_device(radius.copy_to_host() - jaws_in_m)
    fields = ("x", "contact_state", "reward", "obs", "pinch", "done", "is_success", "lost_grasp", "slipped",
              "truncated")
    surf = cores[0].host.sim.surface_nodes
    live = np.ones(num_envs, dtype=bool)  # both precisions still in the first episode, on the same step
    worst = {"position_m": 0.0, "reward": 0.0, "obs": 0.0, "pinch_rel": 0.0}
    same_contact, total_contact, in_contact = 0, 0, 0
    ended_apart = np.zeros(num_envs, dtype=bool)
    outcome_apart = np.zeros(num_envs, dtype=bool)
    t0 = time.perf_counter()
    steps_per_s = 1.0 / config.agent_dt_s
    for k in range(config.max_episode_steps):
        actions = precision_actions(num_envs, k, steps_per_s)
        for core in cores:
            core.step(actions)
        a, b = (core.download(*fields) for core in cores)
        m = live
        if m.any():
            worst["position_m"] = max(worst["position_m"], float(np.abs(a["x"][m] - b["x"][m]).max()))
            worst["reward"] = max(worst["reward"], float(np.abs(a["reward"][m] - b["reward"][m]).max()))
            worst["obs"] = max(worst["obs"], float(np.abs(a["obs"][m] - b["obs"][m]).max()))
            rel = np.abs(a["pinch"][m] - b["pinch"][m]) / np.maximum(np.abs(a["pinch"][m]), 0.1)
            worst["pinch_rel"] = max(worst["pinch_rel"], float(rel.max()))
            same_contact += int((a["contact_state"][m][:, surf] == b["contact_state"][m][:, surf]).sum())
            total_contact += int(m.sum()) * surf.size
            in_contact += int((a["contact_state"][m][:, surf] > 0).any(axis=1).sum())
        for name in ("is_success", "lost_grasp", "slipped", "truncated"):
            outcome_apart |= live & a["done"] & b["done"] & (a[name] != b[name])
        ended_apart |= live & (a["done"] != b["done"])
        live = live & ~a["done"] & ~b["done"]
    return {"available": reason is None, "reason": reason, "resolution": config.resolution, "num_envs": num_envs,
            "agent_steps": config.max_episode_steps, "seed": seed,
            "max_position_diff_m": worst["position_m"], "max_reward_diff": worst["reward"],
            "max_obs_diff": worst["obs"], "max_pinch_rel_diff": worst["pinch_rel"],
            "contact_state_agreement": same_contact / max(total_contact, 1), "env_steps_in_contact": in_contact,
            "envs_ended_on_another_step": int(ended_apart.sum()), "envs_with_another_outcome": int(outcome_apart.sum()),
            "wall_s": round_sig(time.perf_counter() - t0)}


def bench_learners(config=None, batch: int = 4096, iterations: int = 3, steps_per_env: int = 32,
                   threads: int | None = None, force: bool = False) -> dict:
    """Does SB3 keep up with the GPU task? Agent steps/s on the same GPU task (``batch`` envs) of: the env
    alone (actions already on the device), rsl-rl's PPO (torch-native: zero-copy observations) and SB3's PPO
    through :class:`~msdgrasp.envs.sb3.CudaSB3VecEnv` (NumPy: a host round trip and an info dict per env
    each step). Both learners: ``iterations`` x ``steps_per_env`` x ``batch`` steps, 64x64 networks, 5 epochs
    of 4 minibatches, on the GPU where torch has one. The env is timed first, so that no learner pays the
    kernels' compilation. Without a GPU: the reason (``force``: the harness runs anyway, e.g. in the simulator
    for tests; its numbers are not timings)."""
    import tempfile

    reason = gpu_unavailable_reason()
    if reason is not None and not force:
        return {"available": False, "reason": reason}
    from numba import cuda

    from ..agents.torch_ppo import TorchPPOConfig, train_torch
    from ..envs.cuda_core import CudaGraspLiftCore
    from ..envs.sb3 import CudaSB3VecEnv
    from ..physics.config import needs_extra, replace
    from ..physics.cuda_step import THREADS_PER_BLOCK

    with needs_extra("train", "the learners benchmark"):
        import torch
        from stable_baselines3 import PPO

    config = config or TorchPPOConfig().env  # (the task rsl_ppo.yaml trains on: its critic reads privileged obs)
    threads = threads or THREADS_PER_BLOCK
    steps = iterations * steps_per_env * batch
    core = CudaGraspLiftCore(config, batch, seed=0, threads=threads)
    core.reset()
    actions = cuda.to_device(np.tile([0.0, 0.0], (batch, 1)))
    core.step(actions)  # compile
    cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(iterations * steps_per_env):
        core.step(actions)
    cuda.synchronize()
    env_s = time.perf_counter() - t0
    rsl_config = replace(TorchPPOConfig(), num_envs=batch, iterations=iterations, steps_per_env=steps_per_env,
                         validation_episodes=0, env=config)
    with tempfile.TemporaryDirectory() as tmp:
        rsl = train_torch(rsl_config, tmp, progress=False)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    venv = CudaSB3VecEnv(CudaGraspLiftCore(config, batch, seed=0, threads=threads))
    model = PPO("MlpPolicy", venv, n_steps=steps_per_env, batch_size=max(2, steps_per_env * batch // 4), n_epochs=5,
                policy_kwargs={"net_arch": [64, 64]}, device=device, seed=0, verbose=0)
    t0 = time.perf_counter()
    model.learn(steps)
    sb3_s = time.perf_counter() - t0
    return {"available": reason is None, "reason": reason, "resolution": config.resolution, "batch": batch,
            "agent_steps": steps, "torch_device": device, "env_steps_per_s": round_sig(steps / env_s),
            "rsl_steps_per_s": round_sig(rsl["agent_steps_per_s"]), "sb3_steps_per_s": round_sig(steps / sb3_s),
            "sb3_over_rsl": round_sig((steps / sb3_s) / rsl["agent_steps_per_s"])}


#: what ``msdgrasp bench`` measures
BENCH_PARTS = ("physics", "grasp", "env", "gpu", "precision", "learners", "all")


def bench_precision_run(quick: bool) -> dict:
    """:func:`bench_precision` at the command line's sizes: a GPU's default task, 256 envs, a whole 10 s
    episode; ``quick`` (and the simulator's, which runs the kernels in Python): the 60-node spleen, 2 envs,
    a 1 s episode, blocks of 4 threads."""
    from numba import config as numba_config

    from ..envs.core import GraspLiftConfig

    if quick or numba_config.ENABLE_CUDASIM:
        return bench_precision(GraspLiftConfig(resolution=60, time_limit_s=1.0), num_envs=2, threads=4)
    return bench_precision(GraspLiftConfig(), num_envs=256)


def run_bench(what: str = "physics", quick: bool = False, progress: Callable[[str], None] = lambda s: None) -> dict:
    if what not in BENCH_PARTS:
        from ..physics.config import ConfigError

        raise ConfigError(f"bench: what must be one of {', '.join(BENCH_PARTS)}, got {what!r}")
    t0 = time.perf_counter()
    report: dict[str, Any] = {"what": what, "quick": bool(quick), "machine": machine_info()}
    if what in ("physics", "all"):
        report["physics"] = bench_physics(quick, progress=progress)
    elif what == "grasp":
        report["physics"] = bench_physics(quick, include_no_contact=False, progress=progress)
    if what in ("env", "all"):
        report["env"] = bench_env(quick, progress=progress)
    if what in ("gpu", "all"):
        progress("gpu: device-resident batches, with and without contact")
        report["gpu"] = bench_gpu(quick)
        progress("gpu: the same batches and task step on one CPU core, beside it")
        report["gpu_cpu_reference"] = bench_cpu_reference(quick)
    if what in ("learners", "all"):
        progress("learners: SB3's and rsl-rl's PPO on the GPU task, beside the env alone")
        report["learners"] = bench_learners()
    reason = gpu_unavailable_reason() if what in ("gpu", "all") else None
    if what in ("gpu", "all") and reason is not None:  # (the simulator's error run is asked for by name: minutes)
        report["precision"] = {"available": False, "reason": reason}
    elif what in ("gpu", "precision", "all"):
        progress("precision: the GPU task in float32 against float64, one episode")
        report["precision"] = bench_precision_run(quick)
    report["targets"] = evaluate_targets(report)
    flags = [v["pass"] for v in report["targets"].values() if v["pass"] is not None]
    report["all_targets_pass"] = bool(all(flags)) if flags else None
    report["elapsed_s"] = round_sig(time.perf_counter() - t0)
    return report


def bench_cli(args) -> int:
    from ..physics.config import atomic_write_text

    what = getattr(args, "what", "physics") or "physics"
    quick = bool(getattr(args, "quick", False))
    out = getattr(args, "out", None)

    def progress(msg: str) -> None:
        print(f"[bench] {msg}", file=sys.stderr, flush=True)

    report = run_bench(what, quick, progress=progress)
    if out is not None:
        json_path, md_path, png_path = out_paths(out)
        png = plot_scaling(report, png_path)
        gpu_png = plot_gpu(report, png_path.with_name(json_path.stem + "_gpu.png"))
        report["files"] = {"json": str(json_path), "markdown": str(md_path), "png": str(png) if png else None,
                           "gpu_png": str(gpu_png) if gpu_png else None}
        atomic_write_text(json_path, json.dumps(report, indent=2) + "\n")
        atomic_write_text(md_path, markdown(report) + "\n")
    print(json.dumps(report, indent=2))
    return 0
