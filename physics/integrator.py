"""Explicit time integration of a batch of MSD tissues with rigid jaws and plates, in one numba call.

Scheme (per substep of length dt, for each tissue b of the batch, all on the same mesh):

1. forces: nonlinear springs (+ optional dashpots, Maxwell branches) + the volume barrier of strongly
   compressed tets + gravity + external nodal forces;
2. symplectic Euler with *implicit* nodal damping (the paper's Eq. 7, diagonal, so unconditionally
   stable): v <- (v + dt f/m) / (1 + dt (b0 + b1 |r - r0|)/m);  x <- x + dt v;
3. anchors (fixed nodes) are held at their rest positions;
4. the jaws (and plates) advance; surface nodes that penetrate a face become contact nodes and are
   resolved with Coulomb stick/slip (:mod:`.contact`).

The outer physics step is ``dt_outer`` (1 ms by default, the 1 kHz of the haptics literature); it is
split into ``n_sub`` equal substeps chosen from the tissue's stability limit (see
:meth:`.tissue.TissueModel.critical_dt`). Readouts (forces) are averaged over the substeps of the
last outer step, i.e. what a 1 kHz force sensor would report.

State is plain arrays with the batch first: x (B,N,3), v (B,N,3), grasper pose (B,3), radius (B,), ...
Tissues of a batch differ by per-tissue stiffness and mass scale, friction, grasper pose and commands.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .contact import (
    J_CONTACT,
    J_NORMAL,
    J_PEAK_PRESSURE,
    J_SLIP,
    J_SLIP_DIST,
    J_STICK,
    J_TX,
    J_TY,
    J_TZ,
    jaw_candidate,
    resolve_node_contact,
)
from .forces import accumulate_spring_forces, accumulate_volume_forces
from .viscoelastic import accumulate_spring_forces_sls


@njit(cache=True, error_model="numpy")
def simulate(
    # state (modified in place)
    x, v, t,  # (B,N,3), (B,N,3), (B,)
    # tissue (shared by the batch)
    x_rest, edges, rest_length, k1, k2, dlc, cdash, use_dashpot,
    use_sls, kv, tau, fv, dl_prev,  # Maxwell branch: bool, (E,), s, (B,E) state, (B,E) state
    tets, rest_volume, kvol, vol_threshold,  # volume barrier: (T,4), (T,) m^3, (T,) Pa (empty: off), J_c
    mass, b0, b1, fixed, anchor_k, anchor_offset, gravity,  # (N,)x3, (N,) bool, (N,) N/m, (3,) m, (3,)
    surface_nodes, node_area,  # (Ns,) int, (N,) m^2 (midpoint-polygon area of surface nodes)
    kscale, mscale, f_ext,  # (B,), (B,), (B,N,3)
    # grasper (jaw_active False disables it)
    jaw_active, g_tip, g_axis, g_e1, g_radius,  # (B,3) in/out, (B,3), (B,3), (B,) in/out
    g_vradius, g_vpull, g_rmin, g_rmax,  # (B,) m/s, (B,3) m/s, (B,), (B,)
    jaw_length, jaw_half_width, jaw_depth, mu_s, mu_k,  # floats, floats, float, (B,), (B,)
    # plates: infinite planes, normal pointing into the tissue side
    pl_point, pl_normal, pl_vel, pl_mu,  # (B,P,3) in/out, (P,3), (B,P,3), (P,)
    # time stepping
    dt_outer, n_sub, n_steps,
    # outputs
    jaw_out,  # (B,3,N_JAW_COLS)
    plate_out,  # (B,P,3) force on the tissue by each plate, N
    anchor_out,  # (B,3) force on the tissue by the anchors, N
    contact_state,  # (B,N) int8: 0 free, 1 stick, 2 slip (last substep)
    contact_force,  # (B,N,3) force on the tissue at contact nodes, N (last substep)
):
    nb = x.shape[0]
    n = x.shape[1]
    n_pl = pl_normal.shape[0]
    dt = dt_outer / n_sub
    f = np.empty((n, 3))
    # effective mass m + dt b of each node: the implicit nodal damper acts on the *constrained* velocity,
    # so a contact impulse must also overcome it (else reaction forces read low by 1 + dt b/m)
    meff = np.empty(n)
    res = np.empty(6)
    u = np.empty((3, 3))  # jaw outward directions
    tj = np.empty((3, 3))  # jaw lateral directions
    ns = surface_nodes.shape[0]
    two_pi_3 = 2.0 * math.pi / 3.0
    decay = math.exp(-dt / tau)
    gain = tau / dt * (1.0 - decay)
    for b in range(nb):
        xb = x[b]
        vb = v[b]
        ms = mscale[b]
        ks = kscale[b]
        jaw_out[b, :, :] = 0.0
        plate_out[b, :, :] = 0.0
        anchor_out[b, :] = 0.0
        ax, ay, az = g_axis[b, 0], g_axis[b, 1], g_axis[b, 2]
        e1x, e1y, e1z = g_e1[b, 0], g_e1[b, 1], g_e1[b, 2]
        e2x = ay * e1z - az * e1y
        e2y = az * e1x - ax * e1z
        e2z = ax * e1y - ay * e1x
        for k in range(3):
            c = math.cos(two_pi_3 * k)
            s = math.sin(two_pi_3 * k)
            u[k, 0] = c * e1x + s * e2x
            u[k, 1] = c * e1y + s * e2y
            u[k, 2] = c * e1z + s * e2z
            # lateral direction along the face: a x u
            tj[k, 0] = ay * u[k, 2] - az * u[k, 1]
            tj[k, 1] = az * u[k, 0] - ax * u[k, 2]
            tj[k, 2] = ax * u[k, 1] - ay * u[k, 0]
        for step in range(n_steps):
            last_step = step == n_steps - 1
            for sub in range(n_sub):
                last_sub = last_step and sub == n_sub - 1
                avg = 1.0 / n_sub if last_step else 0.0
                # ---- 1. forces
                for i in range(n):
                    m = mass[i] * ms
                    f[i, 0] = m * gravity[0] + f_ext[b, i, 0]
                    f[i, 1] = m * gravity[1] + f_ext[b, i, 1]
                    f[i, 2] = m * gravity[2] + f_ext[b, i, 2]
                if use_sls:
                    accumulate_spring_forces_sls(
                        xb, vb, edges, rest_length, k1, k2, dlc, cdash, ks, use_dashpot, kv, decay, gain,
                        fv[b], dl_prev[b], f,
                    )
                else:
                    accumulate_spring_forces(xb, vb, edges, rest_length, k1, k2, dlc, cdash, ks, use_dashpot, f)
                if kvol.shape[0] > 0:
                    accumulate_volume_forces(xb, tets, rest_volume, kvol, vol_threshold, ks, f)
                # ---- 2-3. symplectic Euler, implicit nodal damping, anchors
                for i in range(n):
                    if fixed[i]:
                        if last_sub:
                            anchor_out[b, 0] -= f[i, 0]
                            anchor_out[b, 1] -= f[i, 1]
                            anchor_out[b, 2] -= f[i, 2]
                        vb[i, 0] = 0.0
                        vb[i, 1] = 0.0
                        vb[i, 2] = 0.0
                        continue
                    m = mass[i] * ms
                    dx = xb[i, 0] - x_rest[i, 0]
                    dy = xb[i, 1] - x_rest[i, 1]
                    dz = xb[i, 2] - x_rest[i, 2]
                    ka = anchor_k[i]
                    if ka > 0.0:  # compliant anchor: a preloaded spring (its preload scales with the mass)
                        fax = -ka * (dx - ms * anchor_offset[0])
                        fay = -ka * (dy - ms * anchor_offset[1])
                        faz = -ka * (dz - ms * anchor_offset[2])
                        f[i, 0] += fax
                        f[i, 1] += fay
                        f[i, 2] += faz
                        if last_sub:
                            anchor_out[b, 0] += fax
                            anchor_out[b, 1] += fay
                            anchor_out[b, 2] += faz
                    damp = b0[i] + b1[i] * math.sqrt(dx * dx + dy * dy + dz * dz)
                    inv = 1.0 / (1.0 + dt * damp / m)
                    meff[i] = m + dt * damp
                    for c in range(3):
                        vb[i, c] = (vb[i, c] + dt * f[i, c] / m) * inv
                        xb[i, c] += dt * vb[i, c]
                t[b] += dt
                if last_sub:
                    for q in range(ns):
                        i = surface_nodes[q]
                        contact_state[b, i] = 0
                        contact_force[b, i, 0] = 0.0
                        contact_force[b, i, 1] = 0.0
                        contact_force[b, i, 2] = 0.0
                # ---- 4a. plates
                for p in range(n_pl):
                    pnx, pny, pnz = pl_normal[p, 0], pl_normal[p, 1], pl_normal[p, 2]
                    pvx, pvy, pvz = pl_vel[b, p, 0], pl_vel[b, p, 1], pl_vel[b, p, 2]
                    pl_point[b, p, 0] += dt * pvx
                    pl_point[b, p, 1] += dt * pvy
                    pl_point[b, p, 2] += dt * pvz
                    px, py, pz = pl_point[b, p, 0], pl_point[b, p, 1], pl_point[b, p, 2]
                    for q in range(ns):
                        i = surface_nodes[q]
                        if fixed[i]:
                            continue
                        d = -((xb[i, 0] - px) * pnx + (xb[i, 1] - py) * pny + (xb[i, 2] - pz) * pnz)
                        if d <= 0.0:
                            continue
                        resolve_node_contact(
                            xb, vb, i, meff[i], pnx, pny, pnz, d, pvx, pvy, pvz, pl_mu[p], pl_mu[p], dt, res
                        )
                        plate_out[b, p, 0] += avg * (res[0] * pnx + res[1])
                        plate_out[b, p, 1] += avg * (res[0] * pny + res[2])
                        plate_out[b, p, 2] += avg * (res[0] * pnz + res[3])
                        if last_sub:
                            contact_state[b, i] = np.int8(res[4])
                            contact_force[b, i, 0] += res[0] * pnx + res[1]
                            contact_force[b, i, 1] += res[0] * pny + res[2]
                            contact_force[b, i, 2] += res[0] * pnz + res[3]
                # ---- 4b. the three jaws (cylindrical detection about the grasper axis)
                if jaw_active:
                    r_old = g_radius[b]
                    r_new = min(max(r_old + dt * g_vradius[b], g_rmin[b]), g_rmax[b])
                    vr = (r_new - r_old) / dt  # closing stops at the radius limits
                    g_radius[b] = r_new
                    for c in range(3):
                        g_tip[b, c] += dt * g_vpull[b, c]
                    cx, cy, cz = g_tip[b, 0], g_tip[b, 1], g_tip[b, 2]
                    n_con0 = 0.0
                    n_con1 = 0.0
                    n_con2 = 0.0
                    slip0 = 0.0
                    slip1 = 0.0
                    slip2 = 0.0
                    for q in range(ns):
                        i = surface_nodes[q]
                        if fixed[i]:
                            continue
                        rx = xb[i, 0] - cx
                        ry = xb[i, 1] - cy
                        rz = xb[i, 2] - cz
                        k = jaw_candidate(rx, ry, rz, ax, ay, az, e1x, e1y, e1z, e2x, e2y, e2z, r_new, jaw_length)
                        if k < 0:
                            continue
                        d = rx * u[k, 0] + ry * u[k, 1] + rz * u[k, 2] - r_new
                        if d <= 0.0 or d > jaw_depth:
                            continue
                        lat = rx * tj[k, 0] + ry * tj[k, 1] + rz * tj[k, 2]
                        pen_side = jaw_half_width - abs(lat)
                        if pen_side <= 0.0:
                            continue
                        # the node is inside jaw k's solid: push it out through the nearest wall (inner
                        # face, a side wall, the tip end or the base end), the closest-feature rule of a box
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
                            xb, vb, i, meff[i], nx, ny, nz, pen,
                            g_vpull[b, 0] + vr * u[k, 0], g_vpull[b, 1] + vr * u[k, 1], g_vpull[b, 2] + vr * u[k, 2],
                            mu_s[b], mu_k[b], dt, res,
                        )
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
                        jaw_out[b, k, J_TX] += avg * ftx
                        jaw_out[b, k, J_TY] += avg * fty
                        jaw_out[b, k, J_TZ] += avg * ftz
                        if last_sub:
                            jaw_out[b, k, J_CONTACT] += 1.0
                            if res[4] == 1.0:
                                jaw_out[b, k, J_STICK] += 1.0
                            else:
                                jaw_out[b, k, J_SLIP] += 1.0
                            contact_state[b, i] = np.int8(res[4])
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


@njit(cache=True, error_model="numpy")
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
