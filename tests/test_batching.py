"""Batching is an implementation detail: a tissue's trajectory does not depend on the batch it runs in.

Batches of LANE_MIN or more tissues run springs, tets and the node update across tissues (SIMD lanes,
in blocks of up to LANE_BLOCK); smaller ones, and the few a batch leaves over, run tissue after tissue.
Each lane performs the same floating-point operations in the same order as the one-tissue kernels, so the
results must agree *bitwise*, not within a tolerance: any drift means the two code paths compute different physics.
"""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.physics.integrator import LANE_BLOCK, LANE_MIN
from msdgrasp.physics.scenario import sphere_scene, spleen_scene
from msdgrasp.physics.simulation import Plate, Simulation

STATE = ("x", "v", "t", "fv", "dl_prev", "g_radius", "g_tip", "pl_point")
READOUTS = ("jaw_out", "plate_out", "anchor_out", "contact_state", "contact_force")


def _varied(sim: Simulation, rng: np.random.Generator, pull_direction: np.ndarray) -> dict:
    """Give every tissue its own stiffness, mass, friction, jaw speed, pull and external load."""
    B = sim.batch_size
    settings = {
        "stiffness": rng.uniform(0.8, 1.3, B),
        "mass": rng.uniform(0.85, 1.2, B),
        "mu": rng.uniform(0.1, 1.2, B),
        "closing": rng.uniform(0.01, 0.03, B),
        "pull": np.outer(rng.uniform(0.0, 0.03, B), pull_direction),
        "load": rng.normal(0.0, 0.02, (B, 3)),
    }
    _apply(sim, settings, np.arange(B))
    return settings


def _apply(sim: Simulation, settings: dict, rows: np.ndarray) -> None:
    sim.set_scales(stiffness=settings["stiffness"][rows], mass=settings["mass"][rows])
    sim.set_friction(settings["mu"][rows])
    sim.command(closing_speed=settings["closing"][rows], pull_velocity=settings["pull"][rows])
    sim.f_ext[:, 7, :] = settings["load"][rows]


def _assert_same(batch: Simulation, alone: Simulation, b: int) -> None:
    for name in STATE + READOUTS:
        got, want = getattr(batch, name)[b], getattr(alone, name)[0]
        assert np.array_equal(got, want), f"tissue {b}: {name} differs by {np.max(np.abs(got - want)):.3g}"


@pytest.mark.parametrize("batch_size", [LANE_MIN, LANE_BLOCK + 3])
def test_a_tissue_in_a_lane_batch_moves_exactly_as_alone(batch_size):
    scene = spleen_scene(resolution="coarse")
    kw = {"max_stiffness_scale": 1.3, "min_mass_scale": 0.85}
    batch = scene.simulation(batch_size, **kw)
    settings = _varied(batch, np.random.default_rng(batch_size), scene.pull_direction)
    batch.step(120)  # jaws close onto the organ: contacts, sticking and slipping, anchors loaded
    batch.step(33)  # a second call: lane state goes out and comes back in
    assert batch.jaw_contact_counts[:, :, 0].sum() > 0, "the scenario must reach contact"
    for b in (0, LANE_MIN - 1, batch_size // 2, batch_size - 1):
        alone = scene.simulation(1, **kw)
        _apply(alone, settings, np.array([b]))
        alone.step(120)
        alone.step(33)
        _assert_same(batch, alone, b)


def test_the_volume_barrier_acting_in_a_lane_batch_acts_exactly_as_alone():
    """The barrier's paths differ between one tissue (a contiguous flag pass) and a lane batch (a flag pass
    across lanes, then the implicit step on strided views); with the barrier acting on every tissue under a
    4-6 N force-loop pinch and a pull they agree bitwise."""
    scene = spleen_scene(resolution="coarse", settle_s=0.5)
    setpoints = np.linspace(4.0, 6.0, LANE_MIN)
    stiffness = np.linspace(0.8, 1.0, LANE_MIN)

    def run(sim, rows):
        sim.set_scales(stiffness=stiffness[rows])
        sim.command_pinch_force(setpoints[rows], 0.05, 0.02)
        sim.step(800)
        sim.command(pull_velocity=np.tile(0.02 * scene.pull_direction, (len(rows), 1)))
        sim.step(200)

    batch = scene.simulation(LANE_MIN, max_stiffness_scale=1.0)
    run(batch, np.arange(LANE_MIN))
    threshold = scene.model.params.volume_threshold
    assert np.all(batch.min_volume_ratio() < threshold), batch.min_volume_ratio()  # the barrier acts in every tissue
    for b in (0, LANE_MIN - 1):
        alone = scene.simulation(1, max_stiffness_scale=1.0)
        run(alone, np.array([b]))
        _assert_same(batch, alone, b)


def test_the_barriers_watch_list_gives_the_trajectory_of_a_full_flag_pass_every_substep():
    """Between full flag passes the barrier looks only at the tets a full pass found near its threshold
    (forces.watch_barrier); with watch_delta 0 every substep is a full pass. Under a 4-6 N force-loop pinch and a
    pull, with tets crossing the threshold, both give the same trajectories bitwise, alone and in a lane batch."""
    scene = spleen_scene(resolution="coarse", settle_s=0.5)
    setpoints = np.linspace(4.0, 6.0, LANE_MIN)

    def run(sim, rows):
        sim.command_pinch_force(setpoints[rows], 0.05, 0.02)
        sim.step(600)
        sim.command(pull_velocity=np.tile(0.03 * scene.pull_direction, (len(rows), 1)))
        sim.step(300)

    for rows in (np.arange(LANE_MIN), np.array([LANE_MIN - 1])):
        watched, full = scene.simulation(len(rows)), scene.simulation(len(rows))
        assert watched.watch_delta > 0.0
        full.watch_delta = 0.0
        run(watched, rows)
        run(full, rows)
        assert np.all(watched.min_volume_ratio() < scene.model.params.volume_threshold)
        for name in STATE + READOUTS:
            got, want = getattr(watched, name), getattr(full, name)
            assert np.array_equal(got, want), f"{name} differs by {np.max(np.abs(got - want)):.3g}"


def test_plates_in_a_lane_batch_act_exactly_as_alone():
    scene = sphere_scene(resolution="coarse")
    z = scene.x_start[:, 2]
    rng = np.random.default_rng(3)

    def sim(batch_size: int) -> Simulation:
        plates = [Plate((0.0, 0.0, z.min()), (0.0, 0.0, 1.0), mu=0.3),
                  Plate((0.0, 0.0, z.max()), (0.0, 0.0, -1.0), (0.0, 0.0, -0.02), mu=0.3)]
        s = Simulation(scene.model, batch_size, plates=plates, max_stiffness_scale=1.2)
        s.set_state(scene.x_start)
        return s

    batch = sim(LANE_MIN + 2)
    scales = rng.uniform(0.9, 1.2, batch.batch_size)
    batch.set_scales(stiffness=scales)
    batch.step(150)
    assert np.all(batch.plate_out[:, 0, 2] > 0.0), "the bottom plate must push up on every tissue"
    for b in (0, batch.batch_size - 1):
        alone = sim(1)
        alone.set_scales(stiffness=scales[b])
        alone.step(150)
        _assert_same(batch, alone, b)


def test_dashpots_compliant_anchors_and_displacement_damping_in_lanes_act_exactly_as_alone():
    """The optional terms the spleen scene leaves off: spring dashpots, b1 > 0 (Eq. 7), sprung anchors."""
    from dataclasses import replace

    from msdgrasp.physics import reference
    from msdgrasp.physics.tissue import TissueModel

    model = reference.spleen_model("coarse")
    params = replace(reference.spleen_params(), spring_damping_time_s=0.002, damping_disp_rate_per_m_s=500.0)
    model = TissueModel.from_params(model.mesh, params, fixed_nodes=model.mesh.node_sets["hilum"],
                                    anchor_stiffness_n_per_m=8.0)
    assert model.b1.max() > 0 and model.anchor_k.max() > 0 and model.cdash.max() > 0
    rng = np.random.default_rng(5)
    loads = rng.normal(0.0, 0.05, (LANE_MIN + 1, 3))
    stiffness = rng.uniform(0.8, 1.2, LANE_MIN + 1)
    mass = rng.uniform(0.8, 1.2, LANE_MIN + 1)

    def run(rows: np.ndarray) -> Simulation:
        s = Simulation(model, len(rows), max_stiffness_scale=1.2, min_mass_scale=0.8)
        s.set_scales(stiffness=stiffness[rows], mass=mass[rows])
        s.f_ext[:, 11, :] = loads[rows]
        s.step(80)
        return s

    batch = run(np.arange(LANE_MIN + 1))
    assert np.abs(batch.anchor_out).max() > 0.0
    for b in (0, LANE_MIN):
        _assert_same(batch, run(np.array([b])), b)


def test_a_blown_up_tissue_does_not_touch_its_lane_neighbours():
    """A NaN in one tissue stays there: the others of its lane block move bitwise as alone."""
    scene = spleen_scene(resolution="coarse")
    batch = scene.simulation(LANE_MIN)
    batch.command(closing_speed=0.01)
    batch.x[3, 10, 0] = np.nan
    batch.step(40)
    assert not batch.finite()[3] and batch.finite()[np.arange(LANE_MIN) != 3].all()
    alone = scene.simulation(1)
    alone.command(closing_speed=0.01)
    alone.step(40)
    for b in (2, 4, LANE_MIN - 1):
        _assert_same(batch, alone, b)


def test_stepping_some_tissues_moves_them_as_the_whole_batch_and_leaves_the_rest():
    """``step(n, indices)`` (what an evaluation uses once some episodes have ended): the tissues named move
    bitwise as in a step of the whole batch (here from a lane block of 26 to 24 lanes and to tissues alone), the
    others, state and readouts, do not change at all."""
    scene = spleen_scene(resolution="coarse")
    kw = {"max_stiffness_scale": 1.3, "min_mass_scale": 0.85}
    B = LANE_MIN + 2
    whole, part = scene.simulation(B, **kw), scene.simulation(B, **kw)
    settings = _varied(whole, np.random.default_rng(7), scene.pull_direction)
    _apply(part, settings, np.arange(B))
    whole.step(120)
    part.step(120)  # in contact: sticking and slipping
    assert part.jaw_contact_counts[:, :, 0].sum() > 0, "the scenario must reach contact"
    for some in (np.arange(2, B), np.array([5, 0, 17])):  # (unsorted: any order names the same tissues)
        kept = {name: getattr(part, name).copy() for name in STATE + READOUTS}
        whole.step(33)
        part.step(33, indices=some)
        rest = np.setdiff1d(np.arange(B), some)
        for name in STATE + READOUTS:
            got = getattr(part, name)
            assert np.array_equal(got[some], getattr(whole, name)[some]), f"{name} of the tissues stepped"
            assert np.array_equal(got[rest], kept[name][rest]), f"{name} of the tissues not stepped"
        # catch up with the whole batch: its state and readouts, whole
        for dst, src in zip((*part.kernel_state(), *part.kernel_readout()),
                            (*whole.kernel_state(), *whole.kernel_readout())):
            dst[...] = src


@pytest.mark.parametrize("indices", [[0, 0], [-1], [LANE_MIN + 2]])
def test_stepping_tissues_that_are_not_distinct_members_of_the_batch_is_refused(indices):
    from msdgrasp.physics.config import ConfigError

    sim = spleen_scene(resolution="coarse").simulation(LANE_MIN + 2)
    x = sim.x.copy()
    with pytest.raises(ConfigError, match="step indices"):
        sim.step(1, indices=indices)
    assert np.array_equal(sim.x, x)


def test_the_cuda_backend_refuses_to_step_some_tissues():
    """Its batch lives on the device and steps whole: a subset is refused, not silently stepped whole."""
    from msdgrasp.physics.config import ConfigError

    sim = spleen_scene(resolution="coarse").simulation(2, backend="cuda")
    with pytest.raises(ConfigError, match="cuda backend advances its whole"):
        sim.step(1, indices=[0])


@pytest.mark.parametrize("nb", [1, LANE_MIN - 1, LANE_MIN, LANE_MIN + 1, 30, 32, LANE_BLOCK, LANE_BLOCK + 3, 72, 257])
def test_lane_blocks_cover_the_batch_in_simd_widths(nb):
    """simulate's blocks: consecutive, covering every tissue once; lane blocks of LANE_MIN..LANE_BLOCK tissues in
    multiples of LANE_WIDTH (the vector width the loops are compiled for); alone only the leftover tissues (fewer
    than LANE_WIDTH) or a whole batch below LANE_MIN."""
    from msdgrasp.physics.integrator import LANE_WIDTH, lane_blocks

    blocks = lane_blocks(nb)
    assert blocks[0, 0] == 0 and blocks[:, 1].sum() == nb
    assert np.array_equal(blocks[1:, 0], blocks[:-1, 0] + blocks[:-1, 1])
    lanes = blocks[blocks[:, 1] > 1, 1]
    assert ((lanes >= LANE_MIN) & (lanes <= LANE_BLOCK) & (lanes % LANE_WIDTH == 0)).all()
    alone = int(np.sum(blocks[:, 1] == 1))
    assert alone == (nb if nb < LANE_MIN else nb % LANE_WIDTH)
