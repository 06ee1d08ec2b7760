"""The kernels' shape: records instead of long argument lists, and one per-element body per law.

Every function of the physics kernel (and of the envs that drive it) takes at most MAX_PARAMS parameters:
beyond that, two arrays of the same type can be swapped silently at a call site, so a kernel receives
records (SimModel, SimState, SimReadout, small NamedTuples) or tuples instead. The spring, tet-barrier and
node-update arithmetic is written once (forces.spring_body, forces.implicit_volume_barrier, integrator's node
bodies) and called by the one-tissue loop, the lane loop and the GPU kernel; the tests below check those
bodies' physics directly and that the GPU kernel does not repeat it.
"""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from msdgrasp.physics.forces import spring_body, spring_force
from msdgrasp.physics.integrator import advance_node, anchor_spring_force, damping_factors, nodal_damping

ROOT = Path(__file__).resolve().parent.parent
MAX_PARAMS = 12


def _long_signatures(folder: Path) -> list[str]:
    """'file:line name count' of every function in ``folder`` with more than MAX_PARAMS parameters."""
    found = []
    for path in sorted(folder.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
                n += (a.vararg is not None) + (a.kwarg is not None)
                if a.args and a.args[0].arg in ("self", "cls"):
                    n -= 1
                if n > MAX_PARAMS:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} {n}")
    return found


@pytest.mark.parametrize("folder", ["physics", "envs"])
def test_no_kernel_function_takes_more_than_twelve_parameters(folder):
    assert _long_signatures(ROOT / folder) == [], f"pass records or tuples instead (at most {MAX_PARAMS})"


def _calls(path: Path, names: set[str] | None = None) -> set[str]:
    """The names the functions of ``path`` (those in ``names``, default all) call."""
    return {n.func.id if isinstance(n.func, ast.Name) else getattr(n.func, "attr", "")
            for fn in ast.walk(ast.parse(path.read_text()))
            if isinstance(fn, ast.FunctionDef) and (names is None or fn.name in names)
            for n in ast.walk(fn) if isinstance(n, ast.Call)}


def test_the_gpu_kernel_calls_the_cpu_bodies_instead_of_repeating_them():
    """The GPU kernel (cuda_step's kernel and device functions) runs the CPU kernel's own functions and computes no
    spring law, tet gradient or square root of its own. Its loops over springs and nodes and its barrier pass are CPU
    functions (integrator's), which call the per-element bodies shared with the CPU loops."""
    gpu = _calls(ROOT / "physics" / "cuda_step.py")
    assert {"springs_to_scratch", "gather_and_advance_nodes", "listed_volume_barrier", "dashpot_pass", "below_barrier",
            "maxwell_factors", "plate_contacts", "jaw_candidates", "resolve_jaw_contacts"} <= gpu
    law = {"_spring_force", "spring_force", "_volume_gradients", "_volume6", "sqrt"}
    assert not gpu & (law | {"spring_body", "barrier_impulse", "advance_node"})
    loops = _calls(ROOT / "physics" / "integrator.py",
                   {"springs_to_scratch", "gather_and_advance_nodes", "listed_volume_barrier"})
    assert {"spring_body", "advance_node", "damping_factors", "nodal_damping", "anchor_spring_force", "barrier_impulse",
            "implicit_volume_barrier"} <= loops
    assert not loops & law


def _gpu_test_tissue(mesh, **params):
    """(model record, state record, readout record) of one coarse spleen at a perturbed state: compliant anchors on
    the hilum, five rigid ones elsewhere, displacement-dependent damping, a Maxwell branch, scales and a load."""
    from dataclasses import replace

    from msdgrasp.physics import reference
    from msdgrasp.physics.simulation import Simulation
    from msdgrasp.physics.tissue import TissueModel

    p = replace(reference.spleen_params(), damping_disp_rate_per_m_s=500.0, relaxation_strength=0.3, **params)
    model = TissueModel.from_params(mesh, p, fixed_nodes=mesh.node_sets["hilum"], anchor_stiffness_n_per_m=8.0)
    sim = Simulation(model, 1, max_stiffness_scale=1.2, min_mass_scale=0.8)
    rng = np.random.default_rng(7)
    sim.set_state(model.rest_positions + 4e-4 * rng.standard_normal((model.n_nodes, 3)))
    sim.v[0] = 0.02 * rng.standard_normal((model.n_nodes, 3))
    sim.fv[0] = 0.01 * rng.standard_normal(len(model.edges))
    sim.set_scales(stiffness=1.1, mass=0.9)
    sim.f_ext[0, 11] = (0.03, 0.05, -0.04)
    fixed = model.fixed.copy()
    fixed[np.setdiff1d(np.arange(model.n_nodes), mesh.node_sets["hilum"])[:5]] = True
    m = sim.kernel_model()._replace(fixed=fixed)
    m = m._replace(n_sub=1, dt_outer=m.dt_outer / m.n_sub)  # one substep per call
    return m, sim.kernel_state(), sim.kernel_readout()


def _copy(record):
    return type(record)(*[a.copy() if isinstance(a, np.ndarray) else a for a in record])


def test_the_gpu_loops_run_on_the_cpu_make_the_cpu_kernels_substep_to_the_bit(spleen_coarse):
    """springs_to_scratch and gather_and_advance_nodes, the GPU kernel's loops (a thread per spring or node), run here
    in three threads' strides: the forces gathered in the scatter's order give the CPU kernel's substep bitwise
    (positions, velocities, Maxwell state, the anchors' readout), rigid and sprung anchors included."""
    from msdgrasp.physics.device_layout import make_scratch
    from msdgrasp.physics.integrator import (anchor_readout, gather_and_advance_nodes, maxwell_factors, simulate,
                                             springs_to_scratch)

    m, st, out = _gpu_test_tissue(spleen_coarse)
    m = m._replace(kvol=m.kvol[:0])  # springs and nodes only (no contacts: no grasper, no plates)
    assert m.use_sls and not m.use_dashpot and not m.jaw_active and np.any(m.b1 != 0)
    assert np.any(m.fixed & (m.anchor_k == 0)) and np.any(~m.fixed & (m.anchor_k > 0))
    gst, gout, w = _copy(st), _copy(out), make_scratch(m, 1)
    simulate(m, st, out, 1, None)
    dt = m.dt_outer
    maxwell = maxwell_factors(dt, m.tau)
    for first in range(3):
        springs_to_scratch(m, gst, w, 0, gst.kscale[0], maxwell, first, 3)
    for first in range(3):
        gather_and_advance_nodes(m, gst, w, 0, gst.mscale[0], dt, first, 3)
    gout.anchor_out[:] = 0.0
    anchor_readout(m, gout, w, 0, 0)
    for name in ("x", "v", "fv", "dl_prev"):
        np.testing.assert_array_equal(getattr(gst, name), getattr(st, name), err_msg=name)
    np.testing.assert_array_equal(gout.anchor_out, out.anchor_out)
    assert not np.array_equal(gst.x, _gpu_test_tissue(spleen_coarse)[1].x) and np.abs(out.anchor_out).max() > 0


def test_the_gpus_listed_barrier_is_the_scan_over_the_flags_to_the_bit(spleen_coarse):
    """listed_volume_barrier, the GPU's barrier pass on its list of flagged tets (in the order the threads found
    them), gives implicit_volume_barrier's scan over every flag bitwise; with more tets than the list holds it scans."""
    from msdgrasp.physics.device_layout import make_scratch
    from msdgrasp.physics.forces import below_barrier, implicit_volume_barrier
    from msdgrasp.physics.integrator import listed_volume_barrier

    m, st, _ = _gpu_test_tissue(spleen_coarse, volume_threshold=1.0)  # (any volume loss flags a tet)
    flags = np.array([below_barrier(st.x[0], m.tets, m.rest_volume, m.vol_threshold, t) for t in range(len(m.tets))],
                     dtype=np.int8)
    k = int(flags.sum())
    assert 10 < k < len(m.tets)
    rng = np.random.default_rng(3)
    meff = rng.uniform(0.5, 1.5, len(m.mass)) * m.mass
    st.held[0, m.tets[np.flatnonzero(flags)[0]]] = 1  # (a held node in a flagged tet)
    want_x, want_v, want_anchor = st.x[0].copy(), st.v[0].copy(), np.zeros(3)
    implicit_volume_barrier(want_x, want_v, meff, (m.fixed, st.held[0]), m.tets, m.rest_volume, m.kvol,
                            m.vol_threshold, 1.1, 2e-4, flags, want_anchor)
    assert not np.array_equal(want_v, st.v[0]) and np.abs(want_anchor).max() > 0
    for room in (k + 5, k - 1):  # the list, shuffled; a list too short: the scan
        gst, w = _copy(st), make_scratch(m, 1)
        w.meff[0], w.tet_on[0], w.vol_out[0] = meff, flags, 7.0
        flag_list = np.zeros(room, dtype=np.int32)
        flag_list[:min(k, room)] = rng.permutation(np.flatnonzero(flags))[:room]
        listed_volume_barrier(m, gst, w, 0, 1.1, 2e-4, flag_list, k)
        np.testing.assert_array_equal(gst.x[0], want_x)
        np.testing.assert_array_equal(gst.v[0], want_v)
        np.testing.assert_array_equal(w.vol_out[0], want_anchor)


def test_spring_body_is_the_spring_law_along_the_spring_with_its_dashpot_and_maxwell_branch():
    d = (0.003, -0.004, 0.012)  # length 0.013 m
    law = (0.010, 50.0, 2.0e5, 0.002)  # stretched 3 mm, beyond dl_c = 2 mm
    ks, c, kv, decay, gain = 1.2, 0.4, 30.0, 0.9, 0.95
    dv = (0.01, 0.02, -0.03)
    fx, fy, fz, fv, dl = spring_body(d, law, ks, (*dv, c), (0.1, 0.002, kv, decay, gain), (True, True))
    u = np.array(d) / 0.013
    dl_want = 0.013 - 0.010
    fv_want = 0.1 * decay + ks * kv * (dl_want - 0.002) * gain
    f_want = ks * spring_force(dl_want, *law[1:]) + fv_want + ks * c * float(np.dot(dv, u))
    np.testing.assert_allclose((fx, fy, fz), f_want * u, rtol=1e-12)
    assert f_want > 0.0  # tension pulls node i toward node j
    assert fv == pytest.approx(fv_want, rel=1e-12) and dl == pytest.approx(dl_want, rel=1e-12)
    # without dashpot and branch the extra inputs are ignored; coincident nodes add nothing, keep the state
    plain = spring_body(d, law, ks, (9.0, 9.0, 9.0, 9.0), (9.0, 9.0, 9.0, decay, gain), (False, False))
    np.testing.assert_allclose(plain[:3], ks * spring_force(dl_want, *law[1:]) * u, rtol=1e-12)
    assert spring_body((0.0, 0.0, 0.0), law, ks, (0.0,) * 4, (0.1, 0.002, kv, decay, gain), (True, True)) == \
        (0.0, 0.0, 0.0, 0.1, 0.002)


def test_node_bodies_are_symplectic_euler_with_implicit_damping_and_a_preloaded_anchor():
    xc, xr, vc, fc = (0.1, 0.2, 0.3), (0.1, 0.2, 0.25), (0.5, -0.5, 0.0), (1.0, 2.0, -3.0)
    m, b0, b1, dt = 0.02, 0.3, 4.0, 1e-4
    damp = nodal_damping(xc, xr, b0, b1)
    assert damp == pytest.approx(b0 + b1 * 0.05, rel=1e-12)
    inv, meff = damping_factors(m, damp, dt)
    assert inv == pytest.approx(m / (m + dt * damp), rel=1e-12) and meff == pytest.approx(m + dt * damp, rel=1e-12)
    xn, vn = advance_node(xc, vc, fc, m, inv, dt)
    v_want = (np.array(vc) + dt * np.array(fc) / m) / (1.0 + dt * damp / m)  # (m v' = m v + dt (f - b v'))
    np.testing.assert_allclose(vn, v_want, rtol=1e-12)
    np.testing.assert_allclose(xn, np.array(xc) + dt * v_want, rtol=1e-12)
    fa = anchor_spring_force(xc, xr, 1.1, 8.0, np.array([0.0, 0.0, 0.01]))
    np.testing.assert_allclose(fa, -8.0 * (np.array(xc) - xr - 1.1 * np.array([0.0, 0.0, 0.01])), rtol=1e-12)
    assert math.isfinite(sum(fa))


def _dashpots_by_definition(x, v, meff, fixed, edges, cdash, ks, dt, anchor):
    """The spring dashpots' implicit pass as its docstring defines it, node values read from and written to memory
    at every use: spring after spring in edge order, the relative speed along the spring r -> r / (1 + c dt W) by
    equal and opposite impulses, x moving with v, an anchored node passing the force to its anchor. (Compiled by
    numba, as the kernel is, so both follow numba's typing of float32 storage.)"""
    for e in range(edges.shape[0]):
        c = ks * cdash[e]
        if c == 0.0:
            continue
        i, j = edges[e, 0], edges[e, 1]
        dx, dy, dz = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
        if length < 1e-15:
            continue
        u = (dx / length, dy / length, dz / length)
        wi = 0.0 if fixed[i] else 1.0 / meff[i]
        wj = 0.0 if fixed[j] else 1.0 / meff[j]
        r = (v[j, 0] - v[i, 0]) * u[0] + (v[j, 1] - v[i, 1]) * u[1] + (v[j, 2] - v[i, 2]) * u[2]
        lam = c * dt * r / (1.0 + c * dt * (wi + wj))
        for node, w, s in ((i, wi, lam), (j, wj, -lam)):
            for k in range(3):
                if w == 0.0:
                    anchor[k] -= s * u[k] / dt
                else:
                    dv = w * s * u[k]
                    v[node, k] = v[node, k] + dv
                    x[node, k] = x[node, k] + dt * dv


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_implicit_dashpot_pass_is_gauss_seidel_in_edge_order_to_the_bit(dtype, sphere_coarse):
    """However the kernel keeps its nodes (it holds a run's first node in registers), the pass is bitwise the
    Gauss-Seidel sweep of its definition: with anchored nodes, springs without a dashpot, a collapsed spring, and
    float32 storage rounding every stored value. And it only damps: no free node gains relative speed overall."""
    from msdgrasp.physics.forces import implicit_spring_dashpots

    rng = np.random.default_rng(3)
    edges = sphere_coarse.edges
    n = sphere_coarse.n_nodes
    x0 = sphere_coarse.nodes.astype(dtype)
    x0[edges[7, 1]] = x0[edges[7, 0]]  # a collapsed spring: no direction, no impulse
    v0 = (0.05 * rng.standard_normal((n, 3))).astype(dtype)
    meff = (3e-4 * rng.uniform(0.5, 1.5, n)).astype(dtype)
    fixed = np.zeros(n, dtype=np.bool_)
    fixed[rng.choice(n, 12, replace=False)] = True
    cdash = np.full(len(edges), 0.25, dtype=dtype)
    cdash[rng.choice(len(edges), 30, replace=False)] = 0.0
    runs = []
    from numba import njit

    for kernel in (implicit_spring_dashpots, njit(error_model="numpy")(_dashpots_by_definition)):
        x, v, anchor = x0.copy(), v0.copy(), np.zeros(3)
        for _ in range(3):
            kernel(x, v, meff, fixed, edges, cdash, 1.3, 3e-4, anchor)
        runs.append((x, v, anchor))
    for got, want in zip(*runs):
        np.testing.assert_array_equal(got, want)
    x, v, _ = runs[0]
    assert not np.array_equal(v, v0) and np.array_equal(v[fixed], v0[fixed]) and np.array_equal(x[fixed], x0[fixed])
    rel = [np.abs(((vv[edges[:, 1]] - vv[edges[:, 0]]) * (sphere_coarse.nodes[edges[:, 1]] - sphere_coarse.nodes[
        edges[:, 0]])).sum(axis=1)).sum() for vv in (v0.astype(np.float64), v.astype(np.float64))]
    assert rel[1] < 0.5 * rel[0], rel
