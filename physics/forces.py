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

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def spring_force(dl: float, k1: float, k2: float, dlc: float) -> float:
    """Tension (N) of one nonlinear spring stretched by ``dl`` metres (Eq. 4-6, corrected B)."""
    adl = abs(dl)
    if adl <= dlc:
        return k1 * dl + k2 * dl * dl * dl
    a = k1 * dlc + k2 * dlc * dlc * dlc
    b = k1 + 3.0 * k2 * dlc * dlc
    f = a + b * (adl - dlc)
    return f if dl > 0.0 else -f


@njit(cache=True, inline="always")
def spring_tangent(dl: float, k1: float, k2: float, dlc: float) -> float:
    """dF/d(dl) (N/m): K1 + 3 K2 dl^2 inside dl_c, the constant B beyond."""
    adl = min(abs(dl), dlc)
    return k1 + 3.0 * k2 * adl * adl


@njit(cache=True)
def spring_force_array(dl: np.ndarray, k1: float, k2: float, dlc: float) -> np.ndarray:
    out = np.empty_like(dl)
    for i in range(dl.size):
        out.flat[i] = spring_force(dl.flat[i], k1, k2, dlc)
    return out


@njit(cache=True)
def accumulate_spring_forces(
    x: np.ndarray,  # (N,3) positions, m
    v: np.ndarray,  # (N,3) velocities, m/s
    edges: np.ndarray,  # (E,2) int
    rest_length: np.ndarray,  # (E,) m
    k1: np.ndarray,  # (E,) N/m
    k2: np.ndarray,  # (E,) N/m^3
    dlc: np.ndarray,  # (E,) m
    cdash: np.ndarray,  # (E,) N s/m, spring dashpot (0 = none)
    kscale: float,  # stiffness multiplier of this tissue (domain randomisation)
    use_dashpot: bool,
    f: np.ndarray,  # (N,3) out: forces are ADDED here
) -> None:
    """Add every spring's (and dashpot's) force to ``f``. Pairwise equal and opposite: momentum-exact."""
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        if length < 1e-15:
            continue  # coincident nodes: direction undefined; happens only in a collapsed mesh
        inv = 1.0 / length
        ux = dx * inv
        uy = dy * inv
        uz = dz * inv
        fs = kscale * spring_force(length - rest_length[e], k1[e], k2[e], dlc[e])
        if use_dashpot:
            rel = (v[j, 0] - v[i, 0]) * ux + (v[j, 1] - v[i, 1]) * uy + (v[j, 2] - v[i, 2]) * uz
            fs += kscale * cdash[e] * rel
        f[i, 0] += fs * ux
        f[i, 1] += fs * uy
        f[i, 2] += fs * uz
        f[j, 0] -= fs * ux
        f[j, 1] -= fs * uy
        f[j, 2] -= fs * uz


@njit(cache=True)
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
