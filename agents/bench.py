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
    (:class:`NumpyMSD`, the reference) with its speed and a force/state cross-check against the numba
    kernel; and MuJoCo's flex soft body on the same tet mesh at 1 kHz when ``mujoco`` is importable.
grasp
    Only the with-contact part of ``physics``.
env
    Agent steps per second of :class:`~msdgrasp.envs.grasp_lift.GraspLiftEnv` and of
    :class:`~msdgrasp.envs.grasp_lift.GraspLiftVectorEnv` with N = 1, 16, 64 (per env and in total),
    random actions from a fixed seed, coarse spleen.

``targets`` holds pass/fail flags against the issue's numbers (coarse <= 10 us per simulated ms, fine
<= 200 us per ms, contact overhead <= 50 % and coarse-with-contact >= 70x real time, env >= 1000 steps/s
single and >= 2000 aggregate batched). Machines are noisy: the flags describe this run on this machine.
"""

from __future__ import annotations

import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: outer physics step of every measurement (the env's 1 kHz)
DT_OUTER = 1e-3
#: batch size of the batched physics measurements: a full lane block (physics/integrator.py), so the
#: per-tissue figure is what the SIMD-across-tissues path delivers
BATCH = 64
#: vector-env sizes of the env benchmark (``--quick`` skips the largest)
ENV_SIZES = (1, 16, 64, 256)

TARGETS = {
    "coarse_us_per_ms": 10.0,  # >= 100x real time
    "fine_us_per_ms": 200.0,  # >= 5x real time
    "contact_overhead": 0.50,  # contact adds <= 50 %
    "coarse_contact_us_per_ms": 10.0,  # >= 100x real time with contact
    "mujoco_speedup": 10.0,  # >= 10x faster than MuJoCo flex at equal nodes
    "env_single_steps_per_s": 1000.0,
    "env_batched_steps_per_s": 2000.0,
}


# ------------------------------------------------------------------------------------------------
# timing helpers
# ------------------------------------------------------------------------------------------------


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
        if len(samples) > 4 * repeats:
            break
    return {"median_s": statistics.median(samples), "best_s": min(samples), "cpu_s": statistics.median(cpu),
            "units": units, "seconds": total}


def _r(x: float, nd: int = 3) -> float:
    """Round to ``nd`` significant digits (JSON readability)."""
    if x is None or not math.isfinite(x) or x == 0:
        return x
    return round(x, -int(math.floor(math.log10(abs(x)))) + nd - 1)


# ------------------------------------------------------------------------------------------------
# models
# ------------------------------------------------------------------------------------------------


def spleen_params():
    from ..physics.config import builtin_config
    from ..physics.scenario import load_params
    from ..physics.tissue import TissueParams

    return load_params(builtin_config("tissue/spleen.yaml"), "tissue", TissueParams)


_MODELS: dict = {}


def spleen_model(resolution: str | int):
    """The spleen anchored (rigidly) at its hilum, at ``resolution`` (cached per process)."""
    if resolution not in _MODELS:
        from ..physics.mesh import spleen_mesh
        from ..physics.tissue import TissueModel

        mesh = spleen_mesh(resolution)
        _MODELS[resolution] = TissueModel.from_params(mesh, spleen_params(), fixed_nodes=mesh.node_sets["hilum"])
    return _MODELS[resolution]


# ------------------------------------------------------------------------------------------------
# the NumPy reference
# ------------------------------------------------------------------------------------------------


def numpy_spring_law(dl: np.ndarray, k1: np.ndarray, k2: np.ndarray, dlc: np.ndarray) -> np.ndarray:
    """The spring law of :func:`msdgrasp.physics.forces.spring_force`, vectorised."""
    adl = np.abs(dl)
    a = k1 * dlc + k2 * dlc * dlc * dlc
    b = k1 + 3.0 * k2 * dlc * dlc
    outer = a + b * (adl - dlc)
    return np.where(adl <= dlc, k1 * dl + k2 * dl * dl * dl, np.where(dl > 0.0, outer, -outer))


class NumpyMSD:
    """Plain NumPy implementation of the same MSD step as the numba kernel (no contact): the reference.

    Springs (the paper's law, optional spring dashpot, the Maxwell branch) and the volume barrier are
    evaluated for all edges / tets at once and scattered to the nodes with ``np.add.at``; symplectic Euler with implicit nodal damping;
    rigid anchors held, compliant anchors as springs. ``x, v`` are (N,3), ``fv, dl_prev`` (E,).
    """

    def __init__(self, model, n_sub: int, dt_outer: float = DT_OUTER, kscale: float = 1.0, mscale: float = 1.0):
        self.model = model
        self.n_sub = int(n_sub)
        self.dt = dt_outer / self.n_sub
        self.kscale = float(kscale)
        self.mscale = float(mscale)
        p = model.params
        self.use_dashpot = p.spring_damping_time_s > 0.0
        self.use_sls = p.relaxation_strength > 0.0
        self.decay = math.exp(-self.dt / p.relaxation_time_s)
        self.gain = p.relaxation_time_s / self.dt * (1.0 - self.decay)
        self.i = model.edges[:, 0]
        self.j = model.edges[:, 1]
        self.m = model.mass * self.mscale
        self.free = ~model.fixed if model.fixed.size else np.ones(model.n_nodes, bool)
        self.x = model.rest_positions.copy()
        self.v = np.zeros_like(self.x)
        self.fv = np.zeros(len(model.edges))
        self.dl_prev = np.zeros(len(model.edges))

    def spring_forces(self, x, v, fv, dl_prev, out=None, update=True) -> np.ndarray:
        """(N,3) spring (+ dashpot + Maxwell) forces; updates ``fv``/``dl_prev`` in place if ``update``."""
        mdl = self.model
        d = x[self.j] - x[self.i]
        length = np.sqrt(np.einsum("ij,ij->i", d, d))
        ok = length >= 1e-15
        u = d / np.where(ok, length, 1.0)[:, None]
        dl = length - mdl.rest_length
        fs = self.kscale * numpy_spring_law(dl, mdl.k1, mdl.k2, mdl.dlc)
        if self.use_sls:
            fve = fv * self.decay + self.kscale * mdl.kv * (dl - dl_prev) * self.gain
            if update:
                fv[ok] = fve[ok]
                dl_prev[ok] = dl[ok]
            fs = fs + fve
        if self.use_dashpot:
            rel = np.einsum("ij,ij->i", v[self.j] - v[self.i], u)
            fs = fs + self.kscale * mdl.cdash * rel
        fu = np.where(ok, fs, 0.0)[:, None] * u
        f = np.zeros_like(x) if out is None else out
        np.add.at(f, self.i, fu)
        np.add.at(f, self.j, -fu)
        return f

    def volume_forces(self, x, out=None) -> np.ndarray:
        """(N,3) forces of the volume barrier (tets compressed below the threshold), vectorised."""
        mdl = self.model
        f = np.zeros_like(x) if out is None else out
        if not mdl.kvol.size:
            return f
        p = x[mdl.tets]
        e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
        g = np.stack([np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)], axis=1) / 6.0  # dV/dx_b,c,d
        jac = np.einsum("ti,ti->t", e1, g[:, 0]) / mdl.rest_volume
        s = np.where(jac < mdl.volume_threshold, -self.kscale * mdl.kvol * (jac - mdl.volume_threshold), 0.0)
        fg = s[:, None, None] * g
        for k in range(3):
            np.add.at(f, mdl.tets[:, k + 1], fg[:, k])
        np.add.at(f, mdl.tets[:, 0], -fg.sum(axis=1))
        return f

    def step(self, n_steps: int = 1) -> None:
        mdl = self.model
        dt = self.dt
        x, v = self.x, self.v
        m = self.m[:, None]
        fg = m * mdl.gravity[None, :]
        x0 = mdl.rest_positions
        fixed = ~self.free
        ka = mdl.anchor_k[:, None] if mdl.anchor_k.size else None
        for _ in range(int(n_steps) * self.n_sub):
            f = fg.copy()
            self.spring_forces(x, v, self.fv, self.dl_prev, out=f)
            self.volume_forces(x, out=f)
            disp = x - x0
            if ka is not None:
                f += -ka * (disp - self.mscale * mdl.anchor_offset[None, :])
            damp = mdl.b0 + mdl.b1 * np.sqrt(np.einsum("ij,ij->i", disp, disp))
            inv = 1.0 / (1.0 + dt * damp / self.m)
            v[:] = (v + dt * f / m) * inv[:, None]
            v[fixed] = 0.0
            x += dt * v  # anchored nodes have v = 0: they stay where they are


def cross_check(resolution: str | int = "coarse", seed: int = 0, steps: int = 10, model=None) -> dict:
    """NumPy vs numba: spring forces at one perturbed state, and the state after ``steps`` ms.

    ``model`` (default: the anchored spleen at ``resolution``) may be any TissueModel. Returns the largest
    difference relative to the largest magnitude (forces, Maxwell forces, positions' displacement).
    """
    from ..physics.forces import accumulate_spring_forces, accumulate_volume_forces
    from ..physics.simulation import Simulation
    from ..physics.viscoelastic import accumulate_spring_forces_sls

    custom = model is not None
    model = model if custom else spleen_model(resolution)
    sim = Simulation(model, 1, dt=DT_OUTER)
    ref = NumpyMSD(model, sim.n_sub)
    rng = np.random.default_rng(seed)
    h = float(np.mean(model.rest_length))
    x = model.rest_positions + rng.normal(0.0, 0.12 * h, (model.n_nodes, 3))  # some springs beyond dl_c
    v = rng.normal(0.0, 0.05, (model.n_nodes, 3))
    E = len(model.edges)
    fv = rng.normal(0.0, 0.01, E)
    dl_prev = rng.normal(0.0, 0.05 * h, E)
    ks = 1.3
    ref.kscale = ks
    f_np = ref.spring_forces(x, v, fv_np := fv.copy(), dlp_np := dl_prev.copy())
    f_nb = np.zeros_like(x)
    fv_nb, dlp_nb = fv.copy(), dl_prev.copy()
    if ref.use_sls:
        accumulate_spring_forces_sls(x, v, model.edges, model.rest_length, model.k1, model.k2, model.dlc, model.cdash,
                                     ks, ref.use_dashpot, model.kv, ref.decay, ref.gain, fv_nb, dlp_nb, f_nb)
    else:
        accumulate_spring_forces(x, v, model.edges, model.rest_length, model.k1, model.k2, model.dlc, model.cdash,
                                 ks, ref.use_dashpot, f_nb)
    if model.kvol.size:
        ref.volume_forces(x, out=f_np)
        accumulate_volume_forces(x, model.tets, model.rest_volume, model.kvol, model.volume_threshold, ks, f_nb)
    beyond = float(np.mean(np.abs(np.linalg.norm(x[ref.j] - x[ref.i], axis=1) - model.rest_length) > model.dlc))
    force_rel = float(np.max(np.abs(f_np - f_nb)) / np.max(np.abs(f_nb)))
    fv_rel = float(np.max(np.abs(fv_np - fv_nb)) / max(np.max(np.abs(fv_nb)), 1e-300))

    # trajectories: `steps` outer steps from rest under gravity, kernel vs reference
    ref.kscale = 1.0
    ref.x = model.rest_positions.copy()
    ref.v[:] = 0.0
    ref.fv[:] = 0.0
    ref.dl_prev[:] = 0.0
    sim.reset()
    sim.step(steps)
    ref.step(steps)
    disp = np.max(np.abs(sim.x[0] - model.rest_positions))
    state_rel = float(np.max(np.abs(sim.x[0] - ref.x)) / max(disp, 1e-300))
    if model.kvol.size:
        p = x[model.tets]
        jac = np.einsum("ti,ti->t", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0
        active = float(np.mean(jac / model.rest_volume < model.volume_threshold))
    else:
        active = 0.0
    return {
        "resolution": model.mesh.name if custom else resolution,
        "springs_beyond_dl_c_fraction": _r(beyond),
        "tets_in_volume_barrier_fraction": _r(active),
        "max_rel_diff_forces": force_rel,
        "max_rel_diff_maxwell_forces": fv_rel,
        "state_steps_ms": steps,
        "max_rel_diff_displacement": state_rel,
    }


# ------------------------------------------------------------------------------------------------
# physics benchmarks
# ------------------------------------------------------------------------------------------------


def _clone(src, dst) -> None:
    """Copy tissue 0 of ``src`` into every tissue of ``dst`` (same model and grasper)."""
    for name in ("x", "v", "t", "fv", "dl_prev", "kscale", "mscale", "f_ext", "g_tip", "g_axis", "g_e1", "g_radius",
                 "g_vradius", "g_vpull", "g_rmin", "g_rmax", "mu_s", "mu_k", "contact_state", "contact_force"):
        getattr(dst, name)[:] = getattr(src, name)[0]


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
        "single_us_per_ms": _r(us1),
        "single_best_us_per_ms": _r(single["best_s"] * 1e6),
        "single_cpu_us_per_ms": _r(single["cpu_s"] * 1e6),
        "single_us_per_substep": _r(us1 / sim1.n_sub),
        # whole substep (springs, tets, nodes) per spring: comparable across mesh sizes
        "single_ns_per_spring_substep": _r(us1 / sim1.n_sub / len(model.edges) * 1e3),
        f"batch{batch}_ns_per_spring_substep": _r(usb / batch / simb.n_sub / len(model.edges) * 1e3),
        "single_realtime_factor": _r(1000.0 / us1),
        f"batch{batch}_total_us_per_ms": _r(usb),
        f"batch{batch}_per_tissue_us_per_ms": _r(usb / batch),
        f"batch{batch}_realtime_factor_per_tissue": _r(1000.0 * batch / usb),
        "finite": bool(sim1.finite().all() and simb.finite().all()),
        "simulated_s_timed": _r(single["units"] * DT_OUTER + batched["units"] * DT_OUTER),
        "setup_s": _r(setup),
    }


def bench_contact(resolution, min_time: float, repeats: int, settle_s: float, close_s: float,
                  batch: int = BATCH) -> dict:
    from ..physics.scenario import spleen_scene
    from ..physics.simulation import Simulation

    t0 = time.perf_counter()
    scene = spleen_scene(resolution=resolution, settle_s=settle_s)
    sim1 = scene.simulation(1, dt=DT_OUTER)
    sim1.command(closing_speed=scene.grasper.max_closing_speed_m_s)
    sim1.step(int(round(close_s / DT_OUTER)))
    sim1.command(closing_speed=0.0)  # hold the grasp: contact stays active while timing
    sim1.step(10)
    setup = time.perf_counter() - t0
    contacts_before = int(sim1.jaw_contact_counts[0, :, 0].sum())
    single = _sim_time(sim1, min_time, repeats)
    contacts_single = int(sim1.jaw_contact_counts[0, :, 0].sum())
    simb = Simulation(scene.model, batch, dt=DT_OUTER, grasper=scene.grasper)
    _clone(sim1, simb)
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
        f"contact_nodes_batch{batch}_mean": _r(float(simb.jaw_contact_counts[:, :, 0].sum(axis=1).mean())),
        "pinch_force_N": _r(float(sim1.pinch_force[0])),
        "single_us_per_ms": _r(us1),
        "single_best_us_per_ms": _r(single["best_s"] * 1e6),
        "single_cpu_us_per_ms": _r(single["cpu_s"] * 1e6),
        "single_realtime_factor": _r(1000.0 / us1),
        f"batch{batch}_total_us_per_ms": _r(usb),
        f"batch{batch}_per_tissue_us_per_ms": _r(usb / batch),
        f"batch{batch}_realtime_factor_per_tissue": _r(1000.0 * batch / usb),
        "finite": bool(sim1.finite().all() and simb.finite().all()),
        "settle_s": settle_s,
        "close_s": close_s,
        "setup_s": _r(setup),
    }


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
        "numpy_us_per_ms": _r(us),
        "numpy_cpu_us_per_ms": _r(t["cpu_s"] * 1e6),
        "numba_us_per_ms": numba_us_per_ms,
        "ratio_ours_over_numpy": _r(numba_us_per_ms / us) if numba_us_per_ms else None,
        "speedup_vs_numpy": _r(us / numba_us_per_ms) if numba_us_per_ms else None,
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
    damping = p.damping_rate_per_s * model.total_mass / model.n_nodes if p.stiffness_mode == "modulus" else p.b0_n_s_per_m
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
        sag = float(np.max(np.abs(vert - model.rest_positions))) if vert is not None and vert.shape == model.rest_positions.shape else None
        rows.append({
            "resolution": res,
            "nodes": int(mj.flex_vertnum[0]),
            "elements": int(mj.nflexelem),
            "dofs": int(mj.nv),
            "timestep_s": float(mj.opt.timestep),
            "mujoco_us_per_ms": _r(us),
            "mujoco_cpu_us_per_ms": _r(t["cpu_s"] * 1e6),
            "ours_us_per_ms": ours_us,
            "ratio_ours_over_mujoco": _r(ours_us / us) if ours_us else None,
            "speedup_vs_mujoco": _r(us / ours_us) if ours_us else None,
            f"ours_batch{BATCH}_per_tissue_us_per_ms": ours_batch,
            "speedup_batch_per_tissue": _r(us / ours_batch) if ours_batch else None,
            "finite": bool(np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))),
            "simulated_s": _r(float(data.time)),
            "max_displacement_m": _r(sag) if sag is not None else None,
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
            "exponent_us_per_ms_vs_nodes": _r(fit_exponent(nodes, [r["single_us_per_ms"] for r in rows])),
            "exponent_us_per_substep_vs_nodes": _r(fit_exponent(nodes, [r["single_us_per_substep"] for r in rows])),
            "exponent_batch_per_tissue_vs_nodes": _r(
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
                r["overhead_single"] = _r(r["single_us_per_ms"] / b["single_us_per_ms"] - 1.0)
                r[f"overhead_batch{BATCH}"] = _r(r[f"batch{BATCH}_total_us_per_ms"] / b[f"batch{BATCH}_total_us_per_ms"] - 1.0)
        out["contact"] = rows
        if "scaling" in out:
            out["scaling"]["exponent_contact_us_per_ms_vs_nodes"] = _r(
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
        "steps_per_s": _r(1.0 / t["median_s"]),
        "us_per_step": _r(t["median_s"] * 1e6),
        "cpu_steps_per_s": _r(1.0 / t["cpu_s"]) if t["cpu_s"] > 0 else None,
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
            "vector_steps_per_s": _r(1.0 / t["median_s"]),
            "total_steps_per_s": _r(n_envs / t["median_s"]),
            "per_env_steps_per_s": _r(1.0 / t["median_s"]),
            "us_per_env_step": _r(t["median_s"] * 1e6 / n_envs),
            "cpu_total_steps_per_s": _r(n_envs / t["cpu_s"]) if t["cpu_s"] > 0 else None,
        })
        venv.close()
    return {"min_time_per_measurement_s": min_time, "seed": seed, "resolution": "coarse", "single": single,
            "vector": vec}


# ------------------------------------------------------------------------------------------------
# targets, report
# ------------------------------------------------------------------------------------------------


def _target(value, limit, kind: str, unit: str, note: str = "", cpu_value=None) -> dict:
    def ok(v):
        return None if v is None else bool(v <= limit if kind == "<=" else v >= limit)

    d = {"value": value, "target": f"{kind} {_r(limit)}", "unit": unit, "pass": ok(value)}
    if cpu_value is not None:  # the same from process CPU time (less sensitive to a busy machine)
        d["value_cpu_time"] = cpu_value
        d["pass_cpu_time"] = ok(cpu_value)
    if note:
        d["note"] = note
    return d


def evaluate_targets(report: dict) -> dict:
    """Pass/fail flags against the issue's targets (wall-clock medians; CPU-time values alongside)."""
    t: dict[str, dict] = {}
    ph = report.get("physics", {})
    nc = {r["resolution"]: r for r in ph.get("no_contact", [])}
    co = {r["resolution"]: r for r in ph.get("contact", [])}
    if "coarse" in nc:
        r = nc["coarse"]
        t["coarse_physics_le_10us_per_ms"] = _target(r["single_us_per_ms"], TARGETS["coarse_us_per_ms"], "<=",
                                                     "us per simulated ms", ">= 100x real time, one tissue",
                                                     r["single_cpu_us_per_ms"])
    if "fine" in nc:
        r = nc["fine"]
        t["fine_physics_le_200us_per_ms"] = _target(r["single_us_per_ms"], TARGETS["fine_us_per_ms"], "<=",
                                                    "us per simulated ms", ">= 5x real time, one tissue",
                                                    r["single_cpu_us_per_ms"])
    if "coarse" in co:
        r = co["coarse"]
        if "overhead_single" in r:
            cpu = _r(r["single_cpu_us_per_ms"] / nc["coarse"]["single_cpu_us_per_ms"] - 1.0)
            t["coarse_contact_overhead_le_50pct"] = _target(r["overhead_single"], TARGETS["contact_overhead"], "<=",
                                                            "fraction", "contact / no-contact - 1, one tissue", cpu)
        t["coarse_contact_ge_100x_realtime"] = _target(r["single_us_per_ms"], TARGETS["coarse_contact_us_per_ms"],
                                                       "<=", "us per simulated ms", "one tissue, jaws closed",
                                                       r["single_cpu_us_per_ms"])
        t[f"coarse_contact_ge_100x_realtime_batch{BATCH}"] = _target(
            r[f"batch{BATCH}_per_tissue_us_per_ms"], TARGETS["coarse_contact_us_per_ms"], "<=",
            "us per simulated ms", f"per tissue in a batch of {BATCH} on one core, jaws closed")
    mj = ph.get("mujoco") or {}
    rows = [r for r in mj.get("rows", []) if r.get("speedup_vs_mujoco")]
    if rows:
        worst = min(rows, key=lambda r: r["speedup_vs_mujoco"])
        t["mujoco_speedup_ge_10x"] = _target(worst["speedup_vs_mujoco"], TARGETS["mujoco_speedup"], ">=",
                                             "MuJoCo time / ours", f"one tissue, worst of {len(rows)} resolutions "
                                             f"({worst['resolution']})")
        batched = [r for r in rows if r.get("speedup_batch_per_tissue")]
        if batched:
            worst_b = min(batched, key=lambda r: r["speedup_batch_per_tissue"])
            t[f"mujoco_speedup_ge_10x_batch{BATCH}"] = _target(
                worst_b["speedup_batch_per_tissue"], TARGETS["mujoco_speedup"], ">=", "MuJoCo time / ours",
                f"ours per tissue in a batch of {BATCH}, worst resolution ({worst_b['resolution']})")
    env = report.get("env")
    if env:
        s = env["single"]
        t["env_single_ge_1000_steps_per_s"] = _target(s["steps_per_s"], TARGETS["env_single_steps_per_s"], ">=",
                                                      "agent steps/s", "GraspLiftEnv, coarse", s.get("cpu_steps_per_s"))
        batched = [r for r in env["vector"] if r["n_envs"] > 1]
        if batched:
            best = max(batched, key=lambda r: r["total_steps_per_s"])
            t["env_batched_ge_2000_steps_per_s"] = _target(best["total_steps_per_s"],
                                                           TARGETS["env_batched_steps_per_s"], ">=",
                                                           "aggregate agent steps/s",
                                                           f"best batched vector env (N={best['n_envs']})",
                                                           best.get("cpu_total_steps_per_s"))
    return t


def machine_info() -> dict:
    import numba

    info = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    try:
        info["load_average_1min"] = _r(os.getloadavg()[0])
    except OSError:
        pass
    return info


def run_bench(what: str = "physics", quick: bool = False, progress: Callable[[str], None] = lambda s: None) -> dict:
    if what not in ("physics", "grasp", "env", "all"):
        from ..physics.config import ConfigError

        raise ConfigError(f"bench: what must be physics, grasp, env or all, got {what!r}")
    t0 = time.perf_counter()
    report: dict[str, Any] = {"what": what, "quick": bool(quick), "machine": machine_info()}
    if what in ("physics", "all"):
        report["physics"] = bench_physics(quick, progress=progress)
    elif what == "grasp":
        report["physics"] = bench_physics(quick, include_no_contact=False, progress=progress)
    if what in ("env", "all"):
        report["env"] = bench_env(quick, progress=progress)
    report["targets"] = evaluate_targets(report)
    flags = [v["pass"] for v in report["targets"].values() if v["pass"] is not None]
    report["all_targets_pass"] = bool(all(flags)) if flags else None
    report["elapsed_s"] = _r(time.perf_counter() - t0)
    return report


def markdown(report: dict) -> str:
    lines = [f"# msdgrasp bench {report['what']}{' (quick)' if report['quick'] else ''}", ""]
    m = report["machine"]
    lines += [f"Python {m['python']}, NumPy {m['numpy']}, numba {m['numba']}, {m['cpu_count']} CPUs, "
              f"{m['platform']}; load {m.get('load_average_1min', '?')}; total {report['elapsed_s']} s.", ""]
    ph = report.get("physics", {})
    b = BATCH
    if ph.get("no_contact"):
        lines += ["## Physics without contact (us of compute per simulated ms)", "",
                  f"| resolution | nodes | springs | n_sub | single | x real time | batch {b} total | per tissue "
                  f"| ns per spring and substep: single / batch {b} |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in ph["no_contact"]:
            lines.append(f"| {r['resolution']} | {r['nodes']} | {r['springs']} | {r['n_sub']} | {r['single_us_per_ms']} | "
                         f"{r['single_realtime_factor']} | {r[f'batch{b}_total_us_per_ms']} | "
                         f"{r[f'batch{b}_per_tissue_us_per_ms']} | {r.get('single_ns_per_spring_substep', '-')} / "
                         f"{r.get(f'batch{b}_ns_per_spring_substep', '-')} |")
        s = ph["scaling"]
        lines += ["", f"Log-log exponent of cost vs nodes: {s['exponent_us_per_ms_vs_nodes']} per simulated ms, "
                      f"{s['exponent_us_per_substep_vs_nodes']} per substep.", ""]
    if ph.get("contact"):
        lines += ["## Physics with contact (jaws closed on the inferior pole)", "",
                  f"| resolution | nodes | n_sub | contact nodes | single | x real time | overhead | batch {b} total | per tissue |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in ph["contact"]:
            lines.append(f"| {r['resolution']} | {r['nodes']} | {r['n_sub']} | {r['contact_nodes']} | "
                         f"{r['single_us_per_ms']} | {r['single_realtime_factor']} | {r.get('overhead_single', '-')} | "
                         f"{r[f'batch{b}_total_us_per_ms']} | {r[f'batch{b}_per_tissue_us_per_ms']} |")
        lines.append("")
    if ph.get("numpy_reference"):
        nr = ph["numpy_reference"]
        cc = nr["cross_check"]
        lines += ["## NumPy reference", "",
                  f"Cross-check ({cc['resolution']}): max rel. force diff {cc['max_rel_diff_forces']:.2e}, "
                  f"Maxwell {cc['max_rel_diff_maxwell_forces']:.2e}, displacement after {cc['state_steps_ms']} ms "
                  f"{cc['max_rel_diff_displacement']:.2e}.", "",
                  "| resolution | nodes | NumPy us/ms | ours us/ms | ours/NumPy |", "|---|---|---|---|---|"]
        for r in nr["rows"]:
            lines.append(f"| {r['resolution']} | {r['nodes']} | {r['numpy_us_per_ms']} | {r['numba_us_per_ms']} | "
                         f"{r['ratio_ours_over_numpy']} |")
        lines.append("")
    mj = ph.get("mujoco")
    if mj:
        lines += ["## MuJoCo flex", ""]
        if not mj["available"]:
            lines += [f"Not available: {mj['reason']}", ""]
        else:
            lines += [f"MuJoCo {mj['version']}: {mj['model']}.", "",
                      f"| resolution | nodes | MuJoCo us/ms | ours us/ms | ours/MuJoCo | ours, batch {b}, per tissue "
                      "| MuJoCo/ours (batched) | finite |", "|---|---|---|---|---|---|---|---|"]
            for r in mj["rows"]:
                if "error" in r:
                    lines.append(f"| {r['resolution']} | - | error: {r['error']} | | | | | |")
                else:
                    lines.append(f"| {r['resolution']} | {r['nodes']} | {r['mujoco_us_per_ms']} | {r['ours_us_per_ms']} | "
                                 f"{r['ratio_ours_over_mujoco']} | {r.get(f'ours_batch{b}_per_tissue_us_per_ms', '-')} | "
                                 f"{r.get('speedup_batch_per_tissue', '-')} | {r['finite']} |")
            lines.append("")
    env = report.get("env")
    if env:
        lines += ["## Env (agent steps/s, coarse spleen, random actions)", "",
                  "| env | N | total steps/s | per env steps/s |", "|---|---|---|---|",
                  f"| GraspLiftEnv | 1 | {env['single']['steps_per_s']} | {env['single']['steps_per_s']} |"]
        for r in env["vector"]:
            lines.append(f"| GraspLiftVectorEnv | {r['n_envs']} | {r['total_steps_per_s']} | {r['per_env_steps_per_s']} |")
        lines.append("")
    if report["targets"]:
        lines += ["## Targets", "", "| target | value (wall) | limit | pass | value (CPU time) | pass (CPU) |",
                  "|---|---|---|---|---|---|"]
        yn = {True: "yes", False: "NO", None: "-"}
        for k, v in report["targets"].items():
            lines.append(f"| {k} | {v['value']} | {v['target']} | {yn[v['pass']]} | {v.get('value_cpu_time', '-')} | "
                         f"{yn[v.get('pass_cpu_time')]} |")
        lines.append("")
    return "\n".join(lines)


def plot_scaling(report: dict, path: Path) -> Path | None:
    ph = report.get("physics", {})
    if not ph.get("no_contact") and not ph.get("contact"):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..physics.config import save_figure

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    b = BATCH

    def series(rows, key, label, style):
        pts = [(r["nodes"], r[key]) for r in rows if r.get(key)]
        if pts:
            n, c = zip(*pts)
            ax.loglog(n, c, style, label=label)

    nc = ph.get("no_contact", [])
    series(nc, "single_us_per_ms", "no contact, 1 tissue", "o-")
    series(nc, f"batch{b}_per_tissue_us_per_ms", f"no contact, batch {b} (per tissue)", "s--")
    series(ph.get("contact", []), "single_us_per_ms", "contact, 1 tissue", "^-")
    if ph.get("numpy_reference"):
        series(ph["numpy_reference"]["rows"], "numpy_us_per_ms", "NumPy reference", "x:")
    mj = ph.get("mujoco") or {}
    if mj.get("available"):
        series([r for r in mj["rows"] if "error" not in r], "mujoco_us_per_ms", "MuJoCo flex", "d:")
    ax.axhline(1000.0, color="k", lw=0.8, ls="--")
    ax.text(ax.get_xlim()[0], 1000.0, " real time", va="bottom", fontsize=8)
    ax.axhline(TARGETS["fine_us_per_ms"], color="0.5", lw=0.8, ls=":")
    ax.axhline(TARGETS["coarse_us_per_ms"], color="0.5", lw=0.8, ls=":")
    exp = (ph.get("scaling") or {}).get("exponent_us_per_ms_vs_nodes")
    ax.set_xlabel("nodes")
    ax.set_ylabel("compute per simulated ms (us)")
    ax.set_title("MSD spleen cost vs mesh size" + (f" (slope {exp})" if exp else ""))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def _out_paths(out: Path) -> tuple[Path, Path, Path]:
    out = Path(out)
    if out.suffix.lower() != ".json":
        out = out / "bench.json"
    return out, out.with_suffix(".md"), out.with_name(out.stem + "_scaling.png")


def bench_cli(args) -> int:
    from ..physics.config import atomic_write_text

    what = getattr(args, "what", "physics") or "physics"
    quick = bool(getattr(args, "quick", False))
    out = getattr(args, "out", None)

    def progress(msg: str) -> None:
        print(f"[bench] {msg}", file=sys.stderr, flush=True)

    report = run_bench(what, quick, progress=progress)
    if out is not None:
        json_path, md_path, png_path = _out_paths(out)
        png = plot_scaling(report, png_path)
        report["files"] = {"json": str(json_path), "markdown": str(md_path), "png": str(png) if png else None}
        atomic_write_text(json_path, json.dumps(report, indent=2) + "\n")
        atomic_write_text(md_path, markdown(report) + "\n")
    print(json.dumps(report, indent=2))
    return 0
