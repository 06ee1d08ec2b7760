"""Perturbations are declared once (envs/perturbations.py): their config fields, draws, privileged entries and suite
conditions follow from the declaration, on both backends.

A toy perturbation, declared in this file only, is drawn by the CPU and the GPU core (numba's CUDA simulator here),
appears in the privileged block as its declaration scales it, and runs as a condition of the robustness suite.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json

import numpy as np
import pytest

from msdgrasp.agents import robustness
from msdgrasp.agents.robustness import MUS
from msdgrasp.cli.main import main
from msdgrasp.envs.core import GraspLiftConfig, GraspLiftCore, RandomizationConfig
from msdgrasp.envs.perturbations import (
    SYMMETRIC, Column, Level, Perturbation, Privileged, column_index, draw_columns, perturbations, privileged_names,
    registered, suite_conditions,
)
from msdgrasp.physics.config import from_dict

#: the toy: a per-episode value uniform in [-0.3, 0.3] with no effect on the task, privileged as value / 0.3
TOY = Perturbation("toy_wobble", "actuation", (), (Column("toy_wobble"),), lambda r: [(SYMMETRIC, 0.0, 0.3)],
                   privileged=(Privileged("toy_wobble", "toy_wobble", 0.0, 0.3),), levels=(Level("toy wobble 0.3"),))


def _config(**fields) -> GraspLiftConfig:
    return from_dict(GraspLiftConfig, {"resolution": 60, "physics_steps_per_action": 2, "privileged_obs": True,
                                       "privileged_perturbations": True, **fields})


def test_every_randomization_field_belongs_to_one_perturbation():
    declared = [f for p in perturbations() for f in p.fields]
    assert sorted(declared) == sorted(f.name for f in dataclasses.fields(RandomizationConfig))
    assert len(set(declared)) == len(declared)


def test_the_built_in_columns_keep_the_draw_order_of_the_random_stream():
    """The drawn columns' order is the random stream's: a new declaration goes last (the derived pose-error
    columns draw nothing)."""
    drawn_order = ("mu", "stiffness_scale", "mass_scale", "offset_dir_x", "offset_dir_y", "offset_dir_z", "offset_r",
                   "tilt_axis_x", "tilt_axis_y", "tilt_axis_z", "tilt", "azimuth", "force_bias_0", "force_bias_1",
                   "force_bias_2", "latency", "force_loop_gain", "sensor_noise")
    assert [column_index(n) for n in drawn_order] == sorted(column_index(n) for n in drawn_order)


def test_a_declared_toy_is_drawn_on_both_backends_and_observed_as_declared():
    from msdgrasp.envs.cuda_core import CudaGraspLiftCore

    n_before, priv_before = len(draw_columns()), len(privileged_names())
    with registered(TOY):
        assert draw_columns()[-1] == "toy_wobble" and privileged_names()[-1] == "toy_wobble"
        config = _config()
        cpu = GraspLiftCore(config, 64)
        for i in range(64):
            cpu.seed(i, 500 + i)
            cpu.reset(i)
        gpu = CudaGraspLiftCore(config, 64, seed=3, threads=2)
        gpu.reset()
        got = gpu.download("draws", "obs")
        for draws, obs in ((cpu.draws, cpu.obs), (got["draws"], got["obs"])):
            toy = draws[:, column_index("toy_wobble")]
            assert np.abs(toy).max() <= 0.3 and toy.min() < -0.2 and toy.max() > 0.2  # uniform on [-0.3, 0.3]
            np.testing.assert_allclose(obs[:, -1], toy / 0.3, rtol=1e-6)  # the last privileged entry
        assert cpu.frame_dim == GraspLiftCore(_config(privileged_perturbations=False), 1).frame_dim + priv_before + 1
    assert len(draw_columns()) == n_before and len(privileged_names()) == priv_before  # gone with the block


def test_a_declared_toy_runs_as_a_suite_condition(tmp_path, monkeypatch):
    with registered(TOY):
        conditions = suite_conditions((0.5,), 2)
        toy = [c for c in conditions if c.name == "toy wobble 0.3"]
        assert len(toy) == 1 and toy[0].axis == "actuation" and toy[0].mus == (0.5,)
        assert [c.axis for c in conditions].index("actuation") < conditions.index(toy[0])
        monkeypatch.setitem(robustness.SUITES, "robustness", conditions)
        from msdgrasp.agents import controllers

        monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--episodes", "1", "--condition",
                       "toy wobble 0.3", "--out", str(tmp_path), "--quiet"])
        assert rc == 0, err.getvalue()
    data = json.loads((tmp_path / "suite_robustness.json").read_text())
    assert [c["name"] for c in data["conditions"]] == ["toy wobble 0.3"]
    assert all(len(r["cells"]) == 1 for r in data["results"])
    assert "toy wobble 0.3" not in {c.name for c in suite_conditions(MUS, 2)}


def test_the_suite_conditions_come_from_the_declarations():
    names = [c.name for c in robustness.CONDITIONS]
    declared = [lv.name for p in perturbations() for lv in p.levels]
    assert sorted(names) == sorted(["nominal", *declared])
    # version 1 lacks the levels version 2 added (the lift tracker's)
    added = {lv.name for p in perturbations() for lv in p.levels if lv.since == 2}
    assert added and [c.name for c in robustness.CONDITIONS_V1] == [n for n in names if n not in added]


@pytest.mark.parametrize("field, level, trained, inside", [
    ("latency_steps", (1, 1), (0, 1), True), ("latency_steps", (2, 2), (0, 1), False),
    ("slip_sensing", "binary", "exact", False), ("pinch_ceiling_N", 3.0, None, False),
    ("pinch_ceiling_N", 3.0, 2.5, True), ("sensor_noise_N", 0.05, 0.08, True), ("force_bias_N", 0.1, 0.05, False),
])
def test_each_field_says_by_its_declaration_whether_a_level_lies_inside_a_trained_range(field, level, trained,
                                                                                          inside):
    from msdgrasp.envs.perturbations import rule_of

    assert rule_of(field)(level, trained) is inside


def test_a_clashing_declaration_is_refused():
    from msdgrasp.envs.perturbations import register_perturbation

    with pytest.raises(ValueError, match="already declared"):
        register_perturbation(dataclasses.replace(TOY, name="latency"))
    with pytest.raises(ValueError, match="column.*mu"):
        register_perturbation(dataclasses.replace(TOY, columns=(Column("mu"),)))
    with pytest.raises(ValueError, match="axis"):
        register_perturbation(dataclasses.replace(TOY, axis="weather"))
