"""The CUDA backend of the physics step against the CPU kernel (numba's CUDA simulator without a GPU).

conftest.py sets ``NUMBA_ENABLE_CUDASIM=1`` unless the environment sets it (``NUMBA_ENABLE_CUDASIM=0`` runs
these tests on a real GPU). The simulator is slow (Python threads), so the case is small: a 60-node spleen
with compliant anchors, the Maxwell branch and the volume barrier, two tissues with different stiffness,
mass and friction, the force loop pinching at 5 N, then a pull: contact with stick and slip; and a 60-node
sphere between two plates.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msdgrasp.physics.config import ConfigError, replace
from msdgrasp.physics.scenario import spleen_scene

# the GPU port's tolerance: positions within 1e-12 m after an episode with contact
POSITION_TOL_M = 1e-12
# the sensors (forces, pressures, slip distances) after an episode with contact: 1e-9 relative, as the task's
SENSOR_RTOL = 1e-9


def _pair(threads: int):
    scene = spleen_scene(resolution=60, anchor_stiffness_n_per_m=8.0, settle_s=0.5)
    # the volume barrier from any volume loss (threshold 1): its implicit step, with nodes held by the jaws,
    # runs on every squeezed tet
    scene = dataclasses.replace(scene, model=dataclasses.replace(
        scene.model, params=replace(scene.model.params, volume_threshold=1.0)))
    sims = []
    for backend in ("cpu", "cuda"):
        sim = scene.simulation(2, backend=backend, max_stiffness_scale=1.2, min_mass_scale=0.9)
        sim.set_scales(stiffness=[0.8, 1.2], mass=[1.1, 0.9])
        sim.set_friction([0.3, 0.9], mu_kinetic=[0.25, 0.8])
        sim.g_radius[:] = sim.g_radius - 0.004  # start close to the tissue: contact within a few steps
        sim.command_pinch_force([5.0, 5.0], 0.02, 0.02)
        sims.append(sim)
    if threads:
        from msdgrasp.physics.cuda_step import CudaBatch

        sims[1]._cuda = CudaBatch(sims[1].kernel_model(), sims[1].kernel_state(), sims[1].kernel_readout(),
                                  threads=threads)
    return scene, sims


def test_the_gpu_code_reaches_no_cpu_function():
    """Every numba CPU function the kernel and its device functions call, directly or through others, is bound to
    its GPU twin (in the simulator a CPU function would run unnoticed; on a GPU the kernel would not compile)."""
    from numba.core.registry import CPUDispatcher

    from msdgrasp.physics import cuda_step

    seen, todo = set(), [cuda_step._simulate_kernel]
    while todo:
        kernel = todo.pop()
        fn = getattr(kernel, "py_func", None) or kernel.fn  # (a GPU's dispatcher, or the simulator's)
        if fn in seen:
            continue
        seen.add(fn)
        for name in fn.__code__.co_names:
            g = fn.__globals__.get(name)
            assert not isinstance(g, CPUDispatcher), f"{fn.__name__} calls the CPU's {name}"
            if type(g).__name__ in ("FakeCUDAKernel", "CUDADispatcher"):
                todo.append(g)
    names = {fn.__name__ for fn in seen}
    assert {"_simulate_kernel", "_barrier", "_contacts", "springs_to_scratch", "spring_body", "advance_node",
            "listed_volume_barrier", "barrier_impulse", "resolve_jaw_contacts"} <= names


def test_cuda_step_matches_the_cpu_kernel_through_a_grasp_with_stick_and_slip():
    from msdgrasp.physics.cuda_step import FLAG_LIST
    from msdgrasp.physics.forces import flag_barrier

    scene, (cpu, gpu) = _pair(threads=4)  # 4 threads: the strided loops and barriers of a real block
    m = cpu.kernel_model()
    flags = np.zeros(m.tets.shape[0], dtype=np.int8)
    n_flagged = []
    seen_stick = seen_slip = 0
    worst = 0.0
    lowest = 1.0
    for k in range(12):  # 12 calls of 8 ms: close, pinch, then pull
        if k == 6:
            for sim in (cpu, gpu):
                sim.command(pull_velocity=np.tile(0.03 * scene.pull_direction, (2, 1)))
        cpu.step(8)
        gpu.step(8)
        worst = max(worst, float(np.abs(cpu.x - gpu.x).max()))
        lowest = min(lowest, float(cpu.min_volume_ratio().min()))
        n_flagged += [flag_barrier(cpu.x[b], m.tets, m.rest_volume, m.vol_threshold, flags) for b in range(2)]
        np.testing.assert_array_equal(gpu.contact_state, cpu.contact_state)  # identical stick/slip decisions
        seen_stick += int((cpu.contact_state == 1).sum())
        seen_slip += int((cpu.contact_state == 2).sum())
    assert seen_stick > 0 and seen_slip > 0, (seen_stick, seen_slip)  # the case exercised both
    assert worst <= POSITION_TOL_M
    assert cpu.pinch_force.min() > 0.2  # the jaws held the tissue
    assert cpu.min_volume_ratio().min() < 1.0 and cpu.model.kvol.max() > 0  # the barrier acted
    assert 0.5 < lowest < 0.99, lowest  # the barrier acted on squeezed tets (from any volume loss) and held them
    # the GPU's two barrier paths both ran: its shared list of flagged tets, and the scan of every flag past it
    assert min(n_flagged) <= FLAG_LIST < max(n_flagged), n_flagged
    for name in ("v", "fv", "dl_prev", "g_radius", "g_tip", "t"):
        np.testing.assert_allclose(getattr(gpu, name), getattr(cpu, name), rtol=0,
                                   atol=1e-9 * max(1.0, np.abs(getattr(cpu, name)).max()))
    for name in ("jaw_out", "anchor_out", "contact_force", "g_force"):  # the sensors read the same
        scale = max(1e-9, np.abs(getattr(cpu, name)).max())
        np.testing.assert_allclose(getattr(gpu, name), getattr(cpu, name), rtol=0, atol=1e-9 * scale)


def test_unknown_backends_name_the_choice():
    from msdgrasp.physics.simulation import Simulation

    scene = spleen_scene(resolution=60, anchor_stiffness_n_per_m=8.0, settle_s=0.5)
    with pytest.raises(ConfigError, match=r"backend = 'gpu' is not allowed; choose one of 'cpu', 'cuda'"):
        Simulation(scene.model, 1, backend="gpu")


def test_plates_on_the_gpu_press_and_shear_the_sphere_as_on_the_cpu():
    """The compression experiment's physics on the GPU: a small sphere between a fixed and a moving plate
    (friction 0.3 below and 0.1 on the top plate, which also slides sideways: nodes stick and slip), the
    volume barrier acting under the plates. Positions within 1e-12 m, identical contact states, the plate
    forces the same."""
    from msdgrasp.physics.config import builtin_config
    from msdgrasp.physics.mesh_gen import sphere_mesh
    from msdgrasp.physics.scenario import load_params
    from msdgrasp.physics.simulation import Plate, Simulation
    from msdgrasp.physics.tissue import TissueModel, TissueParams

    mesh = sphere_mesh(resolution=60)  # the mapped-box sphere: small enough for the simulator
    params = load_params(builtin_config("tissue/sphere.yaml"), "tissue", TissueParams)
    model = TissueModel.from_params(mesh, replace(params, volume_threshold=1.0, gravity_m_per_s2=(0.0, 0.0, 0.0)))
    z = mesh.nodes[:, 2]
    plates = [Plate((0.0, 0.0, z.min()), (0.0, 0.0, 1.0), mu=0.3),
              Plate((0.0, 0.0, z.max()), (0.0, 0.0, -1.0), (0.2, 0.0, -0.2), mu=0.1)]
    sims = []
    for backend in ("cpu", "cuda"):
        sim = Simulation(model, 2, plates=plates, max_stiffness_scale=1.2, backend=backend)
        sim.set_scales(stiffness=[0.9, 1.2])
        sims.append(sim)
    cpu, gpu = sims
    lowest = 1.0
    seen = np.zeros(3, dtype=int)
    for _ in range(6):  # 6 calls of 5 ms: the top plate moves 6 mm down and 6 mm sideways
        cpu.step(5)
        gpu.step(5)
        np.testing.assert_array_equal(gpu.contact_state, cpu.contact_state)
        seen += np.bincount(cpu.contact_state.ravel(), minlength=3)
        lowest = min(lowest, float(cpu.min_volume_ratio().min()))
    assert np.abs(gpu.x - cpu.x).max() <= POSITION_TOL_M
    assert seen[1] > 0 and seen[2] > 0, seen  # stick and slip
    assert np.abs(cpu.plate_out).max() > 0.1  # the plates press
    assert lowest < 0.905, lowest  # the barrier (from any volume loss) acted under the plates
    np.testing.assert_allclose(gpu.pl_point, cpu.pl_point, rtol=0, atol=1e-15)
    for name in ("plate_out", "contact_force"):
        scale = np.abs(getattr(cpu, name)).max()
        np.testing.assert_allclose(getattr(gpu, name), getattr(cpu, name), rtol=0, atol=1e-9 * scale)


def test_a_device_resident_batch_steps_without_host_round_trips_and_matches_the_cpu():
    """State and readouts stay on the device: only the pull command goes up and only the jaw sensors come
    down per call, and the state downloaded at the end is the CPU kernel's."""
    from msdgrasp.physics.cuda_step import CudaBatch

    scene, (cpu, host) = _pair(threads=0)
    batch = CudaBatch(host.kernel_model(), host.kernel_state(), host.kernel_readout(), threads=4)
    sensors = np.zeros_like(cpu.jaw_out)
    for k in range(10):
        if k == 5:
            for sim in (cpu, host):
                sim.command(pull_velocity=np.tile(0.03 * scene.pull_direction, (2, 1)))
            batch.upload(host.kernel_state(), fields=("g_vpull",))
        cpu.step(8)
        batch.step(8)
        batch.download(out=host.kernel_readout()._replace(jaw_out=sensors), fields=("jaw_out",))
        # bit for bit in the simulator; on a GPU its fused multiply-adds round differently (~1e-13 relative seen)
        np.testing.assert_allclose(sensors, cpu.jaw_out, rtol=SENSOR_RTOL, atol=0.0)
    assert cpu.pinch_force.min() > 0.2 and np.abs(host.x - cpu.x).max() > 1e-3  # host copy untouched: stale
    batch.download(host.kernel_state(), host.kernel_readout())
    assert np.abs(host.x - cpu.x).max() <= POSITION_TOL_M
    np.testing.assert_array_equal(host.contact_state, cpu.contact_state)
    arrays = batch.arrays()
    assert {"x", "v", "jaw_out", "contact_state"} <= set(arrays)
    from numba import config as numba_config

    if not numba_config.ENABLE_CUDASIM:  # on a GPU: the arrays go to torch / CuPy without a copy
        assert all(hasattr(a, "__cuda_array_interface__") for a in arrays.values())
    else:  # the simulator's arrays are host arrays in disguise: no interface to check
        assert all(hasattr(a, "copy_to_host") for a in arrays.values())
    with pytest.raises(ValueError, match="field 'xx' is not in the state or readout records"):
        batch.download(host.kernel_state(), fields=("xx",))


def test_gpu_bench_reports_why_it_cannot_time_here_and_its_harness_runs_in_the_simulator(tmp_path):
    """Timings need a GPU: without one (or in the simulator) the bench says why and reports no numbers; the
    harness itself runs here on a tiny case (its numbers are not timings)."""
    from msdgrasp.benchmarks import bench
    from msdgrasp.benchmarks.report import markdown, plot_gpu, speedup
    from numba import config as numba_config

    if not numba_config.ENABLE_CUDASIM:
        pytest.skip("on a GPU the bench measures; `msdgrasp bench gpu` is the timing")
    report = bench.run_bench("gpu", quick=True)
    assert report["gpu"] == {"available": False, "reason": bench.gpu_unavailable_reason(), "rows": []}
    assert "simulator" in report["gpu"]["reason"] and "gpu_ge_200k_agent_steps_per_s" not in report["targets"]
    assert "Not measured: NUMBA_ENABLE_CUDASIM=1" in markdown(report)
    # float32's error run: only when asked for by name in the simulator (minutes of Python kernels)
    assert report["precision"] == {"available": False, "reason": bench.gpu_unavailable_reason()}
    res = bench.bench_gpu(True, resolution=60, batches=(1, 2), settle_s=0.2, close_s=0.3, steps=1,
                          min_time=0.01, force=True, task_warmup_s=0.002, threads=4)
    cases = [(1, True), (2, True), (1, False), (2, False)]
    assert [(r["dtype"], r["batch"], r["contact"]) for r in res["rows"]] == \
        [("float64", *c) for c in cases] + [("float32", *c) for c in cases]
    grasped = [r["contact_nodes_mean"] for r in res["rows"] if r["contact"]]
    assert min(grasped) > 0 and all(r["contact_nodes_mean"] == 0 for r in res["rows"] if not r["contact"])
    # the whole task step's rows: one per batch, the share of envs holding the tissue measured, not assumed
    assert [(r["dtype"], r["batch"]) for r in res["task_rows"]] == [("float64", 1), ("float64", 2), ("float32", 1),
                                                                     ("float32", 2)]
    assert all(r["what"] == "task" and 0.0 <= r["contact_fraction"] <= 1.0 for r in res["task_rows"])
    assert "The whole task step" in markdown({**report, "gpu": res, "targets": {}})
    # beside the GPU rows, the CPU measured the same way (here: real timings of the local numba kernel)
    cpu = report["gpu_cpu_reference"]
    assert [r["batch"] for r in cpu["rows"]] == [r["batch"] for r in cpu["task_rows"]] == [1, 64]
    assert all(r["contact_nodes_mean"] > 0 for r in cpu["rows"])  # grasped, as the GPU rows with contact
    assert all(r["contact_fraction"] >= 0.9 for r in cpu["task_rows"])  # the 2.5 N pinch holds after its warm-up
    for r in cpu["rows"] + cpu["task_rows"]:
        assert r["agent_steps_per_s"] == pytest.approx(r["batch"] / r["ms_per_agent_step"] * 1e3, rel=0.01)
    # GPU / CPU: the float64 GPU row with contact at the same batch over the CPU row, "-" where there is none
    one = cpu["rows"][0]
    gpu_rows = [{"batch": 1, "contact": c, "dtype": d, "agent_steps_per_s": 100.0 * one["agent_steps_per_s"] * k,
                 "ms_per_agent_step": 1.0}
                for k, (c, d) in enumerate([(True, "float64"), (False, "float64"), (True, "float32")], start=1)]
    assert speedup(one, gpu_rows) == 100.0 and speedup(cpu["rows"][1], gpu_rows) is None
    md = markdown({**report, "gpu": {**res, "available": True, "rows": gpu_rows, "task_rows": []}, "targets": {}})
    assert f"| physics | 1 | {one['agent_steps_per_s']} | {one['ms_per_agent_step']} | 100.0x |" in md
    assert f"| physics | 64 | {cpu['rows'][1]['agent_steps_per_s']} | {cpu['rows'][1]['ms_per_agent_step']} | - |" in md
    # the throughput-vs-batch figure: CPU alone here, nothing to draw without either
    png = plot_gpu(report, tmp_path / "bench_gpu.png")
    assert png is not None and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plot_gpu({"gpu": report["gpu"]}, tmp_path / "none.png") is None and not (tmp_path / "none.png").exists()


def test_numba_cuda_beside_numpy_2_5_is_refused_with_the_fix_before_any_kernel():
    from msdgrasp.physics.device_layout import check_numba_cuda_numpy

    # numba-cuda <= 0.30.4 registers np.row_stack, which numpy 2.5 removed: its first launch would fail deep inside
    with pytest.raises(ImportError, match=r"numba-cuda 0\.30\.4 cannot compile kernels with numpy 2\.5\.2 .*"
                                          r"pip install 'numpy<2\.5'"):
        check_numba_cuda_numpy("0.30.4", "2.5.2")
    with pytest.raises(ImportError):
        check_numba_cuda_numpy("0.30.0", "2.6.0rc1")
    check_numba_cuda_numpy("0.30.4", "2.4.6")  # the gpu extra's pin
    check_numba_cuda_numpy(None, "2.5.2")  # numba's own CUDA target / its simulator: no such overload
    check_numba_cuda_numpy("0.31.0", "2.5.2")  # a later release is trusted to have fixed it


def test_a_float32_simulation_runs_the_gpu_kernels_float32_storage_and_tracks_the_cpus_float32():
    """``Simulation(backend="cuda", precision="float32")`` hands its float32 arrays to the GPU kernel's own float32
    storage; through a 5 N pinch it stays within float32's reach of the CPU's float32 step (the two promote
    differently: the CPU computes its springs in float32, the GPU kernel follows numba's typing), 1e-6 m and 1e-4
    of the pinch, with the same contact states on at least 95 % of the nodes."""
    scene = spleen_scene(resolution=60, anchor_stiffness_n_per_m=8.0, settle_s=0.5)
    sims = []
    for backend in ("cpu", "cuda"):
        sim = scene.simulation(2, backend=backend, precision="float32")
        sim.g_radius[:] = sim.g_radius - 0.004  # start close to the tissue: contact within a few steps
        sim.command_pinch_force([5.0, 5.0], 0.02, 0.02)
        sims.append(sim)
    cpu, gpu = sims
    for _ in range(3):
        cpu.step(4)
        gpu.step(4)
    assert cpu.x.dtype == gpu.x.dtype == np.float32
    assert float(np.abs(cpu.x - gpu.x).max()) < 1e-6
    assert cpu.pinch_force.min() > 1.0  # the jaws pinch the tissue
    np.testing.assert_allclose(gpu.pinch_force, cpu.pinch_force, rtol=1e-4)
    assert np.mean(gpu.contact_state == cpu.contact_state) >= 0.95
