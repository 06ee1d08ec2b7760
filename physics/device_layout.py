"""Host-side layout of the GPU step's data (NumPy only; importing it does not import numba.cuda).

What :mod:`.cuda_step` uploads besides the kernel's records: the kernel's scratch and the mesh's node
incidence (CSR, in the CPU kernel's scatter order), the float32 storage option, and the check of the
numba-cuda / numpy pairing that must run before a kernel is compiled.
"""

from __future__ import annotations

from typing import Literal, NamedTuple, get_args

import numpy as np

from .config import check_choice
from .records import SimModel


def check_numba_cuda_numpy(numba_cuda_version: str | None, numpy_version: str) -> None:
    """Refuse numba-cuda <= 0.30.4 beside numpy >= 2.5 with a one-line fix, before any kernel is compiled.

    Those numba-cuda releases register an overload of ``np.row_stack``, which numpy 2.5 removed, so their
    first kernel launch raises ``AttributeError`` deep inside numba (NVIDIA/numba-cuda#907; numba-cuda is in
    maintenance and will not fix it). The ``gpu`` extra pins ``numpy<2.5``; this catches an environment
    that has both anyway (e.g. a GPU image that ships numpy 2.5). ``None``: numba-cuda is not installed
    (numba's built-in CUDA target, or its simulator, which have no such overload)."""
    from packaging.version import Version

    if numba_cuda_version is not None and Version(numba_cuda_version) <= Version("0.30.4") \
            and Version(numpy_version).release >= (2, 5):
        raise ImportError(f"numba-cuda {numba_cuda_version} cannot compile kernels with numpy {numpy_version} "
                          "(np.row_stack was removed in numpy 2.5): pip install 'numpy<2.5'")


def installed_version(name: str) -> str | None:
    """The installed version of distribution ``name``, or None."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None



#: the float types of the per-node, per-spring and per-tet arrays (see :data:`FLOAT32_FIELDS`): a config field's type
Precision = Literal["float64", "float32"]
PRECISIONS = get_args(Precision)
#: the arrays stored in float32 when ``precision="float32"``: those of one entry per node, spring or tet,
#: the memory the step streams through. Per-tissue values (time, friction, scales, the grasper and its force
#: loop, the jaw, plate and anchor sums) stay float64: a clock summed at every substep would drift in float32,
#: and a friction coefficient gains nothing from 4 bytes. Arithmetic follows numba's typing: float32 operands give
#: float32, a float64 constant or per-tissue value promotes the operation to float64. The error against float64 is
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
    "fe", "meff", "fa",
})


def with_precision(record: NamedTuple, precision: str) -> NamedTuple:
    """The record with its :data:`FLOAT32_FIELDS` arrays in ``precision`` ("float64": the record as it is)."""
    check_choice("precision", precision, PRECISIONS)
    if precision == "float64":
        return record
    return record._replace(**{name: np.ascontiguousarray(getattr(record, name), dtype=np.float32)
                              for name in record._fields if name in FLOAT32_FIELDS})


class CudaScratch(NamedTuple):
    """Per-tissue work arrays of the kernel and the mesh's node incidence (CSR, in edge / tet order)."""

    fe: np.ndarray  # (B,E,3) N force of each spring on its first node
    tet_on: np.ndarray  # (B,T) int8: the tet is below the volume barrier's threshold this substep
    vol_out: np.ndarray  # (B,3) N: the anchors' force against the volume barrier in a substep
    dash_out: np.ndarray  # (B,3) N: the anchors' force against the spring dashpots in a substep
    cand: np.ndarray  # (B,S) int8: the jaw each surface node is inside this substep (-1: none)
    meff: np.ndarray  # (B,N) kg effective mass m + dt b (contacts)
    fa: np.ndarray  # (B,N,3) N anchor force on each node (last substep: the anchor readout)
    edge_ptr: np.ndarray  # (N+1,) int: node i's springs are edge_idx[edge_ptr[i]:edge_ptr[i+1]]
    edge_idx: np.ndarray  # int, ascending per node
    edge_sign: np.ndarray  # float: +1 where i is the spring's first node, -1 where it is the second
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
    n, ne, nt, ns = model.x_rest.shape[0], model.edges.shape[0], model.tets.shape[0], model.surface_nodes.shape[0]
    eptr, eidx, ecol = incidence(n, np.asarray(model.edges))
    return CudaScratch(
        fe=np.zeros((batch, ne, 3)), tet_on=np.zeros((batch, max(nt, 1)), dtype=np.int8),
        vol_out=np.zeros((batch, 3)), dash_out=np.zeros((batch, 3)), cand=np.zeros((batch, max(ns, 1)), dtype=np.int8),
        meff=np.zeros((batch, n)), fa=np.zeros((batch, n, 3)),
        edge_ptr=eptr, edge_idx=eidx, edge_sign=np.where(ecol == 0, 1.0, -1.0),
        u=np.zeros((batch, 3, 3)), tj=np.zeros((batch, 3, 3)),
    )


def field_pairs(device_records: tuple, host_records: tuple, fields: tuple[str, ...] | None):
    """(device array, host array) of each field in ``fields`` (None: every array field) of each pair of
    records whose host record is given. An unknown name is refused (ValueError naming the allowed ones)
    before any pair is yielded."""
    known = {name for rec in device_records for name in rec._fields}
    for name in fields or ():
        if name not in known:
            raise ValueError(f"field {name!r} is not in the state or readout records; allowed: {sorted(known)}")
    for dev, host in zip(device_records, host_records):
        for name in dev._fields if host is not None else ():
            if (fields is None or name in fields) and isinstance(getattr(host, name), np.ndarray):
                yield getattr(dev, name), getattr(host, name)
