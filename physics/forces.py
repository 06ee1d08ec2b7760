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
damp rigid motion.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .records import Springs


@njit(cache=True, inline="always", error_model="numpy")
def spring_force(dl: float, k1: float, k2: float, dlc: float) -> float:
    """Tension (N) of one nonlinear spring stretched by ``dl`` metres (Eq. 4-6, corrected B)."""
    adl = abs(dl)
    if adl <= dlc:
        return k1 * dl + k2 * dl * dl * dl
    a = k1 * dlc + k2 * dlc * dlc * dlc
    b = k1 + 3.0 * k2 * dlc * dlc
    f = a + b * (adl - dlc)
    return f if dl > 0.0 else -f


@njit(cache=True, inline="always", error_model="numpy")
def spring_tangent(dl: float, k1: float, k2: float, dlc: float) -> float:
    """dF/d(dl) (N/m): K1 + 3 K2 dl^2 inside dl_c, the constant B beyond."""
    adl = min(abs(dl), dlc)
    return k1 + 3.0 * k2 * adl * adl


@njit(cache=True, error_model="numpy")
def spring_force_array(dl: np.ndarray, k1: float, k2: float, dlc: float) -> np.ndarray:
    out = np.empty_like(dl)
    for i in range(dl.size):
        out.flat[i] = spring_force(dl.flat[i], k1, k2, dlc)
    return out


@njit(cache=True, inline="always", error_model="numpy")
def spring_body(d, law, ks, dash, maxwell, flags):
    """One spring's force on its first node and its new Maxwell state: the arithmetic every spring loop
    (one tissue, lanes, the GPU kernel) runs per spring, in one order, so their results are bitwise equal.

    d (dx, dy, dz): x_j - x_i, m; law (rest length m, k1 N/m, k2 N/m^3, dl_c m); ks: stiffness scale;
    dash (v_j - v_i (3 floats) m/s, c N s/m): read only with dashpots; maxwell (F_v N, dl at the last substep
    m, k_v N/m, e^(-dt/tau), (tau/dt)(1 - e^(-dt/tau))): read only with the Maxwell branch; flags
    (use_dashpot, use_sls). Returns (fx, fy, fz, F_v, dl): the force on node i (minus it on node j) and the
    Maxwell state to store. A spring between coincident nodes (length < 1e-15 m, only in a collapsed mesh)
    has no direction: it adds nothing and keeps its Maxwell state.
    """
    dx, dy, dz = d
    rest, k1, k2, dlc = law
    fv, dl_prev, kv, decay, gain = maxwell
    use_dashpot, use_sls = flags
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    ok = length >= 1e-15
    inv = 1.0 / length
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
    return fs * ux if ok else 0.0, fs * uy if ok else 0.0, fs * uz if ok else 0.0, fv, dl_prev


@njit(cache=True, error_model="numpy")
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
                                           (fv[e], dl_prev[e], kv[e], decay, gain), flags)
        if use_sls:
            fv[e] = fve
            dl_prev[e] = dle
        scratch[6, e] = fx
        scratch[7, e] = fy
        scratch[8, e] = fz
    for e in range(ne):
        i = edges[e, 0]
        j = edges[e, 1]
        f[i, 0] += scratch[6, e]
        f[i, 1] += scratch[7, e]
        f[i, 2] += scratch[8, e]
        f[j, 0] -= scratch[6, e]
        f[j, 1] -= scratch[7, e]
        f[j, 2] -= scratch[8, e]


# -------------------------------------------------------------------------------------------------
# Lane layout: a batch of tissues stored tissue-innermost, x[i, c, lane] (N,3,L). The loops over lanes
# have no branches and unit stride, so LLVM turns them into SIMD code (4 tissues per AVX2 instruction):
# the spring loop costs ~3.5 ns per spring and tissue at L = 64 instead of ~7.4 ns. Each lane does the same
# floating-point operations in the same order as the one-tissue kernels, so results are bitwise equal.
# -------------------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
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
) -> None:
    """:func:`spring_loop` for L tissues at once (lane layout); bitwise equal to it per tissue."""
    edges, use_dashpot, use_sls = springs.edges, springs.use_dashpot, springs.use_sls
    flags = (use_dashpot, use_sls)
    nl = x.shape[2]
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        law = (springs.rest_length[e], springs.k1[e], springs.k2[e], springs.dlc[e])
        kve = springs.kv[e] if use_sls else 0.0
        cd = springs.cdash[e] if use_dashpot else 0.0
        for b in range(nl):
            d = (x[j, 0, b] - x[i, 0, b], x[j, 1, b] - x[i, 1, b], x[j, 2, b] - x[i, 2, b])
            dash = (v[j, 0, b] - v[i, 0, b], v[j, 1, b] - v[i, 1, b], v[j, 2, b] - v[i, 2, b], cd) if use_dashpot \
                else (0.0, 0.0, 0.0, 0.0)
            fx, fy, fz, fve, dle = spring_body(d, law, kscale[b], dash, (fv[e, b], dl_prev[e, b], kve, decay, gain),
                                               flags)
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


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
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


# -------------------------------------------------------------------------------------------------
# Volume barrier per tet (TissueParams.volume_modulus_pa). A spring network resists a tet's collapse
# only through its six edge lengths, so under large local compression (under the jaws, or the sphere
# between plates beyond ~20 %) tets flatten and invert. With J_t = V_t / V0_t and a threshold J_c, the
# energy
#     U_t = (k_t / 2) V0_t (J_c - J_t)^2   for J_t < J_c,   0 otherwise,
# adds a bulk stiffness k_t (Pa) only to strongly compressed tets (J_c = 0.5 by default: a tet that has
# lost half its volume), and keeps growing through J = 0: an inverted tet is pushed back. Below the
# threshold the network is the paper's pure MSD. Forces -dU/dx_a = -k (J - J_c) dV/dx_a, with
# dV/dx_a = (area vector of the face opposite a, pointing away from a) / 3; they sum to zero
# (momentum exact) and exert no torque. A threshold > 1 gives a two-sided volume term.
# -------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always", error_model="numpy")
def _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z):
    """e1 . (e2 x e3): six times the signed volume of the tet spanned by three edge vectors."""
    return e1x * (e2y * e3z - e2z * e3y) + e1y * (e2z * e3x - e2x * e3z) + e1z * (e2x * e3y - e2y * e3x)


@njit(cache=True, inline="always", error_model="numpy")
def _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z):
    """dV/dx_b, dV/dx_c, dV/dx_d (9 floats) of V = e1 . (e2 x e3) / 6 (dV/dx_a is minus their sum)."""
    return (
        (e2y * e3z - e2z * e3y) / 6.0, (e2z * e3x - e2x * e3z) / 6.0, (e2x * e3y - e2y * e3x) / 6.0,
        (e3y * e1z - e3z * e1y) / 6.0, (e3z * e1x - e3x * e1z) / 6.0, (e3x * e1y - e3y * e1x) / 6.0,
        (e1y * e2z - e1z * e2y) / 6.0, (e1z * e2x - e1x * e2z) / 6.0, (e1x * e2y - e1y * e2x) / 6.0,
    )


@njit(cache=True, inline="always", error_model="numpy")
def _tet_edges(x: np.ndarray, tets: np.ndarray, t: int):
    """Edge vectors e1, e2, e3 (9 floats) from node a of tet t, and its signed volume e1 . (e2 x e3) / 6."""
    a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    e1x, e1y, e1z = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
    e2x, e2y, e2z = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
    e3x, e3y, e3z = x[d, 0] - x[a, 0], x[d, 1] - x[a, 1], x[d, 2] - x[a, 2]
    vol = _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z) / 6.0
    return e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol


@njit(cache=True, inline="always", error_model="numpy")
def _tet_edges_lane(x: np.ndarray, a: int, b: int, c: int, d: int, lane: int):
    """:func:`_tet_edges` of one tissue of a lane-layout batch x (N,3,L)."""
    e1x, e1y, e1z = x[b, 0, lane] - x[a, 0, lane], x[b, 1, lane] - x[a, 1, lane], x[b, 2, lane] - x[a, 2, lane]
    e2x, e2y, e2z = x[c, 0, lane] - x[a, 0, lane], x[c, 1, lane] - x[a, 1, lane], x[c, 2, lane] - x[a, 2, lane]
    e3x, e3y, e3z = x[d, 0, lane] - x[a, 0, lane], x[d, 1, lane] - x[a, 1, lane], x[d, 2, lane] - x[a, 2, lane]
    vol = _volume6(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z) / 6.0
    return e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol


@njit(cache=True, inline="always", error_model="numpy")
def tet_barrier_body(geom, v0, kvol, j_threshold, ks):
    """The volume barrier's forces on the four nodes of one tet past its threshold: the arithmetic every
    barrier loop (one tissue, lanes, the GPU kernel) runs per tet.

    geom: the tet's edge vectors and volume (:func:`_tet_edges`); v0: rest volume, m^3; kvol: Pa;
    j_threshold: J_c; ks: stiffness scale. Returns the forces (N) on nodes b, c, d and a (12 floats)."""
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol = geom
    jac = vol / v0
    # gradients of V = e1 . (e2 x e3) / 6 with respect to x_b, x_c, x_d
    gbx, gby, gbz, gcx, gcy, gcz, gdx, gdy, gdz = _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    s = -ks * kvol * (jac - j_threshold)
    return (s * gbx, s * gby, s * gbz, s * gcx, s * gcy, s * gcz, s * gdx, s * gdy, s * gdz,
            -(s * (gbx + gcx + gdx)), -(s * (gby + gcy + gdy)), -(s * (gbz + gcz + gdz)))


@njit(cache=True, error_model="numpy")
def accumulate_volume_forces(
    x: np.ndarray,  # (N,3) positions, m
    tets: np.ndarray,  # (T,4) int, positively oriented at rest
    rest_volume: np.ndarray,  # (T,) m^3
    kvol: np.ndarray,  # (T,) Pa
    j_threshold: float,  # J_c: the barrier acts on tets with V / V0 < J_c
    kscale: float,
    f: np.ndarray,  # (N,3) out: forces are ADDED here
    vols: np.ndarray | None = None,  # (T,) m^3: the tets' volumes at x when the caller has them (the floor's pass)
) -> None:
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        # most tets are far from the threshold: test J before computing the gradients
        if vols is None:
            vol = _tet_edges(x, tets, t)[9]
        else:
            vol = vols[t]
        if vol >= j_threshold * rest_volume[t]:
            continue
        r = tet_barrier_body(_tet_edges(x, tets, t), rest_volume[t], kvol[t], j_threshold, kscale)
        # (adding the force on a is bitwise the same as subtracting its negative)
        for k in range(3):
            f[b, k] += r[k]
            f[c, k] += r[3 + k]
            f[d, k] += r[6 + k]
        for k in range(3):
            f[a, k] += r[9 + k]


@njit(cache=True, error_model="numpy")
def accumulate_volume_forces_lanes(
    x: np.ndarray,  # (N,3,L) positions, m
    tets: np.ndarray,
    rest_volume: np.ndarray,
    kvol: np.ndarray,
    j_threshold: float,
    kscale: np.ndarray,  # (L,)
    f: np.ndarray,  # (N,3,L) out: forces are ADDED here
    s: np.ndarray,  # (L,) scratch
    vols: np.ndarray | None = None,  # (T,L) m^3: the tets' volumes at x when the caller has them
) -> None:
    """:func:`accumulate_volume_forces` for L tissues at once (lane layout); bitwise equal per tissue."""
    nl = x.shape[2]
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        v0 = rest_volume[t]
        vthr = j_threshold * v0
        k = kvol[t]
        active = 0
        for lane in range(nl):  # no division here: this pass runs for every tet and lane
            if vols is None:
                vol = _tet_edges_lane(x, a, b, c, d, lane)[9]
            else:
                vol = vols[t, lane]
            s[lane] = vol
            active += 1 if vol < vthr else 0
        if active == 0:  # the common case: no tissue has this tet past the threshold
            continue
        for lane in range(nl):
            if s[lane] < vthr:  # (the volume in the geometry is s[lane]: the same positions, the same operations)
                r = tet_barrier_body(_tet_edges_lane(x, a, b, c, d, lane), v0, k, j_threshold, kscale[lane])
                for kk in range(3):
                    f[b, kk, lane] += r[kk]
                    f[c, kk, lane] += r[3 + kk]
                    f[d, kk, lane] += r[6 + kk]
                for kk in range(3):
                    f[a, kk, lane] += r[9 + kk]


@njit(cache=True, error_model="numpy")
def volume_energy(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, kvol: np.ndarray, j_threshold: float) -> float:
    """Energy (J) of the volume barrier: sum over tets with J < J_c of (k / 2) V0 (J_c - J)^2."""
    total = 0.0
    for t in range(tets.shape[0]):
        vol = _tet_edges(x, tets, t)[9]
        j = j_threshold - vol / rest_volume[t]
        if j > 0.0:
            total += 0.5 * kvol[t] * rest_volume[t] * j * j
    return total


@njit(cache=True, error_model="numpy")
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


# -------------------------------------------------------------------------------------------------
# Volume floor (TissueParams.volume_floor): an inelastic limit on compression, enforced as a constraint
# like the contacts (a position correction with the matching velocity change), not as a force. The barrier
# above is a force of bounded stiffness (the explicit step's stability limit counts it), so a pinch that
# pushes one surface node past its neighbours can still crush and invert a tet; a stiffer barrier costs
# substeps and stores the crushing energy, which a slip-off releases as a wave that inverts tets anyway.
# The floor stores no energy and costs no substeps: at the end of every substep, every tet with J = V / V0
# below J_f is restored to J_f by moving its nodes along dV/dx, weighted by their inverse effective masses
# (momentum exact), with x and v changed together (x_new = x_old + dt v_new, as a contact does). The tets
# are corrected one after the other (Gauss-Seidel: a later tet sees an earlier one's correction), in tet
# order, for FLOOR_PASSES passes.
# It runs after the contacts, and the nodes a jaw or plate holds in this substep (and anchored nodes) do not
# move in it: the rest of the tet moves, and the force that moves it comes through the held node from its
# holder, which counts it in its readout (:func:`.contact.floor_reactions`).
# Measured alternatives (5 N force-loop pinch in the env, 9 stiffness x mu cases):
# * before the contacts with every node free: the contact undoes the held node's share, so tets under a
#   jaw end substeps below J_f (J_f = 0.2: fine mesh down to -0.04; J_f = 0.3 keeps every resolution > 0.04,
#   but the spleen protocol's T / N at gross slip rises to 1.7 mu);
# * after the contacts with every node free: the correction's sideways kick on sticking nodes breaks stick
#   and the grasp is lost at mu = 0.9;
# * held nodes moving when the free ones can hardly change the volume: the same slips.
# This version, J_f = 0.2 (at the env's former 2 substeps): smallest ratio over the 9 cases 0.178 coarse,
# 0.129 medium, 0.071 fine (the fine mesh's tets end substeps below J_f where one free node sits across a
# sliver face from held ones and FLOOR_MAX_MOVE limits the correction, but none inverts).

#: Gauss-Seidel passes of the volume floor per substep (tets that share nodes correct each other)
FLOOR_PASSES = 2
#: largest move of a node in one correction, in edge lengths of the tet's rest shape (a larger deficit takes
#: more substeps; a substep crushes a tet by far less)
FLOOR_MAX_MOVE = 0.05


@njit(cache=True, inline="always", error_model="numpy")
def below_volume_floor(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, j_floor: float, t: int) -> bool:
    """Is tet t of one tissue x (N,3) compressed below ``j_floor`` x its rest volume?"""
    return _tet_edges(x, tets, t)[9] < j_floor * rest_volume[t]


@njit(cache=True, error_model="numpy")
def enforce_volume_floor(x, v, meff, fixed, held, tets, rest_volume, j_floor, dt, flagged, react) -> bool:
    """The volume floor of one tissue for one substep (CPU): flag the tets below it, then restore them.
    True when it acted (``react`` then holds the reactions at held and anchored nodes)."""
    if flag_volume_floor(x, tets, rest_volume, j_floor, flagged, np.empty(tets.shape[0])) == 0:
        return False
    project_volume_floor(x, v, meff, fixed, held, tets, rest_volume, j_floor, dt, flagged, react)
    return True


@njit(cache=True, error_model="numpy")
def flag_volume_floor(x, tets, rest_volume, j_floor, flagged, vols) -> int:
    """The floor's flag pass for one tissue x (N,3): flagged (T,) int8 and the volumes vols (T,) m^3 out;
    returns how many tets are below the floor. Where the floor then moves nothing, the next substep's barrier
    reuses ``vols`` (the positions are the same), so the floor costs little more than this pass
    (contiguous arrays: on strided (T,1) views both passes were 1.7x slower)."""
    n_flagged = 0
    for t in range(tets.shape[0]):
        vol = _tet_edges(x, tets, t)[9]
        vols[t] = vol
        below = vol < j_floor * rest_volume[t]
        flagged[t] = 1 if below else 0
        n_flagged += 1 if below else 0
    return n_flagged


@njit(cache=True, error_model="numpy")
def refresh_floor_volumes(x, tets, flagged, mark, vols) -> None:
    """After :func:`project_volume_floor` moved nodes of the flagged tets of one tissue x (N,3): recompute
    ``vols`` (T,) m^3 for every tet that shares a node with a flagged tet (only those nodes can have moved), so
    that the next barrier pass can still reuse them. ``mark`` (N,) int8 scratch, zero on entry and on exit.
    On the fine spleen the floor acts at the rigid anchors in every substep, and recomputing all volumes
    there cost the barrier's whole pass."""
    nt = tets.shape[0]
    for t in range(nt):
        if flagged[t]:
            for k in range(4):
                mark[tets[t, k]] = 1
    for t in range(nt):
        if mark[tets[t, 0]] | mark[tets[t, 1]] | mark[tets[t, 2]] | mark[tets[t, 3]]:
            vols[t] = _tet_edges(x, tets, t)[9]
    for t in range(nt):
        if flagged[t]:
            for k in range(4):
                mark[tets[t, k]] = 0


@njit(cache=True, error_model="numpy")
def flag_volume_floor_lanes(x, tets, rest_volume, j_floor, flagged, n_flagged, vols) -> None:
    """:func:`flag_volume_floor` for L tissues at once (lane layout x (N,3,L)): flagged (T,L) int8, n_flagged
    (L,) int64 and the volumes vols (T,L) m^3 out. One pass over the tets across lanes (SIMD, as the
    barrier's): a pass per lane on the strided (N,3) view cost 0.75x the whole batched step."""
    nl = x.shape[2]
    n_flagged[:] = 0
    for t in range(tets.shape[0]):
        a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        vmin = j_floor * rest_volume[t]
        for lane in range(nl):
            vol = _tet_edges_lane(x, a, b, c, d, lane)[9]
            vols[t, lane] = vol
            below = vol < vmin
            flagged[t, lane] = 1 if below else 0
            n_flagged[lane] += 1 if below else 0


@njit(cache=True, error_model="numpy")
def project_volume_floor(
    x: np.ndarray,  # (N,3) positions of one tissue, m (modified)
    v: np.ndarray,  # (N,3) velocities, m/s (modified)
    meff: np.ndarray,  # (N,) effective masses m + dt b, kg (as the contacts use them)
    fixed: np.ndarray,  # (N,) bool: anchored nodes do not move
    held: np.ndarray,  # (N,) int8: != 0 for nodes a jaw or plate holds this substep; they do not move either
    tets: np.ndarray,  # (T,4) int
    rest_volume: np.ndarray,  # (T,) m^3
    j_floor: float,  # J_f: the smallest volume ratio a tet may keep
    dt: float,  # substep, s
    flagged: np.ndarray,  # (T,) int8: 1 for the tets found below the floor (:func:`flag_volume_floor`)
    react: np.ndarray,  # (N,3) N: the force through each held or anchored node is ADDED here
) -> None:
    """Restore every flagged tet to ``j_floor`` x its rest volume (see the comment above)."""
    inv_dt = 1.0 / dt
    for _ in range(FLOOR_PASSES):
        for t in range(tets.shape[0]):
            if flagged[t] == 0:
                continue
            e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, vol = _tet_edges(x, tets, t)
            deficit = j_floor * rest_volume[t] - vol
            if deficit <= 0.0:
                continue
            gbx, gby, gbz, gcx, gcy, gcz, gdx, gdy, gdz = _volume_gradients(e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
            gax, gay, gaz = -(gbx + gcx + gdx), -(gby + gcy + gdy), -(gbz + gcz + gdz)
            a, b, c, d = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
            ga2, gb2 = gax * gax + gay * gay + gaz * gaz, gbx * gbx + gby * gby + gbz * gbz
            gc2, gd2 = gcx * gcx + gcy * gcy + gcz * gcz, gdx * gdx + gdy * gdy + gdz * gdz
            wa = 0.0 if fixed[a] or held[a] != 0 else 1.0 / meff[a]
            wb = 0.0 if fixed[b] or held[b] != 0 else 1.0 / meff[b]
            wc = 0.0 if fixed[c] or held[c] != 0 else 1.0 / meff[c]
            wd = 0.0 if fixed[d] or held[d] != 0 else 1.0 / meff[d]
            denom = wa * ga2 + wb * gb2 + wc * gc2 + wd * gd2
            if denom <= 0.0:  # a degenerate tet (all gradients zero) or four held nodes
                continue
            lam = deficit / denom  # linearised: V(x + lam W g) = V + lam g.W g
            # no node moves more than FLOOR_MAX_MOVE edge lengths per pass: with held nodes, the free one may sit
            # across a sliver face (tiny g), where the linearised step would throw it far (and blow up)
            move2 = max(wa * wa * ga2, wb * wb * gb2, wc * wc * gc2, wd * wd * gd2)
            cap = FLOOR_MAX_MOVE * 2.04 * rest_volume[t] ** (1.0 / 3.0)  # a regular tet's edge is 2.04 V^(1/3)
            if lam * lam * move2 > cap * cap:
                lam = cap / math.sqrt(move2)
            # each moving node gains momentum lam g_i / dt (the four g_i sum to zero), so over the substep a held
            # node passes the force -lam g / dt^2 from its holder
            f = -lam * inv_dt * inv_dt
            _floor_move(x, v, react, a, wa, lam, f, gax, gay, gaz, inv_dt)
            _floor_move(x, v, react, b, wb, lam, f, gbx, gby, gbz, inv_dt)
            _floor_move(x, v, react, c, wc, lam, f, gcx, gcy, gcz, inv_dt)
            _floor_move(x, v, react, d, wd, lam, f, gdx, gdy, gdz, inv_dt)


@njit(cache=True, inline="always", error_model="numpy")
def _floor_move(x, v, react, i, w, lam, f, gx, gy, gz, inv_dt):
    """Move node i by lam w g and change its velocity by the same displacement over the substep; a held node
    (w = 0) stays and records the force f g its holder supplies."""
    if w == 0.0:
        react[i, 0] += f * gx
        react[i, 1] += f * gy
        react[i, 2] += f * gz
        return
    s = lam * w
    x[i, 0] += s * gx
    x[i, 1] += s * gy
    x[i, 2] += s * gz
    v[i, 0] += s * gx * inv_dt
    v[i, 1] += s * gy * inv_dt
    v[i, 2] += s * gz * inv_dt
