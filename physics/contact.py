"""Node-on-rigid-face contact with Coulomb stick/slip friction (numba, called from the step kernel).

A contact node is constrained to the face: its penetration ``d`` beyond the face plane (predicted by the
explicit step) is removed by a normal velocity change d/dt, i.e. a normal impulse J_n = m d / dt. The
reaction force on the tissue is J_n / dt: computed from the constraint, not from a penalty spring.

Tangentially, Coulomb's law per node (the paper's two boundary conditions):

* stick (geometric condition, the node follows the jaw's velocity) while the impulse needed to cancel the
  relative tangential velocity, m |v_rel,t|, does not exceed mu_s J_n;
* slip (force condition) otherwise: a friction impulse mu_k J_n opposing the relative sliding.

Because the jaws are rigid with prescribed motion and the spring forces are explicit within a step,
the constraints of different nodes are independent: this per-node solution is exact for the step (no
iterative solver). A node whose predicted position is back on the tissue side (d <= 0) would need a
tensile reaction to stay on the face, so it leaves contact.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: contact state codes stored per node
FREE, STICK, SLIP = 0, 1, 2

# jaw readout columns (physics.integrator fills jaw_out[b, jaw, col])
J_NORMAL = 0  # normal force on the tissue, N (>= 0, pushing into the tissue)
J_TX, J_TY, J_TZ = 1, 2, 3  # tangential (friction) force on the tissue, N (vector)
J_CONTACT = 4  # number of contact nodes
J_STICK = 5  # of which sticking
J_SLIP = 6  # of which slipping
J_SLIP_DIST = 7  # slip distance accumulated over the call, m (mean over the jaw's contact nodes)
J_PEAK_PRESSURE = 8  # peak nodal contact pressure during the call, Pa
N_JAW_COLS = 9


@njit(cache=True, inline="always", error_model="numpy")
def resolve_node_contact(
    x: np.ndarray,  # (N,3) positions after the explicit prediction (modified)
    v: np.ndarray,  # (N,3) velocities after the explicit prediction (modified)
    i: int,
    m: float,  # effective mass m + dt b (implicit nodal damping), kg
    nx: float,
    ny: float,
    nz: float,  # unit face normal pointing INTO the tissue
    d: float,  # penetration beyond the face plane, m (> 0)
    fvx: float,
    fvy: float,
    fvz: float,  # face velocity, m/s
    mu_s: float,
    mu_k: float,
    dt: float,
    out: np.ndarray,  # (6,) out: [normal force N, ftx, fty, ftz, state, slip speed m/s]
) -> None:
    dvn = d / dt
    vx = v[i, 0] + dvn * nx
    vy = v[i, 1] + dvn * ny
    vz = v[i, 2] + dvn * nz
    jn = m * dvn  # normal impulse, N s
    # relative tangential velocity w.r.t. the face
    rx = vx - fvx
    ry = vy - fvy
    rz = vz - fvz
    rn = rx * nx + ry * ny + rz * nz
    tx = rx - rn * nx
    ty = ry - rn * ny
    tz = rz - rn * nz
    vt = math.sqrt(tx * tx + ty * ty + tz * tz)
    if m * vt <= mu_s * jn:
        # stick: the node takes the face's tangential velocity
        vx -= tx
        vy -= ty
        vz -= tz
        out[1] = -m * tx / dt
        out[2] = -m * ty / dt
        out[3] = -m * tz / dt
        out[4] = 1.0
        out[5] = 0.0
    else:
        dvt = mu_k * jn / m
        s = dvt / vt
        vx -= s * tx
        vy -= s * ty
        vz -= s * tz
        out[1] = -m * s * tx / dt
        out[2] = -m * s * ty / dt
        out[3] = -m * s * tz / dt
        out[4] = 2.0
        out[5] = vt - dvt
    out[0] = jn / dt
    # keep x consistent with the corrected velocity (x_new = x_old + dt v_new)
    x[i, 0] += dt * (vx - v[i, 0])
    x[i, 1] += dt * (vy - v[i, 1])
    x[i, 2] += dt * (vz - v[i, 2])
    v[i, 0] = vx
    v[i, 1] = vy
    v[i, 2] = vz


@njit(cache=True, inline="always", error_model="numpy")
def jaw_candidate(
    rx: float, ry: float, rz: float,  # node position relative to the grasper tip (axis point)
    ax: float, ay: float, az: float,  # grasper axis (unit, pointing from handle to tip)
    e1x: float, e1y: float, e1z: float,  # azimuth-0 direction (unit, normal to the axis)
    e2x: float, e2y: float, e2z: float,  # a x e1
    radius: float,
    jaw_length: float,
) -> int:
    """The paper's cylindrical detection: which jaw (0, 1, 2) a surface node may touch, or -1.

    In cylindrical coordinates about the grasper axis, one radius test (rho >= R) finds candidates for
    all three jaws at once; the axial coordinate must lie on the jaws; the azimuth then picks the jaw
    (jaw k is centred at azimuth 2 pi k / 3).
    """
    s = rx * ax + ry * ay + rz * az
    if s > 0.0 or s < -jaw_length:
        return -1
    p1 = rx * e1x + ry * e1y + rz * e1z
    p2 = rx * e2x + ry * e2y + rz * e2z
    if p1 * p1 + p2 * p2 < radius * radius:
        return -1
    phi = math.atan2(p2, p1)
    k = int(math.floor(phi / (2.0 * math.pi / 3.0) + 0.5)) % 3
    return k
