"""The kernel takes three records (model, state, readout) instead of 58 positional arrays, and computes
exactly what it computed before.

Three short scenarios cover every path of the kernel: the spleen gripped by the force loop and pulled
(contacts, stick, slip, anchors, an external load), the sphere between two moving plates with friction
(Maxwell branch, volume barrier), and the optional terms (spring dashpots, displacement-dependent damping,
sprung anchors, the volume barrier from any volume loss). Their final state was recorded in
``tests/data/kernel_golden.npz`` by the kernel as it was *before* its arguments became records, and
re-recorded for deliberate changes of the physics since: the scenes' start states at the converged substep
rule, and the volume barrier integrated implicitly (replacing the explicit barrier and the volume floor).
Re-record only for a deliberate change of the physics:
``python tests/test_kernel_records.py tests/data/kernel_golden.npz``.
"""

from __future__ import annotations

import inspect
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from msdgrasp.physics.integrator import simulate
from msdgrasp.physics.records import SimModel, SimReadout, SimState
from msdgrasp.physics.scenario import spleen_scene

GOLDEN = Path(__file__).parent / "data" / "kernel_golden.npz"
#: the substep safety factor the recording was made with (the simulation's SUBSTEP_SAFETY rule has moved since)
RECORDED_SUBSTEP_SAFETY = 0.95
NAMES = ("x", "v", "t", "fv", "dl_prev", "g_radius", "g_tip", "g_force", "pl_point",
         "jaw_out", "plate_out", "anchor_out", "contact_state", "contact_force")


def run_scenarios() -> dict[str, np.ndarray]:
    """{"<scenario>.<array>": final value} of the three scenarios (one tissue each)."""
    from msdgrasp.physics import reference
    from msdgrasp.physics.scenario import sphere_scene, spleen_scene
    from msdgrasp.physics.simulation import Plate, Simulation
    from msdgrasp.physics.tissue import TissueModel

    out: dict[str, np.ndarray] = {}

    def grab(tag: str, s: Simulation) -> None:
        for n in NAMES:
            out[f"{tag}.{n}"] = getattr(s, n).copy()

    # the substep rule when the recording was made (SUBSTEP_SAFETY is 0.6 since)
    scene = spleen_scene(resolution="coarse")
    s = scene.simulation(1, max_stiffness_scale=1.3, min_mass_scale=0.85, safety=RECORDED_SUBSTEP_SAFETY)
    s.set_scales(stiffness=1.17, mass=0.93)
    s.set_friction(0.45, 0.4)
    s.command_pinch_force(1.6, 0.02, 0.03)
    s.step(100)
    s.command(pull_velocity=0.02 * scene.pull_direction)
    s.f_ext[:, 7, :] = (0.01, -0.02, 0.015)
    s.step(150)
    grab("spleen", s)

    sp = sphere_scene(resolution="coarse")
    z = sp.x_start[:, 2]
    plates = [Plate((0.0, 0.0, z.min()), (0.0, 0.0, 1.0), mu=0.3),
              Plate((0.0, 0.0, z.max()), (0.0, 0.0, -1.0), (0.0, 0.0, -0.02), mu=0.3)]
    s = Simulation(sp.model, 1, plates=plates, max_stiffness_scale=1.2, safety=RECORDED_SUBSTEP_SAFETY)
    s.set_state(sp.x_start)
    s.set_scales(stiffness=1.1)
    s.step(200)
    grab("plates", s)

    model = reference.spleen_model("coarse")
    params = replace(reference.spleen_params(), spring_damping_time_s=0.002, damping_disp_rate_per_m_s=500.0,
                     volume_threshold=1.0)  # the barrier on the sag, with anchored nodes in tets
    model = TissueModel.from_params(model.mesh, params, fixed_nodes=model.mesh.node_sets["hilum"],
                                    anchor_stiffness_n_per_m=8.0)
    s = Simulation(model, 1, max_stiffness_scale=1.2, min_mass_scale=0.8, safety=RECORDED_SUBSTEP_SAFETY)
    s.set_scales(stiffness=0.9, mass=1.1)
    s.f_ext[:, 11, :] = (0.03, 0.05, -0.04)
    s.step(80)
    grab("optional_terms", s)
    return out



def test_trajectories_match_the_recording_made_before_the_records():
    """Bitwise on the machine that recorded it. On another CPU LLVM may pick other vector widths and fused
    multiply-adds for the same source, so the last bits differ (measured on a second machine: at most
    3e-12 of an array's largest value, in the velocities after 250 ms; every contact state identical).
    A wrong or swapped argument changes a trajectory at the percent level, so each array must agree to
    1e-9 of its largest value, and the discrete contact states exactly."""
    want = np.load(GOLDEN)
    got = run_scenarios()
    assert sorted(got) == sorted(want.files)
    for name in want.files:
        if name.endswith("contact_state"):
            np.testing.assert_array_equal(got[name], want[name], err_msg=name)
            continue
        scale = float(np.abs(want[name]).max()) if want[name].size else 0.0
        np.testing.assert_allclose(got[name], want[name], rtol=0.0, atol=1e-9 * scale, err_msg=name)
    assert np.abs(want["spleen.jaw_out"][:, :, 0]).sum() > 0.5, "the spleen scenario must grip"
    assert np.abs(want["plates.plate_out"]).max() > 0.1, "the plates must press"


def test_the_kernel_is_called_with_named_records():
    assert list(inspect.signature(simulate.py_func).parameters) == ["model", "state", "out", "n_steps", "lanes"]
    sim = spleen_scene(resolution="coarse").simulation(2)
    model, state, out = sim.kernel_model(), sim.kernel_state(), sim.kernel_readout()
    assert isinstance(model, SimModel) and isinstance(state, SimState) and isinstance(out, SimReadout)
    # the state record aliases the simulation's arrays: the kernel advances them in place
    assert state.x is sim.x and state.g_force is sim.g_force and out.jaw_out is sim.jaw_out
    assert model.n_sub == sim.n_sub and model.jaw_active
    # every per-tissue array is batch-first
    for name, arr in state._asdict().items():
        assert arr.shape[0] == 2, name


if __name__ == "__main__":
    np.savez_compressed(sys.argv[1], **run_scenarios())
