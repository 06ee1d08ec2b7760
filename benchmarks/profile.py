"""Where the time goes (``msdgrasp bench profile``): per physics substep, per agent step, per training.

substep
    The coarse spleen with the jaws closed on it (the bench's grasp set-up, contact active), one tissue and a
    batch of 64 (lane layout, as :func:`~msdgrasp.physics.integrator.simulate` runs it). Each phase of one
    substep of :func:`~msdgrasp.physics.integrator._advance_block` is timed by calling that phase's own kernel
    function with the arguments the integrator passes it, repeatedly inside one compiled loop (so Python's
    dispatch does not count), on the state the phase meets in a substep: force reset (gravity and external
    forces), spring loop (Maxwell branch as configured), node update, volume barrier (the flag pass over the
    watched tets, as most substeps run it, with the full pass that makes the watch list timed beside it; the
    implicit step where tets are flagged, their nodes restored before each repetition), contacts (plates and
    jaws per tissue, the nodes they move restored before each repetition); a restore is timed alone and subtracted
    (interleaved rounds, fastest CPU time of each: :func:`_us_difference`). The whole
    ``simulate`` call per substep is timed beside it; ``remainder`` = whole - sum of the phases (loop overhead,
    readouts, cache effects; it can be negative: a phase timed alone keeps its data in cache).
agent step
    Per agent step of the default training env (``TrainConfig().env``): the physics (``sim.step`` of the
    env's outer steps), the task (``command_batch`` + ``update_batch``), the whole core step (the rest is the
    env's Python: readouts, sensor noise, the info dict) and the SB3 vector env's whole step (adds autoreset
    and per-env info dicts); policy inference of the default PPO policy (untrained) on one observation and on
    a batch of 64.
training
    A short SB3 PPO run of the default config (``--quick``: fewer steps): wall time split into rollouts (env
    stepping and the policy's forward passes), PPO updates and validation, measured with an SB3 callback.

Substep times are the fastest process CPU time (``time.process_time``) of repeated measurements after a warm-up, in
three rounds over all phases and the whole call from the same state (the two phases timed as a difference, barrier
step and contacts, also interleave with their restore); agent-step and training times are wall clock
(``time.perf_counter``), medians of repeated measurements.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numba import njit

from ..physics.config import needs_extra
from ..physics.contact import clear_contacts, jaw_contacts, jaw_directions, plate_contacts
from ..physics.forces import (
    displacement_spread,
    flag_watched,
    implicit_volume_barrier_lanes,
    spring_loop,
    spring_loop_lanes,
    watch_barrier,
)
from ..physics.integrator import _constant_damping, _to_lanes, _update_nodes
from ..physics.records import Springs
from ..physics.reference import DT_OUTER
from ..physics.numba_cache import key_on_physics
from .bench import _clone, _grasped, time_per_unit
from .report import _r

# the phase timers below call the physics kernels and are cached: without this, an edit of physics/ would leave
# them timing the old kernels (numba checks a cached function against its own file only)
key_on_physics(__file__)

#: batch of the lane-layout rows (one lane block)
PROFILE_BATCH = 64
#: the phases of one substep, in the integrator's order
PHASES = ("force_reset", "springs", "node_update", "barrier_flag", "barrier_step", "contacts")

# ------------------------------------------------------------------------------------------------
# compiled repetition loops: each calls one phase's kernel function ``reps`` times, as _advance_block does
# ------------------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _rep_force_reset(f_flat, f0_flat, reps):
    for _ in range(reps):
        for k in range(f_flat.shape[0]):
            f_flat[k] = f0_flat[k]


@njit(cache=True, error_model="numpy")
def _rep_springs(x, v, springs, ks, decay, gain, fv, dl_prev, f, tmp, scratch, lanes, reps):
    n = x.shape[0]
    ne = fv.shape[0]
    if lanes:
        for _ in range(reps):
            spring_loop_lanes(x, v, springs, ks, decay, gain, fv, dl_prev, f, tmp)
    else:
        x_one = x.reshape((n, 3))
        v_one = v.reshape((n, 3))
        f_one = f.reshape((n, 3))
        fv_one = fv.reshape(ne)
        dl_one = dl_prev.reshape(ne)
        for _ in range(reps):
            spring_loop(x_one, v_one, springs, ks[0], decay, gain, fv_one, dl_one, f_one, scratch)


@njit(cache=True, error_model="numpy")
def _rep_springs_as(x, v, springs, ks, rates, fv, dl_prev, f, tmp, units, reps):
    """:func:`_rep_springs` of a lane block in the arithmetic of ``units`` (one, tiny): float32 arrays with float32
    units compile the same spring code for float32."""
    decay, gain = rates
    one, tiny = units
    for _ in range(reps):
        spring_loop_lanes(x, v, springs, ks, decay, gain, fv, dl_prev, f, tmp, one, tiny)


@njit(cache=True, error_model="numpy")
def _rep_divider(l2, out, one, reps):
    """A square root and a division per entry of ``l2`` (contiguous), in ``one``'s type: the two operations every spring
    of every tissue needs per substep (its length and the inverse that makes its direction), with nothing else."""
    for _ in range(reps):
        for k in range(l2.shape[0]):
            out[k] = one / math.sqrt(l2[k])


def _divider_floor(x, edges, min_time, repeats) -> dict:
    """us per substep that the springs' square roots and divisions alone take (float64 and float32), on the
    substep's squared spring lengths of every tissue: the vector divider's floor under any float64 spring pass that
    keeps the spring law's arithmetic (the spring loops compute exactly these two per spring and tissue)."""
    d = x[edges[:, 1]] - x[edges[:, 0]]  # (E, 3, L)
    l2 = np.ascontiguousarray((d * d).sum(axis=1)).reshape(-1)
    floor = {}
    for name, typ in (("float64", np.float64), ("float32", np.float32)):
        a = l2.astype(typ)
        out = np.empty_like(a)
        floor[name] = _r(_us(lambda k, a=a, out=out, one=typ(1.0): _rep_divider(a, out, one, k), min_time, repeats))
    return floor


def _spring_pass_float32(springs, x, v, ks, decay, gain, fv, dl, min_time, repeats) -> dict:
    """What float32 arithmetic does to the lane block's spring pass (the largest phase), on float32 copies of the
    same state: its time per substep, and its forces' largest deviation from float64's, relative to the largest
    spring force. The physics stays float64: this measures the option, it does not take it."""
    c32 = np.float32
    s32 = Springs(springs.edges, *(np.asarray(a, dtype=c32) for a in springs[1:7]), springs.use_dashpot,
                  springs.use_sls)
    x32, v32, ks32 = x.astype(c32), v.astype(c32), ks.astype(c32)
    rates, units = (c32(decay), c32(gain)), (c32(1.0), c32(1e-15))
    f64 = np.zeros_like(x)
    _rep_springs_as(x, v, springs, ks, (decay, gain), fv.copy(), dl.copy(), f64, np.empty((3, x.shape[2])),
                    (1.0, 1e-15), 1)
    f32 = np.zeros_like(x32)
    tmp = np.empty((3, x.shape[2]), dtype=c32)
    _rep_springs_as(x32, v32, s32, ks32, rates, fv.astype(c32), dl.astype(c32), f32, tmp, units, 1)
    err = float(np.max(np.abs(f32 - f64)) / np.max(np.abs(f64)))
    fv32, dl32 = fv.astype(c32), dl.astype(c32)
    us = _us(lambda k: _rep_springs_as(x32, v32, s32, ks32, rates, fv32, dl32, f32, tmp, units, k), min_time, repeats)
    return {"us_per_substep": _r(us), "force_rel_err": _r(err)}


@njit(cache=True, error_model="numpy")
def _rep_nodes(model, x, v, f, meff, damp_inv, fa, ms, lane0, dt, anchor_out, lanes, reps):
    # (the node update's cost does not depend on the positions: repeating it on a copy that drifts is fair)
    work = (meff, damp_inv, fa)
    nl = x.shape[2]
    for _ in range(reps):
        if lanes:
            _update_nodes(model, x, v, f, work, ms, nl, lane0, False, dt, anchor_out)
        else:
            _update_nodes(model, x, v, f, work, ms, 1, lane0, False, dt, anchor_out)


@njit(cache=True, error_model="numpy")
def _restore(x, v, x0, v0, nodes):
    for q in range(nodes.shape[0]):
        i = nodes[q]
        for c in range(3):
            for lane in range(x.shape[2]):
                x[i, c, lane] = x0[i, c, lane]
                v[i, c, lane] = v0[i, c, lane]


@njit(cache=True, error_model="numpy")
def _rep_contacts(model, state, out, x, v, x0, v0, nodes, meff, held, u, tj, sub_info, res, lane0, run, reps):
    """The contact phase (run False: only the restore of ``nodes``, to be subtracted)."""
    nl = x.shape[2]
    dt, _, last_sub, _ = sub_info
    cand = np.empty(0, dtype=np.int8)  # (as the integrator: jaw_contacts tests each node where it resolves it)
    for _ in range(reps):
        _restore(x, v, x0, v0, nodes)
        if not run:
            continue
        for lane in range(nl):
            b = lane0 + lane
            state.t[b] += dt
            xb = x[:, :, lane]
            vb = v[:, :, lane]
            mb = meff[:, lane]
            hb = held[lane]
            clear_contacts(b, model, out, hb, last_sub)
            plate_contacts(b, xb, vb, mb, model, state, out, sub_info, res, hb)
            if model.jaw_active:
                jaw_contacts(b, xb, vb, mb, model, state, out, (u[lane], tj[lane]), sub_info, res, (hb, cand))


@njit(cache=True, error_model="numpy")
def _rep_barrier_flag(x, tets, rest_volume, thr, delta, flags, n_flagged, watch, full, reps):
    """The barrier's flag pass as the integrator runs it: ``full``, the full pass that also makes the watch list
    (returns its length); else the check of the nodes' displacement against the budget and the pass over the
    watched tets alone (``watch[:n]``, n from a full pass)."""
    n_watch = watch_barrier(x, tets, rest_volume, thr, delta, flags, n_flagged, watch)
    nl = x.shape[2]
    x_one = x.reshape((x.shape[0], 3 * nl))
    x_ref = x_one.copy()
    lohi = np.empty((3, 3 * nl))
    for _ in range(reps):
        if full:
            n_watch = watch_barrier(x, tets, rest_volume, thr, delta, flags, n_flagged, watch)
        elif displacement_spread(x_one, x_ref, nl, lohi) <= delta:
            flag_watched(x, tets, rest_volume, thr, watch, n_watch, flags, n_flagged)
    return n_watch


@njit(cache=True, error_model="numpy")
def _rep_barrier_step(model, x, v, x0, v0, nodes, meff, held, ks, dt, visit, anchor_vol, lanes, run, reps):
    """The barrier's implicit step on the flagged tets (run False: only the restore of their nodes); visit:
    (flags (T,L), n_flagged (L,), watch, n_watch) as the flag pass left them."""
    flags, n_flagged, watch, n_watch = visit
    for _ in range(reps):
        _restore(x, v, x0, v0, nodes)
        if not run:
            continue
        if lanes or n_flagged[0] > 0:  # (as the integrator: one tissue is its (N,3,1) block)
            anchor_vol[:] = 0.0
            implicit_volume_barrier_lanes(x, v, meff, (model.fixed, held), model.tets, model.rest_volume, model.kvol,
                                          model.vol_threshold, ks, dt, (flags, watch, n_watch), anchor_vol)


# ------------------------------------------------------------------------------------------------
# per substep
# ------------------------------------------------------------------------------------------------


def _us(run: Callable[[int], Any], min_time: float, repeats: int) -> float:
    """us per unit of ``run``: the fastest process CPU time of its repetitions. A phase's cost is what it takes
    undisturbed; a busy machine only adds to it, and wall-clock medians of single quick-mode samples read the
    whole call at twice the sum of its phases when a burst of load fell on one of them."""
    run(1)  # compile / load the cache
    return time_per_unit(run, min_time, repeats, max_units=10**7)["best_cpu_s"] * 1e6


DIFF_ROUNDS = 5


def _us_difference(with_part: Callable[[int], Any], without: Callable[[int], Any], min_time: float,
                   repeats: int) -> float:
    """us per unit of the part that ``with_part`` runs and ``without`` does not (a restore both run).

    Timed in :data:`DIFF_ROUNDS` interleaved rounds in process CPU time and taken as the difference of each one's
    fastest round: a busy machine only ever adds time, CPU time leaves out the time the process was descheduled, and
    interleaving lets both see the same machine, where two wall-clock medians taken one after the other read a part
    of ~1 us as zero when a burst of load falls on the subtrahend's timing.
    """
    best_with = best_without = math.inf
    for _ in range(DIFF_ROUNDS):
        best_with = min(best_with, _us(with_part, min_time, repeats))
        best_without = min(best_without, _us(without, min_time, repeats))
    return max(best_with - best_without, 0.0)


def profile_substep(sim, min_time: float, repeats: int) -> dict:
    """us per substep of each phase and of the whole ``simulate`` call for ``sim`` (all tissues in one lane
    block, or one tissue), on copies of its state: ``sim`` itself is only advanced by the whole-call timing."""
    model, state, out = sim.kernel_model(), sim.kernel_state(), sim.kernel_readout()
    nb, n, ne, nt = sim.x.shape[0], sim.x.shape[1], sim.fv.shape[1], model.tets.shape[0]
    lanes = nb > 1
    if lanes and nb > 64:
        raise ValueError(f"profile_substep: batch must fit one lane block (<= 64 tissues), got {nb}")
    m = model
    dt = m.dt_outer / m.n_sub
    # the batch in lanes (x[i, c, lane]), as simulate copies it in
    x = np.empty((n, 3, nb))
    v = np.empty((n, 3, nb))
    fv = np.empty((ne, nb))
    dl = np.empty((ne, nb))
    _to_lanes(state.x, state.v, state.fv, state.dl_prev, 0, x, v, fv, dl, True)
    springs = Springs(m.edges, m.rest_length, m.k1, m.k2, m.dlc, m.cdash,
                      m.kv if m.kv.shape[0] == ne else np.zeros(ne), m.use_dashpot, m.use_sls)
    ks = np.ascontiguousarray(state.kscale)
    ms = np.ascontiguousarray(state.mscale)
    decay = math.exp(-dt / m.tau)
    gain = m.tau / dt * (1.0 - decay)
    tmp = np.empty((3, nb))
    scratch = np.zeros((9, 0 if lanes else ne))
    f0 = np.empty((n, 3, nb))
    for lane in range(nb):
        f0[:, :, lane] = m.mass[:, None] * ms[lane] * m.gravity[None, :] + state.f_ext[lane]
    meff = np.empty((n, nb))
    damp_inv = np.empty((n, nb))
    fa = np.empty((3, nb))
    _constant_damping(m.mass, m.b0, m.b1, ms, dt, meff, damp_inv)
    u = np.empty((nb, 3, 3))
    tj = np.empty((nb, 3, 3))
    for lane in range(nb):
        jaw_directions(state.g_axis[lane], state.g_e1[lane], u[lane], tj[lane])
    flags = np.empty((nt, nb), dtype=np.int8)
    n_flagged = np.zeros(nb, dtype=np.int64)
    anchor_vol = np.zeros((nb, 3))  # per tissue: the anchors' force against the barrier
    # the contacts' memory of the last substep: the barrier's step reads it (a copy: the contacts rewrite it)
    held = np.ascontiguousarray(state.held, dtype=np.int8).copy()
    res = np.empty(6)
    sub_info = (dt, 0.0, False, 1.0 / m.n_sub)  # a substep before the last one of a call: no readout fill
    anchor_out = np.zeros_like(out.anchor_out)
    barrier_on = m.kvol.shape[0] > 0
    rows: dict[str, float] = {}
    # ---- 1. forces (on scratch copies: the phase's state changes do not carry into the next phase)
    f = f0.copy()
    rows["force_reset"] = _us(lambda k: _rep_force_reset(f.reshape(-1), f0.reshape(-1), k), min_time, repeats)
    fv_c, dl_c = fv.copy(), dl.copy()
    rows["springs"] = _us(lambda k: _rep_springs(x, v, springs, ks, decay, gain, fv_c, dl_c, f, tmp, scratch, lanes, k),
                          min_time, repeats)
    float32 = _spring_pass_float32(springs, x, v, ks, decay, gain, fv, dl, min_time, repeats) if lanes else None
    divider = _divider_floor(x, m.edges, min_time, repeats)
    # the substep's real forces, from the real state
    f = f0.copy()
    _rep_springs(x, v, springs, ks, decay, gain, fv, dl, f, tmp, scratch, lanes, 1)
    # ---- 2-3. node update (on copies of x, v)
    xc, vc = x.copy(), v.copy()
    rows["node_update"] = _us(lambda k: _rep_nodes(m, xc, vc, f, meff, damp_inv, fa, ms, 0,
                                                   dt, anchor_out, lanes, k), min_time, repeats)
    meff[:] = 0.0
    _constant_damping(m.mass, m.b0, m.b1, ms, dt, meff, damp_inv)
    _rep_nodes(m, x, v, f, meff, damp_inv, fa, ms, 0, dt, anchor_out, lanes, 1)  # the real state moves on
    # ---- 4. volume barrier: flag pass, then the implicit step on the flagged tets (their nodes restored)
    rows["barrier_flag"] = 0.0
    rows["barrier_step"] = 0.0
    flagged = 0
    full_pass = 0.0
    watch = np.empty(nt, dtype=np.int64)
    n_watch = 0
    if barrier_on:
        flags_c, n_flagged_c, watch_c = flags.copy(), n_flagged.copy(), watch.copy()

        def flag_pass(full: bool) -> Callable[[int], None]:
            return lambda k: _rep_barrier_flag(x, m.tets, m.rest_volume, m.vol_threshold, m.watch_delta, flags_c,
                                               n_flagged_c, watch_c, full, k)

        rows["barrier_flag"] = _us(flag_pass(False), min_time, repeats)
        full_pass = _us(flag_pass(True), min_time, repeats)
        n_watch = _rep_barrier_flag(x, m.tets, m.rest_volume, m.vol_threshold, m.watch_delta, flags, n_flagged,
                                    watch, True, 0)
        flagged = int(n_flagged.sum())
        if flagged:
            tet_nodes = np.unique(m.tets[np.flatnonzero(flags.any(axis=1))].ravel()).astype(np.int64)
            x0, v0 = x.copy(), v.copy()
            visit = (flags, n_flagged, watch, n_watch)

            def step(run: bool) -> Callable[[int], None]:
                return lambda k: _rep_barrier_step(m, x, v, x0, v0, tet_nodes, meff, held, ks, dt, visit, anchor_vol,
                                                   lanes, run, k)

            rows["barrier_step"] = _us_difference(step(True), step(False), min_time / DIFF_ROUNDS, repeats)
            x[:], v[:] = x0, v0
            _rep_barrier_step(m, x, v, x0, v0, tet_nodes, meff, held, ks, dt, visit, anchor_vol, lanes, True, 1)
    # ---- 5. contacts: the nodes that penetrated the jaws in this substep are pushed out; restore them
    surf = np.ascontiguousarray(m.surface_nodes, dtype=np.int64)
    x0, v0 = x.copy(), v.copy()
    t_save = state.t.copy()
    g_save = state.g_force.copy()
    jaw_save, cs_save, cf_save = out.jaw_out.copy(), out.contact_state.copy(), out.contact_force.copy()

    # restore only the nodes the pass moves (a few dozen): restoring all surface nodes costs several times the
    # contacts themselves, and the difference of two timings would drown in the machine's noise
    moved = np.zeros(n, dtype=np.bool_)
    for _ in range(3):  # (the contacts' memory changes between repetitions: the union over a few)
        _rep_contacts(m, state, out, x, v, x0, v0, surf, meff, held, u, tj, sub_info, res, 0, True, 1)
        moved |= np.any(x != x0, axis=(1, 2)) | np.any(v != v0, axis=(1, 2))
    x[:], v[:] = x0, v0
    touched = np.flatnonzero(moved).astype(np.int64)

    def contacts(run: bool) -> Callable[[int], None]:
        return lambda k: _rep_contacts(m, state, out, x, v, x0, v0, touched, meff, held, u, tj, sub_info, res, 0,
                                       run, k)

    rows["contacts"] = _us_difference(contacts(True), contacts(False), min_time / DIFF_ROUNDS, repeats)
    if not (np.array_equal(x[~moved], x0[~moved]) and np.array_equal(v[~moved], v0[~moved])):
        raise RuntimeError("profile: the contacts moved nodes outside the set restored between repetitions")
    x[:], v[:] = x0, v0
    _rep_contacts(m, state, out, x, v, x0, v0, surf, meff, held, u, tj, sub_info, res, 0, True, 1)
    contact_nodes = int(np.count_nonzero(held > 0))
    # (the kernel's time, grasper pinch and readouts were advanced by the repetitions: put them back)
    state.t[:], state.g_force[:] = t_save, g_save
    out.jaw_out[:], out.contact_state[:], out.contact_force[:] = jaw_save, cs_save, cf_save
    # ---- the whole call, per substep (many outer steps per call, as the env's 33 ms agent step)
    steps = 33
    whole_ms = _us(lambda k: sim.step(k * steps), min_time, repeats) / steps  # us per outer step
    whole = whole_ms / sim.n_sub
    total = sum(rows[p] for p in PHASES)
    return {
        "tissues": nb,
        "layout": "lanes" if lanes else "one tissue",
        "n_sub": sim.n_sub,
        "maxwell_branch": bool(m.use_sls),
        "dashpots": bool(m.use_dashpot),
        "contact_nodes": contact_nodes,
        "tets_below_barrier_threshold": flagged,
        "tets_watched": n_watch,
        "barrier_full_flag_pass_us": _r(full_pass),
        "phases_us_per_substep": {p: _r(rows[p]) for p in PHASES},
        "phases_share_of_whole": {p: _r(rows[p] / whole) for p in PHASES},
        "sum_of_phases_us": _r(total),
        "whole_us_per_substep": _r(whole),
        "remainder_us": _r(whole - total),
        "sum_over_whole": _r(total / whole),
        "per_tissue_whole_us_per_substep": _r(whole / nb),
        "springs_float32": float32,
        "springs_sqrt_div_us": divider,
    }


PROFILE_ROUNDS = 3


def profile_substep_rounds(sim, min_time: float, repeats: int, rounds: int = PROFILE_ROUNDS) -> dict:
    """:func:`profile_substep` ``rounds`` times from the same state of ``sim`` (restored before each round), each
    time taken as its fastest round: every phase and the whole call are sampled across the same stretch of time, so
    a stretch of load on the machine cannot fall on one of them alone."""
    snapshot = {k: a.copy() for k, a in vars(sim).items() if isinstance(a, np.ndarray) and a.flags.writeable}
    runs = []
    for _ in range(rounds):
        for k, a in snapshot.items():
            getattr(sim, k)[...] = a
        runs.append(profile_substep(sim, min_time / rounds, repeats))
    return _fastest(runs)


def _fastest(runs: list[dict]) -> dict:
    """One :func:`profile_substep` row from several: each time the fastest, the sums and shares made from those."""
    row = dict(runs[0])
    phases = {p: min(r["phases_us_per_substep"][p] for r in runs) for p in PHASES}
    whole = min(r["whole_us_per_substep"] for r in runs)
    total = sum(phases.values())
    nb = row["tissues"]
    row.update({
        "barrier_full_flag_pass_us": min(r["barrier_full_flag_pass_us"] for r in runs),
        "phases_us_per_substep": phases,
        "phases_share_of_whole": {p: _r(phases[p] / whole) for p in PHASES},
        "sum_of_phases_us": _r(total),
        "whole_us_per_substep": whole,
        "remainder_us": _r(whole - total),
        "sum_over_whole": _r(total / whole),
        "per_tissue_whole_us_per_substep": _r(whole / nb),
        "springs_sqrt_div_us": {k: min(r["springs_sqrt_div_us"][k] for r in runs) for k in row["springs_sqrt_div_us"]},
    })
    if row["springs_float32"] is not None:
        row["springs_float32"] = {"us_per_substep": min(r["springs_float32"]["us_per_substep"] for r in runs),
                                  "force_rel_err": max(r["springs_float32"]["force_rel_err"] for r in runs)}
    return row


def profile_substeps(quick: bool, progress: Callable[[str], None] = lambda s: None, resolution="coarse") -> dict:
    """:func:`profile_substep_rounds` of the grasped coarse spleen, one tissue and a batch of
    :data:`PROFILE_BATCH`."""
    from ..physics.simulation import Simulation

    min_time = 0.1 if quick else 0.5
    repeats = 3
    settle_s, close_s = (0.5, 1.0) if quick else (2.0, 2.0)
    progress(f"profile: grasping the {resolution} spleen")
    scene, sim1 = _grasped(resolution, settle_s, close_s)
    progress("profile: substep phases, one tissue")
    one = profile_substep_rounds(sim1, min_time, repeats)
    simb = Simulation(scene.model, PROFILE_BATCH, dt=DT_OUTER, grasper=scene.grasper)
    _clone(sim1, simb)
    progress(f"profile: substep phases, batch of {PROFILE_BATCH}")
    batch = profile_substep_rounds(simb, min_time, repeats)
    return {"resolution": resolution, "nodes": scene.model.n_nodes, "springs": int(len(scene.model.edges)),
            "tets": int(len(scene.model.tets)), "surface_nodes": int(len(scene.mesh.surface_nodes)),
            "min_time_per_measurement_s": min_time, "rows": [one, batch]}


# ------------------------------------------------------------------------------------------------
# per agent step
# ------------------------------------------------------------------------------------------------


def _default_train_config():
    # PPO from scratch (configs/train/ppo_scratch.yaml): the learner's own cost; the default run adds a controller's
    # per-step work on top (docs/performance.md)
    from ..agents.models import TrainConfig

    return TrainConfig()


def build_default_ppo(venv, config):
    """An untrained PPO of ``config``'s policy settings on ``venv``, built as agents/training.py's ``train`` does."""
    from ..agents.networks import AsymmetricActorCriticPolicy
    from ..envs.core import OBS_NAMES, actor_mask

    with needs_extra("train", "the PPO profile"):
        from stable_baselines3 import PPO

    kwargs = dict(config.ppo)
    policy, policy_kwargs = "MlpPolicy", {"net_arch": list(config.policy_net),
                                          "log_std_init": float(config.log_std_init)}
    if config.squash_actions:
        policy_kwargs["squash_output"] = True
    if config.asymmetric_critic:
        policy = AsymmetricActorCriticPolicy
        policy_kwargs["actor_mask"] = actor_mask(len(OBS_NAMES), venv.core.frame_dim, config.env.obs_history)
    return PPO(policy, venv, seed=config.seed, device="cpu", verbose=0, policy_kwargs=policy_kwargs, **kwargs)


def profile_agent_step(quick: bool, progress: Callable[[str], None] = lambda s: None) -> dict:
    """ms per agent step of the default env's parts (batch of 1 and of the default n_envs) and of the policy."""
    with needs_extra("train", "the agent-step profile"):
        import torch

    from ..envs import core as core_module
    from ..envs.sb3 import GraspLiftSB3VecEnv
    from ..envs.task import command_batch, update_batch

    config = _default_train_config()
    torch.set_num_threads(config.torch_threads)
    min_time = 0.2 if quick else 1.0
    repeats = 1 if quick else 3
    rows = []
    for n_envs in (1, config.n_envs):
        progress(f"profile: agent step, {n_envs} env(s)")
        venv = GraspLiftSB3VecEnv(n_envs, config.env, seed=config.seed)
        venv.reset()
        core = venv.core
        rng = np.random.default_rng(0)
        for _ in range(5):  # into the episode: the jaws move towards the tissue
            venv.step(rng.uniform(-1.0, 1.0, (n_envs, 2)).astype(np.float32))
        # the parts are timed inside real vector-env steps (random actions, autoreset), by timers around
        # the physics call, the task's two functions and the blow-up/volume readouts, restored afterwards
        spent = {"physics": 0.0, "task": 0.0, "readouts": 0.0}

        def timed(fn: Callable, part: str) -> Callable:
            def wrapper(*args: Any, **kwargs: Any) -> Any:
                t0 = time.perf_counter()
                try:
                    return fn(*args, **kwargs)
                finally:
                    spent[part] += time.perf_counter() - t0
            return wrapper

        sim = core.sim
        sim.step = timed(sim.step, "physics")
        sim.finite = timed(sim.finite, "readouts")
        sim.min_volume_ratio = timed(sim.min_volume_ratio, "readouts")
        core_module.command_batch = timed(command_batch, "task")
        core_module.update_batch = timed(update_batch, "task")
        try:
            n_steps, t0 = 0, time.perf_counter()
            while n_steps < 3 or time.perf_counter() - t0 < min_time:
                venv.step(rng.uniform(-1.0, 1.0, (n_envs, 2)).astype(np.float32))
                n_steps += 1
            wall = time.perf_counter() - t0
        finally:
            core_module.command_batch, core_module.update_batch = command_batch, update_batch
            for name in ("step", "finite", "min_volume_ratio"):
                delattr(sim, name)
        vec = wall / n_steps * 1e3
        physics, task_ms, readouts = (spent[k] / n_steps * 1e3 for k in ("physics", "task", "readouts"))
        steps = core.config.physics_steps_per_action
        rows.append({
            "n_envs": n_envs,
            "physics_ms_per_agent_step": steps,
            "agent_steps_timed": n_steps,
            "ms": {"physics": _r(physics), "task": _r(task_ms), "readouts_finite_volume": _r(readouts),
                   "python_rest": _r(vec - physics - task_ms - readouts), "sb3_vec_env_step": _r(vec)},
            "share_of_sb3_step": {"physics": _r(physics / vec), "task": _r(task_ms / vec),
                                  "readouts_finite_volume": _r(readouts / vec),
                                  "python_rest": _r((vec - physics - task_ms - readouts) / vec)},
            "agent_steps_per_s": _r(n_envs / vec * 1e3),
        })
        if n_envs == config.n_envs:
            progress("profile: policy inference")
            model = build_default_ppo(venv, config)
            policy = model.policy

            def ms(run: Callable[[int], Any]) -> float:
                run(1)
                return time_per_unit(run, min_time, repeats, max_units=10**6)["median_s"] * 1e3

            obs = venv.reset()
            inference = {"policy": type(policy).__name__, "net_arch": list(config.policy_net),
                         "obs_dim": int(obs.shape[1]), "torch_threads": config.torch_threads}
            for batch in (1, PROFILE_BATCH):
                o = np.resize(obs, (batch, obs.shape[1])).astype(np.float32)
                t = torch.as_tensor(o)

                def predict(k: int, o=o) -> None:
                    for _ in range(k):
                        policy.predict(o, deterministic=True)

                def forward(k: int, t=t) -> None:
                    with torch.no_grad():
                        for _ in range(k):
                            policy(t)  # what the rollout calls: actions, values, log-probabilities

                inference[f"predict_batch{batch}_ms"] = _r(ms(predict))
                inference[f"forward_batch{batch}_ms"] = _r(ms(forward))
            del model
        venv.close()
    return {"resolution": config.env.resolution, "min_time_per_measurement_s": min_time, "rows": rows,
            "policy_inference": inference}


# ------------------------------------------------------------------------------------------------
# per training
# ------------------------------------------------------------------------------------------------


def profile_training(quick: bool, progress: Callable[[str], None] = lambda s: None) -> dict:
    """A short SB3 PPO run of the default config (default n_envs and rollout length; ``--quick``: one rollout
    of 4 envs): wall time of rollouts, PPO updates and one validation (:class:`~..agents.training.BestModel`,
    as at a checkpoint), with an SB3 callback. Nothing is written outside a temporary folder."""
    import tempfile

    with needs_extra("train", "the training profile"):
        import torch
        from stable_baselines3.common.callbacks import BaseCallback

    from ..agents.training import BestModel
    from ..envs.sb3 import GraspLiftSB3VecEnv
    from ..physics.config import replace

    config = _default_train_config()
    if quick:
        config = replace(config, n_envs=4, validation_episodes=1, validation_mu=(0.5,),
                         ppo={**dict(config.ppo), "n_steps": 32, "batch_size": 64, "n_epochs": 2})
    torch.set_num_threads(config.torch_threads)
    total = config.n_envs * config.ppo["n_steps"]  # one rollout and one update
    progress(f"profile: training {total} steps ({config.n_envs} envs)")
    venv = GraspLiftSB3VecEnv(config.n_envs, config.env, seed=config.seed)
    model = build_default_ppo(venv, config)
    times = {"rollout": 0.0, "update": 0.0}
    marks: dict[str, float] = {}

    class Timer(BaseCallback):
        def _on_rollout_start(self) -> None:
            now = time.perf_counter()
            if "rollout_end" in marks:
                times["update"] += now - marks["rollout_end"]
            marks["rollout_start"] = now

        def _on_rollout_end(self) -> None:
            now = time.perf_counter()
            times["rollout"] += now - marks["rollout_start"]
            marks["rollout_end"] = now

        def _on_step(self) -> bool:
            return True

    t0 = time.perf_counter()
    model.learn(total, callback=Timer())
    end = time.perf_counter()
    learn = end - t0
    if "rollout_end" in marks:  # the last update runs after the last rollout, before learn returns
        times["update"] += end - marks["rollout_end"]
    with tempfile.TemporaryDirectory() as tmp:
        from pathlib import Path

        selector = BestModel(config, Path(tmp))
        path = Path(tmp) / "model.zip"
        model.save(path)
        progress("profile: one validation")
        t1 = time.perf_counter()
        selector.consider(model, path)
        validation = time.perf_counter() - t1
    venv.close()
    checkpoints = config.total_timesteps / config.checkpoint_every
    full_s = {"rollout": times["rollout"] / total * config.total_timesteps,
              "update": times["update"] / total * config.total_timesteps, "validation": validation * checkpoints}
    full_total = sum(full_s.values())
    return {
        "n_envs": config.n_envs, "n_steps": config.ppo["n_steps"], "agent_steps": total,
        "n_epochs": config.ppo["n_epochs"], "batch_size": config.ppo["batch_size"],
        "validation_episodes": config.validation_episodes, "validation_mu": list(config.validation_mu),
        "seconds": {"learn": _r(learn), "rollout": _r(times["rollout"]), "update": _r(times["update"]),
                    "learn_rest": _r(learn - times["rollout"] - times["update"]), "one_validation": _r(validation)},
        "rollout_agent_steps_per_s": _r(total / times["rollout"]) if times["rollout"] > 0 else None,
        "extrapolated_default_run": {"total_timesteps": config.total_timesteps, "checkpoints": _r(checkpoints),
                                     "hours": {k: _r(s / 3600.0) for k, s in full_s.items()},
                                     "share": {k: _r(s / full_total) for k, s in full_s.items()}},
    }


# ------------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------------


def run_profile(quick: bool = False, progress: Callable[[str], None] = lambda s: None, training: bool = True) -> dict:
    from .report import machine_info

    t0 = time.perf_counter()
    report: dict[str, Any] = {"what": "profile", "quick": bool(quick), "machine": machine_info()}
    report["substep"] = profile_substeps(quick, progress)
    report["agent_step"] = profile_agent_step(quick, progress)
    if training:
        report["training"] = profile_training(quick, progress)
    report["elapsed_s"] = _r(time.perf_counter() - t0)
    return report


def _divider_line(one: dict, batch: dict) -> str:
    """The profile's sentence on the springs' divider floor (:func:`_divider_floor`) of one tissue and the batch."""
    f1, fb, nb = one["springs_sqrt_div_us"], batch["springs_sqrt_div_us"], batch["tissues"]
    return ("The springs' square roots and divisions alone (one of each per spring and tissue, nothing else: the "
            "vector divider's floor under a spring pass that keeps the spring law's arithmetic), us per substep, "
            f"float64 / float32: one tissue {f1['float64']} / {f1['float32']}, batch {fb['float64']} / {fb['float32']} "
            f"({_r(fb['float64'] / nb)} / {_r(fb['float32'] / nb)} per tissue); float64 at {one['n_sub']} substeps per "
            f"ms: {_r(f1['float64'] * one['n_sub'])} us per simulated ms one tissue, "
            f"{_r(fb['float64'] * batch['n_sub'] / nb)} per tissue of the batch.")


def markdown_table(report: dict) -> str:
    """The profile's tables (markdown)."""
    lines = []
    sub = report["substep"]
    one, batch = sub["rows"]
    lines += [f"Per substep, {sub['resolution']} spleen ({sub['nodes']} nodes, {sub['springs']} springs, "
              f"{sub['tets']} tets), jaws closed (contact nodes: {one['contact_nodes']} one tissue), n_sub "
              f"{one['n_sub']}, Maxwell branch {'on' if one['maxwell_branch'] else 'off'}:", "",
              f"| phase | one tissue us | share | batch {batch['tissues']} us | per tissue us | share |",
              "|---|---|---|---|---|---|"]
    for p in PHASES:
        lines.append(f"| {p} | {one['phases_us_per_substep'][p]} | {one['phases_share_of_whole'][p]} | "
                     f"{batch['phases_us_per_substep'][p]} | "
                     f"{_r(batch['phases_us_per_substep'][p] / batch['tissues'])} "
                     f"| {batch['phases_share_of_whole'][p]} |")
    for key, label in (("sum_of_phases_us", "sum of phases"), ("whole_us_per_substep", "whole simulate"),
                       ("remainder_us", "remainder (whole - sum)")):
        lines.append(f"| {label} | {one[key]} | {_r(one[key] / one['whole_us_per_substep'])} | {batch[key]} | "
                     f"{_r(batch[key] / batch['tissues'])} | {_r(batch[key] / batch['whole_us_per_substep'])} |")
    lines += ["", f"Volume barrier: {one['tets_watched']} / {batch['tets_watched']} tets watched (one tissue / batch), "
              f"{one['tets_below_barrier_threshold']} / {batch['tets_below_barrier_threshold']} flagged; the full "
              f"flag pass that remakes the watch list (where a node has left its budget) "
              f"{one['barrier_full_flag_pass_us']} / {batch['barrier_full_flag_pass_us']} us, not in the phases.",
              "", f"The batch's spring pass in float32 arithmetic (the same code on float32 copies of the state; the "
              f"physics stays float64): {batch['springs_float32']['us_per_substep']} us "
              f"({_r(batch['springs_float32']['us_per_substep'] / batch['tissues'])} per tissue) against "
              f"{batch['phases_us_per_substep']['springs']}, forces within "
              f"{batch['springs_float32']['force_rel_err']} of float64's (relative to the largest).",
              "", _divider_line(one, batch),
              "", "Per agent step, ms (share of the SB3 vector env's step):", "",
              "| n_envs | physics | task | finite + volume | Python rest | SB3 vec step | agent steps/s |",
              "|---|---|---|---|---|---|---|"]
    for r in report["agent_step"]["rows"]:
        t, sh = r["ms"], r["share_of_sb3_step"]
        lines.append(f"| {r['n_envs']} | {t['physics']} ({sh['physics']}) | {t['task']} ({sh['task']}) | "
                     f"{t['readouts_finite_volume']} ({sh['readouts_finite_volume']}) | {t['python_rest']} "
                     f"({sh['python_rest']}) | {t['sb3_vec_env_step']} | {r['agent_steps_per_s']} |")
    inf = report["agent_step"]["policy_inference"]
    lines += ["", f"Policy inference ({inf['policy']}, net {inf['net_arch']}, obs {inf['obs_dim']}, torch threads "
              f"{inf['torch_threads']}), ms: predict 1 obs {inf['predict_batch1_ms']}, predict {PROFILE_BATCH} obs "
              f"{inf[f'predict_batch{PROFILE_BATCH}_ms']}, forward 1 obs {inf['forward_batch1_ms']}, forward "
              f"{PROFILE_BATCH} obs {inf[f'forward_batch{PROFILE_BATCH}_ms']}"]
    if "training" in report:
        tr = report["training"]
        s = tr["seconds"]
        ext = tr["extrapolated_default_run"]
        lines += ["", f"Training ({tr['agent_steps']} agent steps, {tr['n_envs']} envs, {tr['n_epochs']} epochs): "
                  f"rollout {s['rollout']} s, PPO update {s['update']} s, one validation {s['one_validation']} s; "
                  f"extrapolated to the default {ext['total_timesteps']} steps: rollout {ext['hours']['rollout']} h, "
                  f"update {ext['hours']['update']} h, validation {ext['hours']['validation']} h (shares "
                  f"{ext['share']['rollout']} / {ext['share']['update']} / {ext['share']['validation']})"]
    return "\n".join(lines)


def profile_cli(quick: bool, out) -> int:
    """``msdgrasp bench profile``: print the JSON report (and the tables on stderr); ``out`` also writes it
    (JSON and markdown, atomically)."""
    from ..physics.config import atomic_write_text
    from .report import _out_paths

    def progress(msg: str) -> None:
        print(f"[bench] {msg}", file=sys.stderr, flush=True)

    report = run_profile(quick, progress=progress)
    table = markdown_table(report)
    if out is not None:
        json_path, md_path, _ = _out_paths(out)
        report["files"] = {"json": str(json_path), "markdown": str(md_path)}
        atomic_write_text(json_path, json.dumps(report, indent=2) + "\n")
        atomic_write_text(md_path, table + "\n")
    print(table, file=sys.stderr)
    print(json.dumps(report, indent=2))
    return 0
