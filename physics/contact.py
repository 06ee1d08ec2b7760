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
from .jit import kernel

#: contact state codes stored per node: on a jaw's inner face or a plate (STICK, SLIP), or pushed by a jaw's side
#: or end wall (WALL_STICK, WALL_SLIP: the jaw's solid, not its gripping face)
FREE, STICK, SLIP, WALL_STICK, WALL_SLIP = 0, 1, 2, 3, 4

# jaw readout columns (physics.integrator fills jaw_out[b, jaw, col])
J_NORMAL = 0  # normal force on the tissue, N (>= 0, pushing into the tissue)
J_TX, J_TY, J_TZ = 1, 2, 3  # tangential (friction) force on the tissue, N (vector)
J_CONTACT = 4  # number of contact nodes
J_STICK = 5  # of which sticking
J_SLIP = 6  # of which slipping
J_SLIP_DIST = 7  # slip distance accumulated over the call, m (mean over the jaw's contact nodes)
J_PEAK_PRESSURE = 8  # peak nodal contact pressure during the call, Pa
J_WALL_X, J_WALL_Y, J_WALL_Z = 9, 10, 11  # the part of the jaw's force on the tissue (N, vector) that its side
#                                           and end walls exert (included in J_NORMAL and J_T*, which are the
#                                           whole jaw's force split on its face's normal)
N_JAW_COLS = 12

# columns of the jaw force loop g_force[b, col] (the 1 kHz pinch-force controller of a torque-driven jaw
# motor, run by the integrator at every outer step; see physics.integrator)
G_SETPOINT = 0  # pinch-force set-point, N; < 0 switches the loop off (the closing speed is then commanded)
G_GAIN = 1  # closing speed per newton of force error, m/s/N
G_VMAX = 2  # largest closing/opening speed the loop may command, m/s
G_PINCH = 3  # pinch force (sum of the jaws' normal forces) averaged over the last outer step, N
G_COLS = 4


@kernel(inline="always")
def resolve_node_contact(
    x: np.ndarray,  # (N,3) positions after the explicit prediction (modified)
    v: np.ndarray,  # (N,3) velocities after the explicit prediction (modified)
    i: int,
    m: float,  # effective mass m + dt b (implicit nodal damping), kg
    normal: tuple,  # (nx, ny, nz) unit face normal pointing INTO the tissue
    d: float,  # penetration beyond the face plane, m (> 0)
    face_v: tuple,  # (vx, vy, vz) face velocity, m/s
    mu: tuple,  # (mu_s, mu_k) static and kinetic friction coefficients
    dt: float,
    out: np.ndarray,  # (6,) out: [normal force N, ftx, fty, ftz, state, slip speed m/s]
) -> None:
    nx, ny, nz = normal
    fvx, fvy, fvz = face_v
    mu_s, mu_k = mu
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


@kernel(inline="always")
def jaw_candidate(
    r: tuple,  # (3 floats) node position relative to the grasper tip (axis point), m
    axis: tuple,  # (3 floats) grasper axis (unit, pointing from handle to tip)
    e1: tuple,  # (3 floats) azimuth-0 direction (unit, normal to the axis)
    e2: tuple,  # (3 floats) a x e1
    radius: float,
    jaw_length: float,
) -> int:
    """The paper's cylindrical detection: which jaw (0, 1, 2) a surface node may touch, or -1.

    In cylindrical coordinates about the grasper axis, one radius test (rho >= R) finds candidates for
    all three jaws at once; the axial coordinate must lie on the jaws; the azimuth then picks the jaw
    (jaw k is centred at azimuth 2 pi k / 3).
    """
    rx, ry, rz = r
    ax, ay, az = axis
    e1x, e1y, e1z = e1
    e2x, e2y, e2z = e2
    s = rx * ax + ry * ay + rz * az
    if s > 0.0 or s < -jaw_length:
        return -1
    p1 = rx * e1x + ry * e1y + rz * e1z
    p2 = rx * e2x + ry * e2y + rz * e2z
    if p1 * p1 + p2 * p2 < radius * radius:
        return -1
    return jaw_sector(p1, p2)


#: sin(2 pi / 3): jaw k's centre lies at (cos, sin)(2 pi k / 3) = (1, 0), (-1/2, +-SIN_120) in (e1, e2)
SIN_120 = math.sqrt(3.0) / 2.0


@kernel(inline="always")
def jaw_sector(p1: float, p2: float) -> int:
    """The jaw whose centre azimuth (2 pi k / 3) is nearest to the direction (p1, p2) (components along e1, e2; not
    both zero): the largest projection on the three centre directions, a tie going to the jaw counter-clockwise of
    the edge. That is the paper's k = floor(phi / (2 pi / 3) + 1/2) mod 3, phi = atan2(p2, p1), except within
    round-off of a sector edge (where that formula's own rounding decides), without the atan2, which took two thirds
    of the contact pass's node tests."""
    c0 = p1
    c1 = -0.5 * p1 + SIN_120 * p2
    c2 = -0.5 * p1 - SIN_120 * p2
    if c1 >= c0 and c1 > c2:
        return 1
    if c2 >= c1 and c2 > c0:
        return 2
    return 0


@kernel
def jaw_reach(x, nodes, tip, axis, e1, jaw_length: float, jaw_half_width: float):
    """(reach_0, reach_1, reach_2): for each jaw k of a grasper at ``tip`` with ``axis`` and azimuth-0 direction
    ``e1`` (3-tuples, m; unit), the largest outward distance (x_i - tip).u_k of the nodes ``nodes`` of ``x`` (N,3)
    on its footprint (axial coordinate on the jaws, lateral offset within the half width, in front of the face):
    the jaw touches the tissue only below that radius (0: no node on its footprint). The one rule behind a scene's
    jaw centring and start radius and each episode's start radius."""
    ax, ay, az = axis
    e1x, e1y, e1z = e1
    e2x, e2y, e2z = ay * e1z - az * e1y, az * e1x - ax * e1z, ax * e1y - ay * e1x
    two_pi_3 = 2.0 * math.pi / 3.0
    reach0 = 0.0
    reach1 = 0.0
    reach2 = 0.0
    for q in range(nodes.shape[0]):
        i = nodes[q]
        rx, ry, rz = x[i, 0] - tip[0], x[i, 1] - tip[1], x[i, 2] - tip[2]
        s = rx * ax + ry * ay + rz * az
        if s > 0.0 or s < -jaw_length:
            continue
        for k in range(3):
            c = math.cos(two_pi_3 * k)
            sn = math.sin(two_pi_3 * k)
            ux, uy, uz = c * e1x + sn * e2x, c * e1y + sn * e2y, c * e1z + sn * e2z
            lat = rx * (ay * uz - az * uy) + ry * (az * ux - ax * uz) + rz * (ax * uy - ay * ux)
            dist = rx * ux + ry * uy + rz * uz
            if dist > 0.0 and abs(lat) <= jaw_half_width:
                if k == 0:
                    reach0 = max(reach0, dist)
                elif k == 1:
                    reach1 = max(reach1, dist)
                else:
                    reach2 = max(reach2, dist)
    return reach0, reach1, reach2


#: how far outside the tissue the jaws open at an episode's start, m: beyond the largest reach on their footprints
JAW_CLEARANCE_M = 1e-3


@kernel
def jaw_start_radius(reach, open_radius: float) -> float:
    """The radius the jaws open to at a start: clear of the jaws' reaches (:func:`jaw_reach`) by JAW_CLEARANCE_M,
    at most the grasper's widest opening ``open_radius`` (m)."""
    return min(open_radius, max(reach[0], max(reach[1], reach[2])) + JAW_CLEARANCE_M)


@kernel
def jaw_directions(axis: np.ndarray, e1: np.ndarray, u: np.ndarray, tj: np.ndarray) -> None:
    """Outward direction u[k] of jaw k (azimuth 2 pi k / 3 about the axis from e1) and its lateral tj[k] = a x u."""
    ax, ay, az = axis[0], axis[1], axis[2]
    e1x, e1y, e1z = e1[0], e1[1], e1[2]
    e2x = ay * e1z - az * e1y
    e2y = az * e1x - ax * e1z
    e2z = ax * e1y - ay * e1x
    two_pi_3 = 2.0 * math.pi / 3.0
    for k in range(3):
        c = math.cos(two_pi_3 * k)
        s = math.sin(two_pi_3 * k)
        u[k, 0] = c * e1x + s * e2x
        u[k, 1] = c * e1y + s * e2y
        u[k, 2] = c * e1z + s * e2z
        tj[k, 0] = ay * u[k, 2] - az * u[k, 1]
        tj[k, 1] = az * u[k, 0] - ax * u[k, 2]
        tj[k, 2] = ax * u[k, 1] - ay * u[k, 0]


@kernel
def clear_readouts(b: int, out) -> None:
    """Zero tissue b's jaw, plate and anchor readouts (SimReadout ``out``) at the start of a call."""
    for k in range(out.jaw_out.shape[1]):
        for c in range(out.jaw_out.shape[2]):
            out.jaw_out[b, k, c] = 0.0
    for p in range(out.plate_out.shape[1]):
        for c in range(3):
            out.plate_out[b, p, c] = 0.0
    for c in range(3):
        out.anchor_out[b, c] = 0.0


@kernel(inline="always")
def clear_contact_node(b: int, model, out, held, last_sub: bool, q: int) -> None:
    """Before a substep's contacts: surface node q of tissue b is not held (``held`` (N,) int8) and, in the last
    substep, its contact readouts restart from zero. Nodes are independent (the GPU clears them in parallel)."""
    i = model.surface_nodes[q]
    held[i] = 0
    if last_sub:
        out.contact_state[b, i] = 0
        for c in range(3):
            out.contact_force[b, i, c] = 0.0


@kernel
def clear_contacts(b: int, model, out, held, last_sub: bool) -> None:
    """:func:`clear_contact_node` for every surface node of tissue b."""
    for q in range(model.surface_nodes.shape[0]):
        clear_contact_node(b, model, out, held, last_sub, q)


@kernel
def plate_contacts(
    b, xb, vb, meff,  # tissue index; its (N,3) positions and velocities (modified), (N,) effective masses
    model, state, out,  # SimModel, SimState (plate points advanced), SimReadout (plate_out, contacts filled)
    sub,  # (dt s, avg, last_sub, inv_sub): the substep; its weight in the readouts; fill the last-substep readouts
    res,  # (6,) scratch
    held,  # (N,) int8 out: -(p + 1) for the nodes plate p holds this substep
) -> None:
    """Advance tissue b's plates by one substep and resolve every surface node behind one."""
    dt, avg, last_sub, _ = sub
    fixed, surface_nodes, pl_normal, pl_mu = model.fixed, model.surface_nodes, model.pl_normal, model.pl_mu
    pl_point, pl_vel = state.pl_point, state.pl_vel
    plate_out, contact_state, contact_force = out.plate_out, out.contact_state, out.contact_force
    for p in range(pl_normal.shape[0]):
        pnx, pny, pnz = pl_normal[p, 0], pl_normal[p, 1], pl_normal[p, 2]
        pvx, pvy, pvz = pl_vel[b, p, 0], pl_vel[b, p, 1], pl_vel[b, p, 2]
        pl_point[b, p, 0] += dt * pvx
        pl_point[b, p, 1] += dt * pvy
        pl_point[b, p, 2] += dt * pvz
        px, py, pz = pl_point[b, p, 0], pl_point[b, p, 1], pl_point[b, p, 2]
        for q in range(surface_nodes.shape[0]):
            i = surface_nodes[q]
            if fixed[i]:
                continue
            d = -((xb[i, 0] - px) * pnx + (xb[i, 1] - py) * pny + (xb[i, 2] - pz) * pnz)
            if d <= 0.0:
                continue
            resolve_node_contact(xb, vb, i, meff[i], (pnx, pny, pnz), d, (pvx, pvy, pvz), (pl_mu[p], pl_mu[p]), dt, res)
            held[i] = -(p + 1)
            plate_out[b, p, 0] += avg * (res[0] * pnx + res[1])
            plate_out[b, p, 1] += avg * (res[0] * pny + res[2])
            plate_out[b, p, 2] += avg * (res[0] * pnz + res[3])
            if last_sub:
                contact_state[b, i] = np.int8(res[4])
                contact_force[b, i, 0] += res[0] * pnx + res[1]
                contact_force[b, i, 1] += res[0] * pny + res[2]
                contact_force[b, i, 2] += res[0] * pnz + res[3]


@kernel(inline="always")
def advance_jaws(b, state, dt):
    """Advance tissue b's grasper by one substep of ``dt`` s: the jaws' radius (closing stops at its limits)
    and the tip (the pull). Returns the radial speed the jaws moved at, m/s."""
    g_radius = state.g_radius
    r_old = g_radius[b]
    r_new = min(max(r_old + dt * state.g_vradius[b], state.g_rmin[b]), state.g_rmax[b])
    g_radius[b] = r_new
    for c in range(3):
        state.g_tip[b, c] += dt * state.g_vpull[b, c]
    return (r_new - r_old) / dt


@kernel(inline="always")
def jaw_frame(b, state):
    """Tissue b's grasper after :func:`advance_jaws`, as scalars: (tip, axis, e1, e2 = axis x e1, radius), the
    vectors as 3-tuples (m; unit). Read once per substep: per-node code takes it, not the state record."""
    ax, ay, az = state.g_axis[b, 0], state.g_axis[b, 1], state.g_axis[b, 2]
    e1x, e1y, e1z = state.g_e1[b, 0], state.g_e1[b, 1], state.g_e1[b, 2]
    e2 = (ay * e1z - az * e1y, az * e1x - ax * e1z, ax * e1y - ay * e1x)
    tip = (state.g_tip[b, 0], state.g_tip[b, 1], state.g_tip[b, 2])
    return tip, (ax, ay, az), (e1x, e1y, e1z), e2, state.g_radius[b]


@kernel(inline="always")
def jaw_node_geometry(xb, i, frame, jaw, dirs):
    """Where (free) node i lies against the jaws: (k, rx, ry, rz, d, lat), k the jaw whose solid holds the node
    (-1: none; then the rest is meaningless), r = x_i - tip (m), d its outward depth past the jaw's inner face (m),
    lat its lateral coordinate on the jaw (m). ``frame``: :func:`jaw_frame`; ``jaw``: (length, half width, depth),
    m; ``dirs``: the jaws' outward and lateral directions. Reads node i only, so nodes can be tested in any order,
    in parallel (the GPU does), before any is resolved."""
    u, tj = dirs
    tip, axis, e1, e2, r_new = frame
    jaw_length, jaw_half_width, jaw_depth = jaw
    rx = xb[i, 0] - tip[0]
    ry = xb[i, 1] - tip[1]
    rz = xb[i, 2] - tip[2]
    k = jaw_candidate((rx, ry, rz), axis, e1, e2, r_new, jaw_length)
    # d and lat computed for every node (jaw 0's where none): values defined in branches made this function,
    # inlined into the contact loop, 3x slower
    kk = max(k, 0)
    d = rx * u[kk, 0] + ry * u[kk, 1] + rz * u[kk, 2] - r_new
    lat = rx * tj[kk, 0] + ry * tj[kk, 1] + rz * tj[kk, 2]
    inside = k >= 0 and not (d <= 0.0 or d > jaw_depth) and not (jaw_half_width - abs(lat) <= 0.0)
    return (k if inside else -1), rx, ry, rz, d, lat


@kernel(inline="always")
def jaw_candidates(b, xb, model, state, dirs, cand, first, stride):
    """``cand[q]`` = the jaw around surface node q (-1: none, anchored nodes included) for q = first, first +
    stride, ... (a GPU block shares the nodes out among its threads), after :func:`advance_jaws`."""
    frame = jaw_frame(b, state)
    jaw = (model.jaw_length, model.jaw_half_width, model.jaw_depth)
    fixed, surface_nodes = model.fixed, model.surface_nodes
    for q in range(first, surface_nodes.shape[0], stride):
        i = surface_nodes[q]
        cand[q] = -1 if fixed[i] else jaw_node_geometry(xb, i, frame, jaw, dirs)[0]


@kernel
def jaw_contacts(
    b, xb, vb, meff,  # tissue index; its (N,3) positions and velocities (modified), (N,) effective masses
    model, state, out,  # SimModel, SimState (grasper advanced, pinch accumulated), SimReadout (filled)
    dirs,  # ((3,3), (3,3)): jaw outward and lateral directions of tissue b (:func:`jaw_directions`)
    sub,  # (dt s, avg, last_sub, inv_sub): the substep; its weight in the readouts; fill the last-substep
    #       readouts; 1 / n_sub, the weight of the pinch accumulated into state.g_force[b, G_PINCH]
    res,  # (6,) scratch
    marks,  # (held, cand): (N,) int8 out: k + 1 for the nodes jaw k holds this substep;
    #         (S,) int8: the jaw each surface node is inside (:func:`jaw_candidates`), or empty: test here
) -> None:
    """Advance tissue b's grasper by one substep and resolve its three jaws (cylindrical detection): each surface
    node tested (:func:`jaw_node_geometry`) and, inside a jaw, resolved, in surface order
    (:func:`resolve_jaw_contacts`). The GPU tests the nodes in parallel first (:func:`jaw_candidates`); the CPU
    tests each node where it resolves it (one pass: several times faster than a separate test pass)."""
    vr = advance_jaws(b, state, sub[0])
    resolve_jaw_contacts(b, xb, vb, meff, model, state, out, dirs, sub, res, marks, vr)


@kernel(inline="always")
def resolve_jaw_contacts(b, xb, vb, meff, model, state, out, dirs, sub, res, marks, vr) -> None:
    """Resolve the surface nodes of tissue b inside a jaw, in surface order, after :func:`advance_jaws` (which
    returned ``vr``): those ``marks[1]`` names (from :func:`jaw_candidates`), or, with ``marks[1]`` empty, those
    its own test finds; the rest as :func:`jaw_contacts`."""
    dt, avg, last_sub, inv_sub = sub
    held, cand = marks
    u, tj = dirs
    surface_nodes, node_area, fixed = model.surface_nodes, model.node_area, model.fixed
    jaw_length, jaw_half_width = model.jaw_length, model.jaw_half_width
    g_vpull, mu_s, mu_k, g_force = state.g_vpull, state.mu_s, state.mu_k, state.g_force
    jaw_out, contact_state, contact_force = out.jaw_out, out.contact_state, out.contact_force
    frame = jaw_frame(b, state)
    ax, ay, az = frame[1]
    jaw = (jaw_length, jaw_half_width, model.jaw_depth)
    n_con0 = 0.0
    n_con1 = 0.0
    n_con2 = 0.0
    slip0 = 0.0
    slip1 = 0.0
    slip2 = 0.0
    tested = cand.shape[0] > 0
    for q in range(surface_nodes.shape[0]):
        if tested and cand[q] < 0:
            continue
        i = surface_nodes[q]
        if not tested and fixed[i]:
            continue
        k, rx, ry, rz, d, lat = jaw_node_geometry(xb, i, frame, jaw, dirs)
        if k < 0:
            continue
        pen_side = jaw_half_width - abs(lat)
        # the node is inside jaw k's solid: push it out through the nearest wall (inner face, a side
        # wall, the tip end or the base end), the closest-feature rule of a box
        s_ax = rx * ax + ry * ay + rz * az
        nx, ny, nz, pen = -u[k, 0], -u[k, 1], -u[k, 2], d
        face = True
        if pen_side < pen:
            sg = 1.0 if lat > 0.0 else -1.0
            nx, ny, nz, pen = sg * tj[k, 0], sg * tj[k, 1], sg * tj[k, 2], pen_side
            face = False
        if -s_ax < pen:
            nx, ny, nz, pen = ax, ay, az, -s_ax
            face = False
        if s_ax + jaw_length < pen:
            nx, ny, nz, pen = -ax, -ay, -az, s_ax + jaw_length
            face = False
        resolve_node_contact(
            xb, vb, i, meff[i], (nx, ny, nz), pen,
            (g_vpull[b, 0] + vr * u[k, 0], g_vpull[b, 1] + vr * u[k, 1], g_vpull[b, 2] + vr * u[k, 2]),
            (mu_s[b], mu_k[b]), dt, res,
        )
        held[i] = k + 1
        # contact force on the tissue, split into the jaw face's normal and tangential parts
        fx = res[0] * nx + res[1]
        fy = res[0] * ny + res[2]
        fz = res[0] * nz + res[3]
        fn = -(fx * u[k, 0] + fy * u[k, 1] + fz * u[k, 2])
        ftx = fx + fn * u[k, 0]
        fty = fy + fn * u[k, 1]
        ftz = fz + fn * u[k, 2]
        if face and node_area[i] > 0.0:
            pressure = res[0] / node_area[i]
            if pressure > jaw_out[b, k, J_PEAK_PRESSURE]:
                jaw_out[b, k, J_PEAK_PRESSURE] = pressure
        jaw_out[b, k, J_NORMAL] += avg * fn
        g_force[b, G_PINCH] += inv_sub * fn
        jaw_out[b, k, J_TX] += avg * ftx
        jaw_out[b, k, J_TY] += avg * fty
        jaw_out[b, k, J_TZ] += avg * ftz
        if not face:
            jaw_out[b, k, J_WALL_X] += avg * fx
            jaw_out[b, k, J_WALL_Y] += avg * fy
            jaw_out[b, k, J_WALL_Z] += avg * fz
        if last_sub:
            jaw_out[b, k, J_CONTACT] += 1.0
            if res[4] == 1.0:
                jaw_out[b, k, J_STICK] += 1.0
            else:
                jaw_out[b, k, J_SLIP] += 1.0
            contact_state[b, i] = np.int8(res[4] if face else res[4] + 2.0)
            contact_force[b, i, 0] += fx
            contact_force[b, i, 1] += fy
            contact_force[b, i, 2] += fz
        if k == 0:
            n_con0 += 1.0
            slip0 += res[5] * dt
        elif k == 1:
            n_con1 += 1.0
            slip1 += res[5] * dt
        else:
            n_con2 += 1.0
            slip2 += res[5] * dt
    if n_con0 > 0.0:
        jaw_out[b, 0, J_SLIP_DIST] += slip0 / n_con0
    if n_con1 > 0.0:
        jaw_out[b, 1, J_SLIP_DIST] += slip1 / n_con1
    if n_con2 > 0.0:
        jaw_out[b, 2, J_SLIP_DIST] += slip2 / n_con2
