"""The physics step on a CUDA GPU (numba's CUDA target): :func:`.integrator.simulate`'s records, one thread block
per tissue, each substep's phases a device function, the threads meeting between them. Springs (a thread each)
write their forces to a scratch; each node (a thread) *gathers* them in the order in which the CPU kernel scatters
them, so its force is the same sum term by term (no atomics), and advances; tets below the volume barrier's
threshold are flagged in parallel and thread 0 integrates the barrier on them and resolves the contacts in the CPU's
order. Written here is which thread does what and where the threads meet; the loops over springs and nodes, and
what a spring, a tet, a node and a contact compute, are the CPU kernel's own functions (:mod:`.integrator`,
:mod:`.forces`, :mod:`.contact`), compiled for the GPU from their source (:func:`device_twin`): one source, two
backends.
The scratch's host-side layout is in :mod:`.device_layout`. Under ``NUMBA_ENABLE_CUDASIM=1`` the kernel runs in
numba's CUDA simulator (slow: tests only), with the CPU's arithmetic bit for bit; on a GPU, fused multiply-adds
round differently (~1e-16 relative per operation).
"""

from __future__ import annotations

import functools
import types
from typing import NamedTuple

import numpy as np

from .device_layout import check_numba_cuda_numpy, installed_version

check_numba_cuda_numpy(installed_version("numba-cuda"), np.__version__)  # before numba.cuda compiles anything

from numba import config as _numba_config  # noqa: E402
from numba import cuda  # noqa: E402
from numba.core.registry import CPUDispatcher  # noqa: E402

from . import forces as _forces  # noqa: E402
from .contact import (advance_jaws, clear_contact_node, clear_readouts, jaw_candidates, jaw_directions,  # noqa: E402
                      plate_contacts, resolve_jaw_contacts)
from .device_layout import FLOAT32_FIELDS, PRECISIONS, field_pairs, make_scratch, with_precision  # noqa: E402, F401
from .forces import below_barrier  # noqa: E402
from .integrator import (anchor_readout, dashpot_pass, gather_and_advance_nodes, listed_volume_barrier,  # noqa: E402
                         maxwell_factors, pinch_force_loop, springs_to_scratch)
from .records import SimModel, SimReadout, SimState  # noqa: E402

#: threads per block (one block per tissue); the loops stride over springs, tets and nodes
THREADS_PER_BLOCK = 128
#: flagged tets a block lists in shared memory for the barrier (the coarse spleen flags 2 at rest, about 5 under a
#: grasp); with more, thread 0 scans every tet's flag instead, as the CPU does: the same impulses either way
FLAG_LIST = 64
#: registers per thread the physics kernel may use. Uncapped it takes so many that an SM holds 2 blocks (12.5 %
#: occupancy, measured), and a large batch waits on latency; capped at 64 it holds 8, and spills to the L1. On one
#: data-centre GPU the cap took the task step at 16,384 coarse spleens from 53,200 to 94,400 agent steps/s and a
#: batch of 1 from 153 to 132 (msdgrasp bench gpu); 48, 96 and 128 were slower at scale. Spilling changes no arithmetic.
MAX_REGISTERS = 64


def _bound(py, callees: dict):
    """``py`` with the numba CPU functions it calls bound to their GPU twins (or to ``callees``, by name). Its
    globals are a copy: what it calls must be defined before it is bound."""
    calls = {name: device_twin(g) for name in py.__code__.co_names
             if isinstance(g := py.__globals__.get(name), CPUDispatcher) and name not in callees}
    return types.FunctionType(py.__code__, {**py.__globals__, **calls, **callees}, py.__name__, py.__defaults__,
                              py.__closure__)


@functools.cache  # one twin per function: the kernel and every caller share it
def device_twin(cpu_function, **callees):
    """The GPU twin of a CPU kernel function: its Python source compiled by numba's CUDA target, with the
    numba functions it calls bound to their own twins (or to ``callees``, by name). One source, two targets:
    an edit of the CPU function changes both."""
    return cuda.jit(device=True)(_bound(cpu_function.py_func, callees))


def _device(fn):
    """A device function of the GPU kernel alone; the CPU kernel's functions it calls run as their twins."""
    return cuda.jit(device=True)(_bound(fn, {}))


def _kernel(fn):
    """``cuda.jit`` with :data:`MAX_REGISTERS` (the simulator takes no register cap: it runs Python), the CPU
    kernel's functions it calls bound to their twins."""
    fn = _bound(fn, {})
    return cuda.jit(fn) if _numba_config.ENABLE_CUDASIM else cuda.jit(max_registers=MAX_REGISTERS)(fn)


tet_edges = device_twin(_forces._tet_edges)  # (the task kernel's volume-ratio check, envs/cuda_core.py)


@_device
def _barrier(m, s, w, b, ks, dt, n_flagged, flag_list):
    """4. Volume barrier: tets flagged and listed in parallel; only where any is (as on the CPU), thread 0 integrates
    the barrier on the listed ones in the CPU's (tet) order (:func:`.integrator.listed_volume_barrier`; a scan over
    every tet's flag, 810 dependent loads on the coarse spleen, cost as much as the rest of the substep)."""
    for t in range(cuda.threadIdx.x, m.tets.shape[0], cuda.blockDim.x):
        on = below_barrier(s.x[b], m.tets, m.rest_volume, m.vol_threshold, t)
        w.tet_on[b, t] = 1 if on else 0
        if on:
            slot = cuda.atomic.add(n_flagged, 0, 1)
            if slot < FLAG_LIST:
                flag_list[slot] = t
    cuda.syncthreads()
    if cuda.threadIdx.x == 0 and n_flagged[0] > 0:
        listed_volume_barrier(m, s, w, b, ks, dt, flag_list, n_flagged[0])
    cuda.syncthreads()


@_device
def _contacts(m, s, out, w, b, sub_info, res, flagged):
    """5. Contacts: cleared and tested in parallel, resolved by thread 0 in the CPU's (surface) order."""
    tid, nth, last_sub = cuda.threadIdx.x, cuda.blockDim.x, sub_info[2]
    x, v, held = s.x[b], s.v[b], s.held[b]
    for q in range(tid, m.surface_nodes.shape[0], nth):
        clear_contact_node(b, m, out, held, last_sub, q)
    cuda.syncthreads()
    vr = 0.0  # (thread 0) the jaws' radial speed in this substep
    if tid == 0:
        if last_sub:
            anchor_readout(m, out, w, b, flagged[0])
        s.t[b] += sub_info[0]
        plate_contacts(b, x, v, w.meff[b], m, s, out, sub_info, res, held)
        if m.jaw_active:
            vr = advance_jaws(b, s, sub_info[0])
    cuda.syncthreads()
    if m.jaw_active:  # (a node's test reads that node only: the order of the tests does not matter)
        jaw_candidates(b, x, m, s, (w.u[b], w.tj[b]), w.cand[b], tid, nth)
        cuda.syncthreads()
        if tid == 0:
            resolve_jaw_contacts(b, x, v, w.meff[b], m, s, out, (w.u[b], w.tj[b]), sub_info, res, (held, w.cand[b]), vr)
        cuda.syncthreads()


@_kernel
def _simulate_kernel(m, s, out, w, n_steps):
    """Advance tissue blockIdx.x by ``n_steps`` outer steps (see the module docstring): each substep the phases of
    :func:`.integrator.simulate`, a device function each, the threads meeting between them."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0]:
        return
    tid = cuda.threadIdx.x
    dt, inv_sub = m.dt_outer / m.n_sub, 1.0 / m.n_sub
    maxwell = maxwell_factors(dt, m.tau)
    ks, ms = s.kscale[b], s.mscale[b]
    res = cuda.local.array(6, np.float64)
    n_flagged = cuda.shared.array(1, np.int32)  # tets of this tissue below the barrier's threshold in this substep
    flag_list = cuda.shared.array(FLAG_LIST, np.int32)  # (their indices, in the order the threads found them)
    if tid == 0:
        clear_readouts(b, out)
        jaw_directions(s.g_axis[b], s.g_e1[b], w.u[b], w.tj[b])
    cuda.syncthreads()
    for step in range(n_steps):
        last_step = step == n_steps - 1
        if tid == 0 and m.jaw_active:
            pinch_force_loop(s.g_force, s.g_vradius, b)
        for sub in range(m.n_sub):
            sub_info = (dt, inv_sub if last_step else 0.0, last_step and sub == m.n_sub - 1, inv_sub)
            springs_to_scratch(m, s, w, b, ks, maxwell, tid, cuda.blockDim.x)
            if tid == 0:
                n_flagged[0] = 0
            cuda.syncthreads()
            gather_and_advance_nodes(m, s, w, b, ms, dt, tid, cuda.blockDim.x)
            cuda.syncthreads()
            if m.use_dashpot:  # ---- 3b. spring dashpots, implicit: thread 0 in the CPU's (edge) order
                if tid == 0:
                    dashpot_pass(s.x[b], s.v[b], w.meff[b], m.fixed, (m.edges, m.cdash), ks, dt, w.dash_out[b])
                cuda.syncthreads()
            if m.kvol.shape[0] > 0:
                _barrier(m, s, w, b, ks, dt, n_flagged, flag_list)
            _contacts(m, s, out, w, b, sub_info, res, n_flagged)


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
