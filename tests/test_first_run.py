"""A first run compiles the task's kernels in a helper process beside the physics (`msdgrasp.envs.compile_helper`,
`first_run` its program):
the helper compiles what the core then loads, it simulates nothing, and it starts only where it helps."""

from __future__ import annotations

import json

import pytest

from msdgrasp.benchmarks import compile_time
from msdgrasp.envs import compile_helper as first_run
from msdgrasp.envs.core import GraspLiftConfig, benchmark_config
from msdgrasp.physics.config import from_dict, to_dict
from msdgrasp.physics.jit import NOTICE

FIRST_STEP = ("import gymnasium as gym, numpy as np, msdgrasp\n"
              "env = gym.make('msdgrasp/GraspLift-v1')\nenv.reset(seed=0)\nenv.step(np.zeros(2, dtype=np.float32))\n")


@pytest.mark.timeout(600)
@pytest.mark.skipif(first_run.usable_cores() < 2, reason="one core: no helper (it would only compete)")
def test_a_cold_first_step_links_the_physics_itself_and_loads_the_task_kernels_its_helper_compiled(monkeypatch):
    """In a child with an empty numba cache (the benchmark's harness): the core's own process compiles ``simulate``
    and none of the task's kernels that a reset and a step call from Python (the helper compiled and cached them
    while the core settled its scene)."""
    monkeypatch.delenv(first_run.SWITCH, raising=False)
    report = compile_time.measure(FIRST_STEP, timeout_s=580)
    compiled = set(report["functions"])
    assert "msdgrasp.physics.integrator.simulate.python_call" in compiled
    task_entries = {f"msdgrasp.envs.task.{name}.python_call" for name in ("start_episode", "update_batch",
                                                                          "command_batch", "noise_scales")}
    assert not compiled & task_entries, compiled & task_entries


@pytest.mark.parametrize("scene, version", [("spleen", 1), ("spleen", 2), ("sphere", 2)])
def test_the_helper_gets_the_cores_config_whole(scene, version):
    config = benchmark_config(scene, version)
    assert from_dict(GraspLiftConfig, json.loads(json.dumps(to_dict(GraspLiftConfig())))) == GraspLiftConfig()  # v0
    assert from_dict(GraspLiftConfig, json.loads(json.dumps(to_dict(config)))) == config


def test_no_helper_where_the_task_kernels_are_cached_or_it_is_switched_off_or_one_ran(monkeypatch):
    monkeypatch.setattr(first_run, "_started", False)
    monkeypatch.setattr(first_run, "task_kernels_cached", lambda: True)
    assert first_run.helper(GraspLiftConfig(), "float64") is None
    monkeypatch.setattr(first_run, "task_kernels_cached", lambda: False)
    monkeypatch.setenv(first_run.SWITCH, "0")
    assert first_run.helper(GraspLiftConfig(), "float64") is None
    monkeypatch.delenv(first_run.SWITCH)
    monkeypatch.setattr(first_run, "usable_cores", lambda: 1)
    assert first_run.helper(GraspLiftConfig(), "float64") is None
    assert 1 <= first_run.usable_cores() <= (first_run.os.cpu_count() or 1)
    monkeypatch.setattr(first_run, "usable_cores", lambda: 2)
    monkeypatch.setattr(first_run, "_started", True)  # (one helper per process: a cache it cannot write stays cold)
    assert first_run.helper(GraspLiftConfig(), "float64") is None


def test_the_notice_names_what_compiles_and_that_it_happens_once():
    assert NOTICE.startswith("msdgrasp: compiling") and "once" in NOTICE and "\n" not in NOTICE


def test_a_core_whose_construction_fails_stops_its_helper(monkeypatch):
    import subprocess
    import sys

    from msdgrasp.envs import core
    from msdgrasp.physics.config import ConfigError

    started = []

    def fake_helper(config, precision):  # a helper that would compile for a minute
        started.append(subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"]))
        return started[-1]

    def broken_scene(*args, **kwargs):
        raise ConfigError("tissue: a broken scene")

    monkeypatch.setattr(first_run, "helper", fake_helper)
    monkeypatch.setattr(core, "spleen_scene", broken_scene)
    with pytest.raises(ConfigError, match="broken scene"):
        core.GraspLiftCore(benchmark_config("spleen", 2))
    assert started and started[0].poll() is not None  # stopped and reaped, not left compiling
