"""The physics step on a CUDA GPU (numba's CUDA target): :func:`.integrator.simulate`'s records, one thread block
per tissue. Only the loops are written here: springs and tets (a thread each) write their forces to a scratch;
each node (a thread) *gathers* them in the order in which the CPU kernel scatters them, so its force is the same
sum term by term (no atomics), and advances; tets below the volume barrier's threshold are flagged in parallel
and thread 0 integrates the barrier on them and resolves the contacts in the CPU's order. What a spring, a tet, a
node and a contact compute is the CPU kernel's own functions (:func:`.forces.spring_body`,
:func:`.forces.implicit_volume_barrier`, the node bodies in :mod:`.integrator`, :mod:`.contact`) compiled for the GPU
from their source (:func:`device_twin`): one source, two backends.
The scratch's host-side layout is in :mod:`.device_layout`. Under ``NUMBA_ENABLE_CUDASIM=1`` the kernel runs in
numba's CUDA simulator (slow: tests only), with the CPU's arithmetic bit for bit; on a GPU, fused multiply-adds
round differently (~1e-16 relative per operation).
"""

from __future__ import annotations

import functools
import math
import types
from typing import NamedTuple

import numpy as np

from .device_layout import check_numba_cuda_numpy, installed_version

check_numba_cuda_numpy(installed_version("numba-cuda"), np.__version__)  # before numba.cuda compiles anything

from numba import config as _numba_config  # noqa: E402
from numba import cuda  # noqa: E402
from numba.core.dispatcher import Dispatcher  # noqa: E402

from . import contact as _contact  # noqa: E402
from . import forces as _forces  # noqa: E402
from . import integrator as _integrator  # noqa: E402
from .device_layout import FLOAT32_FIELDS, PRECISIONS, field_pairs, make_scratch, with_precision  # noqa: E402, F401
from .records import SimModel, SimReadout, SimState  # noqa: E402

#: threads per block (one block per tissue); the loops stride over springs, tets and nodes
THREADS_PER_BLOCK = 128
#: flagged tets a block lists in shared memory for the barrier (the coarse spleen flags 2 at rest, about 5 under a
#: grasp); with more, thread 0 scans every tet's flag instead, as the CPU does: the same impulses either way
FLAG_LIST = 64
#: registers per thread the physics kernel may use. Uncapped it takes so many that an SM holds 2 blocks (12.5 %
#: occupancy, measured), and a large batch waits on latency; capped at 64 it holds 8, and spills to the L1. On an
#: H100 the cap took the task step at 16,384 coarse spleens from 53,200 to 94,400 agent steps/s and a batch of 1
#: from 153 to 132 (docs/performance.md); 48, 96 and 128 were slower at scale. Spilling changes no arithmetic.
MAX_REGISTERS = 64


@functools.cache  # one twin per function: the kernel and every caller share it
def device_twin(cpu_function, **callees):
    """The GPU twin of a CPU kernel function: its Python source compiled by numba's CUDA target, with the
    numba functions it calls bound to their own twins (or to ``callees``, by name). One source, two targets:
    an edit of the CPU function changes both."""
    py = cpu_function.py_func
    calls = {name: device_twin(g) for name in py.__code__.co_names
             if isinstance(g := py.__globals__.get(name), Dispatcher) and name not in callees}
    bound = types.FunctionType(py.__code__, {**py.__globals__, **calls, **callees}, py.__name__, py.__defaults__,
                               py.__closure__)
    return cuda.jit(device=True)(bound)


# the kernel's per-element functions: the CPU kernel's own
_tet_edges = device_twin(_forces._tet_edges)  # (the task kernel's volume-ratio check, envs/cuda_core.py)
_spring_body = device_twin(_forces.spring_body)
_anchor_spring_force = device_twin(_integrator.anchor_spring_force)
_nodal_damping = device_twin(_integrator.nodal_damping)
_damping_factors = device_twin(_integrator.damping_factors)
_advance_node = device_twin(_integrator.advance_node)
_below_barrier = device_twin(_forces.below_barrier)
_implicit_volume_barrier = device_twin(_forces.implicit_volume_barrier)
_barrier_impulse = device_twin(_forces.barrier_impulse)
_implicit_spring_dashpots = device_twin(_forces.implicit_spring_dashpots)
_jaw_directions = device_twin(_contact.jaw_directions)
_clear_readouts = device_twin(_contact.clear_readouts)
_clear_contact_node = device_twin(_contact.clear_contact_node)
_force_loop = device_twin(_integrator._force_loop)
_advance_jaws = device_twin(_contact.advance_jaws)
_jaw_candidates = device_twin(_contact.jaw_candidates)
_resolve_jaw_contacts = device_twin(_contact.resolve_jaw_contacts)
_plate_contacts = device_twin(_contact.plate_contacts)


@cuda.jit(device=True)
def _sort_ints(a, k):
    """Insertion sort of a[:k] (a few flagged tets) in place."""
    for i in range(1, k):
        key = a[i]
        j = i - 1
        while j >= 0 and a[j] > key:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = key


def _kernel(fn):
    """``cuda.jit`` with :data:`MAX_REGISTERS` (the simulator takes no register cap: it runs Python)."""
    return cuda.jit(fn) if _numba_config.ENABLE_CUDASIM else cuda.jit(max_registers=MAX_REGISTERS)(fn)


@_kernel
def _simulate_kernel(m, s, out, w, n_steps):
    """Advance tissue blockIdx.x by ``n_steps`` outer steps (see the module docstring)."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0]:
        return
    tid, nth = cuda.threadIdx.x, cuda.blockDim.x
    x, v, n, ne = s.x, s.v, s.x.shape[1], m.edges.shape[0]
    nt = m.tets.shape[0] if m.kvol.shape[0] > 0 else 0
    dt, inv_sub = m.dt_outer / m.n_sub, 1.0 / m.n_sub
    decay = math.exp(-dt / m.tau)
    gain = m.tau / dt * (1.0 - decay)
    ks, ms = s.kscale[b], s.mscale[b]
    flags = (False, m.use_sls)  # (the dashpots act in their own implicit pass)
    res = cuda.local.array(6, np.float64)
    n_flagged = cuda.shared.array(1, np.int32)  # tets of this tissue below the barrier's threshold in this substep
    flag_list = cuda.shared.array(FLAG_LIST, np.int32)  # (their indices, in the order the threads found them)
    vr = 0.0  # (thread 0) the jaws' radial speed in this substep
    if tid == 0:
        _clear_readouts(b, out)
        _jaw_directions(s.g_axis[b], s.g_e1[b], w.u[b], w.tj[b])
    cuda.syncthreads()
    for step in range(n_steps):
        last_step = step == n_steps - 1
        if tid == 0 and m.jaw_active:
            _force_loop(s.g_force, s.g_vradius, b)
        for sub in range(m.n_sub):
            last_sub = last_step and sub == m.n_sub - 1
            sub_info = (dt, inv_sub if last_step else 0.0, last_sub, inv_sub)
            # ---- 1a. springs: the force on the first node (and the Maxwell state) to the scratch
            for e in range(tid, ne, nth):
                i, j = m.edges[e, 0], m.edges[e, 1]
                d = (x[b, j, 0] - x[b, i, 0], x[b, j, 1] - x[b, i, 1], x[b, j, 2] - x[b, i, 2])
                dash = (0.0, 0.0, 0.0, 0.0)
                kve = m.kv[e] if m.use_sls else m.k1[e]  # (kv may be empty without the branch, which ignores it;
                # fv, dl_prev and kv read as their own types, so float32 storage keeps float32 arithmetic)
                w.fe[b, e, 0], w.fe[b, e, 1], w.fe[b, e, 2], fve, dle = _spring_body(
                    d, (m.rest_length[e], m.k1[e], m.k2[e], m.dlc[e]), ks, dash,
                    (s.fv[b, e], s.dl_prev[b, e], kve, decay, gain), flags, 1.0, 1e-15)
                if m.use_sls:
                    s.fv[b, e], s.dl_prev[b, e] = fve, dle
            if tid == 0:
                n_flagged[0] = 0
            cuda.syncthreads()
            # ---- 2-3. nodes: gather in the CPU's order, then symplectic Euler with implicit damping, anchors
            for i in range(tid, n, nth):
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
                    a0, a1, a2 = _anchor_spring_force(xc, xr, ms, m.anchor_k[i], m.anchor_offset)
                    f0, f1, f2 = f0 + a0, f1 + a1, f2 + a2
                    w.fa[b, i, 0], w.fa[b, i, 1], w.fa[b, i, 2] = a0, a1, a2
                damp = _nodal_damping(xc, xr, m.b0[i], m.b1[i]) if m.b1[i] != 0.0 else m.b0[i]
                dinv, w.meff[b, i] = _damping_factors(mi, damp, dt)
                xn, vn = _advance_node(xc, (v[b, i, 0], v[b, i, 1], v[b, i, 2]), (f0, f1, f2), mi, dinv, dt)
                x[b, i, 0], x[b, i, 1], x[b, i, 2] = xn
                v[b, i, 0], v[b, i, 1], v[b, i, 2] = vn
            cuda.syncthreads()
            # ---- 3b. spring dashpots, implicit: thread 0 in the CPU's (edge) order
            if m.use_dashpot:
                if tid == 0:
                    for c in range(3):
                        w.dash_out[b, c] = 0.0
                    _implicit_spring_dashpots(x[b], v[b], w.meff[b], m.fixed, m.edges, m.cdash, ks, dt, w.dash_out[b])
                cuda.syncthreads()
            # ---- 4. volume barrier: tets flagged and listed in parallel; only where any is (as on the CPU), thread 0
            # sorts the list into the CPU's (tet) order and integrates the barrier on those tets (a scan over every
            # tet's flag, 810 dependent loads on the coarse spleen, cost as much as the rest of the substep)
            if nt > 0:
                for t in range(tid, nt, nth):
                    on = _below_barrier(x[b], m.tets, m.rest_volume, m.vol_threshold, t)
                    w.tet_on[b, t] = 1 if on else 0
                    if on:
                        slot = cuda.atomic.add(n_flagged, 0, 1)
                        if slot < FLAG_LIST:
                            flag_list[slot] = t
                cuda.syncthreads()
                if tid == 0 and n_flagged[0] > 0:
                    for c in range(3):
                        w.vol_out[b, c] = 0.0
                    k = n_flagged[0]
                    if k <= FLAG_LIST:
                        _sort_ints(flag_list, k)
                        for q in range(k):
                            _barrier_impulse(x[b], v[b], w.meff[b], (m.fixed, s.held[b]), m.tets, m.rest_volume,
                                             m.kvol, m.vol_threshold, ks, dt, flag_list[q], w.vol_out[b])
                    else:
                        _implicit_volume_barrier(x[b], v[b], w.meff[b], (m.fixed, s.held[b]), m.tets, m.rest_volume,
                                                 m.kvol, m.vol_threshold, ks, dt, w.tet_on[b], w.vol_out[b])
                cuda.syncthreads()
            # ---- 5. contacts: cleared and tested in parallel, resolved by thread 0 in the CPU's (surface) order
            for q in range(tid, m.surface_nodes.shape[0], nth):
                _clear_contact_node(b, m, out, s.held[b], last_sub, q)
            cuda.syncthreads()
            if tid == 0:
                if last_sub:
                    for i in range(n):
                        if m.fixed[i] or m.anchor_k[i] > 0.0:
                            for c in range(3):
                                out.anchor_out[b, c] += w.fa[b, i, c]
                    if m.use_dashpot:  # (after the nodes' share, in the CPU's order)
                        for c in range(3):
                            out.anchor_out[b, c] += w.dash_out[b, c]
                    if nt > 0 and n_flagged[0] > 0:
                        for c in range(3):
                            out.anchor_out[b, c] += w.vol_out[b, c]
                s.t[b] += dt
                _plate_contacts(b, x[b], v[b], w.meff[b], m, s, out, sub_info, res, s.held[b])
                if m.jaw_active:
                    vr = _advance_jaws(b, s, dt)
            cuda.syncthreads()
            if m.jaw_active:  # (a node's test reads that node only: the order of the tests does not matter)
                _jaw_candidates(b, x[b], m, s, (w.u[b], w.tj[b]), w.cand[b], tid, nth)
                cuda.syncthreads()
                if tid == 0:
                    _resolve_jaw_contacts(b, x[b], v[b], w.meff[b], m, s, out, (w.u[b], w.tj[b]), sub_info, res,
                                          (s.held[b], w.cand[b]), vr)
                cuda.syncthreads()


def to_device(record: NamedTuple) -> NamedTuple:
    """The record with each array copied to the GPU (scalars as they are)."""
    return type(record)(*[cuda.to_device(np.ascontiguousarray(a)) if isinstance(a, np.ndarray) else a for a in record])


class CudaBatch:
    """A batch of tissues resident on the GPU: state and readouts stay on the device between calls.

    Made from host records once; :meth:`step` only launches the kernel (one block of ``threads`` threads per
    tissue). ``precision="float32"`` stores the per-node, per-spring and per-tet arrays in float32
    (:data:`.device_layout.FLOAT32_FIELDS`). Only what a caller asks for crosses to the host (:meth:`download`,
    by field: e.g. ``jaw_out`` for the sensors, 108 bytes per tissue; into float64 host records) or to the
    device (:meth:`upload`: commands, resets). :meth:`arrays` hands the device arrays to a GPU consumer without
    a copy (``__cuda_array_interface__``: ``torch.as_tensor(batch.arrays()["x"], device="cuda")`` is a view).
    """

    def __init__(self, model: SimModel, state: SimState, out: SimReadout, threads: int = THREADS_PER_BLOCK,
                 precision: str = "float64") -> None:
        self.precision = precision
        self.model, self.state, self.out, self.scratch = (
            to_device(with_precision(r, precision)) for r in (model, state, out, make_scratch(model, state.x.shape[0])))
        self.threads = int(threads)

    def step(self, n_steps: int) -> None:
        """Advance every tissue by ``n_steps`` outer steps (:func:`.integrator.simulate` on the GPU)."""
        _simulate_kernel[self.state.x.shape[0], self.threads](self.model, self.state, self.out, self.scratch,
                                                              int(n_steps))

    def download(self, state: SimState | None = None, out: SimReadout | None = None,
                 fields: tuple[str, ...] | None = None) -> None:
        """Copy the device arrays of ``fields`` (default all) into the given host records, in place."""
        for dev, host in field_pairs((self.state, self.out), (state, out), fields):
            if dev.dtype == host.dtype:
                dev.copy_to_host(host)
            else:  # (a float32 array into a float64 record)
                host[...] = dev.copy_to_host()

    def upload(self, state: SimState | None = None, out: SimReadout | None = None,
               fields: tuple[str, ...] | None = None) -> None:
        """Copy host arrays of ``fields`` (default all) into the device arrays (no reallocation)."""
        for dev, host in field_pairs((self.state, self.out), (state, out), fields):
            dev.copy_to_device(np.ascontiguousarray(host, dtype=dev.dtype))

    def arrays(self) -> dict[str, object]:
        """The device arrays of the state and the readouts, by field name (no copy)."""
        return {name: getattr(rec, name) for rec in (self.state, self.out) for name in rec._fields
                if hasattr(getattr(rec, name), "copy_to_host")}
