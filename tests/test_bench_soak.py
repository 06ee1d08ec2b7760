"""Smoke tests of ``msdgrasp bench`` and the soak test (benchmarks/bench.py, benchmarks/soak.py).

Speed targets are *not* asserted (machines are noisy); the bench must produce valid JSON with the
documented keys and positive numbers, the NumPy reference must agree with the numba kernel, and a short
soak must see episodes, no silent NaN and no exception. The whole file runs in well under a minute.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from msdgrasp.benchmarks import bench, soak
from msdgrasp.physics import reference
from msdgrasp.cli.main import main
from msdgrasp.physics.config import ConfigError, replace
from msdgrasp.physics.mesh_gen import spleen_mesh
from msdgrasp.physics.simulation import Simulation
from msdgrasp.physics.tissue import TissueModel


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.fixture(scope="module")
def bench_quick(tmp_path_factory):
    """`msdgrasp bench physics --quick --out DIR/bench.json`: (printed JSON, output folder)."""
    import contextlib
    import io

    out = tmp_path_factory.mktemp("bench") / "bench.json"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["bench", "physics", "--quick", "--out", str(out)])
    assert rc == 0
    return json.loads(buf.getvalue()), out


def test_bench_physics_quick_json(bench_quick):
    report, _ = bench_quick
    assert report["what"] == "physics" and report["quick"] is True
    ph = report["physics"]
    for key in ("no_contact", "contact", "scaling", "numpy_reference", "mujoco"):
        assert key in ph
    assert [r["resolution"] for r in ph["no_contact"]] == ["coarse", "medium", "fine"]
    nodes = [r["nodes"] for r in ph["no_contact"]]
    assert nodes == sorted(nodes)
    for r in ph["no_contact"]:
        for key in ("nodes", "springs", "n_sub", "single_us_per_ms", "single_cpu_us_per_ms", "single_realtime_factor",
                    f"batch{bench.BATCH}_total_us_per_ms", f"batch{bench.BATCH}_per_tissue_us_per_ms",
                    "single_ns_per_spring_substep", f"batch{bench.BATCH}_ns_per_spring_substep"):
            assert _positive(r[key]), (r["resolution"], key, r[key])
        assert r["finite"] is True
    for r in ph["contact"]:
        for key in ("n_sub", "contact_nodes", "single_us_per_ms", f"batch{bench.BATCH}_total_us_per_ms",
                    f"batch{bench.BATCH}_per_tissue_us_per_ms"):
            assert _positive(r[key]), (r["resolution"], key, r[key])
        assert isinstance(r["overhead_single"], float)
        assert r["finite"] is True
    # the float32 option on the coarse spleen: timed, and its error against float64 stated (test_float32.py bounds it)
    f32 = {r["resolution"]: r["float32"] for r in ph["contact"]}
    assert f32["medium"] is None and f32["fine"] is None
    for key in ("single_us_per_ms", f"batch{bench.BATCH}_per_tissue_us_per_ms", "max_position_error_m"):
        assert _positive(f32["coarse"][key]), (key, f32["coarse"])
    assert 0.0 <= f32["coarse"]["pinch_rel_error"] < 1.0 and 0.0 < f32["coarse"]["same_contact_state"] <= 1.0
    assert _positive(ph["scaling"]["exponent_us_per_ms_vs_nodes"])
    nr = ph["numpy_reference"]
    assert nr["cross_check"]["max_rel_diff_forces"] < 1e-10
    assert [r["resolution"] for r in nr["rows"]] == ["coarse", "medium"]
    for r in nr["rows"]:
        assert _positive(r["numpy_us_per_ms"]) and _positive(r["ratio_ours_over_numpy"])
    mj = ph["mujoco"]
    assert isinstance(mj["available"], bool)
    if mj["available"]:
        assert all(_positive(r["mujoco_us_per_ms"]) for r in mj["rows"] if "error" not in r)
    else:
        assert mj["reason"]
    # pass/fail flags for the physics targets of benchmarks/report.py: TARGETS (values not asserted: noisy machines)
    for key in ("coarse_physics_le_10us_per_ms", "fine_physics_le_200us_per_ms", "coarse_contact_overhead_le_50pct",
                "coarse_contact_ge_100x_realtime", f"coarse_contact_ge_100x_realtime_batch{bench.BATCH}"):
        assert isinstance(report["targets"][key]["pass"], bool)
        assert "value" in report["targets"][key]
    assert isinstance(report["all_targets_pass"], bool)
    assert "env" not in report


def test_bench_writes_files(bench_quick):
    report, out = bench_quick
    assert json.loads(out.read_text()) == {k: v for k, v in report.items()}
    md = out.with_suffix(".md").read_text()
    assert "| coarse |" in md and "Targets" in md
    png = out.with_name("bench_scaling.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert report["files"]["png"] == str(png)
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # no temp files left


@pytest.mark.parametrize("variant", ["spleen_sls", "dashpot_compliant_anchors"])
def test_numpy_reference_matches_numba(variant):
    if variant == "spleen_sls":
        res = reference.cross_check("coarse", seed=3)
    else:
        mesh = spleen_mesh("coarse")
        params = replace(reference.spleen_params(), relaxation_strength=0.0, spring_damping_time_s=0.002,
                         damping_disp_rate_per_m_s=500.0)
        model = TissueModel.from_params(mesh, params, fixed_nodes=mesh.node_sets["hilum"], anchor_stiffness_n_per_m=8.0)
        res = reference.cross_check(model=model, seed=4)
    assert res["springs_beyond_dl_c_fraction"] > 0.05  # both branches of the spring law are exercised
    assert res["max_rel_diff_forces"] < 1e-10
    assert res["max_rel_diff_maxwell_forces"] < 1e-10
    assert res["max_rel_diff_displacement"] < 1e-8


def test_numpy_spring_law_matches_kernel():
    from msdgrasp.physics.forces import spring_force_array

    dl = np.linspace(-0.01, 0.01, 2001)
    k1, k2, dlc = 50.0, 5e5, 2e-3
    ref = reference.numpy_spring_law(dl, np.full_like(dl, k1), np.full_like(dl, k2), np.full_like(dl, dlc))
    np.testing.assert_allclose(ref, spring_force_array(dl, k1, k2, dlc), rtol=1e-13, atol=1e-15)


def test_time_per_unit_runs_long_enough():
    calls = []
    t = bench.time_per_unit(lambda n: calls.append(n) or sum(range(200 * n)), 0.03, repeats=2)
    assert t["seconds"] >= 0.03 and t["units"] > 0 and t["median_s"] > 0 and t["best_s"] <= t["median_s"]


def test_bench_rejects_bad_what():
    with pytest.raises(ConfigError):
        bench.run_bench("nonsense")


# ------------------------------------------------------------------------------------------------
# soak
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def soak_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("soak")
    args = argparse.Namespace(steps=3000, n_envs=8, seed=1, out=out, quiet=True)
    rc = soak.soak_cli(args)
    return rc, json.loads((out / "report.json").read_text())


@pytest.mark.parametrize("argv, match", [(["msdgrasp", "--rounds", "3"], "--rounds must be >= 4 (quartiles), got 3"),
                                         (["msdgrasp,no_such_build"], "'no_such_build' cannot be imported"),
                                         (["msdgrasp", "--env", "--sphere"], "--env and --sphere: give one of them"),
                                         (["msdgrasp", "--cpu", "100000"], "--cpu must be one of the CPUs"),
                                         (["msdgrasp", "--batch-ms", "0"], "--batch-ms must be >= 1")])
def test_interleaved_ab_refuses_bad_input_before_timing(argv, match, capsys):
    from msdgrasp.benchmarks.interleaved import main

    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert match in capsys.readouterr().err


def test_short_soak_is_clean(soak_run):
    rc, rep = soak_run
    assert rc == 0 and rep["ok"] is True
    assert rep["steps"] == 3000 and rep["n_envs"] == 8
    assert rep["episodes"] > 0
    assert rep["silent_nan"] == 0
    assert rep["exceptions"] == 0 and rep["first_traceback"] is None
    assert rep["blowups_unflagged"] == 0
    assert rep["memory"]["peak_rss_mb"] > 0 and isinstance(rep["memory"]["growth_after_warmup"], float)
    rnd = rep["randomization"]
    assert rnd["fraction_mu_outside_training"] > 0 and rnd["fraction_stiffness_outside_training"] > 0
    assert rnd["mu_seen"][0] >= 0.0 and rnd["stiffness_seen"][1] <= soak.STIFFNESS_RANGE[1]


class _Faulty:
    """A vector env that misbehaves at vector step ``at``: NaN observation, NaN reward, an exception, or a
    physics blow-up (which the env reports properly, so the soak stays clean)."""

    def __init__(self, env, fault: str, at: int = 3):
        self.env, self.fault, self.at, self.k = env, fault, at, 0

    def __getattr__(self, name):
        return getattr(self.env, name)

    def step(self, actions):
        self.k += 1
        if self.k == self.at and self.fault == "blowup":
            self.env.core.sim.x[1, 0, 0] = np.nan  # a genuine blow-up: the env must flag it, not leak it
        obs, rew, term, trunc, info = self.env.step(actions)
        if self.k == self.at:
            if self.fault == "raise":
                raise RuntimeError("injected failure")
            if self.fault == "nan_obs":
                obs = obs.copy()
                obs[1, 2] = np.nan
            if self.fault == "nan_reward":
                rew = rew.copy()
                rew[0] = np.inf
        return obs, rew, term, trunc, info


@pytest.mark.parametrize("fault", ["raise", "nan_obs", "nan_reward"])
def test_soak_exit_code_on_faults(fault, tmp_path, monkeypatch, capsys):
    real = soak.make_env
    monkeypatch.setattr(soak, "make_env", lambda n: _Faulty(real(n), fault))
    rc = soak.soak_cli(argparse.Namespace(steps=40, n_envs=4, seed=0, out=tmp_path, quiet=True))
    rep = json.loads(capsys.readouterr().out)
    assert rc == 1 and rep["ok"] is False
    assert rep == json.loads((tmp_path / "report.json").read_text())
    if fault == "raise":
        assert rep["exceptions"] == 1 and "injected failure" in rep["first_traceback"]
        assert rep["silent_nan"] == 0
    else:
        assert rep["silent_nan"] == 1 and rep["exceptions"] == 0
        assert rep["first_silent_nan"]["vector_step"] == 2


def test_soak_counts_a_flagged_blowup_as_clean(tmp_path, monkeypatch, capsys):
    real = soak.make_env
    monkeypatch.setattr(soak, "make_env", lambda n: _Faulty(real(n), "blowup"))
    rc = soak.soak_cli(argparse.Namespace(steps=40, n_envs=4, seed=0, out=tmp_path, quiet=True))
    rep = json.loads(capsys.readouterr().out)
    assert rep["blowups"] == 1 and rep["outcomes"]["numerical_failure"] == 1
    assert rep["blowups_unflagged"] == 0 and rep["silent_nan"] == 0 and rep["exceptions"] == 0
    assert rc == 0 and rep["ok"] is True


def test_soak_clean_exit_zero_and_validation(tmp_path, capsys):
    assert soak.soak_cli(argparse.Namespace(steps="1e2", n_envs=4, seed=None, out=tmp_path, quiet=True)) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == 100
    for bad in ({"steps": 0}, {"steps": "abc"}, {"steps": 1.5}, {"n_envs": 0}):
        kw = {"steps": 10, "n_envs": 2, "seed": 0, "out": tmp_path, "quiet": True, **bad}
        with pytest.raises(ConfigError):
            soak.soak_cli(argparse.Namespace(**kw))


def test_profile_substep_parts_add_up(tmp_path, monkeypatch, capsys):
    """`msdgrasp bench profile --quick`'s per-substep part: the parts switched off in turn add up to the whole call,
    the whole call takes time, the switches leave the kernel's types alone (no recompilation: a signature of
    ``simulate`` that the grasp's own steps in float64 and float32 do not use would be one); the command writes its
    JSON and table (the agent-step and training parts are stubbed here: they need SB3 and take longer). A part's
    time is a difference of two timings: on a shared machine its sign is noise where the part is small (the Maxwell
    branch of one tissue is about 0.2 us of 8), so that each switch takes its part away is asserted on the kernel's
    results (below), not on the clock."""
    from msdgrasp.benchmarks import profile
    from msdgrasp.benchmarks.harness import grasped
    from msdgrasp.physics.integrator import simulate

    scene, _ = grasped("coarse", 0.05, 0.05)
    Simulation(scene.model, 1, dt=reference.DT_OUTER, grasper=scene.grasper, precision="float32").step(1)
    before = set(simulate.signatures)
    sub = profile.profile_substeps(quick=True)
    assert set(simulate.signatures) == before
    assert [r["tissues"] for r in sub["rows"]] == [1, profile.PROFILE_BATCH]
    for row in sub["rows"]:
        phases = row["phases_us_per_substep"]
        assert set(phases) == set(profile.PHASES)
        assert all(math.isfinite(phases[name]) for name in profile.PHASES), (row["layout"], phases)
        assert row["contact_nodes"] > 0  # the jaws hold the tissue while the kernel is timed
        assert _positive(row["whole_us_per_substep"])
        assert math.isclose(sum(phases.values()), row["whole_us_per_substep"], rel_tol=0.01), row
        # the Maxwell branch is timed within the springs' step; the float32 springs like the float64 ones
        assert set(row["springs_within_us"]) == {"maxwell_branch"}, row  # (dashpots are off in the spleen's config)
        assert math.isfinite(row["springs_within_us"]["maxwell_branch"]), row
        assert math.isfinite(row["springs_float32"]["us_per_substep"]), row
        assert math.isfinite(row["barrier_full_flag_pass_us"]), row
        # the divider's floor is timed on its own (no difference): it takes time
        floor = row["springs_sqrt_div_us"]
        assert _positive(floor["float64"]) and _positive(floor["float32"]), floor
    monkeypatch.setattr(profile, "profile_substeps", lambda quick, progress: sub)
    monkeypatch.setattr(profile, "profile_agent_step", lambda quick, progress: {
        "rows": [], "policy_inference": {"policy": "p", "net_arch": [64, 64], "obs_dim": 1, "torch_threads": 1,
                                         "predict_batch1_ms": 1.0, "forward_batch1_ms": 1.0,
                                         f"predict_batch{profile.PROFILE_BATCH}_ms": 1.0,
                                         f"forward_batch{profile.PROFILE_BATCH}_ms": 1.0}})
    parts = {"rollout": 1.0, "update": 1.0, "validation": 1.0}
    monkeypatch.setattr(profile, "profile_training", lambda quick, progress: {
        "agent_steps": 1, "n_envs": 1, "n_epochs": 1, "seconds": {"rollout": 1.0, "update": 1.0, "one_validation": 1.0},
        "extrapolated_default_run": {"total_timesteps": 1, "hours": parts, "share": parts}})
    out = tmp_path / "profile.json"
    assert main(["bench", "profile", "--quick", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert json.loads(out.read_text())["substep"] == printed["substep"] == json.loads(json.dumps(sub))
    assert "springs" in out.with_suffix(".md").read_text()


def test_profile_switches_turn_parts_of_the_kernel_off():
    """The profile's switches act on the real kernel: with the contacts off the jaws hold no node, and the call
    restored from the saved state is the same call each time; the tets' volume ratios are the kernel's."""
    from msdgrasp.benchmarks import profile
    from msdgrasp.benchmarks.harness import grasped

    _, sim = grasped("coarse", 0.5, 1.0)
    ratios = profile.volume_ratios(sim.x, sim.model.tets, sim.model.rest_volume)
    np.testing.assert_allclose(ratios.min(axis=1), sim.min_volume_ratio(), rtol=1e-12)
    calls = profile.Restored(sim)
    calls.run()(1)
    held, x = int(np.count_nonzero(sim.held > 0)), sim.x.copy()
    calls.run()(1)
    assert held > 0 and np.array_equal(sim.x, x)
    calls.run("contacts")(1)
    assert np.count_nonzero(sim.held > 0) == 0 and not np.array_equal(sim.x, x)
    # each part the profile times does work in this state: switched off, the kernel's result changes
    for part in ("springs", "maxwell_branch"):
        calls.run(part)(1)
        assert not np.array_equal(sim.x, x), part
    # the barrier acts only on tets below its volume threshold, the watch list only spares the check of the others
    below = int((ratios < calls.model.vol_threshold).sum())
    for part in ("watch_list",) + (("barrier",) if below == 0 else ()):
        calls.run(part)(1)
        assert np.array_equal(sim.x, x), part
    calls.run("barrier", "contacts", "springs")(1)  # a model without springs: its spring state is left alone
    assert sim.fv.shape == x.shape[:1] + (len(sim.model.edges),)
