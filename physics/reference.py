"""The NumPy reference of the MSD step: the same physics as the numba kernel, written for clarity, not speed.

:class:`NumpyMSD` evaluates springs (the paper's law, the optional spring dashpot, the Maxwell branch) and
the volume barrier for all edges / tets at once and integrates with the kernel's scheme; :func:`cross_check`
compares forces and trajectories with the kernel (the tests' oracle; ``msdgrasp bench physics`` reports it
and times the reference beside the kernel).
"""

from __future__ import annotations

import math

import numpy as np

DT_OUTER = 1e-3  # s: the outer physics step of the env and the benchmarks


# ------------------------------------------------------------------------------------------------
# models
# ------------------------------------------------------------------------------------------------


def spleen_params():
    from .config import builtin_config
    from .scenario import load_params
    from .tissue import TissueParams

    return load_params(builtin_config("tissue/spleen.yaml"), "tissue", TissueParams)


_MODELS: dict = {}


def spleen_model(resolution: str | int):
    """The spleen anchored (rigidly) at its hilum, at ``resolution`` (cached per process)."""
    if resolution not in _MODELS:
        from .mesh_gen import spleen_mesh
        from .tissue import TissueModel

        mesh = spleen_mesh(resolution)
        _MODELS[resolution] = TissueModel.from_params(mesh, spleen_params(), fixed_nodes=mesh.node_sets["hilum"])
    return _MODELS[resolution]


# ------------------------------------------------------------------------------------------------
# the NumPy reference
# ------------------------------------------------------------------------------------------------


def numpy_spring_law(dl: np.ndarray, k1: np.ndarray, k2: np.ndarray, dlc: np.ndarray) -> np.ndarray:
    """The spring law of :func:`msdgrasp.physics.forces.spring_force`, vectorised."""
    adl = np.abs(dl)
    a = k1 * dlc + k2 * dlc * dlc * dlc
    b = k1 + 3.0 * k2 * dlc * dlc
    outer = a + b * (adl - dlc)
    return np.where(adl <= dlc, k1 * dl + k2 * dl * dl * dl, np.where(dl > 0.0, outer, -outer))


def numpy_barrier_slopes(jac: np.ndarray, j_c: float) -> tuple[np.ndarray, np.ndarray]:
    """psi'(J), psi''(J) of the volume barrier per unit modulus, psi = -(J - J_c)^2 ln(J / J_c) below J_c,
    continued linearly in psi' below VOLUME_J_MIN x J_c (:func:`.forces.barrier_slopes`, vectorised)."""
    from .forces import VOLUME_J_MIN

    j = np.maximum(jac, VOLUME_J_MIN * j_c)
    dj = j - j_c
    lg = np.log(j / j_c)
    d2 = -(2.0 * lg + 4.0 * dj / j - dj * dj / (j * j))
    d1 = -(2.0 * dj * lg + dj * dj / j) + d2 * (jac - j)
    below = jac < j_c
    return np.where(below, d1, 0.0), np.where(below, d2, 0.0)


class NumpyMSD:
    """Plain NumPy implementation of the same MSD step as the numba kernel (no contact): the reference.

    Springs (the paper's law, optional spring dashpot, the Maxwell branch) and the volume barrier are
    evaluated for all edges / tets at once and scattered to the nodes with ``np.add.at``; symplectic Euler with
    implicit nodal damping; rigid anchors held, compliant anchors as springs. ``x, v`` are (N,3), ``fv, dl_prev`` (E,).
    """

    def __init__(self, model, n_sub: int, dt_outer: float = DT_OUTER, kscale: float = 1.0, mscale: float = 1.0):
        self.model = model
        self.n_sub = int(n_sub)
        self.dt = dt_outer / self.n_sub
        self.kscale = float(kscale)
        self.mscale = float(mscale)
        p = model.params
        self.use_dashpot = p.spring_damping_time_s > 0.0
        self.use_sls = p.relaxation_strength > 0.0
        self.decay = math.exp(-self.dt / p.relaxation_time_s)
        self.gain = p.relaxation_time_s / self.dt * (1.0 - self.decay)
        self.i = model.edges[:, 0]
        self.j = model.edges[:, 1]
        self.m = model.mass * self.mscale
        self.free = ~model.fixed if model.fixed.size else np.ones(model.n_nodes, bool)
        self.x = model.rest_positions.copy()
        self.v = np.zeros_like(self.x)
        self.fv = np.zeros(len(model.edges))
        self.dl_prev = np.zeros(len(model.edges))

    def spring_forces(self, x, v, fv, dl_prev, out=None, update=True, dashpot=True) -> np.ndarray:
        """(N,3) spring (+ dashpot + Maxwell) forces; updates ``fv``/``dl_prev`` in place if ``update``. The
        step integrates the dashpots implicitly (:meth:`dashpot_step`) and leaves them out here (``dashpot``)."""
        mdl = self.model
        d = x[self.j] - x[self.i]
        length = np.sqrt(np.einsum("ij,ij->i", d, d))
        ok = length >= 1e-15
        u = d / np.where(ok, length, 1.0)[:, None]
        dl = length - mdl.rest_length
        fs = self.kscale * numpy_spring_law(dl, mdl.k1, mdl.k2, mdl.dlc)
        if self.use_sls:
            fve = fv * self.decay + self.kscale * mdl.kv * (dl - dl_prev) * self.gain
            if update:
                fv[ok] = fve[ok]
                dl_prev[ok] = dl[ok]
            fs = fs + fve
        if self.use_dashpot and dashpot:
            rel = np.einsum("ij,ij->i", v[self.j] - v[self.i], u)
            fs = fs + self.kscale * mdl.cdash * rel
        fu = np.where(ok, fs, 0.0)[:, None] * u
        f = np.zeros_like(x) if out is None else out
        np.add.at(f, self.i, fu)
        np.add.at(f, self.j, -fu)
        return f

    def volume_forces(self, x, out=None) -> np.ndarray:
        """(N,3) forces -k psi'(J) dV/dx of the volume barrier (tets compressed below the threshold), vectorised
        (what the kernel integrates implicitly; see :meth:`volume_barrier_step`)."""
        mdl = self.model
        f = np.zeros_like(x) if out is None else out
        if not mdl.kvol.size:
            return f
        g, jac = self._volume_gradients(x)
        s = -self.kscale * mdl.kvol * numpy_barrier_slopes(jac, mdl.volume_threshold)[0]
        fg = s[:, None, None] * g
        for k in range(4):
            np.add.at(f, mdl.tets[:, k], fg[:, k])
        return f

    def _volume_gradients(self, x) -> tuple[np.ndarray, np.ndarray]:
        """dV/dx (T,4,3) of every tet at x and its volume ratio J (T,)."""
        p = x[self.model.tets]
        e1, e2, e3 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
        g = np.stack([np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)], axis=1) / 6.0  # dV/dx_b,c,d
        g = np.concatenate([-g.sum(axis=1, keepdims=True), g], axis=1)
        return g, np.einsum("ti,ti->t", e1, g[:, 1]) / self.model.rest_volume

    def dashpot_step(self, x, v, meff) -> None:
        """The spring dashpots' backward-Euler impulses, spring after spring in edge order (the kernel's pass;
        x, v (N,3) modified; meff (N,) effective masses, kg)."""
        if not self.use_dashpot:
            return
        w = np.where(self.free, 1.0 / meff, 0.0)
        for e, (i, j) in enumerate(self.model.edges):
            c = self.kscale * self.model.cdash[e]
            d = x[j] - x[i]
            u = d / np.linalg.norm(d)
            lam = c * self.dt * float((v[j] - v[i]) @ u) / (1.0 + c * self.dt * (w[i] + w[j]))
            v[i] += w[i] * lam * u
            v[j] -= w[j] * lam * u
            x[i] += self.dt * w[i] * lam * u
            x[j] -= self.dt * w[j] * lam * u

    def volume_barrier_step(self, x, v, meff) -> None:
        """The barrier's backward-Euler impulses, tet after tet in tet order, on the tets below the threshold at
        x (the kernel's Gauss-Seidel pass, without contacts: no node is held; x, v (N,3) modified; meff (N,)
        effective masses, kg)."""
        mdl = self.model
        if not mdl.kvol.size:
            return
        w_node = np.where(self.free, 1.0 / meff, 0.0)
        for t in np.nonzero(self._volume_gradients(x)[1] < mdl.volume_threshold)[0]:
            tet = mdl.tets[t]
            p = x[tet]
            g = (np.cross(p[2] - p[0], p[3] - p[0]), np.cross(p[3] - p[0], p[1] - p[0]),
                 np.cross(p[1] - p[0], p[2] - p[0]))
            g = np.array([-(g[0] + g[1] + g[2]), g[0], g[1], g[2]]) / 6.0
            jac = float((p[1] - p[0]) @ g[1]) / mdl.rest_volume[t]
            d1, d2 = numpy_barrier_slopes(np.array([jac]), mdl.volume_threshold)
            k = self.kscale * mdl.kvol[t]
            w = w_node[tet]
            p_t = k * d1[0] / (1.0 + self.dt**2 * k * d2[0] * float(w @ np.einsum("ij,ij->i", g, g))
                               / mdl.rest_volume[t])
            dv = -self.dt * p_t * w[:, None] * g
            v[tet] += dv
            x[tet] += self.dt * dv

    def step(self, n_steps: int = 1) -> None:
        mdl = self.model
        dt = self.dt
        x, v = self.x, self.v
        m = self.m[:, None]
        fg = m * mdl.gravity[None, :]
        x0 = mdl.rest_positions
        fixed = ~self.free
        ka = mdl.anchor_k[:, None] if mdl.anchor_k.size else None
        for _ in range(int(n_steps) * self.n_sub):
            f = fg.copy()
            self.spring_forces(x, v, self.fv, self.dl_prev, out=f, dashpot=False)
            disp = x - x0
            if ka is not None:
                f += -ka * (disp - self.mscale * mdl.anchor_offset[None, :])
            damp = mdl.b0 + mdl.b1 * np.sqrt(np.einsum("ij,ij->i", disp, disp))
            inv = 1.0 / (1.0 + dt * damp / self.m)
            v[:] = (v + dt * f / m) * inv[:, None]
            v[fixed] = 0.0
            x += dt * v  # anchored nodes have v = 0: they stay where they are
            self.dashpot_step(x, v, self.m + dt * damp)
            self.volume_barrier_step(x, v, self.m + dt * damp)


def cross_check(resolution: str | int = "coarse", seed: int = 0, steps: int = 10, model=None) -> dict:
    """NumPy vs numba: spring forces at one perturbed state, and the state after ``steps`` ms.

    ``model`` (default: the anchored spleen at ``resolution``) may be any TissueModel. Returns the largest
    difference relative to the largest magnitude (forces, Maxwell forces, positions' displacement).
    """
    from .forces import accumulate_spring_forces, volume_forces
    from .records import Springs
    from .simulation import Simulation
    from .viscoelastic import accumulate_spring_forces_sls

    custom = model is not None
    model = model if custom else spleen_model(resolution)
    sim = Simulation(model, 1, dt=DT_OUTER)
    ref = NumpyMSD(model, sim.n_sub)
    rng = np.random.default_rng(seed)
    h = float(np.mean(model.rest_length))
    x = model.rest_positions + rng.normal(0.0, 0.12 * h, (model.n_nodes, 3))  # some springs beyond dl_c
    v = rng.normal(0.0, 0.05, (model.n_nodes, 3))
    E = len(model.edges)
    fv = rng.normal(0.0, 0.01, E)
    dl_prev = rng.normal(0.0, 0.05 * h, E)
    ks = 1.3
    ref.kscale = ks
    f_np = ref.spring_forces(x, v, fv_np := fv.copy(), dl_prev.copy())
    f_nb = np.zeros_like(x)
    fv_nb, dlp_nb = fv.copy(), dl_prev.copy()
    if ref.use_sls:
        springs = Springs(model.edges, model.rest_length, model.k1, model.k2, model.dlc, model.cdash, model.kv,
                          ref.use_dashpot, True)
        accumulate_spring_forces_sls(x, v, springs, ks, ref.decay, ref.gain, fv_nb, dlp_nb, f_nb)
    else:
        accumulate_spring_forces(x, v, model.edges, model.rest_length, model.k1, model.k2, model.dlc, model.cdash,
                                 ks, ref.use_dashpot, f_nb)
    if model.kvol.size:
        ref.volume_forces(x, out=f_np)
        volume_forces(x, model.tets, model.rest_volume, model.kvol, model.volume_threshold, ks, f_nb)
    beyond = float(np.mean(np.abs(np.linalg.norm(x[ref.j] - x[ref.i], axis=1) - model.rest_length) > model.dlc))
    force_rel = float(np.max(np.abs(f_np - f_nb)) / np.max(np.abs(f_nb)))
    fv_rel = float(np.max(np.abs(fv_np - fv_nb)) / max(np.max(np.abs(fv_nb)), 1e-300))

    # trajectories: `steps` outer steps from rest under gravity, kernel vs reference
    ref.kscale = 1.0
    ref.x = model.rest_positions.copy()
    ref.v[:] = 0.0
    ref.fv[:] = 0.0
    ref.dl_prev[:] = 0.0
    sim.reset()
    sim.step(steps)
    ref.step(steps)
    disp = np.max(np.abs(sim.x[0] - model.rest_positions))
    state_rel = float(np.max(np.abs(sim.x[0] - ref.x)) / max(disp, 1e-300))
    if model.kvol.size:
        p = x[model.tets]
        jac = np.einsum("ti,ti->t", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0
        active = float(np.mean(jac / model.rest_volume < model.volume_threshold))
    else:
        active = 0.0
    return {
        "resolution": model.mesh.name if custom else resolution,
        "springs_beyond_dl_c_fraction": beyond,
        "tets_in_volume_barrier_fraction": active,
        "max_rel_diff_forces": force_rel,
        "max_rel_diff_maxwell_forces": fv_rel,
        "state_steps_ms": steps,
        "max_rel_diff_displacement": state_rel,
    }
