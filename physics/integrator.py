"""Explicit time integration of a batch of MSD tissues with rigid jaws and plates, in one numba call.

Scheme (per substep of length dt, for each tissue b of the batch, all on the same mesh):

1. forces: nonlinear springs (+ Maxwell branches) + gravity + external nodal forces;
2. symplectic Euler with *implicit* nodal damping (the paper's Eq. 7, diagonal, so unconditionally
   stable): v <- (v + dt f/m) / (1 + dt (b0 + b1 |r - r0|)/m);  x <- x + dt v;
3. anchors (fixed nodes) are held at their rest positions; the optional spring dashpots act implicitly,
   spring by spring (:func:`.forces.implicit_spring_dashpots`);
4. the volume barrier of strongly compressed tets, integrated implicitly tet by tet
   (:func:`.forces.implicit_volume_barrier`): a force like the springs', so the contacts see it;
5. the jaws (and plates) advance; surface nodes that penetrate a face become contact nodes and are
   resolved with Coulomb stick/slip (:mod:`.contact`).

The outer physics step is ``dt_outer`` (1 ms by default, the 1 kHz of the haptics literature); it is
split into ``n_sub`` equal substeps chosen from the tissue's stability limit (see
:meth:`.tissue.TissueModel.critical_dt`). Readouts (forces) are averaged over the substeps of the
last outer step, i.e. what a 1 kHz force sensor would report.

State is plain arrays with the batch first: x (B,N,3), v (B,N,3), grasper pose (B,3), radius (B,), ...
Tissues of a batch differ by per-tissue stiffness and mass scale, friction, grasper pose and commands.

Vectorisation across tissues: a batch of LANE_MIN or more runs in blocks of up to LANE_BLOCK tissues (a
multiple of LANE_WIDTH each; the few left over run alone) copied into a tissue-innermost "lane" layout
(x[i, c, lane]) for the duration of the call. Springs, tets and the node update then loop over lanes
innermost, with unit stride and no branches, and LLVM emits SIMD code for them (7.0 us per tissue and
substep at 32 lanes against 10.2 us for one tissue alone on the bench's grasp). Contacts and the volume
barrier's impulses stay per tissue (few nodes, branchy). Every lane performs the one-tissue kernels'
floating-point operations in the same order, so a tissue's trajectory is bitwise the same in any batch
(tests/test_batching.py).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from .contact import (
    G_GAIN,
    G_PINCH,
    G_SETPOINT,
    G_VMAX,
    clear_contacts,
    clear_readouts,
    jaw_contacts,
    jaw_directions,
    plate_contacts,
)
from .forces import (
    barrier_impulse,
    displacement_spread,
    flag_watched,
    implicit_spring_dashpots,
    implicit_volume_barrier,
    implicit_volume_barrier_lanes,
    spring_body,
    spring_loop,
    spring_loop_lanes,
    watch_barrier,
)
from .jit import kernel
from .records import SimModel, SimReadout, SimState, Springs

if TYPE_CHECKING:
    from .device_layout import CudaScratch


#: lane blocks hold a multiple of this many tissues: LLVM vectorises the loops over lanes in chunks of 8 doubles
#: and runs a remainder scalar (measured per tissue and substep on the bench's grasp: 31 lanes 9.0 us, 32 lanes
#: 7.0 us, one tissue alone 10.2 us)
LANE_WIDTH = 8
#: batches of at least this many tissues compute springs and tets across tissues (SIMD lanes); smaller
#: ones, and the fewer than LANE_WIDTH tissues left over by the blocks, loop over tissues with the one-tissue
#: kernels. (LLVM guards the vectorised spring loop with a trip-count check: 16 lanes ran it scalar, 12.4 us per
#: tissue and substep against 7.4 at 24 lanes.)
LANE_MIN = 24
#: tissues advanced together in one lane block (bounds the block's state to a few MB of cache)
LANE_BLOCK = 64


@kernel
def lane_blocks(nb: int) -> np.ndarray:
    """(first tissue, tissues) of each block :func:`simulate` advances a batch of ``nb`` tissues in: blocks of
    LANE_MIN..LANE_BLOCK tissues, a multiple of LANE_WIDTH each and as equal as that allows, then the rest (fewer
    than LANE_WIDTH, or the whole batch below LANE_MIN) one tissue per block."""
    in_lanes = nb // LANE_WIDTH * LANE_WIDTH if nb >= LANE_MIN else 0
    units = in_lanes // LANE_WIDTH
    n_blocks = -(-in_lanes // LANE_BLOCK)
    out = np.empty((n_blocks + nb - in_lanes, 2), dtype=np.int64)
    lane0 = 0
    for k in range(n_blocks):
        nl = (units // n_blocks + (1 if k < units % n_blocks else 0)) * LANE_WIDTH
        out[k, 0] = lane0
        out[k, 1] = nl
        lane0 += nl
    for k in range(n_blocks, out.shape[0]):
        out[k, 0] = lane0
        out[k, 1] = 1
        lane0 += 1
    return out


def batch_lanes(nb: int) -> np.ndarray | None:
    """What :func:`simulate` takes as ``lanes`` for a batch of ``nb`` tissues: its lane blocks
    (:func:`lane_blocks`) from LANE_MIN tissues on, else None (every tissue alone)."""
    return lane_blocks(nb) if nb >= LANE_MIN else None


@kernel
def simulate(model: SimModel, state: SimState, out: SimReadout, n_steps: int, lanes: np.ndarray | None) -> None:
    """Advance every tissue of the batch by ``n_steps`` outer steps of ``model.dt_outer`` (``model.n_sub``
    substeps each). ``state`` is advanced in place, ``out`` holds the readouts of the last outer step.
    Tissues are independent.

    ``lanes``: :func:`batch_lanes` of the batch. With its blocks, the batch runs in blocks of up to LANE_BLOCK
    tissues stored tissue-innermost (lane layout, x[i, c, lane]): copied in at the start of the call and back at the
    end, so the per-substep loops over springs, tets and nodes run across tissues with SIMD; a block of one runs
    alone. With None every tissue runs alone, and numba compiles no lane code (it prunes the branches on
    ``lanes is None`` from the types: a first single-env run compiles only what it runs).
    """
    x, v, fv, dl_prev = state.x, state.v, state.fv, state.dl_prev
    nb = x.shape[0]
    n = x.shape[1]
    ne = fv.shape[1]
    if lanes is None:
        for b in range(nb):
            _advance_alone(b, model, state, out, n_steps)
        return
    for k in range(lanes.shape[0]):
        lane0 = lanes[k, 0]
        nl = lanes[k, 1]
        if nl == 1:
            _advance_alone(lane0, model, state, out, n_steps)
            continue
        xl = np.empty((n, 3, nl), dtype=x.dtype)
        vl = np.empty((n, 3, nl), dtype=x.dtype)
        fvl = np.empty((ne, nl), dtype=fv.dtype)
        dll = np.empty((ne, nl), dtype=fv.dtype)
        _to_lanes(x, v, fv, dl_prev, lane0, xl, vl, fvl, dll, True)
        _advance_block(lane0, xl, vl, fvl, dll, model, state, out, n_steps, lanes)
        _to_lanes(x, v, fv, dl_prev, lane0, xl, vl, fvl, dll, False)


@kernel
def _advance_alone(b, model, state, out, n_steps):
    """:func:`_advance_block` for tissue b alone: its (N,3) state as an (N,3,1) block (the same memory)."""
    n, ne = state.x.shape[1], state.fv.shape[1]
    _advance_block(b, state.x[b].reshape((n, 3, 1)), state.v[b].reshape((n, 3, 1)), state.fv[b].reshape((ne, 1)),
                   state.dl_prev[b].reshape((ne, 1)), model, state, out, n_steps, None)


@kernel
def _to_lanes(x, v, fv, dl_prev, lane0, xl, vl, fvl, dll, forward):
    """Copy tissues lane0.. of the batch state into the lane block (forward) or back. Explicit loops:
    numba's slice assignment would compile its shape-mismatch error formatting (~5 s of first-call compile)."""
    n = xl.shape[0]
    for lane in range(xl.shape[2]):
        b = lane0 + lane
        for i in range(n):
            for c in range(3):
                if forward:
                    xl[i, c, lane] = x[b, i, c]
                    vl[i, c, lane] = v[b, i, c]
                else:
                    x[b, i, c] = xl[i, c, lane]
                    v[b, i, c] = vl[i, c, lane]
        for e in range(fvl.shape[0]):
            if forward:
                fvl[e, lane] = fv[b, e]
                dll[e, lane] = dl_prev[b, e]
            else:
                fv[b, e] = fvl[e, lane]
                dl_prev[b, e] = dll[e, lane]


@kernel
def _advance_block(lane0, x, v, fv, dl_prev, model, state, out, n_steps, lanes):
    """:func:`simulate` for the L tissues of one lane block: x, v (N,3,L) and fv, dl_prev (E,L) are the
    block's state in lanes (lane l is tissue lane0 + l); the rest of the state is read from ``state``.
    ``lanes`` None: a block of one tissue (numba compiles this call without the lane code). Each substep runs
    the phases of the module docstring."""
    m = model
    n_sub = m.n_sub
    n = x.shape[0]
    nl = x.shape[2]
    dt = m.dt_outer / n_sub
    f = np.empty((n, 3, nl), dtype=x.dtype)
    # one tissue: plain C-contiguous (N,3) views, the layout the one-tissue kernels are fastest on (in a lane
    # block they are unused; the reshape there only gives numba one type for both branches)
    if lanes is None:
        x_one = x.reshape((n, 3))
        v_one = v.reshape((n, 3))
        f_one = f.reshape((n, 3))
    else:
        x_one = x.reshape((n, 3 * nl))
        v_one = v.reshape((n, 3 * nl))
        f_one = f.reshape((n, 3 * nl))
    ks = np.ascontiguousarray(state.kscale[lane0 : lane0 + nl])
    ms = np.ascontiguousarray(state.mscale[lane0 : lane0 + nl])
    ne = fv.shape[0]
    # the springs with kv of E entries: the one-tissue loop reads it unconditionally (zeros without the branch);
    # their dashpots act in their own implicit pass after the node update, not in the force loop
    springs = Springs(m.edges, m.rest_length, m.k1, m.k2, m.dlc, m.cdash,
                      m.kv if m.kv.shape[0] == ne else np.zeros(ne, dtype=m.kv.dtype), False, m.use_sls)
    ks_springs, units, tmp, spring_scratch = _spring_setup(m, x, ks, dt, ne)
    # effective mass m + dt b of each node: the implicit nodal damper acts on the *constrained* velocity,
    # so a contact impulse must also overcome it (else reaction forces read low by 1 + dt b/m)
    meff = np.empty((n, nl))
    damp_inv = np.empty((n, nl))
    _constant_damping(m.mass, m.b0, m.b1, ms, dt, meff, damp_inv)
    node_work = (meff, damp_inv, np.empty((3, nl)))  # (and the anchor spring force of one node)
    watching = _barrier_work(m.tets.shape[0], n, nl)
    n_watch = np.int64(-1)  # (no watch list yet: the first substep makes one; typed, not a literal: one compile)
    anchor_vol = np.zeros(3)  # the anchors' force against the spring dashpots in one tissue's substep, N
    anchor_lanes = np.zeros((nl, 3))  # per tissue: the anchors' force against the volume barrier in a substep, N
    held = state.held[lane0 : lane0 + nl]  # per tissue: the jaw (k + 1) or plate (-(p + 1)) holding a node
    u = np.empty((nl, 3, 3))  # per tissue: jaw outward directions
    tj = np.empty((nl, 3, 3))  # per tissue: jaw lateral directions
    res = np.empty(6)
    cand = np.empty(0, dtype=np.int8)  # (no separate test pass on the CPU: jaw_contacts tests where it resolves)
    f0 = _start_block(lane0, x, m, state, out, ms, (u, tj))
    f_flat = f.reshape(n * 3 * nl)
    f0_flat = f0.reshape(n * 3 * nl)
    inv_sub = 1.0 / n_sub
    for step in range(n_steps):
        last_step = step == n_steps - 1
        if m.jaw_active:
            for lane in range(nl):
                pinch_force_loop(state.g_force, state.g_vradius, lane0 + lane)
        for sub in range(n_sub):
            last_sub = last_step and sub == n_sub - 1
            sub_info = (dt, inv_sub if last_step else 0.0, last_sub, inv_sub)  # what the contacts' readouts need
            acc = (out.anchor_out, lane0, last_sub)  # where (and whether) the anchors' readout adds up
            # ---- 1. forces (in the loop itself: as a function, even inlined, they cost 1 % of a one-tissue substep)
            for k in range(f_flat.shape[0]):  # a flat loop: numba's f[:] = f0 on 3-D arrays is slow
                f_flat[k] = f0_flat[k]
            if lanes is None:
                spring_loop(x_one, v_one, springs, ks_springs[0], units[2], units[3], fv.reshape(ne),
                            dl_prev.reshape(ne), f_one, spring_scratch, units[0], units[1])
            else:
                spring_loop_lanes(x, v, springs, ks_springs, units[2], units[3], fv, dl_prev, f, tmp, units[0],
                                  units[1])
            # ---- 2-3. symplectic Euler, implicit nodal damping, anchors
            if lanes is None:  # a literal bound: once LLVM inlines the call, the lane loops vanish for one tissue
                _update_nodes(m, x, v, f, node_work, ms, 1, lane0, last_sub, dt, out.anchor_out)
            else:
                _update_nodes(m, x, v, f, node_work, ms, nl, lane0, last_sub, dt, out.anchor_out)
            # ---- 3b. the spring dashpots, implicit
            if m.use_dashpot:
                _dashpot_lanes(x, v, (x_one, v_one), meff, m, ks, dt, anchor_vol, acc, lanes)
            # ---- 4. the volume barrier, implicit, on the tets below its threshold (flagged across lanes)
            if m.kvol.shape[0] > 0:
                n_watch = _volume_barrier(x, v, x_one, (meff, held), m, ks, dt, (watching, n_watch), anchor_lanes, acc)
            # ---- 5. contacts, one tissue at a time (branchy, few nodes; in the loop itself: as a function, even
            # inlined, they cost 4 % of a one-tissue substep)
            for lane in range(nl):
                b = lane0 + lane
                state.t[b] += dt
                # (N,3) views of one lane, strided in a lane block: one compiled contact code for both paths
                xb = x[:, :, lane]
                vb = v[:, :, lane]
                mb = meff[:, lane]
                hb = held[lane]
                clear_contacts(b, m, out, hb, last_sub)
                plate_contacts(b, xb, vb, mb, m, state, out, sub_info, res, hb)
                if m.jaw_active:
                    jaw_contacts(b, xb, vb, mb, m, state, out, (u[lane], tj[lane]), sub_info, res, (hb, cand))


@kernel
def _spring_setup(m, x, ks, dt, ne):
    """The spring loops' work for a block of the model's E = ``ne`` springs: (ks (L,), units (4,), tmp (3,L), scratch
    (9,E) or (9,0)), in the state's type (a float32 state computes its springs in float32; float64: as they are).
    units: 1, 1e-15, e^(-dt/tau), (tau/dt)(1 - e^(-dt/tau))."""
    nl = x.shape[2]
    units = np.empty(4, dtype=x.dtype)
    units[0] = 1.0
    units[1] = 1e-15
    units[2], units[3] = maxwell_factors(dt, m.tau)
    ks_springs = np.empty(nl, dtype=x.dtype)
    for lane in range(nl):
        ks_springs[lane] = ks[lane]
    tmp = np.empty((3, nl), dtype=x.dtype)
    return ks_springs, units, tmp, np.zeros((9, 0 if nl > 1 else ne), dtype=x.dtype)


@kernel
def _barrier_work(nt, n, nl):
    """The volume barrier's flags for ``nt`` tets and ``nl`` tissues of ``n`` nodes: (flags (T,L) int8: below the
    threshold; n_flagged (L,): how many per tissue; the watch list (T,) of :func:`.forces.watch_barrier`: the tets a
    full pass found near the threshold; x_ref (N,3L), the positions it saw, m; lohi (3,3L) scratch)."""
    flags = np.zeros((nt, nl), dtype=np.int8)
    n_flagged = np.zeros(nl, dtype=np.int64)
    watch = np.empty(nt, dtype=np.int64)
    return flags, n_flagged, watch, np.empty((n, 3 * nl)), np.empty((3, 3 * nl))


@kernel
def _start_block(lane0, x, m, state, out, ms, dirs):
    """At the start of a call: the block's readouts cleared, its jaws' directions (u, tj) set, and its constant
    nodal load returned: gravity + external forces f0 (N,3,L), N (they do not change during the call)."""
    n, nl = x.shape[0], x.shape[2]
    u, tj = dirs
    f0 = np.empty((n, 3, nl), dtype=x.dtype)
    for lane in range(nl):
        b = lane0 + lane
        for i in range(n):
            for c in range(3):
                f0[i, c, lane] = m.mass[i] * ms[lane] * m.gravity[c] + state.f_ext[b, i, c]
    for lane in range(nl):
        b = lane0 + lane
        clear_readouts(b, out)
        jaw_directions(state.g_axis[b], state.g_e1[b], u[lane], tj[lane])
    return f0


@kernel
def dashpot_pass(x: np.ndarray, v: np.ndarray, meff: np.ndarray, fixed: np.ndarray, dashpots: tuple, ks: float,
                 dt: float, anchor: np.ndarray) -> None:
    """Step 3b for one tissue: the spring dashpots, implicit (:func:`.forces.implicit_spring_dashpots`) on x, v
    (N,3) with effective masses meff (N,), kg, anchors ``fixed``, ``dashpots`` (edges, cdash N s/m), stiffness scale
    ks, substep dt, s; ``anchor`` (3,) is set to the force the anchors supply against them, N. The GPU kernel's pass
    too. (Arrays, not the model record of several dozen: it runs per tissue and substep.)"""
    for c in range(3):
        anchor[c] = 0.0
    implicit_spring_dashpots(x, v, meff, fixed, dashpots[0], dashpots[1], ks, dt, anchor)


@kernel
def _dashpot_lanes(x, v, one, meff, m, ks, dt, anchor_vol, acc, lanes):
    """:func:`dashpot_pass` for each tissue of the block (``one``: the (N,3) views of x, v for a block of one,
    ``lanes`` None; a function of its own, called once per substep, so that numba prunes the other layout's
    branch from ``lanes``' type); in the last substep the anchors' force adds to the readout ``acc`` (anchor_out,
    lane0, last_sub)."""
    anchor_out, lane0, last_sub = acc
    for lane in range(x.shape[2]):
        if lanes is None:
            dashpot_pass(one[0], one[1], meff[:, 0], m.fixed, (m.edges, m.cdash), ks[0], dt, anchor_vol)
        else:
            dashpot_pass(x[:, :, lane], v[:, :, lane], meff[:, lane], m.fixed, (m.edges, m.cdash), ks[lane], dt,
                         anchor_vol)
        if last_sub:
            for c in range(3):
                anchor_out[lane0 + lane, c] += anchor_vol[c]


@kernel(inline="always")
def _volume_barrier(x, v, x_one, nodes, m, ks, dt, watching, anchor_lanes, acc):
    """Step 4: the volume barrier, implicit, on the tets below its threshold, flagged across lanes by a full pass
    where the nodes have left the watch list's budget m.watch_delta (or are not finite), else on the watched tets
    only. ``nodes``: (meff (N,L) kg, held); ``watching``: (:func:`_barrier_work`'s, the watch list's length or -1);
    the anchors' force (N) adds to the readout ``acc`` in the last substep. Returns the watch list's length."""
    meff, held = nodes
    (flags, n_flagged, watch, x_ref, lohi), n_watch = watching
    anchor_out, lane0, last_sub = acc
    nl = x.shape[2]
    if n_watch < 0 or not displacement_spread(x_one, x_ref, nl, lohi) <= m.watch_delta:
        n_watch = watch_barrier(x, m.tets, m.rest_volume, m.vol_threshold, m.watch_delta, flags, n_flagged, watch)
        for k in range(x_ref.shape[0]):
            for c in range(x_ref.shape[1]):
                x_ref[k, c] = x_one[k, c]
    else:
        flag_watched(x, m.tets, m.rest_volume, m.vol_threshold, watch, n_watch, flags, n_flagged)
    anchor_lanes[:] = 0.0
    if nl > 1 or n_flagged[0] > 0:  # (one tissue: its (N,3,1) block)
        implicit_volume_barrier_lanes(x, v, meff, (m.fixed, held), m.tets, m.rest_volume, m.kvol, m.vol_threshold,
                                      ks, dt, (flags, watch, n_watch), anchor_lanes)
    if last_sub:
        for lane in range(nl):
            if n_flagged[lane] > 0:
                for c in range(3):
                    anchor_out[lane0 + lane, c] += anchor_lanes[lane, c]
    return n_watch


@kernel(inline="always")
def maxwell_factors(dt: float, tau: float) -> tuple[float, float]:
    """(e^(-dt/tau), (tau/dt)(1 - e^(-dt/tau))): the Maxwell branches' decay and gain over a substep dt, s, of
    relaxation time tau, s (:func:`.forces.spring_body`)."""
    decay = math.exp(-dt / tau)
    return decay, tau / dt * (1.0 - decay)


@kernel
def pinch_force_loop(g_force: np.ndarray, g_vradius: np.ndarray, b: int) -> None:
    """The jaw motor's 1 kHz pinch-force loop of tissue b, run once per outer step: closing speed
    proportional to the force error of the last step, limited to the motor's speed (P control of the
    radius rate = integral action on the radius, so a steady set-point is held without offset).
    Then it clears the pinch accumulator that :func:`.contact.jaw_contacts` fills during the step."""
    if g_force[b, G_SETPOINT] >= 0.0:
        vmax = g_force[b, G_VMAX]
        vc = g_force[b, G_GAIN] * (g_force[b, G_SETPOINT] - g_force[b, G_PINCH])
        g_vradius[b] = -min(max(vc, -vmax), vmax)
    g_force[b, G_PINCH] = 0.0


# The node update's bodies: the arithmetic every node loop (one tissue, lanes, the GPU kernel) runs per node.
# xc, vc, fc: the node's position (m), velocity (m/s), force (N) as 3-tuples; m: its mass x mass scale, kg.


@kernel(inline="always")
def anchor_spring_force(xc, xr, ms, ka, offset):
    """Force (N, 3-tuple) of a compliant anchor of stiffness ka (N/m) on a node at xc whose rest position is
    xr: a spring to xr + ms offset (its preload scales with the mass scale ms; offset (3,) m)."""
    return (-ka * (xc[0] - xr[0] - ms * offset[0]), -ka * (xc[1] - xr[1] - ms * offset[1]),
            -ka * (xc[2] - xr[2] - ms * offset[2]))


@kernel(inline="always")
def nodal_damping(xc, xr, b0, b1):
    """Eq. 7's damping coefficient b0 + b1 |x - x_rest| (N s/m) of a node at xc with rest position xr."""
    dx = xc[0] - xr[0]
    dy = xc[1] - xr[1]
    dz = xc[2] - xr[2]
    return b0 + b1 * math.sqrt(dx * dx + dy * dy + dz * dz)


@kernel(inline="always")
def damping_factors(m, damp, dt):
    """(1 / (1 + dt b / m), m + dt b): implicit damping's velocity factor and the effective mass (kg) that
    the contacts use (the damper acts on the constrained velocity too)."""
    return 1.0 / (1.0 + dt * damp / m), m + dt * damp


@kernel(inline="always")
def advance_node(xc, vc, fc, m, inv, dt):
    """Symplectic Euler with implicit damping (velocity factor ``inv``): the node's new (x, v) 3-tuples."""
    v0 = (vc[0] + dt * fc[0] / m) * inv
    v1 = (vc[1] + dt * fc[1] / m) * inv
    v2 = (vc[2] + dt * fc[2] / m) * inv
    return (xc[0] + dt * v0, xc[1] + dt * v1, xc[2] + dt * v2), (v0, v1, v2)


@kernel
def _constant_damping(mass, b0, b1, ms, dt, meff, damp_inv):
    """meff = m + dt b0 and damp_inv = 1 / (1 + dt b0 / m) of the nodes whose damping does not vary (b1 = 0)."""
    for i in range(mass.shape[0]):
        if b1[i] == 0.0:
            for lane in range(ms.shape[0]):
                damp_inv[i, lane], meff[i, lane] = damping_factors(mass[i] * ms[lane], b0[i], dt)


@kernel
def _update_nodes(model, x, v, f, work, ms, nl, lane0, last_sub, dt, anchor_out):
    """Symplectic Euler with implicit nodal damping for lanes 0..nl-1; anchors held or sprung (steps 2-3).

    work (meff, damp_inv, fa): meff and damp_inv (N,L) are m + dt b and 1 / (1 + dt b / m); for nodes with
    b1 = 0 they are constant and filled by :func:`_constant_damping`, which saves a square root and two
    divisions per node and substep; fa (3,L) scratch.
    """
    meff, damp_inv, fa = work
    fixed, anchor_k, off, x_rest, mass, b0, b1 = model.fixed, model.anchor_k, model.anchor_offset, model.x_rest, \
        model.mass, model.b0, model.b1
    n = x.shape[0]
    for i in range(n):
        if fixed[i]:
            for lane in range(nl):
                if last_sub:
                    anchor_out[lane0 + lane, 0] -= f[i, 0, lane]
                    anchor_out[lane0 + lane, 1] -= f[i, 1, lane]
                    anchor_out[lane0 + lane, 2] -= f[i, 2, lane]
                v[i, 0, lane] = 0.0
                v[i, 1, lane] = 0.0
                v[i, 2, lane] = 0.0
            continue
        xr = (x_rest[i, 0], x_rest[i, 1], x_rest[i, 2])
        ka = anchor_k[i]
        if ka > 0.0:  # compliant anchor: a preloaded spring (its preload scales with the mass)
            for lane in range(nl):
                fa[0, lane], fa[1, lane], fa[2, lane] = anchor_spring_force(
                    (x[i, 0, lane], x[i, 1, lane], x[i, 2, lane]), xr, ms[lane], ka, off)
                f[i, 0, lane] += fa[0, lane]
                f[i, 1, lane] += fa[1, lane]
                f[i, 2, lane] += fa[2, lane]
            if last_sub:
                for lane in range(nl):
                    anchor_out[lane0 + lane, 0] += fa[0, lane]
                    anchor_out[lane0 + lane, 1] += fa[1, lane]
                    anchor_out[lane0 + lane, 2] += fa[2, lane]
        mi = mass[i]
        if b1[i] != 0.0:  # displacement-dependent damping (Eq. 7); else damp_inv, meff hold for the call
            bi0 = b0[i]
            bi1 = b1[i]
            for lane in range(nl):
                damp = nodal_damping((x[i, 0, lane], x[i, 1, lane], x[i, 2, lane]), xr, bi0, bi1)
                damp_inv[i, lane], meff[i, lane] = damping_factors(mi * ms[lane], damp, dt)
        for lane in range(nl):
            xn, vn = advance_node((x[i, 0, lane], x[i, 1, lane], x[i, 2, lane]),
                                  (v[i, 0, lane], v[i, 1, lane], v[i, 2, lane]),
                                  (f[i, 0, lane], f[i, 1, lane], f[i, 2, lane]), mi * ms[lane], damp_inv[i, lane], dt)
            v[i, 0, lane], v[i, 1, lane], v[i, 2, lane] = vn
            x[i, 0, lane], x[i, 1, lane], x[i, 2, lane] = xn


# The GPU kernel's loops over springs and nodes (:mod:`.cuda_step`: a thread block per tissue b, a thread per spring
# or node: first = the thread, stride = the block's threads), written as CPU functions so that the CPU runs and
# tests them too. w is the kernel's scratch (:func:`.device_layout.make_scratch`).


@kernel
def springs_to_scratch(m: SimModel, s: SimState, w: CudaScratch, b: int, ks: float, maxwell: tuple[float, float],
                       first: int, stride: int) -> None:
    """Step 1 without the scatter, for springs first, first + stride, ... of tissue b (stiffness scale ks; maxwell:
    :func:`maxwell_factors`): each spring's force on its first node to w.fe, N, and its Maxwell state advanced."""
    x, flags = s.x, (False, m.use_sls)  # (the dashpots act in their own implicit pass)
    for e in range(first, m.edges.shape[0], stride):
        i, j = m.edges[e, 0], m.edges[e, 1]
        d = (x[b, j, 0] - x[b, i, 0], x[b, j, 1] - x[b, i, 1], x[b, j, 2] - x[b, i, 2])
        kve = m.kv[e] if m.use_sls else m.k1[e]  # (kv may be empty without the branch, which ignores it;
        # fv, dl_prev and kv read as their own types, so float32 storage keeps float32 arithmetic)
        w.fe[b, e, 0], w.fe[b, e, 1], w.fe[b, e, 2], fve, dle = spring_body(
            d, (m.rest_length[e], m.k1[e], m.k2[e], m.dlc[e]), ks, (0.0, 0.0, 0.0, 0.0),
            (s.fv[b, e], s.dl_prev[b, e], kve, maxwell[0], maxwell[1]), flags, 1.0, 1e-15)
        if m.use_sls:
            s.fv[b, e], s.dl_prev[b, e] = fve, dle


@kernel
def gather_and_advance_nodes(m: SimModel, s: SimState, w: CudaScratch, b: int, ms: float, dt: float, first: int,
                             stride: int) -> None:
    """Steps 2-3 for nodes first, first + stride, ... of tissue b (mass scale ms): gravity, the external load and
    the springs' forces from w.fe gathered in the order in which :func:`.forces.spring_loop` scatters them (the same
    sum, term by term), then symplectic Euler with implicit damping. An anchored node is held (its anchor's force to
    w.fa, N), a sprung one pulled (likewise); the effective masses to w.meff, kg."""
    x, v = s.x, s.v
    for i in range(first, x.shape[1], stride):
        mi = m.mass[i] * ms
        f0 = mi * m.gravity[0] + s.f_ext[b, i, 0]  # (mass x scale) x g, as the CPU groups it
        f1 = mi * m.gravity[1] + s.f_ext[b, i, 1]
        f2 = mi * m.gravity[2] + s.f_ext[b, i, 2]
        for p in range(w.edge_ptr[i], w.edge_ptr[i + 1]):
            e, sg = w.edge_idx[p], w.edge_sign[p]  # (f + (-1 x g) is f - g, bit for bit)
            f0, f1, f2 = f0 + sg * w.fe[b, e, 0], f1 + sg * w.fe[b, e, 1], f2 + sg * w.fe[b, e, 2]
        if m.fixed[i]:  # the anchor holds the node against its whole force
            w.fa[b, i, 0], w.fa[b, i, 1], w.fa[b, i, 2] = -f0, -f1, -f2
            v[b, i, 0], v[b, i, 1], v[b, i, 2] = 0.0, 0.0, 0.0
            continue
        xc = (x[b, i, 0], x[b, i, 1], x[b, i, 2])
        xr = (m.x_rest[i, 0], m.x_rest[i, 1], m.x_rest[i, 2])
        if m.anchor_k[i] > 0.0:
            a0, a1, a2 = anchor_spring_force(xc, xr, ms, m.anchor_k[i], m.anchor_offset)
            f0, f1, f2 = f0 + a0, f1 + a1, f2 + a2
            w.fa[b, i, 0], w.fa[b, i, 1], w.fa[b, i, 2] = a0, a1, a2
        damp = nodal_damping(xc, xr, m.b0[i], m.b1[i]) if m.b1[i] != 0.0 else m.b0[i]
        dinv, w.meff[b, i] = damping_factors(mi, damp, dt)
        xn, vn = advance_node(xc, (v[b, i, 0], v[b, i, 1], v[b, i, 2]), (f0, f1, f2), mi, dinv, dt)
        x[b, i, 0], x[b, i, 1], x[b, i, 2] = xn
        v[b, i, 0], v[b, i, 1], v[b, i, 2] = vn


@kernel
def listed_volume_barrier(m: SimModel, s: SimState, w: CudaScratch, b: int, ks: float, dt: float,
                          flag_list: np.ndarray, k: int) -> None:
    """Step 4's impulses on tissue b's ``k`` flagged tets, listed in ``flag_list`` in any order (sorted into tet order
    here, in place) or, where more were flagged than the list holds, on every tet flagged in w.tet_on: the impulses
    of :func:`.forces.implicit_volume_barrier` either way (stiffness scale ks, substep dt, s); the anchors' force to
    w.vol_out, N."""
    x, v, meff, pins = s.x[b], s.v[b], w.meff[b], (m.fixed, s.held[b])
    for c in range(3):
        w.vol_out[b, c] = 0.0
    if k > flag_list.shape[0]:
        implicit_volume_barrier(x, v, meff, pins, m.tets, m.rest_volume, m.kvol, m.vol_threshold, ks, dt, w.tet_on[b],
                                w.vol_out[b])
        return
    for q in range(1, k):  # insertion sort: a few tets
        t = flag_list[q]
        j = q - 1
        while j >= 0 and flag_list[j] > t:
            flag_list[j + 1] = flag_list[j]
            j -= 1
        flag_list[j + 1] = t
    for q in range(k):
        barrier_impulse(x, v, meff, pins, m.tets, m.rest_volume, m.kvol, m.vol_threshold, ks, dt, flag_list[q],
                        w.vol_out[b])


@kernel
def anchor_readout(m: SimModel, out: SimReadout, w: CudaScratch, b: int, flagged: int) -> None:
    """The anchors' forces of tissue b's substep into its readout out.anchor_out, N, in the CPU's order: against the
    nodes (w.fa), the spring dashpots (w.dash_out) and, where ``flagged`` tets were, the volume barrier (w.vol_out)."""
    for i in range(m.fixed.shape[0]):
        if m.fixed[i] or m.anchor_k[i] > 0.0:
            for c in range(3):
                out.anchor_out[b, c] += w.fa[b, i, c]
    if m.use_dashpot:  # (after the nodes' share, as on the CPU)
        for c in range(3):
            out.anchor_out[b, c] += w.dash_out[b, c]
    if flagged > 0:
        for c in range(3):
            out.anchor_out[b, c] += w.vol_out[b, c]


@kernel
def all_finite(x: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """out[b] = False where tissue b has a non-finite position or velocity (blow-up detection)."""
    for b in range(x.shape[0]):
        ok = True
        for i in range(x.shape[1]):
            for c in range(3):
                if not (math.isfinite(x[b, i, c]) and math.isfinite(v[b, i, c])):
                    ok = False
                    break
            if not ok:
                break
        out[b] = ok
