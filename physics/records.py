"""The kernel's records: what :func:`.integrator.simulate` reads, changes and reports, passed whole.

In the spirit of MuJoCo's ``mj_step(model, data)``: a call site names three records instead of ~58
positional arrays, so two arrays of the same type cannot be swapped silently. numba compiles them as
NamedTuples of arrays and scalars (a struct of pointers: no copies, field access costs nothing).

* :class:`SimModel` holds what is constant during a call and shared by the batch (mesh, material
  arrays, grasper geometry, plate normals, time stepping);
* :class:`SimState` holds the batch's state and per-tissue settings (batch first), advanced in place;
* :class:`SimReadout` holds the sensor readouts the call fills in;
* :class:`Springs` holds one mesh's springs for the spring loops alone.

:class:`.simulation.Simulation` owns the arrays and builds the records for each call.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class SimModel(NamedTuple):
    """Constant during a call, shared by every tissue of the batch. SI units."""

    # tissue: springs (nonlinear spring law k1, k2, dl_c; optional dashpots and Maxwell branches)
    x_rest: np.ndarray  # (N,3) m rest positions
    edges: np.ndarray  # (E,2) int node pairs
    rest_length: np.ndarray  # (E,) m
    k1: np.ndarray  # (E,) N/m
    k2: np.ndarray  # (E,) N/m
    dlc: np.ndarray  # (E,) m: elongation where the second stiffness takes over
    cdash: np.ndarray  # (E,) N s/m spring dashpots
    use_dashpot: bool
    use_sls: bool  # Maxwell branch on
    kv: np.ndarray  # (E,) N/m Maxwell-branch stiffness
    tau: float  # s Maxwell relaxation time
    # volume barrier of strongly compressed tets, integrated implicitly (empty kvol: off)
    tets: np.ndarray  # (T,4) int
    rest_volume: np.ndarray  # (T,) m^3
    kvol: np.ndarray  # (T,) Pa
    vol_threshold: float  # volume ratio below which the barrier acts
    watch_delta: float  # m: how far nodes may move between the barrier's full flag passes (forces.watch_barrier;
    #                     0: a full pass every substep)
    # nodes
    mass: np.ndarray  # (N,) kg
    b0: np.ndarray  # (N,) N s/m nodal damping
    b1: np.ndarray  # (N,) N s/m^2 displacement-dependent damping (Eq. 7)
    fixed: np.ndarray  # (N,) bool anchors held at rest
    anchor_k: np.ndarray  # (N,) N/m compliant anchors (0: none)
    anchor_offset: np.ndarray  # (3,) m anchor preload offset per unit mass scale
    gravity: np.ndarray  # (3,) m/s^2
    surface_nodes: np.ndarray  # (Ns,) int
    node_area: np.ndarray  # (N,) m^2 midpoint-polygon area of surface nodes
    # grasper geometry (jaw_active False: no grasper)
    jaw_active: bool
    jaw_length: float  # m
    jaw_half_width: float  # m
    jaw_depth: float  # m
    # plates: infinite planes, normal pointing into the tissue side
    pl_normal: np.ndarray  # (P,3)
    pl_mu: np.ndarray  # (P,)
    # time stepping
    dt_outer: float  # s outer step (1 ms)
    n_sub: int  # substeps per outer step


class SimState(NamedTuple):
    """The batch's state and per-tissue settings, batch first; the kernel advances it in place."""

    x: np.ndarray  # (B,N,3) m
    v: np.ndarray  # (B,N,3) m/s
    t: np.ndarray  # (B,) s
    fv: np.ndarray  # (B,E) N Maxwell-branch force per spring
    dl_prev: np.ndarray  # (B,E) m spring elongation at the last substep
    # per-tissue settings (domain randomisation, loads)
    kscale: np.ndarray  # (B,) stiffness scale
    mscale: np.ndarray  # (B,) mass scale
    f_ext: np.ndarray  # (B,N,3) N external nodal forces
    mu_s: np.ndarray  # (B,) static friction coefficient of the jaws
    mu_k: np.ndarray  # (B,) kinetic friction coefficient of the jaws
    # grasper
    g_tip: np.ndarray  # (B,3) m, advanced by g_vpull
    g_axis: np.ndarray  # (B,3) unit
    g_e1: np.ndarray  # (B,3) unit, direction of jaw 0
    g_radius: np.ndarray  # (B,) m, advanced by g_vradius
    g_vradius: np.ndarray  # (B,) m/s (set by the force loop when it is on)
    g_vpull: np.ndarray  # (B,3) m/s
    g_rmin: np.ndarray  # (B,) m
    g_rmax: np.ndarray  # (B,) m
    g_force: np.ndarray  # (B,G_COLS) jaw force loop: set-point, gain, speed limit (in), pinch (out)
    # plates
    pl_point: np.ndarray  # (B,P,3) m, advanced by pl_vel
    pl_vel: np.ndarray  # (B,P,3) m/s
    # contact memory: the jaw (k + 1) or plate (-(p + 1)) that held each node in the last substep (0: none);
    # the volume barrier reads it (a held node does not move with the barrier's impulse)
    held: np.ndarray  # (B,N) int8


class SimReadout(NamedTuple):
    """Sensor readouts of the last outer step (forces averaged over its substeps)."""

    jaw_out: np.ndarray  # (B,3,N_JAW_COLS) per jaw: normal and friction force, contact counts, slip, pressure
    plate_out: np.ndarray  # (B,P,3) N force on the tissue by each plate
    anchor_out: np.ndarray  # (B,3) N force on the tissue by the anchors
    contact_state: np.ndarray  # (B,N) int8: 0 free, 1 stick, 2 slip (last substep)
    contact_force: np.ndarray  # (B,N,3) N force on the tissue at contact nodes (last substep)


class Springs(NamedTuple):
    """The springs of one mesh, as :func:`.forces.spring_loop` reads them (the field names of :class:`SimModel`)."""

    edges: np.ndarray  # (E,2) int
    rest_length: np.ndarray  # (E,) m
    k1: np.ndarray  # (E,) N/m
    k2: np.ndarray  # (E,) N/m^3
    dlc: np.ndarray  # (E,) m
    cdash: np.ndarray  # (E,) N s/m, spring dashpot (used only with use_dashpot)
    kv: np.ndarray  # (E,) N/m Maxwell spring stiffness (used only with use_sls)
    use_dashpot: bool
    use_sls: bool  # Maxwell branch (physics/viscoelastic.py)
