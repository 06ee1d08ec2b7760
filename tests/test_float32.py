"""``Simulation(precision="float32")`` on the CPU: an option for throughput, never the physics the package's results
use. It must really be float32 (a float64 constant promoting the springs back would leave it float64 at float32's
memory), keep float64 the default, and track float64 through a grasp within what the task can tell apart. A training
may roll out in float32 (``TrainConfig.precision``); its validation, which picks the model, runs float64."""

from __future__ import annotations

import numpy as np
import pytest

from msdgrasp.benchmarks.harness import clone, grasped
from msdgrasp.physics.config import ConfigError
from msdgrasp.physics.integrator import LANE_MIN
from msdgrasp.physics.reference import DT_OUTER
from msdgrasp.physics.simulation import Simulation


@pytest.fixture(scope="module")
def grasp():
    """The coarse spleen settled and held between the closed jaws (the bench's grasp, shortened)."""
    return grasped("coarse", 0.5, 1.0)


def _clone_of(grasp, batch: int, precision: str) -> Simulation:
    scene, held = grasp
    sim = Simulation(scene.model, batch, dt=DT_OUTER, grasper=scene.grasper, precision=precision)
    clone(held, sim)
    return sim


def test_float64_is_the_default_and_a_bad_precision_is_refused(grasp):
    scene, held = grasp
    assert held.precision == "float64" and held.x.dtype == held.fv.dtype == np.float64
    with pytest.raises(ConfigError, match="precision"):
        Simulation(scene.model, 1, precision="float16")
    # float32's model record is cast once, and again where a caller has replaced an array since
    sim = Simulation(scene.model, 1, dt=DT_OUTER, grasper=scene.grasper, precision="float32")
    first = sim.kernel_model()
    assert sim.kernel_model() is first and first.mass.dtype == np.float32
    sim.pl_mu = np.full_like(sim.pl_mu, 0.3)
    assert sim.kernel_model().pl_mu is sim.pl_mu


@pytest.mark.parametrize("batch", [1, LANE_MIN])
def test_float32_tracks_float64_through_a_held_grasp(grasp, batch):
    """50 ms of the hold from the same state, one tissue and a lane block: the float32 arrays stay float32 and
    differ from float64 (so the springs did compute in float32), and every tissue stays within 0.1 mm of float64's
    positions (the grasp deforms the tissue by millimetres), its pinch within 1 %, its nodes' contact states (free,
    stick, slip) the same on at least 95 % of the nodes."""
    a, b = _clone_of(grasp, batch, "float64"), _clone_of(grasp, batch, "float32")
    a.step(50)
    b.step(50)
    assert b.x.dtype == b.v.dtype == b.fv.dtype == b.dl_prev.dtype == np.float32
    assert b.kernel_model().k1.dtype == np.float32 and b.t.dtype == np.float64  # per-tissue values stay float64
    assert b.finite().all()
    err = np.abs(b.x.astype(np.float64) - a.x).max(axis=(1, 2))
    assert (err > 1e-10).all(), err  # not float64 in disguise
    assert (err < 1e-4).all(), err
    np.testing.assert_allclose(b.pinch_force, a.pinch_force, rtol=1e-2)
    assert (a.pinch_force > 0.5).all()  # (a real grasp was compared)
    assert (np.mean(a.contact_state == b.contact_state, axis=1) >= 0.95).all()


def test_a_float32_training_rolls_out_in_float32_and_validates_in_float64(tmp_path, monkeypatch):
    """``TrainConfig.precision = "float32"``: the training env's tissue arrays are float32; every core the validation
    (model selection) builds is float64, the physics of the results."""
    from msdgrasp.agents.models import TrainConfig
    from msdgrasp.agents.training import train
    from msdgrasp.envs import core as core_module
    from msdgrasp.physics.config import from_dict

    built = []
    init = core_module.GraspLiftCore.__init__

    def recording_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        built.append((self.num_envs, self.precision, self.sim.x.dtype, self.sim.fv.dtype))

    monkeypatch.setattr(core_module.GraspLiftCore, "__init__", recording_init)
    config = from_dict(TrainConfig, {"n_envs": 2, "precision": "float32", "total_timesteps": 256,
                                     "checkpoint_every": 128, "validation_episodes": 1, "validation_mu": [0.5],
                                     "ppo": {"n_steps": 128, "batch_size": 128, "n_epochs": 1, "use_sde": True}})
    summary = train(config, tmp_path / "run", progress=False)
    assert summary["precision"] == "float32" and summary["timesteps"] >= 256
    assert built[0] == (2, "float32", np.float32, np.float32)  # the training env
    assert len(built) >= 2 and all(b[1:] == ("float64", np.float64, np.float64) for b in built[1:]), built
    with pytest.raises(ConfigError, match="precision"):
        from_dict(TrainConfig, {"precision": "float16"})
