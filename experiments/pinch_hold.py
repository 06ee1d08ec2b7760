"""A force-controlled pinch, a pull and a hold on the anchored spleen: how steady the pinch readout is, whether
every node a jaw face holds stays inside its friction cone, and whether any tet inverts.

Protocol: the env's grasper around the inferior pole; the jaw motor's 1 kHz force loop closes to the pinch
set-point for ``close_s``, the grasper pulls away from the anchors at ``pull_speed_m_s`` for ``pull_s``, then
holds for ``hold_s``. Every 1 ms physics step is read: the pinch (the jaws' normal forces), each face-held
node's contact force split on its jaw face (normal Fn, tangential Ft), the smallest tet volume ratio.
``msdgrasp experiment pinch-hold`` runs it and prints the result as JSON.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..physics.config import builtin_config
from ..physics.contact import SLIP, STICK, jaw_directions
from ..physics.forces import volume_energy
from ..physics.scenario import spleen_scene

PHASES = ("close", "pull", "hold")


@dataclass(frozen=True)
class PinchHoldResult:
    #: the spleen's tissue config that was run
    tissue_config: str
    resolution: str
    substeps: int
    mu: float
    stiffness_scale: float
    pinch_setpoint_N: float
    #: mean pinch over the hold, N
    hold_pinch_N: float
    #: standard deviation of the pinch's step-to-step change (1 ms) in the pull and in the hold, N
    pinch_step_std_pull_N: float
    pinch_step_std_hold_N: float
    #: largest |Ft| / (mu_s |Fn|) over every step and every node a jaw face holds (<= 1: inside the cone)
    max_friction_cone_ratio: float
    #: face-held node samples read (node x step)
    held_node_samples: int
    #: smallest tet volume ratio V / V0 over the run (<= 0: a tet inverted)
    min_volume_ratio: float
    #: energy stored in the volume barrier at the end of each phase, J
    barrier_energy_J: tuple[float, float, float]


def run_pinch_hold(resolution: str = "coarse", mu: float = 0.3, stiffness_scale: float = 0.8, pinch_N: float = 5.0,
                   pull_speed_m_s: float = 0.015, close_s: float = 3.0, pull_s: float = 2.0,
                   hold_s: float = 2.0, tissue_config: str | Path | None = None) -> PinchHoldResult:
    """Run the protocol (module docstring) on the spleen at ``resolution`` as the GraspLift env sets it up: its
    grasper, compliant hilum anchors (8 N/m), 35 mm grasp depth, force loop (gain 0.02 m/s/N, the grasper's
    closing-speed limit) and substep count (stiffness scales up to 1.2, mass scales down to 0.9). ``tissue_config``:
    the spleen's (default ``configs/tissue/spleen.yaml``; ``spleen-j1.yaml`` is its nodes on the J1 split)."""
    scene = spleen_scene(tissue_config, builtin_config("grasper/env.yaml"), resolution=resolution,
                         insert_depth_m=0.035, anchor_stiffness_n_per_m=8.0)
    sim = scene.simulation(1, max_stiffness_scale=max(1.2, stiffness_scale), min_mass_scale=0.9)
    sim.set_scales(stiffness=stiffness_scale)
    sim.set_friction(mu, mu)
    sim.command_pinch_force(pinch_N, 0.02, scene.grasper.max_closing_speed_m_s)
    u, tj = np.empty((3, 3)), np.empty((3, 3))
    jaw_directions(sim.g_axis[0], sim.g_e1[0], u, tj)
    mdl = sim.model
    pinch: list[list[float]] = [[], [], []]
    cone, samples, jmin, energy = 0.0, 0, np.inf, []
    for phase, (seconds, pull) in enumerate(((close_s, 0.0), (pull_s, pull_speed_m_s), (hold_s, 0.0))):
        sim.command(pull_velocity=pull * scene.pull_direction)
        for _ in range(int(round(seconds * 1000))):
            sim.step(1)
            pinch[phase].append(float(sim.pinch_force[0]))
            jmin = min(jmin, float(sim.min_volume_ratio()[0]))
            held = np.flatnonzero(np.isin(sim.contact_state[0], (STICK, SLIP)))
            if held.size:
                f = sim.contact_force[0, held]
                k = np.argmax((sim.x[0, held] - sim.g_tip[0]) @ u.T, axis=1)  # the jaw whose face holds the node
                fn = -np.einsum("ij,ij->i", f, u[k])
                ft = np.linalg.norm(f + fn[:, None] * u[k], axis=1)
                ok = fn > 0.0
                if ok.any():
                    cone = max(cone, float(np.max(ft[ok] / (sim.mu_s[0] * fn[ok]))))
                samples += int(ok.sum())
        energy.append(float(volume_energy(sim.x[0], mdl.tets, mdl.rest_volume, mdl.kvol * sim.kscale[0],
                                          mdl.volume_threshold)) if mdl.kvol.size else 0.0)
    return PinchHoldResult(
        tissue_config=str(tissue_config or builtin_config("tissue/spleen.yaml")), resolution=str(resolution),
        substeps=int(sim.n_sub), mu=float(mu), stiffness_scale=float(stiffness_scale),
        pinch_setpoint_N=float(pinch_N), hold_pinch_N=float(np.mean(pinch[2])),
        pinch_step_std_pull_N=float(np.std(np.diff(pinch[1]))), pinch_step_std_hold_N=float(np.std(np.diff(pinch[2]))),
        max_friction_cone_ratio=cone, held_node_samples=samples, min_volume_ratio=jmin,
        barrier_energy_J=(energy[0], energy[1], energy[2]),
    )


def result_dict(result: PinchHoldResult) -> dict:
    return asdict(result)
