"""The three-jaw grasper: Coulomb stick/slip, the paper's Fig. 9 claims, and bad inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msdgrasp.physics.config import ConfigError, write_yaml
from msdgrasp.physics.contact import J_CONTACT, J_SLIP
from msdgrasp.experiments.grasp import GraspProtocol, run_grasp, run_sphere_grasp
from msdgrasp.physics.grasper import GrasperParams, GrasperPose, reachable_radius
from msdgrasp.physics.scenario import sphere_scene, spleen_scene

PAPER_MUS = (0.4, 0.6, 0.8)


@pytest.fixture(scope="module")
def fig9():
    """One batch: the paper's three mu, plus mu = 0 and a huge mu (rigid hilum anchors, as the paper)."""
    scene = spleen_scene()
    runs = run_grasp(scene, [*PAPER_MUS, 0.0, 100.0], GraspProtocol(pull_time_s=12.0))
    return {r.mu: r for r in runs}


def _phase(run, name):
    return run.data["phase"] == name


def test_normal_force_rises_while_closing_and_relaxes_during_hold(fig9):
    for mu in PAPER_MUS:
        d = fig9[mu].data
        close = d["normal_force_N"][_phase(fig9[mu], "close")]
        # rising: the last second of closing carries far more force than the first contact
        assert close[-1] > 3 * close[len(close) // 5], (mu, close[::50])
        s = fig9[mu].summary
        # stress relaxation: held jaws, the Maxwell branches relax (tau = 1.5 s over a 7 s hold)
        assert s["normal_end_hold_N"] < 0.8 * s["normal_end_close_N"], s


def test_normal_force_before_pulling_does_not_depend_on_mu(fig9):
    for key in ("normal_end_close_N", "normal_end_hold_N"):
        vals = np.array([fig9[mu].summary[key] for mu in PAPER_MUS])
        assert np.ptp(vals) / vals.mean() < 0.05, (key, vals)


def test_tangential_force_rises_during_pull_then_falls_after_sliding(fig9):
    for mu in PAPER_MUS:
        run = fig9[mu]
        pull = _phase(run, "pull")
        ft = run.data["pull_force_N"][pull]
        k = int(np.argmax(ft))
        assert 0 < k < len(ft) - 1, "the peak must lie inside the pull phase"
        assert ft[k] > 5 * abs(ft[0]) and ft[k] > 0.2
        assert ft[-1] < 0.5 * ft[k], "after sliding starts the tangential force falls"
        assert run.summary["outcome"] == "grasp lost"


def test_higher_mu_slips_later_and_carries_more(fig9):
    onset = [fig9[mu].summary["slip_onset_time_s"] for mu in PAPER_MUS]
    peak = [fig9[mu].summary["tangential_peak_N"] for mu in PAPER_MUS]
    assert all(np.isfinite(onset))
    assert onset[0] < onset[1] < onset[2], onset
    assert peak[0] < peak[1] < peak[2], peak


def test_zero_friction_never_holds(fig9):
    run = fig9[0.0]
    pull = _phase(run, "pull")
    # no friction: the only axial resistance left is tissue bulging against the jaws' end walls
    assert np.max(run.data["pull_force_N"][pull]) < 0.5 * fig9[0.4].summary["tangential_peak_N"]
    assert run.summary["slip_onset_time_s"] < fig9[0.4].summary["slip_onset_time_s"]
    assert run.summary["outcome"] == "grasp lost"


def test_huge_friction_never_slips_before_tearing(fig9):
    s = fig9[100.0].summary
    assert s["outcome"] in ("torn from anchors", "time limit"), s
    assert math.isnan(s["slip_onset_time_s"]) or s["slip_onset_time_s"] >= s["end_time_s"], s


@pytest.fixture(scope="module")
def coulomb_scene(tmp_path_factory):
    """The free sphere held by jaws longer than it (no end-wall interlock), with light nodal damping."""
    d = tmp_path_factory.mktemp("coulomb")
    write_yaml(d / "sphere.yaml", {
        "mesh": {"shape": "sphere", "resolution": "coarse", "diameter_m": 0.05},
        "tissue": {"youngs_modulus_pa": 60e3, "density_kg_m3": 1050.0, "damping_rate_per_s": 30.0,
                   "damping_disp_rate_per_m_s": 0.0},
    })
    write_yaml(d / "grasper.yaml", {"grasper": {"jaw_length_m": 0.07, "jaw_width_m": 0.014, "min_radius_m": 0.005}})
    return sphere_scene(d / "sphere.yaml", d / "grasper.yaml")


def test_grasp_slips_when_the_load_reaches_mu_times_normal_force(coulomb_scene):
    """Coulomb: a ramped axial load on a held sphere breaks it loose at mu * N (within 10%)."""
    scene = coulomb_scene
    mus = np.array([0.2, 0.5, 0.8])
    sim = scene.simulation(len(mus))
    sim.set_friction(mus)
    sim.command(closing_speed=0.004)
    sim.step(1000)
    sim.command(closing_speed=0.0)
    sim.step(1000)
    m = scene.model.mass
    axis = scene.pose.axis
    ratio = np.full(len(mus), np.nan)
    load = 0.0
    for _ in range(3000):
        load += 0.5 * 0.005  # N, ramp 0.5 N/s
        sim.f_ext[:] = (m / m.sum())[None, :, None] * load * axis
        sim.step(5)
        v_axial = np.einsum("bni,n,i->b", sim.v, m, axis) / m.sum()
        newly = np.isnan(ratio) & (v_axial > 2e-3)  # gross sliding: the sphere runs away
        ratio[newly] = load / (mus[newly] * sim.pinch_force[newly])
        if not np.isnan(ratio).any():
            break
    assert np.all(np.abs(ratio - 1.0) < 0.10), ratio


def test_stick_then_slip_counts(coulomb_scene):
    sim = coulomb_scene.simulation(1)
    sim.set_friction(0.5)
    sim.command(closing_speed=0.004)
    sim.step(1000)
    counts = sim.jaw_out[0, :, J_CONTACT]
    assert np.all(counts > 0), "each jaw touches the sphere"
    sim.command(closing_speed=0.0, pull_velocity=0.05 * coulomb_scene.pose.axis)  # yank: gross slip
    sim.step(50)
    assert sim.jaw_out[0, :, J_SLIP].sum() > 0


def test_sphere_pinch_force_grows_with_jaw_displacement():
    data = run_sphere_grasp(sphere_scene(), travel_m=0.008)
    f = data["pinch_force_N"]
    assert f[-1] > 1.0
    # step-like but increasing: the force at the end exceeds the force at half travel
    half = np.searchsorted(data["jaw_displacement_mm"], 0.5 * data["jaw_displacement_mm"][-1])
    assert f[-1] > 1.5 * f[half]


def test_bad_grasper_inputs_name_the_field():
    with pytest.raises(ConfigError, match="mu"):
        GrasperParams(mu=-0.1)
    with pytest.raises(ConfigError, match="jaw_length_m"):
        GrasperParams(jaw_length_m=0.0)
    with pytest.raises(ConfigError, match="jaw_width_m"):
        GrasperParams(jaw_width_m=-0.01)
    with pytest.raises(ConfigError, match="overlap"):
        GrasperParams(jaw_width_m=0.02, min_radius_m=0.004)
    with pytest.raises(ConfigError, match="mu_kinetic"):
        GrasperParams(mu=0.3, mu_kinetic=0.5)


def test_negative_mu_in_the_experiment_is_refused():
    with pytest.raises(ConfigError, match=r"mu\[0\]"):
        run_grasp(spleen_scene(), [-0.2])


def test_axis_missing_the_tissue_is_a_clear_no_contact_result():
    scene = spleen_scene()
    far = GrasperPose(scene.pose.tip + np.array([0.0, 0.0, 0.5]), scene.pose.axis, scene.pose.e1)
    reach = reachable_radius(scene.x_start[scene.mesh.surface_nodes], far, scene.grasper)
    assert np.all(reach == 0.0)
    from dataclasses import replace

    with pytest.raises(ConfigError, match="no contact"):
        run_grasp(replace(scene, pose=far, reach=reach), [0.5])


def test_each_node_is_assigned_the_jaw_whose_centre_azimuth_is_nearest():
    """The cylindrical detection's jaw choice (contact.jaw_sector, projections on the jaw centres): the jaw whose
    centre azimuth 2 pi k / 3 is nearest; the paper's rule k = floor(phi / (2 pi / 3) + 1/2) mod 3 wherever the azimuth
    is more than round-off from a sector edge; on an exact edge, the jaw counter-clockwise of it."""
    import math

    from msdgrasp.physics.contact import jaw_sector

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(20000, 2)) * np.exp(rng.uniform(-12.0, 2.0, size=(20000, 1)))
    edge = rng.choice([math.pi / 3, -math.pi / 3, math.pi, -math.pi], size=20000)
    near = edge + rng.normal(size=20000) * rng.choice([1e-15, 1e-9, 1e-4], size=20000)
    pts_edge = np.stack([np.cos(near), np.sin(near)], axis=1) * rng.uniform(1e-4, 1.0, size=(20000, 1))
    centres = 2.0 * math.pi / 3.0 * np.arange(3)
    for p1, p2 in np.concatenate([pts, pts_edge]):
        phi = math.atan2(p2, p1)
        gap = np.abs((phi - centres + math.pi) % (2.0 * math.pi) - math.pi)  # angle to each jaw centre
        k = jaw_sector(p1, p2)
        assert gap[k] <= gap.min() + 1e-12, (p1, p2)
        if np.sort(gap)[1] - gap.min() > 1e-12:  # clear of an edge: the paper's formula
            assert k == int(math.floor(phi / (2.0 * math.pi / 3.0) + 0.5)) % 3, (p1, p2)
    # an exact edge (the two nearest centres equally near, phi = pi): counter-clockwise of it, as floor(3/2 + 1/2)
    assert jaw_sector(-1.0, 0.0) == 2 and jaw_sector(-0.25, 0.0) == 2
