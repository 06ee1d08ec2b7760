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


def test_the_gpu_kernel_calls_the_cpu_bodies_instead_of_repeating_them():
    """The kernel in cuda_step calls the twins of the per-element bodies and computes no spring law, tet
    gradient or square root of its own (those live in the bodies, shared with the CPU loops)."""
    tree = ast.parse((ROOT / "physics" / "cuda_step.py").read_text())
    kernel = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "_simulate_kernel")
    called = {n.func.id if isinstance(n.func, ast.Name) else getattr(n.func, "attr", "")
              for n in ast.walk(kernel) if isinstance(n, ast.Call)}
    assert {"_spring_body", "_implicit_volume_barrier", "_advance_node", "_damping_factors", "_nodal_damping",
            "_anchor_spring_force"} <= called
    assert not called & {"_spring_force", "spring_force", "_volume_gradients", "_volume6", "sqrt"}


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
