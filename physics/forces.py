"""Force laws of the mass-spring-damper tissue (small, pure numba kernels).

Spring law, the paper's Eq. 4-6 (Dehghani Ashkezari et al. 2015), with dl = |r_j - r_i| - |r0_j - r0_i|
(the paper's Eq. 3 writes dl as a vector; the force law needs the scalar change of length):

    F(dl) = K1 dl + K2 dl^3                          for |dl| <= dl_c
    F(dl) = (A + B (|dl| - dl_c)) sgn(dl)            for |dl| >  dl_c
    A = K1 dl_c + K2 dl_c^3
    B = K1 + 3 K2 dl_c^2

MISPRINT in the paper: its Eq. 6 reads B = K1 + 3 K2 dl_c^3, which is dimensionally wrong (K2 is N/m^3,
so K2 dl_c^3 is a force, not a stiffness). B = K1 + 3 K2 dl_c^2 is dF/d(dl) at dl_c, which makes the law
continuous in value *and* slope. F > 0 is tension: it pulls node i toward node j.

Nodal damping, the paper's Eq. 7: F_i = -(b0 + b1 |r_i - r0_i|) v_i (absolute velocity; the paper prints
it without the minus sign, but a damping force opposes the velocity). It is integrated implicitly
in :mod:`.integrator` (diagonal, so unconditionally stable). An optional linear dashpot along each spring
(relative velocity projected on the spring, coefficient c = tau K1) adds rate dependence that does not
damp rigid motion; the integrator applies it implicitly (:func:`implicit_spring_dashpots`), and
:func:`spring_body` computes its explicit force for diagnostics (``flags``).
"""

from __future__ import annotations

import math

import numpy as np
from .jit import kernel

from .records import Springs


@kernel(inline="always")
def spring_force(dl: float, k1: float, k2: float, dlc: float) -> float:
    """Tension (N) of one nonlinear spring stretched by ``dl`` metres (Eq. 4-6, corrected B)."""
    adl = abs(dl)
    if adl <= dlc:
        return k1 * dl + k2 * dl * dl * dl
    a = k1 * dlc + k2 * dlc * dlc * dlc
    # (k2 + k2 + k2: 3 k2 rounded once, bitwise 3.0 * k2, without a float64 literal that would promote float32 args)
    b = k1 + (k2 + k2 + k2) * dlc * dlc
    f = a + b * (adl - dlc)
    return f if dl > 0.0 else -f


@kernel(inline="always")
def spring_tangent(dl: float, k1: float, k2: float, dlc: float) -> float:
    """dF/d(dl) (N/m): K1 + 3 K2 dl^2 inside dl_c, the constant B beyond."""
    adl = min(abs(dl), dlc)
    return k1 + 3.0 * k2 * adl * adl


@kernel
def spring_force_array(dl: np.ndarray, k1: float, k2: float, dlc: float) -> np.ndarray:
    out = np.empty_like(dl)
    for i in range(dl.size):
        out.flat[i] = spring_force(dl.flat[i], k1, k2, dlc)
    return out


@kernel(inline="always")
def spring_body(d, law, ks, dash, maxwell, flags, one=1.0, tiny=1e-15):
    """One spring's force on its first node and its new Maxwell state: the arithmetic every spring loop
    (one tissue, lanes, the GPU kernel) runs per spring, in one order, so their results are bitwise equal.

    d (dx, dy, dz): x_j - x_i, m; law (rest length m, k1 N/m, k2 N/m^3, dl_c m); ks: stiffness scale;
    dash (v_j - v_i (3 floats) m/s, c N s/m): read only with dashpots; maxwell (F_v N, dl at the last substep
    m, k_v N/m, e^(-dt/tau), (tau/dt)(1 - e^(-dt/tau))): read only with the Maxwell branch; flags
    (use_dashpot, use_sls); one, tiny: 1 and 1e-15 in the arithmetic's type (float32 inputs with np.float32
    ones compute in float32: no float64 literal promotes them). Returns (fx, fy, fz, F_v, dl): the force on node i
    (minus it on node j) and the Maxwell state to store. A spring between coincident nodes (length < 1e-15 m, only in a
    collapsed mesh) has no direction: it adds nothing and keeps its Maxwell state.
    """
    dx, dy, dz = d
    rest, k1, k2, dlc = law
    fv, dl_prev, kv, decay, gain = maxwell
    use_dashpot, use_sls = flags
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    ok = length >= tiny
    inv = one / length
    zero = one - one
    ux = dx * inv
    uy = dy * inv
    uz = dz * inv
    dl = length - rest
    fs = ks * spring_force(dl, k1, k2, dlc)
    if use_sls:
        fve = fv * decay + ks * kv * (dl - dl_prev) * gain
        fv = fve if ok else fv
        dl_prev = dl if ok else dl_prev
        fs += fve
    if use_dashpot:
        rel = dash[0] * ux + dash[1] * uy + dash[2] * uz
        fs += ks * dash[3] * rel
    return fs * ux if ok else zero, fs * uy if ok else zero, fs * uz if ok else zero, fv, dl_prev


@kernel
def spring_loop(
    x: np.ndarray,  # (N,3) positions, m
    v: np.ndarray,  # (N,3) velocities, m/s
    springs: Springs,  # (or a record with its fields, as SimModel)
    kscale: float,  # stiffness multiplier of this tissue (domain randomisation)
    decay: float,  # e^(-dt/tau)
    gain: float,  # (tau/dt) (1 - e^(-dt/tau))
    fv: np.ndarray,  # (E,) Maxwell branch force, N (state, updated; unused without the branch)
    dl_prev: np.ndarray,  # (E,) elongation at the previous substep, m (state, updated; likewise)
    f: np.ndarray,  # (N,3) out: forces are ADDED here
    scratch: np.ndarray,  # (9,E) work space; rows 3-5 zero (or finite) when there are no dashpots
    one: float = 1.0,  # 1 and 1e-15 in the arithmetic's type (as spring_body's)
    tiny: float = 1e-15,
) -> None:
    """The one-tissue spring loop: springs (+ dashpots, + Maxwell branches) added to ``f``, momentum-exact.
    ``springs.kv``, ``springs.cdash``, ``fv`` and ``dl_prev`` need E entries even where unused (zeros).

    Three passes: gather the edge vectors (indexed loads), compute every spring's force (contiguous
    arrays, no branches: LLVM emits SIMD code), scatter in edge order. ~20% faster than one fused loop,
    and bitwise the same (each spring's arithmetic and the order of the additions into f are unchanged).
    """
    edges, use_dashpot, use_sls = springs.edges, springs.use_dashpot, springs.use_sls
    rest_length, k1, k2, dlc = springs.rest_length, springs.k1, springs.k2, springs.dlc
    cdash, kv = springs.cdash, springs.kv
    flags = (use_dashpot, use_sls)
    ne = edges.shape[0]
    for e in range(ne):
        i = edges[e, 0]
        j = edges[e, 1]
        scratch[0, e] = x[j, 0] - x[i, 0]
        scratch[1, e] = x[j, 1] - x[i, 1]
        scratch[2, e] = x[j, 2] - x[i, 2]
        if use_dashpot:
            scratch[3, e] = v[j, 0] - v[i, 0]
            scratch[4, e] = v[j, 1] - v[i, 1]
            scratch[5, e] = v[j, 2] - v[i, 2]
    for e in range(ne):  # every input read unconditionally: conditional loads here cost LLVM the SIMD code
        fx, fy, fz, fve, dle = spring_body((scratch[0, e], scratch[1, e], scratch[2, e]),
                                           (rest_length[e], k1[e], k2[e], dlc[e]), kscale,
                                           (scratch[3, e], scratch[4, e], scratch[5, e], cdash[e]),
                                           (fv[e], dl_prev[e], kv[e], decay, gain), flags, one, tiny)
        if use_sls:
            fv[e] = fve
            dl_prev[e] = dle
        scratch[6, e] = fx
        scratch[7, e] = fy
        scratch[8, e] = fz
    if ne == 0:
        return
    # The scatter keeps the first node's sum in registers while consecutive springs share it (80 % of them do in
    # the meshes' edge order, sorted by first node): f[i] += ... spring after spring made each addition wait for the
    # store of the last (1.4x the time). The additions into every node are the same, in the same order (a spring's
    # second node is never its first), so the result is bitwise that of the plain scatter.
    ci = edges[0, 0]
    ax = f[ci, 0]
    ay = f[ci, 1]
    az = f[ci, 2]
    for e in range(ne):
        i = edges[e, 0]
        j = edges[e, 1]
        if i != ci:
            f[ci, 0] = ax
            f[ci, 1] = ay
            f[ci, 2] = az
            ci = i
            ax = f[i, 0]
            ay = f[i, 1]
            az = f[i, 2]
        ax += scratch[6, e]
        ay += scratch[7, e]
        az += scratch[8, e]
        f[j, 0] -= scratch[6, e]
        f[j, 1] -= scratch[7, e]
        f[j, 2] -= scratch[8, e]
    f[ci, 0] = ax
    f[ci, 1] = ay
    f[ci, 2] = az


# -------------------------------------------------------------------------------------------------
# Lane layout: a batch of tissues stored tissue-innermost, x[i, c, lane] (N,3,L). The loops over lanes
# have no branches and unit stride, so LLVM turns them into SIMD code (4 tissues per AVX2 instruction):
# the spring loop costs ~3.5 ns per spring and tissue at L = 64 instead of ~7.4 ns. Each lane does the same
# floating-point operations in the same order as the one-tissue kernels, so results are bitwise equal.
# -------------------------------------------------------------------------------------------------


@kernel
def spring_loop_lanes(
    x: np.ndarray,  # (N,3,L) positions, m
    v: np.ndarray,  # (N,3,L) velocities, m/s
    springs: Springs,  # (or a record with its fields, as SimModel)
    kscale: np.ndarray,  # (L,) stiffness multiplier of each tissue
    decay: float,
    gain: float,
    fv: np.ndarray,  # (E,L) Maxwell branch force, N (state, updated)
    dl_prev: np.ndarray,  # (E,L) elongation at the previous substep, m (state, updated)
    f: np.ndarray,  # (N,3,L) out: forces are ADDED here
    tmp: np.ndarray,  # (3,L) scratch
    one: float = 1.0,  # 1 and 1e-15 in the arithmetic's type: np.float32 ones with float32 arrays compute in float32
    tiny: float = 1e-15,
) -> None:
    """:func:`spring_loop` for L tissues at once (lane layout); bitwise equal to it per tissue."""
    # one copy of the loop per combination of the flags, each compiled with them constant: with run-time flags
    # LLVM computed both sides of the dashpot's select and read v (the spring pass 1.2x slower at 64 lanes)
    if springs.use_dashpot:
        if springs.use_sls:
            _spring_lanes_pass(x, v, springs, kscale, (decay, gain), fv, dl_prev, f, tmp, True, True, (one, tiny))
        else:
            _spring_lanes_pass(x, v, springs, kscale, (decay, gain), fv, dl_prev, f, tmp, True, False, (one, tiny))
    elif springs.use_sls:
        _spring_lanes_pass(x, v, springs, kscale, (decay, gain), fv, dl_prev, f, tmp, False, True, (one, tiny))
    else:
        _spring_lanes_pass(x, v, springs, kscale, (decay, gain), fv, dl_prev, f, tmp, False, False, (one, tiny))


@kernel(inline="always")
def _spring_lanes_pass(x, v, springs, kscale, rates, fv, dl_prev, f, tmp, use_dashpot, use_sls, units) -> None:
    """The body of :func:`spring_loop_lanes` with the flags given (constants where it inlines this); rates (decay,
    gain) and units (one, tiny) as its arguments."""
    decay, gain = rates
    edges = springs.edges
    flags = (use_dashpot, use_sls)
    nl = x.shape[2]
    one, tiny = units
    zero = one - one  # (the unused entries in the arithmetic's type)
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        law = (springs.rest_length[e], springs.k1[e], springs.k2[e], springs.dlc[e])
        kve = springs.kv[e] if use_sls else zero
        cd = springs.cdash[e] if use_dashpot else zero
        for b in range(nl):
            d = (x[j, 0, b] - x[i, 0, b], x[j, 1, b] - x[i, 1, b], x[j, 2, b] - x[i, 2, b])
            dash = (v[j, 0, b] - v[i, 0, b], v[j, 1, b] - v[i, 1, b], v[j, 2, b] - v[i, 2, b], cd) if use_dashpot \
                else (zero, zero, zero, zero)
            fx, fy, fz, fve, dle = spring_body(d, law, kscale[b], dash, (fv[e, b], dl_prev[e, b], kve, decay, gain),
                                               flags, one, tiny)
            if use_sls:
                fv[e, b] = fve
                dl_prev[e, b] = dle
            tmp[0, b] = fx
            tmp[1, b] = fy
            tmp[2, b] = fz
        # scatter in separate loops: fewer streams per loop keeps LLVM's runtime alias checks cheap
        for cc in range(3):
            for b in range(nl):
                f[i, cc, b] += tmp[cc, b]
        for cc in range(3):
            for b in range(nl):
                f[j, cc, b] -= tmp[cc, b]


@kernel
def accumulate_spring_forces(
    x: np.ndarray,
    v: np.ndarray,
    edges: np.ndarray,
    rest_length: np.ndarray,
    k1: np.ndarray,
    k2: np.ndarray,
    dlc: np.ndarray,
    cdash: np.ndarray,
    kscale: float,
    use_dashpot: bool,
    f: np.ndarray,
) -> None:
    """Add every spring's (and dashpot's) force to ``f`` (no Maxwell branch)."""
    zero = np.zeros(edges.shape[0])
    spring_loop(x, v, Springs(edges, rest_length, k1, k2, dlc, cdash, zero, use_dashpot, False), kscale, 1.0, 0.0,
                zero, zero, f, np.zeros((9, edges.shape[0])))


@kernel
def spring_energy(
    x: np.ndarray, edges: np.ndarray, rest_length: np.ndarray, k1: np.ndarray, k2: np.ndarray, dlc: np.ndarray
) -> float:
    """Elastic energy (J): integral of the spring law from 0 to dl, summed over springs."""
    total = 0.0
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        dl = np.sqrt(dx * dx + dy * dy + dz * dz) - rest_length[e]
        adl = abs(dl)
        c = dlc[e]
        if adl <= c:
            total += 0.5 * k1[e] * adl * adl + 0.25 * k2[e] * adl**4
        else:
            a = k1[e] * c + k2[e] * c**3
            b = k1[e] + 3.0 * k2[e] * c * c
            s = adl - c
            total += 0.5 * k1[e] * c * c + 0.25 * k2[e] * c**4 + a * s + 0.5 * b * s * s
    return total


@kernel
def implicit_spring_dashpots(
    x: np.ndarray,  # (N,3) positions of one tissue after the explicit update, m (modified)
    v: np.ndarray,  # (N,3) velocities, m/s (modified)
    meff: np.ndarray,  # (N,) effective masses m + dt b, kg
    fixed: np.ndarray,  # (N,) bool: anchored nodes do not move; their anchor takes the force
    edges: np.ndarray,  # (E,2) int
    cdash: np.ndarray,  # (E,) N s/m
    ks: float,  # stiffness scale of this tissue (scales the dashpots with the springs)
    dt: float,  # substep, s
    anchor: np.ndarray,  # (3,) N: the force the anchors supply against the dashpots is ADDED here
) -> None:
    """The linear dashpot along each spring (F = c (v_j - v_i) . u on node i), integrated implicitly spring by
    spring in edge order (Gauss-Seidel): each spring's relative speed along itself r becomes r / (1 + c dt W),
    W = 1/m_i + 1/m_j, by equal and opposite impulses (momentum exact), and x moves with v. Backward Euler on
    each spring's own mode: unconditionally stable and only dissipative, so the dashpots do not bound the
    substep (an explicit dashpot of 1 ms x K1 took the sphere from 4 to 18 substeps per ms).

    The pass is one dependency chain (each spring reads the nodes the springs before it moved): node i of a run of
    consecutive springs with the same first node (most of them, in the meshes' edge order) is held in registers
    and stored once at the end of its run, so the chain does not wait for its stores (the paper's sphere: 398 -> 298
    us per simulated ms, msdgrasp bench physics).
    Its arithmetic and order are unchanged: the result is bitwise that of kicking both nodes through memory (a
    spring's second node is never its first)."""
    ne = edges.shape[0]
    if ne == 0:
        return
    as_x = x.dtype.type  # (the held values round as a store into x would: float32 storage stays bitwise)
    ci = edges[0, 0]  # the node held: (p, u) its position and velocity, wi its inverse mass
    p = (x[ci, 0], x[ci, 1], x[ci, 2])
    u = (v[ci, 0], v[ci, 1], v[ci, 2])
    wi = 0.0 if fixed[ci] else 1.0 / meff[ci]
    for e in range(ne):
        i, j = edges[e, 0], edges[e, 1]
        if i != ci:
            x[ci, 0], x[ci, 1], x[ci, 2] = p
            v[ci, 0], v[ci, 1], v[ci, 2] = u
            ci = i
            p = (x[ci, 0], x[ci, 1], x[ci, 2])
            u = (v[ci, 0], v[ci, 1], v[ci, 2])
            wi = 0.0 if fixed[ci] else 1.0 / meff[ci]
        c = ks * cdash[e]
        if c == 0.0:
            continue
        dx, dy, dz = x[j, 0] - p[0], x[j, 1] - p[1], x[j, 2] - p[2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if length < 1e-15:
            continue
        ux, uy, uz = dx / length, dy / length, dz / length
        wj = 0.0 if fixed[j] else 1.0 / meff[j]
        r = (v[j, 0] - u[0]) * ux + (v[j, 1] - u[1]) * uy + (v[j, 2] - u[2]) * uz
        lam = c * dt * r / (1.0 + c * dt * (wi + wj))  # impulse on node i along u (on node j: minus it), N s
        dvx, dvy, dvz, fx, fy, fz = node_impulse(wi, lam, ux, uy, uz, dt)  # node i: the held values
        if wi == 0.0:
            anchor[0] -= fx
            anchor[1] -= fy
            anchor[2] -= fz
        else:
            u = (as_x(u[0] + dvx), as_x(u[1] + dvy), as_x(u[2] + dvz))
            p = (as_x(p[0] + dt * dvx), as_x(p[1] + dt * dvy), as_x(p[2] + dt * dvz))
        dvx, dvy, dvz, fx, fy, fz = node_impulse(wj, -lam, ux, uy, uz, dt)
        if wj == 0.0:
            anchor[0] -= fx
            anchor[1] -= fy
            anchor[2] -= fz
        else:
            kick_node(x, v, j, (dvx, dvy, dvz), dt)
    x[ci, 0], x[ci, 1], x[ci, 2] = p
    v[ci, 0], v[ci, 1], v[ci, 2] = u


# -------------------------------------------------------------------------------------------------
# Volume barrier per tet (TissueParams.volume_modulus_pa, volume_threshold). A spring network resists a
# tet's collapse only through its six edge lengths, so under large local compression (under the jaws, or
# the sphere between plates) tets flatten and invert. With J = V / V0 and a threshold J_c, each tet stores
#     U = k V0 psi(J),   psi(J) = -(J - J_c)^2 ln(J / J_c)   for J < J_c,   0 otherwise
# (the barrier of Li et al., "Incremental Potential Contact", SIGGRAPH 2020, applied to the volume ratio):
# zero with zero slope and curvature at J_c, so below the threshold the network is the paper's pure MSD,
# and unbounded as J -> 0, so no finite load crushes a tet flat. Its forces -k psi'(J) dV/dx act along the
# volume gradients dV/dx_a = (area vector of the face opposite a, pointing away from a) / 3; they sum to
# zero (momentum exact) and exert no torque.
#
# An explicit step cannot carry an unbounded stiffness, so the barrier is integrated implicitly, tet by
# tet: after the explicit node update (springs, gravity, damping) and before the contacts, each tet below
# J_c takes the backward-Euler impulse of its own force, linearised at its predicted state,
#     dv_a = -dt p dV/dx_a / m_a,   p = k psi'(J*) / (1 + dt^2 k psi''(J*) W / V0),
#     W = sum_a |dV/dx_a|^2 / m_a,
# (and x moves with it, x_new = x_old + dt v_new), one tet after the other in tet order (Gauss-Seidel).
# For the tet's own mode this is unconditionally stable (p -> the impulse that stops further collapse as
# psi'' grows), so the barrier costs no substeps and the stability rule does not count it. Because it is a
# force applied before the contacts, a node a jaw holds receives its share like any other force, and the
# contact law then keeps that node inside its friction cone and counts the force in the jaw's readout.
# Measured against the inelastic volume floor it replaces (a position projection after the contacts, which
# held nodes passed to their jaws outside the friction law), on a 5 N force-loop pinch of the coarse spleen:
# see docs/design.md.
# -------------------------------------------------------------------------------------------------

#: below VOLUME_J_MIN x J_c the barrier's slope continues linearly (finite arithmetic through J <= 0)
VOLUME_J_MIN = 0.02


@kernel(inline="always")
def _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z):
    """e1 . (e2 x e3): six times the signed volume of the tet spanned by three edge vectors."""
    return e1x * (e2y * e3z - e2z * e3y) + e1y * (e2z * e3x - e2x * e3z) + e1z * (e2x * e3y - e2y * e3x)


@kernel(inline="always")
def _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z):
    """dV/dx_b, dV/dx_c, dV/dx_d (9 floats) of V = e1 . (e2 x e3) / 6 (dV/dx_a is minus their sum)."""
    return (
        (e2y * e3z - e2z * e3y) / 6.0, (e2z * e3x - e2x * e3z) / 6.0, (e2x * e3y - e2y * e3x) / 6.0,
        (e3y * e1z - e3z * e1y) / 6.0, (e3z * e1x - e3x * e1z) / 6.0, (e3x * e1y - e3y * e1x) / 6.0,
        (e1y * e2z - e1z * e2y) / 6.0, (e1z * e2x - e1x * e2z) / 6.0, (e1x * e2y - e1y * e2x) / 6.0,
    )


@kernel(inline="always")
def _tet_edges(x: np.ndarray, tets: np.ndarray, t: int):
    """Edge vectors e1, e2, e3 (9 floats) from node a of tet t, and its signed volume e1 . (e2 x e3) / 6."""
    a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    e3x, e3y, e3z = x[d, 0] - x[a, 0], x[d, 1] - x[a, 1], x[d, 2] - x[a, 2]
    vol = _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z) / 6.0
    return e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol


@kernel(inline="always")
def _tet_edges_lane(x: np.ndarray, a: int, b: int, c: int, d: int, lane: int):
    """:func:`_tet_edges` of one tissue of a lane-layout batch x (N,3,L)."""
    e1x, e1y, e1z = x[b, 0, lane] - x[a, 0, lane], x[b, 1, lane] - x[a, 1, lane], x[b, 2, lane] - x[a, 2, lane]
    e2x, e2y, e2z = x[c, 0, lane] - x[a, 0, lane], x[c, 1, lane] - x[a, 1, lane], x[c, 2, lane] - x[a, 2, lane]
    e3x, e3y, e3z = x[d, 0, lane] - x[a, 0, lane], x[d, 1, lane] - x[a, 1, lane], x[d, 2, lane] - x[a, 2, lane]
    vol = _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z) / 6.0
    return e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol




@kernel(inline="always")
def barrier_slopes(jac: float, j_c: float):
    """(psi'(J), psi''(J)) of the volume barrier per unit modulus at volume ratio ``jac`` (threshold ``j_c``);
    (0, 0) at and above the threshold."""
    if jac >= j_c:
        return 0.0, 0.0
    j = max(jac, VOLUME_J_MIN * j_c)
    dj = j - j_c
    lg = math.log(j / j_c)
    d1 = -(2.0 * dj * lg + dj * dj / j)
    d2 = -(2.0 * lg + 4.0 * dj / j - dj * dj / (j * j))
    return d1 + d2 * (jac - j), d2  # (jac - j is 0 above VOLUME_J_MIN x J_c)


@kernel(inline="always")
def barrier_psi(jac: float, j_c: float) -> float:
    """psi(J) of the volume barrier per unit modulus (its energy is k V0 psi); continued as a quadratic below
    VOLUME_J_MIN x J_c, with the slopes :func:`barrier_slopes` returns there."""
    if jac >= j_c:
        return 0.0
    j = max(jac, VOLUME_J_MIN * j_c)
    dj = j - j_c
    psi = -dj * dj * math.log(j / j_c)
    if jac < j:
        d1, d2 = barrier_slopes(j, j_c)
        s = jac - j
        psi += d1 * s + 0.5 * d2 * s * s
    return psi


@kernel(inline="always")
def below_barrier(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, j_c: float, t: int) -> bool:
    """Is tet t of one tissue x (N,3) compressed below the barrier's threshold ``j_c`` x its rest volume?"""
    return _tet_edges(x, tets, t)[9] < j_c * rest_volume[t]


@kernel
def flag_barrier(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, j_c: float, flagged: np.ndarray) -> int:
    """The barrier's flag pass for one tissue x (N,3): flagged (T,) int8 out (1: below ``j_c``); returns how
    many tets are flagged."""
    n_flagged = 0
    for t in range(tets.shape[0]):
        below = _tet_edges(x, tets, t)[9] < j_c * rest_volume[t]
        flagged[t] = 1 if below else 0
        n_flagged += 1 if below else 0
    return n_flagged


# -------------------------------------------------------------------------------------------------
# The flag pass's watch list (CPU). Finding the tets below J_c takes a volume per tet and substep, a quarter of a
# one-tissue substep, although a tet far above the threshold cannot reach it in a few substeps. So a full pass
# also lists the tets that could. V = e1 . (e2 x e3) / 6 with e_i = x_i - x_a; let every node move by u_a with
# |u_a - c| <= delta for a common translation c (which leaves volumes unchanged). Each edge vector then moves by
# at most 2 delta, and expanding the triple product (its first-order term is sum_a g_a . (u_a - c), with the
# volume gradients g_a, which sum to zero) gives
#     |V - V_ref| <= delta sum_a |g_a| + (2/3) delta^2 (|e1| + |e2| + |e3|) + (4/3) delta^3
#                 <= delta 2 sqrt(sum_a |g_a|^2) + (2/3) delta^2 sqrt(3 sum_i |e_i|^2) + (4/3) delta^3
# (Cauchy-Schwarz, equal where the gradients are, as in a well-shaped tet; tested squared, :func:`_watched`).
# A tet whose slack V_ref - J_c V0 exceeds that bound (with head room for round-off) for the budget delta cannot
# be below the threshold while the nodes stay within the budget; between full passes only the listed tets'
# volumes are computed. The flags are exactly those of a full pass, so impulses and trajectories are bitwise
# unchanged.
# -------------------------------------------------------------------------------------------------

#: a tet is watched where its slack is at most this multiple of the bound above (head room for round-off, which
#: is ~1e-16 of the terms)
WATCH_SAFETY = 1.25
#: the displacement budget between full passes, as a fraction of the mesh's mean rest spring length (coarse
#: spleen under a pinch: the watch list and the full passes' frequency, msdgrasp bench profile)
WATCH_DELTA = 0.02


@kernel(inline="always")
def _watched(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, slack, delta) -> bool:
    """Could a tet with edge vectors e1-e3 (m) and volume slack ``slack`` (m^3) above the threshold fall below it
    while no node moves more than ``delta`` (m, after a common translation)? The bound above, S (a + b + c), tested
    without square roots (branch-free, SIMD): (a + b)^2 <= 1.1 a^2 + 11 b^2, which loosens it by at most 5 % where
    b << a (b / a ~ delta / edge length)."""
    gbx, gby, gbz, gcx, gcy, gcz, gdx, gdy, gdz = _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    gax, gay, gaz = gbx + gcx + gdx, gby + gcy + gdy, gbz + gcz + gdz
    g2 = (gax * gax + gay * gay + gaz * gaz + gbx * gbx + gby * gby + gbz * gbz + gcx * gcx + gcy * gcy + gcz * gcz
          + gdx * gdx + gdy * gdy + gdz * gdz)
    e2 = e1x * e1x + e1y * e1y + e1z * e1z + e2x * e2x + e2y * e2y + e2z * e2z + e3x * e3x + e3y * e3y + e3z * e3z
    s2 = WATCH_SAFETY * WATCH_SAFETY * delta * delta
    a2 = 4.0 * s2 * g2  # (S delta 2 sqrt(g2))^2
    b2 = (4.0 / 3.0) * s2 * delta * delta * e2  # (S (2/3) delta^2 sqrt(3 e2))^2
    rest = slack - WATCH_SAFETY * (4.0 / 3.0) * delta * delta * delta
    return not (rest > 0.0 and rest * rest > 1.1 * a2 + 11.0 * b2)  # (a NaN slack is watched)


@kernel
def displacement_spread(x: np.ndarray, x_ref: np.ndarray, nl: int, lohi: np.ndarray) -> float:
    """How far (m) any node of any lane has moved from x_ref, after the best common translation of its lane:
    half the diagonal of the bounding box of the displacements. x, x_ref (N, 3 L) in lane layout (column
    c L + lane), lohi (3, 3 L) scratch. NaN where a position is not finite."""
    if nl == 1:
        return _displacement_spread_one(x, x_ref)
    w = x.shape[1]
    for k in range(w):
        lohi[0, k] = x[0, k] - x_ref[0, k]
        lohi[1, k] = lohi[0, k]
        lohi[2, k] = 0.0
    for i in range(x.shape[0]):
        for k in range(w):  # selects, not min/max (NaN rules): SIMD; non-finite values reach lohi[2] as NaN
            d = x[i, k] - x_ref[i, k]
            lo = lohi[0, k]
            hi = lohi[1, k]
            lohi[0, k] = d if d < lo else lo
            lohi[1, k] = d if d > hi else hi
            lohi[2, k] += d * 0.0
    spread = 0.0
    bad = 0.0
    for lane in range(nl):
        s2 = 0.0
        for c in range(3):
            k = c * nl + lane
            h = 0.5 * (lohi[1, k] - lohi[0, k])
            s2 += h * h
            bad += lohi[2, k]
        spread = max(spread, math.sqrt(s2))
    return spread if bad == 0.0 else math.nan


@kernel
def _displacement_spread_one(x: np.ndarray, x_ref: np.ndarray) -> float:
    """:func:`displacement_spread` of one tissue (N, 3): the bounds in scalars instead of a loop over 3 columns
    per node (2.4x faster, the same value: the same minima and maxima, summed in the same order)."""
    lx = x[0, 0] - x_ref[0, 0]
    ly = x[0, 1] - x_ref[0, 1]
    lz = x[0, 2] - x_ref[0, 2]
    hx, hy, hz = lx, ly, lz
    bad = 0.0
    for i in range(x.shape[0]):
        dx = x[i, 0] - x_ref[i, 0]
        dy = x[i, 1] - x_ref[i, 1]
        dz = x[i, 2] - x_ref[i, 2]
        lx = dx if dx < lx else lx
        hx = dx if dx > hx else hx
        ly = dy if dy < ly else ly
        hy = dy if dy > hy else hy
        lz = dz if dz < lz else lz
        hz = dz if dz > hz else hz
        bad += dx * 0.0 + dy * 0.0 + dz * 0.0  # NaN where any displacement is not finite
    h0 = 0.5 * (hx - lx)
    h1 = 0.5 * (hy - ly)
    h2 = 0.5 * (hz - lz)
    s2 = h0 * h0 + h1 * h1 + h2 * h2
    return math.sqrt(s2) if bad == 0.0 else math.nan


@kernel
def watch_barrier(x, tets, rest_volume, j_c, delta, flagged, n_flagged, watch) -> int:
    """The barrier's full flag pass over the lanes of x (N,3,L): flagged (T,L) int8 and n_flagged (L,) out, and
    ``watch`` (T,) filled in tet order with the tets any lane could push below ``j_c`` within the displacement
    budget ``delta`` (m); returns their count. One tissue is L = 1."""
    nl = x.shape[2]
    n_flagged[:] = 0
    nw = 0
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        vmin = j_c * rest_volume[t]
        near = 0
        for lane in range(nl):  # branch-free across lanes
            e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol = _tet_edges_lane(x, a, b, c, d, lane)
            below = vol < vmin
            flagged[t, lane] = 1 if below else 0
            n_flagged[lane] += 1 if below else 0
            near |= 1 if _watched(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol - vmin, delta) else 0
        watch[nw] = t
        nw += near
    return nw


@kernel
def flag_watched(x, tets, rest_volume, j_c, watch, n_watch, flagged, n_flagged) -> None:
    """The barrier's flag pass between full passes: only the watched tets (the rest stay unflagged, as a full pass
    would leave them while the nodes are within its budget). Arguments as :func:`watch_barrier`'s."""
    nl = x.shape[2]
    n_flagged[:] = 0
    if nl == 1:  # one tissue: no loop over one lane (half the time)
        count = 0
        for k in range(n_watch):
            t = watch[k]
            below = _tet_edges_lane(x, tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3], 0)[9] < j_c * rest_volume[t]
            flagged[t, 0] = 1 if below else 0
            count += 1 if below else 0
        n_flagged[0] = count
        return
    for k in range(n_watch):
        t = watch[k]
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        vmin = j_c * rest_volume[t]
        for lane in range(nl):
            below = _tet_edges_lane(x, a, b, c, d, lane)[9] < vmin
            flagged[t, lane] = 1 if below else 0
            n_flagged[lane] += 1 if below else 0


#: :func:`barrier_tet`'s gradients where the tet does not act (nothing reads them)
_NO_GRADIENTS = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@kernel(inline="always")
def barrier_tet(e, v0, k, j_c, dt, w, held):
    """The implicit barrier's law for one tet, in scalars (see above): e (9 floats) the edge vectors b - a, c - a,
    d - a (m); v0 its rest volume (m^3); k its modulus times the tissue's stiffness scale (Pa); j_c the threshold;
    dt the substep (s); w (4 floats) its nodes' inverse effective masses (1/kg; 0 for an anchored node); held (4
    bools) whether a jaw or plate holds each node. Returns (on, s, g): on False where the tet is at or above the
    threshold (then nothing moves), else the impulse s (N s / m^2: node q's velocity changes by s w_q g_q) along the
    volume gradients g (12 floats, nodes a, b, c, d; m^2). Every barrier loop (one tissue, lanes, the GPU's) calls
    this and applies :func:`node_impulse` to the four nodes; scalars only, so its loops keep no array references
    per tet (numba's reference counting of arrays passed into an inlined body cost 3-4x the arithmetic)."""
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = e
    vol = _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z) / 6.0
    jac = vol / v0
    d1, d2 = barrier_slopes(jac, j_c)
    if d1 == 0.0:  # (above the threshold, or moved back above it by an earlier tet's impulse)
        return False, 0.0, _NO_GRADIENTS
    gbx, gby, gbz, gcx, gcy, gcz, gdx, gdy, gdz = _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    gax, gay, gaz = -(gbx + gcx + gdx), -(gby + gcy + gdy), -(gbz + gcz + gdz)
    g = (gax, gay, gaz, gbx, gby, gbz, gcx, gcy, gcz, gdx, gdy, gdz)
    wa, wb, wc, wd = w
    # the mode's mobility W counts only the nodes that can follow the impulse: a node a jaw or plate holds
    # receives its share (which its contact then reacts to, inside the friction law) but does not move with
    # it, so counting it would size the impulse as if the tet could open there, and a held apex pressed into
    # a tet would creep through it (measured: the fine spleen inverted in a 2 s hold under a 5 N pinch)
    ww = ((0.0 if held[0] else wa) * (gax * gax + gay * gay + gaz * gaz)
          + (0.0 if held[1] else wb) * (gbx * gbx + gby * gby + gbz * gbz)
          + (0.0 if held[2] else wc) * (gcx * gcx + gcy * gcy + gcz * gcz)
          + (0.0 if held[3] else wd) * (gdx * gdx + gdy * gdy + gdz * gdz))
    p = k * d1 / (1.0 + dt * dt * k * d2 * ww / v0)
    return True, -dt * p, g


@kernel(inline="always")
def node_impulse(w, s, gx, gy, gz, dt):
    """A node's share s g (N s) of an implicit impulse (a tet's barrier, a spring's dashpot), w its inverse mass
    (1/kg): (dvx, dvy, dvz, fx, fy, fz), its velocity change w s g (its position moves dt times that), and for an
    anchored node (w = 0), which does not move, the force s g / dt that its anchor supplies against the impulse
    is minus (fx, fy, fz). Scalars only (see :func:`barrier_tet`)."""
    if w == 0.0:
        return 0.0, 0.0, 0.0, s * gx / dt, s * gy / dt, s * gz / dt
    return w * s * gx, w * s * gy, w * s * gz, 0.0, 0.0, 0.0


@kernel(inline="always")
def kick_node(x, v, i, dv, dt) -> None:
    """Node i of x, v (N,3) takes the velocity change dv (3 floats, m/s; :func:`node_impulse`) and moves dt times it.
    Straight-line code, so numba's reference counts of the arrays it inlines with cancel within one block (a body
    that branches keeps them: see :func:`barrier_tet`)."""
    v[i, 0] += dv[0]
    v[i, 1] += dv[1]
    v[i, 2] += dv[2]
    x[i, 0] += dt * dv[0]
    x[i, 1] += dt * dv[1]
    x[i, 2] += dt * dv[2]


@kernel(inline="always")
def barrier_impulse(x, v, meff, pins, tets, rest_volume, kvol, j_c, ks, dt, t, anchor) -> None:
    """Tet t's implicit barrier impulse on one tissue x, v (N,3) (:func:`barrier_tet` and :func:`node_impulse`; the
    arguments as :func:`implicit_volume_barrier`'s): the body of its loop, which the GPU step runs on its own list
    of flagged tets."""
    fixed, held = pins
    a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    nodes = (a, b, c, d)
    w = (0.0 if fixed[a] else 1.0 / meff[a], 0.0 if fixed[b] else 1.0 / meff[b],
         0.0 if fixed[c] else 1.0 / meff[c], 0.0 if fixed[d] else 1.0 / meff[d])
    on, s, g = barrier_tet((x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2],
                            x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2],
                            x[d, 0] - x[a, 0], x[d, 1] - x[a, 1], x[d, 2] - x[a, 2]),
                           rest_volume[t], ks * kvol[t], j_c, dt, w,
                           (held[a] != 0, held[b] != 0, held[c] != 0, held[d] != 0))
    if not on:
        return
    for q in range(4):
        i = nodes[q]
        dvx, dvy, dvz, fx, fy, fz = node_impulse(w[q], s, g[3 * q], g[3 * q + 1], g[3 * q + 2], dt)
        if w[q] == 0.0:
            anchor[0] -= fx
            anchor[1] -= fy
            anchor[2] -= fz
        else:
            kick_node(x, v, i, (dvx, dvy, dvz), dt)


@kernel
def implicit_volume_barrier(
    x: np.ndarray,  # (N,3) positions of one tissue after the explicit update, m (modified)
    v: np.ndarray,  # (N,3) velocities, m/s (modified)
    meff: np.ndarray,  # (N,) effective masses m + dt b, kg (as the contacts use them)
    pins: tuple,  # (fixed (N,) bool: anchored nodes, which do not move (their anchor takes the force); held (N,)
    #               int8: != 0 for the nodes a jaw or plate held in the last substep's contacts)
    tets: np.ndarray,  # (T,4) int
    rest_volume: np.ndarray,  # (T,) m^3
    kvol: np.ndarray,  # (T,) Pa
    j_c: float,  # the barrier's threshold J_c
    ks: float,  # stiffness scale of this tissue
    dt: float,  # substep, s
    flagged: np.ndarray,  # (T,) int8: 1 for the tets below J_c (:func:`flag_barrier`)
    anchor: np.ndarray,  # (3,) N: the force the anchors supply against the barrier is ADDED here
) -> None:
    """The volume barrier's implicit impulses on every flagged tet of one tissue, in tet order (see above)."""
    for t in range(tets.shape[0]):
        if flagged[t] != 0:
            barrier_impulse(x, v, meff, pins, tets, rest_volume, kvol, j_c, ks, dt, t, anchor)


@kernel
def implicit_volume_barrier_lanes(x, v, meff, pins, tets, rest_volume, kvol, j_c, ks, dt, visit, anchor) -> None:
    """:func:`implicit_volume_barrier` on the watched tets of every tissue of a lane block x, v (N,3,L), meff
    (N,L), ks (L,) (one tissue: L = 1): pins (fixed (N,) bool, held (L,N) int8), visit (flags (T,L) int8, watch,
    n_watch: ``watch[:n_watch]`` in tet order, every flagged tet among them), anchor (L,3) N ADDED to per tissue.
    Tet after tet, the tissues innermost: each tissue sees its tets in the same order and the same arithmetic as
    alone (bitwise), and the tissues' impulses, independent of each other, overlap in the CPU (15 % faster than
    tissue after tissue on the bench's grasp). The loop reads and writes the arrays itself and hands
    :func:`barrier_tet` and :func:`node_impulse` scalars: 4x faster than inlining :func:`barrier_impulse` on
    views, whose array arguments numba reference-counts per tet (the bench's grasp, one tissue)."""
    fixed, held = pins
    flags, watch, n_watch = visit
    for k in range(n_watch):
        t = watch[k]
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        nodes = (a, b, c, d)
        v0 = rest_volume[t]
        kt = kvol[t]
        for lane in range(x.shape[2]):
            if flags[t, lane] == 0:
                continue
            w = (0.0 if fixed[a] else 1.0 / meff[a, lane], 0.0 if fixed[b] else 1.0 / meff[b, lane],
                 0.0 if fixed[c] else 1.0 / meff[c, lane], 0.0 if fixed[d] else 1.0 / meff[d, lane])
            xa0, xa1, xa2 = x[a, 0, lane], x[a, 1, lane], x[a, 2, lane]
            on, s, g = barrier_tet((x[b, 0, lane] - xa0, x[b, 1, lane] - xa1, x[b, 2, lane] - xa2,
                                    x[c, 0, lane] - xa0, x[c, 1, lane] - xa1, x[c, 2, lane] - xa2,
                                    x[d, 0, lane] - xa0, x[d, 1, lane] - xa1, x[d, 2, lane] - xa2),
                                   v0, ks[lane] * kt, j_c, dt, w,
                                   (held[lane, a] != 0, held[lane, b] != 0, held[lane, c] != 0, held[lane, d] != 0))
            if not on:
                continue
            for q in range(4):
                i = nodes[q]
                dvx, dvy, dvz, fx, fy, fz = node_impulse(w[q], s, g[3 * q], g[3 * q + 1], g[3 * q + 2], dt)
                if w[q] == 0.0:
                    anchor[lane, 0] -= fx
                    anchor[lane, 1] -= fy
                    anchor[lane, 2] -= fz
                else:
                    v[i, 0, lane] += dvx
                    v[i, 1, lane] += dvy
                    v[i, 2, lane] += dvz
                    x[i, 0, lane] += dt * dvx
                    x[i, 1, lane] += dt * dvy
                    x[i, 2, lane] += dt * dvz


@kernel
def volume_energy(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, kvol: np.ndarray,
                  j_threshold: float) -> float:
    """Energy (J) of the volume barrier: sum over tets with J < J_c of k V0 psi(J)."""
    total = 0.0
    for t in range(tets.shape[0]):
        total += kvol[t] * rest_volume[t] * barrier_psi(_tet_edges(x, tets, t)[9] / rest_volume[t], j_threshold)
    return total


@kernel
def volume_forces(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, kvol: np.ndarray, j_threshold: float,
                  kscale: float, f: np.ndarray) -> None:
    """The barrier's (explicit) forces -k psi'(J) dV/dx ADDED to f (N,3): what the implicit step integrates; for
    diagnostics, the static reference and tests."""
    for t in range(tets.shape[0]):
        e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol = _tet_edges(x, tets, t)
        d1 = barrier_slopes(vol / rest_volume[t], j_threshold)[0]
        if d1 == 0.0:
            continue
        s = -kscale * kvol[t] * d1
        gb = _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        for kk in range(3):
            f[b, kk] += s * gb[kk]
            f[c, kk] += s * gb[3 + kk]
            f[d, kk] += s * gb[6 + kk]
            f[a, kk] -= s * (gb[kk] + gb[3 + kk] + gb[6 + kk])


@kernel
def min_volume_ratios(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, out: np.ndarray) -> None:
    """out[b] = smallest current / rest volume over the tets of tissue b of a batch x (B,N,3); <= 0 means a tet
    has inverted. (A kernel: the env checks it every agent step, where NumPy's gathers cost ~10x more.)"""
    for b in range(x.shape[0]):
        xb = x[b]
        lo = np.inf
        for t in range(tets.shape[0]):
            r = _tet_edges(xb, tets, t)[9] / rest_volume[t]
            if r < lo:
                lo = r
        out[b] = lo

