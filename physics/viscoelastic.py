"""Stress relaxation: a Maxwell branch on every spring (standard linear solid), integrated exactly.

The paper's viscosity is nodal and absolute (Eq. 7): it resists any motion, so a realistic stress
relaxation under a held grasp (Fig. 9: the normal force drops sharply once the jaws stop) would need a
drag that also resists the organ's rigid sagging and pulling. A Maxwell branch in parallel with each
nonlinear spring gives relaxation from *deformation rate* instead: a linear spring k_v = g K1 in series
with a dashpot of time constant tau,

    dF_v/dt = k_v d(dl)/dt - F_v / tau.

For dl varying linearly over a step the exact update is

    F_v(t + dt) = F_v(t) e^(-dt/tau) + k_v (dl(t+dt) - dl(t)) (tau/dt) (1 - e^(-dt/tau)),

which is unconditionally stable; the only stability cost is the extra instantaneous stiffness k_v in
the critical time step. Under a held strain F_v decays with time constant tau; at a constant strain rate
r the branch carries k_v r tau (1 - e^(-t/tau)) (NOTES.md's standard linear solid).
"""

from __future__ import annotations

import numpy as np
from .jit import kernel

from .forces import spring_loop
from .records import Springs


@kernel
def accumulate_spring_forces_sls(
    x: np.ndarray,  # (N,3) positions, m
    v: np.ndarray,  # (N,3) velocities, m/s
    springs: Springs,  # use_sls is taken as True
    kscale: float,
    decay: float,  # e^(-dt/tau)
    gain: float,  # (tau/dt) (1 - e^(-dt/tau))
    fv: np.ndarray,  # (E,) Maxwell branch force, N (state, updated)
    dl_prev: np.ndarray,  # (E,) spring elongation at the previous substep, m (state, updated)
    f: np.ndarray,  # (N,3) forces are ADDED here
) -> None:
    """Springs + dashpots (as :func:`.forces.accumulate_spring_forces`) plus the Maxwell branch."""
    sp = springs
    with_sls = Springs(sp.edges, sp.rest_length, sp.k1, sp.k2, sp.dlc, sp.cdash, sp.kv, sp.use_dashpot, True)
    spring_loop(x, v, with_sls, kscale, decay, gain, fv, dl_prev, f, np.zeros((9, sp.edges.shape[0])))


def elongations(x: np.ndarray, edges: np.ndarray, rest_length: np.ndarray) -> np.ndarray:
    """(..., E) current length minus rest length of every spring, m (vectorised NumPy)."""
    d = x[..., edges[:, 1], :] - x[..., edges[:, 0], :]
    return np.linalg.norm(d, axis=-1) - rest_length
