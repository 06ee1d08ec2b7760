"""The physics step on a CUDA GPU (numba's CUDA target): the same model, state and readout records as
:func:`.integrator.simulate`, one thread block per tissue.

Layout (after the measured prototype in the issue: one block per tissue, per-node gather in edge order):

* springs, one thread per spring: each spring's force vector (and its Maxwell state) goes to a scratch
  array; tets likewise, one thread per tet;
* nodes, one thread per node: the node *gathers* its springs' forces in edge order and then its tets'
  in tet order, the order in which the CPU kernel scatters them, so each node's force is the same sum,
  term by term (no atomics, no order-dependent rounding); then symplectic Euler with implicit damping;
* contacts (plates, then jaws), thread 0 of the block: the surface nodes in the CPU's order (few nodes,
  branchy, and the jaw and plate readouts are sums in node order).

The contact pass and the leaf functions (spring law, tet volume, per-node Coulomb contact, force loop)
are the CPU kernel's own functions compiled for the GPU from their Python source (:func:`device_twin`),
so a change there changes both backends; the spring and tet passes repeat the CPU loops' arithmetic.
The grasper and the plates (the compression experiments) run on the GPU alike.

Under ``NUMBA_ENABLE_CUDASIM=1`` the kernel runs on the CPU in numba's CUDA simulator (slow: tests only);
there the arithmetic is the CPU's bit for bit. On a GPU, fused multiply-adds round differently
(~1e-16 relative per operation).
"""

from __future__ import annotations

import math
import types
from typing import NamedTuple

import numpy as np
from numba import cuda

from . import contact as _contact
from . import forces as _forces
from . import integrator as _integrator
from .config import check_choice
from .records import SimModel, SimReadout, SimState


def check_numba_cuda_numpy(numba_cuda_version: str | None, numpy_version: str) -> None:
    """Refuse numba-cuda <= 0.30.4 beside numpy >= 2.5 with a one-line fix, before any kernel is compiled.

    Those numba-cuda releases register an overload of ``np.row_stack``, which numpy 2.5 removed, so their
    first kernel launch raises ``AttributeError`` deep inside numba (NVIDIA/numba-cuda#907; numba-cuda is in
    maintenance and will not fix it). The ``gpu`` extra pins ``numpy<2.5``; this catches an environment
    that has both anyway (the lent GPU image has numpy 2.5.2). ``None``: numba-cuda is not installed
    (numba's built-in CUDA target, or its simulator, which have no such overload)."""
    from packaging.version import Version

    if numba_cuda_version is not None and Version(numba_cuda_version) <= Version("0.30.4") \
            and Version(numpy_version).release >= (2, 5):
        raise ImportError(f"numba-cuda {numba_cuda_version} cannot compile kernels with numpy {numpy_version} "
                          "(np.row_stack was removed in numpy 2.5): pip install 'numpy<2.5'")


def _installed(name: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None


check_numba_cuda_numpy(_installed("numba-cuda"), np.__version__)


#: threads per block (one block per tissue); the loops stride over springs, tets and nodes
THREADS_PER_BLOCK = 128
#: the float types of the per-node, per-spring and per-tet arrays (see :data:`FLOAT32_FIELDS`)
PRECISIONS = ("float64", "float32")
#: the arrays stored in float32 when ``precision="float32"``: those of one entry per node, spring or tet,
#: the memory the step streams through. Per-tissue values (time, friction, scales, the grasper and its force
#: loop, the jaw, plate and anchor sums) stay float64: a clock summed at every substep would drift in float32,
#: and a friction coefficient gains nothing from 4 bytes. Arithmetic follows numba's typing: float32 operands give float32,
#: a float64 constant or per-tissue value promotes the operation to float64. The error against float64 is
#: measured, not assumed (``msdgrasp bench precision``).
FLOAT32_FIELDS = frozenset({
    # SimModel
    "x_rest", "rest_length", "k1", "k2", "dlc", "cdash", "kv", "rest_volume", "kvol", "mass", "b0", "b1",
    "anchor_k", "node_area",
    # SimState
    "x", "v", "fv", "dl_prev", "f_ext",
    # SimReadout
    "contact_force",
    # CudaScratch
    "fe", "ft", "react", "meff", "fa",
})


def with_precision(record: NamedTuple, precision: str) -> NamedTuple:
    """The record with its :data:`FLOAT32_FIELDS` arrays in ``precision`` ("float64": the record as it is)."""
    check_choice("precision", precision, PRECISIONS)
    if precision == "float64":
        return record
    return record._replace(**{name: np.ascontiguousarray(getattr(record, name), dtype=np.float32)
                              for name in record._fields if name in FLOAT32_FIELDS})


def device_twin(cpu_function, **callees):
    """The GPU twin of a CPU kernel function: its Python source compiled by numba's CUDA target, with the
    CPU functions it calls bound to their GPU twins (``callees``). One source, two targets: an edit of the
    CPU function changes both."""
    py = cpu_function.py_func
    bound = types.FunctionType(py.__code__, {**py.__globals__, **callees}, py.__name__, py.__defaults__, py.__closure__)
    return cuda.jit(device=True)(bound)


_spring_force = device_twin(_forces.spring_force)
_volume6 = device_twin(_forces._volume6)
_volume_gradients = device_twin(_forces._volume_gradients)
_tet_edges = device_twin(_forces._tet_edges, _volume6=_volume6)
_below_volume_floor = device_twin(_forces.below_volume_floor, _tet_edges=_tet_edges)
_project_volume_floor = device_twin(
    _forces.project_volume_floor,
    _tet_edges=_tet_edges,
    _volume_gradients=_volume_gradients,
    _floor_move=device_twin(_forces._floor_move),
)
_floor_reactions = device_twin(_contact.floor_reactions)
_jaw_directions = device_twin(_contact.jaw_directions)
_force_loop = device_twin(_integrator._force_loop)
_resolve_node_contact = device_twin(_contact.resolve_node_contact)
_jaw_contacts = device_twin(
    _contact.jaw_contacts,
    jaw_candidate=device_twin(_contact.jaw_candidate),
    resolve_node_contact=_resolve_node_contact,
)
_plate_contacts = device_twin(_contact.plate_contacts, resolve_node_contact=_resolve_node_contact)


class CudaScratch(NamedTuple):
    """Per-tissue work arrays of the kernel and the mesh's node incidence (CSR, in edge / tet order)."""

    fe: np.ndarray  # (B,E,3) N force of each spring on its first node
    ft: np.ndarray  # (B,T,12) N volume-barrier force of each tet on nodes b, c, d and minus on node a
    tet_on: np.ndarray  # (B,T) int8: the barrier acts on the tet this substep
    floor_on: np.ndarray  # (B,T) int8: the tet is below the volume floor after the contacts
    held: np.ndarray  # (B,N) int8: the jaw (k + 1) or plate (-(p + 1)) holding each node this substep
    react: np.ndarray  # (B,N,3) N the volume floor's force through held and anchored nodes
    meff: np.ndarray  # (B,N) kg effective mass m + dt b (contacts)
    fa: np.ndarray  # (B,N,3) N anchor force on each node (last substep: the anchor readout)
    edge_ptr: np.ndarray  # (N+1,) int: node i's springs are edge_idx[edge_ptr[i]:edge_ptr[i+1]]
    edge_idx: np.ndarray  # int, ascending per node
    edge_sign: np.ndarray  # float: +1 where i is the spring's first node, -1 where it is the second
    tet_ptr: np.ndarray  # (N+1,) int
    tet_idx: np.ndarray  # int, ascending per node
    tet_slot: np.ndarray  # int: 0..3, the node's place in the tet
    u: np.ndarray  # (B,3,3) jaw outward directions
    tj: np.ndarray  # (B,3,3) jaw lateral directions


def incidence(n_nodes: int, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR of which rows of ``pairs`` (E,k) hold node i, in ascending row order, and the node's column."""
    rows = np.repeat(np.arange(pairs.shape[0]), pairs.shape[1])
    cols = np.tile(np.arange(pairs.shape[1]), pairs.shape[0])
    nodes = pairs.reshape(-1).astype(np.int64)
    order = np.lexsort((rows, nodes))  # by node, then by row: the CPU's scatter order
    ptr = np.zeros(n_nodes + 1, dtype=np.int64)
    np.add.at(ptr, nodes + 1, 1)
    return np.cumsum(ptr), rows[order].astype(np.int64), cols[order].astype(np.int64)


def make_scratch(model: SimModel, batch: int) -> CudaScratch:
    """Host arrays of the kernel's scratch for ``batch`` tissues of ``model``."""
    n, ne, nt = model.x_rest.shape[0], model.edges.shape[0], model.tets.shape[0]
    eptr, eidx, ecol = incidence(n, np.asarray(model.edges))
    tptr, tidx, tcol = incidence(n, np.asarray(model.tets))
    return CudaScratch(
        fe=np.zeros((batch, ne, 3)), ft=np.zeros((batch, max(nt, 1), 12)),
        tet_on=np.zeros((batch, max(nt, 1)), dtype=np.int8), floor_on=np.zeros((batch, max(nt, 1)), dtype=np.int8),
        held=np.zeros((batch, n), dtype=np.int8), react=np.zeros((batch, n, 3)), meff=np.zeros((batch, n)),
        fa=np.zeros((batch, n, 3)),
        edge_ptr=eptr, edge_idx=eidx, edge_sign=np.where(ecol == 0, 1.0, -1.0), tet_ptr=tptr, tet_idx=tidx,
        tet_slot=tcol, u=np.zeros((batch, 3, 3)), tj=np.zeros((batch, 3, 3)),
    )


@cuda.jit
def _simulate_kernel(m, s, out, w, n_steps):
    """Advance tissue blockIdx.x by ``n_steps`` outer steps (see the module docstring)."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0]:
        return
    tid = cuda.threadIdx.x
    nth = cuda.blockDim.x
    x, v = s.x, s.v
    n = x.shape[1]
    ne = m.edges.shape[0]
    nt = m.tets.shape[0] if m.kvol.shape[0] > 0 else 0
    n_sub = m.n_sub
    dt = m.dt_outer / n_sub
    inv_sub = 1.0 / n_sub
    decay = math.exp(-dt / m.tau)
    gain = m.tau / dt * (1.0 - decay)
    ks = s.kscale[b]
    ms = s.mscale[b]
    res = cuda.local.array(6, np.float64)
    if tid == 0:
        for k in range(3):
            for c in range(9):
                out.jaw_out[b, k, c] = 0.0
            out.anchor_out[b, k] = 0.0
        for p in range(m.pl_normal.shape[0]):
            for c in range(3):
                out.plate_out[b, p, c] = 0.0
        _jaw_directions(s.g_axis[b], s.g_e1[b], w.u[b], w.tj[b])
    cuda.syncthreads()
    for step in range(n_steps):
        last_step = step == n_steps - 1
        if tid == 0 and m.jaw_active:
            _force_loop(s.g_force, s.g_vradius, b)
        for sub in range(n_sub):
            last_sub = last_step and sub == n_sub - 1
            avg = 1.0 / n_sub if last_step else 0.0
            # ---- 1a. springs: force on the first node (and the Maxwell state), as spring_loop computes it
            for e in range(tid, ne, nth):
                i = m.edges[e, 0]
                j = m.edges[e, 1]
                dx = x[b, j, 0] - x[b, i, 0]
                dy = x[b, j, 1] - x[b, i, 1]
                dz = x[b, j, 2] - x[b, i, 2]
                length = math.sqrt(dx * dx + dy * dy + dz * dz)
                ok = length >= 1e-15
                inv = 1.0 / length
                ux = dx * inv
                uy = dy * inv
                uz = dz * inv
                dl = length - m.rest_length[e]
                fs = ks * _spring_force(dl, m.k1[e], m.k2[e], m.dlc[e])
                if m.use_sls:
                    fve = s.fv[b, e] * decay + ks * m.kv[e] * (dl - s.dl_prev[b, e]) * gain
                    if ok:
                        s.fv[b, e] = fve
                        s.dl_prev[b, e] = dl
                    fs += fve
                if m.use_dashpot:
                    rel = (v[b, j, 0] - v[b, i, 0]) * ux + (v[b, j, 1] - v[b, i, 1]) * uy + (v[b, j, 2] - v[b, i, 2]) * uz
                    fs += ks * m.cdash[e] * rel
                w.fe[b, e, 0] = fs * ux if ok else 0.0
                w.fe[b, e, 1] = fs * uy if ok else 0.0
                w.fe[b, e, 2] = fs * uz if ok else 0.0
            # ---- 1b. volume barrier: the force of each compressed tet, as accumulate_volume_forces computes it
            for t in range(tid, nt, nth):
                a, bb, c, d = m.tets[t, 0], m.tets[t, 1], m.tets[t, 2], m.tets[t, 3]
                e1x, e1y, e1z = x[b, bb, 0] - x[b, a, 0], x[b, bb, 1] - x[b, a, 1], x[b, bb, 2] - x[b, a, 2]
                e2x, e2y, e2z = x[b, c, 0] - x[b, a, 0], x[b, c, 1] - x[b, a, 1], x[b, c, 2] - x[b, a, 2]
                e3x, e3y, e3z = x[b, d, 0] - x[b, a, 0], x[b, d, 1] - x[b, a, 1], x[b, d, 2] - x[b, a, 2]
                vol = _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z) / 6.0
                if vol >= m.vol_threshold * m.rest_volume[t]:
                    w.tet_on[b, t] = 0
                    continue
                w.tet_on[b, t] = 1
                jac = vol / m.rest_volume[t]
                gbx, gby, gbz, gcx, gcy, gcz, gdx, gdy, gdz = _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
                sc = -ks * m.kvol[t] * (jac - m.vol_threshold)
                w.ft[b, t, 0] = sc * gbx
                w.ft[b, t, 1] = sc * gby
                w.ft[b, t, 2] = sc * gbz
                w.ft[b, t, 3] = sc * gcx
                w.ft[b, t, 4] = sc * gcy
                w.ft[b, t, 5] = sc * gcz
                w.ft[b, t, 6] = sc * gdx
                w.ft[b, t, 7] = sc * gdy
                w.ft[b, t, 8] = sc * gdz
                w.ft[b, t, 9] = sc * (gbx + gcx + gdx)
                w.ft[b, t, 10] = sc * (gby + gcy + gdy)
                w.ft[b, t, 11] = sc * (gbz + gcz + gdz)
            cuda.syncthreads()
            # ---- 2-3. nodes: gather in the CPU's order, then symplectic Euler with implicit damping, anchors
            for i in range(tid, n, nth):
                mi = m.mass[i] * ms
                f0 = mi * m.gravity[0] + s.f_ext[b, i, 0]  # (mass x scale) x g, as the CPU groups it
                f1 = mi * m.gravity[1] + s.f_ext[b, i, 1]
                f2 = mi * m.gravity[2] + s.f_ext[b, i, 2]
                for p in range(w.edge_ptr[i], w.edge_ptr[i + 1]):
                    e = w.edge_idx[p]
                    if w.edge_sign[p] > 0.0:
                        f0 += w.fe[b, e, 0]
                        f1 += w.fe[b, e, 1]
                        f2 += w.fe[b, e, 2]
                    else:
                        f0 -= w.fe[b, e, 0]
                        f1 -= w.fe[b, e, 1]
                        f2 -= w.fe[b, e, 2]
                if nt > 0:
                    for p in range(w.tet_ptr[i], w.tet_ptr[i + 1]):
                        t = w.tet_idx[p]
                        if w.tet_on[b, t] == 0:
                            continue
                        slot = w.tet_slot[p]
                        if slot == 0:
                            f0 -= w.ft[b, t, 9]
                            f1 -= w.ft[b, t, 10]
                            f2 -= w.ft[b, t, 11]
                        else:
                            f0 += w.ft[b, t, 3 * slot - 3]
                            f1 += w.ft[b, t, 3 * slot - 2]
                            f2 += w.ft[b, t, 3 * slot - 1]
                if m.fixed[i]:
                    w.fa[b, i, 0] = -f0  # the anchor holds the node against its whole force
                    w.fa[b, i, 1] = -f1
                    w.fa[b, i, 2] = -f2
                    v[b, i, 0] = 0.0
                    v[b, i, 1] = 0.0
                    v[b, i, 2] = 0.0
                    continue
                ka = m.anchor_k[i]
                if ka > 0.0:
                    a0 = -ka * (x[b, i, 0] - m.x_rest[i, 0] - ms * m.anchor_offset[0])
                    a1 = -ka * (x[b, i, 1] - m.x_rest[i, 1] - ms * m.anchor_offset[1])
                    a2 = -ka * (x[b, i, 2] - m.x_rest[i, 2] - ms * m.anchor_offset[2])
                    f0 += a0
                    f1 += a1
                    f2 += a2
                    w.fa[b, i, 0] = a0
                    w.fa[b, i, 1] = a1
                    w.fa[b, i, 2] = a2
                damp = m.b0[i]
                if m.b1[i] != 0.0:
                    dx = x[b, i, 0] - m.x_rest[i, 0]
                    dy = x[b, i, 1] - m.x_rest[i, 1]
                    dz = x[b, i, 2] - m.x_rest[i, 2]
                    damp = m.b0[i] + m.b1[i] * math.sqrt(dx * dx + dy * dy + dz * dz)
                dinv = 1.0 / (1.0 + dt * damp / mi)
                w.meff[b, i] = mi + dt * damp
                v0 = (v[b, i, 0] + dt * f0 / mi) * dinv
                v1 = (v[b, i, 1] + dt * f1 / mi) * dinv
                v2 = (v[b, i, 2] + dt * f2 / mi) * dinv
                v[b, i, 0] = v0
                v[b, i, 1] = v1
                v[b, i, 2] = v2
                x[b, i, 0] += dt * v0
                x[b, i, 1] += dt * v1
                x[b, i, 2] += dt * v2
            cuda.syncthreads()
            # ---- 4. anchor readout and contacts: thread 0, nodes in the CPU's order
            if tid == 0:
                if last_sub:
                    for i in range(n):
                        if m.fixed[i] or m.anchor_k[i] > 0.0:
                            out.anchor_out[b, 0] += w.fa[b, i, 0]
                            out.anchor_out[b, 1] += w.fa[b, i, 1]
                            out.anchor_out[b, 2] += w.fa[b, i, 2]
                s.t[b] += dt
                if m.vol_floor > 0.0:  # only the floor reads the holders
                    for q in range(m.surface_nodes.shape[0]):
                        w.held[b, m.surface_nodes[q]] = 0
                if last_sub:
                    for q in range(m.surface_nodes.shape[0]):
                        i = m.surface_nodes[q]
                        out.contact_state[b, i] = 0
                        out.contact_force[b, i, 0] = 0.0
                        out.contact_force[b, i, 1] = 0.0
                        out.contact_force[b, i, 2] = 0.0
                _plate_contacts(b, x[b], v[b], w.meff[b], m, s, out, dt, avg, last_sub, res, w.held[b])
                if m.jaw_active:
                    _jaw_contacts(b, x[b], v[b], w.meff[b], m, s, out, w.u[b], w.tj[b], dt, avg, last_sub, res, inv_sub,
                                  w.held[b])
            cuda.syncthreads()
            # ---- 5. volume floor: tets flagged in parallel, restored by thread 0 in the CPU's (tet) order
            if m.vol_floor > 0.0:
                for t in range(tid, m.tets.shape[0], nth):
                    w.floor_on[b, t] = 1 if _below_volume_floor(x[b], m.tets, m.rest_volume, m.vol_floor, t) else 0
                cuda.syncthreads()
                if tid == 0:  # both skip what they need not touch (unflagged tets, nodes without a reaction)
                    _project_volume_floor(x[b], v[b], w.meff[b], m.fixed, w.held[b], m.tets, m.rest_volume,
                                          m.vol_floor, dt, w.floor_on[b], w.react[b])
                    _floor_reactions(b, w.held[b], w.react[b], m.fixed, w.u[b], out, s, avg, inv_sub, last_sub)
                cuda.syncthreads()


def cuda_simulate(model: SimModel, state: SimState, out: SimReadout, scratch: CudaScratch, n_steps: int,
                  threads: int = THREADS_PER_BLOCK) -> None:
    """:func:`.integrator.simulate` on the GPU: records of device arrays (or host arrays: numba copies them
    in and out around the launch). One block of ``threads`` threads per tissue."""
    nb = state.x.shape[0]
    _simulate_kernel[nb, threads](model, state, out, scratch, n_steps)


def to_device(record: NamedTuple) -> NamedTuple:
    """The record with each array copied to the GPU (scalars as they are)."""
    return type(record)(*[cuda.to_device(np.ascontiguousarray(a)) if isinstance(a, np.ndarray) else a for a in record])


def copy_back(device_record: NamedTuple, host_record: NamedTuple) -> None:
    """Copy each array of a device record into the host record's array of the same field."""
    for dev, host in zip(device_record, host_record):
        if isinstance(host, np.ndarray):
            dev.copy_to_host(host)


class CudaBatch:
    """A batch of tissues resident on the GPU: state and readouts stay on the device between calls.

    Made from host records once; :meth:`step` only launches the kernel. ``precision="float32"`` stores the
    per-node, per-spring and per-tet arrays in float32 (:data:`FLOAT32_FIELDS`); downloads into float64 host
    records convert. (:class:`.simulation.Simulation`
    with ``backend="cuda"`` uploads and downloads everything around each step, so that every host-side API
    works unchanged.) Only what a caller asks for crosses
    to the host (:meth:`download`, by field: e.g. ``jaw_out`` for the sensors, 108 bytes per tissue), and
    host-side changes go up the same way (:meth:`upload`: commands, resets). :meth:`arrays` hands the device
    arrays to a GPU consumer without a copy: each has ``__cuda_array_interface__``, so
    ``torch.as_tensor(batch.arrays()["x"], device="cuda")`` is a view of the positions.
    """

    def __init__(self, model: SimModel, state: SimState, out: SimReadout, threads: int = THREADS_PER_BLOCK,
                 precision: str = "float64") -> None:
        self.precision = precision
        self.model = to_device(with_precision(model, precision))
        self.state = to_device(with_precision(state, precision))
        self.out = to_device(with_precision(out, precision))
        self.scratch = to_device(with_precision(make_scratch(model, state.x.shape[0]), precision))
        self.threads = int(threads)

    def step(self, n_steps: int) -> None:
        cuda_simulate(self.model, self.state, self.out, self.scratch, int(n_steps), self.threads)

    def _pairs(self, host_state: SimState | None, host_out: SimReadout | None, fields):
        recs = [(d, h) for d, h in ((self.state, host_state), (self.out, host_out)) if h is not None]
        for dev, host in recs:
            for name in dev._fields:
                if (fields is None or name in fields) and isinstance(getattr(host, name), np.ndarray):
                    yield name, getattr(dev, name), getattr(host, name)

    def download(self, state: SimState | None = None, out: SimReadout | None = None,
                 fields: tuple[str, ...] | None = None) -> None:
        """Copy the device arrays of ``fields`` (default all) into the given host records, in place."""
        self._check(fields)
        for _, dev, host in self._pairs(state, out, fields):
            if dev.dtype == host.dtype:
                dev.copy_to_host(host)
            else:  # (a float32 array into a float64 record)
                host[...] = dev.copy_to_host()

    def upload(self, state: SimState | None = None, out: SimReadout | None = None,
               fields: tuple[str, ...] | None = None) -> None:
        """Copy host arrays of ``fields`` (default all) into the device arrays (no reallocation)."""
        self._check(fields)
        for _, dev, host in self._pairs(state, out, fields):
            dev.copy_to_device(np.ascontiguousarray(host, dtype=dev.dtype))

    def arrays(self) -> dict[str, object]:
        """The device arrays of the state and the readouts, by field name (no copy)."""
        return {name: getattr(rec, name) for rec in (self.state, self.out) for name in rec._fields
                if hasattr(getattr(rec, name), "copy_to_host")}

    def _check(self, fields) -> None:
        if fields is None:
            return
        known = set(self.state._fields) | set(self.out._fields)
        for name in fields:
            if name not in known:
                raise ValueError(f"field {name!r} is not in the state or readout records; allowed: {sorted(known)}")
