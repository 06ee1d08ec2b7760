"""``msdgrasp evaluate --suite robustness``: the versioned protocol, its files and its leaderboard (a two-condition
stand-in suite and a stubbed minimal-force bisection keep it short; the conditions themselves are the task's axes,
tests/test_robustness_axes.py)."""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest

from msdgrasp.agents import evaluation_jobs, robustness
from msdgrasp.agents.protocol import EVALUATION_SEED, SEALED_SEEDS
from msdgrasp.agents.reference import reference_force_N
from msdgrasp.agents.robustness import (CONDITIONS, CONDITIONS_V1, EPISODES, MUS, POOLED_EPISODES, PROTOCOLS,
                                        SUITE_VERSION, Condition, condition_config)
from msdgrasp.agents.stats import episodes_for_lower_bound, wilson_lower_bound
from msdgrasp.agents.training import TrainConfig
from msdgrasp.cli.main import main


def row_of(data, spec, condition):
    [res] = [r for r in data["results"] if r["spec"] == spec]
    [cell] = [c for c in res["cells"] if c["condition"] == condition]
    return cell


def _run_main(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def test_the_protocol_covers_every_axis_at_the_levels_it_names():
    axes = {c.axis for c in CONDITIONS}
    assert axes == {"nominal", "sensing", "actuation", "placement", "friction", "tissue"}
    names = [c.name for c in CONDITIONS]
    assert len(set(names)) == len(names) and SUITE_VERSION == 2
    # the levels the protocol promises: force noise up to 0.1 N, latency up to 3 steps, placement up to 5 mm / 10 deg
    assert max(c.randomization.get("sensor_noise_N", 0) for c in CONDITIONS) == 0.1
    assert max(c.randomization.get("latency_steps", (0, 0))[1] for c in CONDITIONS) == 3
    assert max(c.randomization.get("pose_offset_m", 0) for c in CONDITIONS) == 0.005
    assert {m for c in CONDITIONS if c.axis == "friction" for m in c.mus} == {0.1, 0.15, 1.2, 1.5}
    base = TrainConfig().env
    for c in CONDITIONS:  # every condition is a valid task: one change from the base
        cfg = condition_config(base, c)
        changed = {k for k, v in vars(cfg.randomization).items() if v != getattr(base.randomization, k)}
        assert changed == set(c.randomization), c.name


def test_version_2_pools_enough_episodes_per_condition_for_a_95_percent_lower_bound():
    """Version 2: mu 0.2 joins the in-range grid; every condition, those at one mu too, pools at least the fewest
    episodes whose all-success Wilson 95 % lower bound reaches 0.95 (73), and no fewer per mu than the grid gives."""
    assert MUS == (0.2, 0.3, 0.5, 0.8) and EPISODES * len(MUS) == POOLED_EPISODES == 76
    need = episodes_for_lower_bound(0.95)
    assert need == 73 and wilson_lower_bound(need, need) >= 0.95 > wilson_lower_bound(need - 1, need - 1)
    v2 = PROTOCOLS["robustness", 2]
    assert v2.conditions == CONDITIONS and v2.version == SUITE_VERSION
    for c in CONDITIONS:
        assert v2.pooled_episodes(c) >= need and v2.episodes_per_mu(c) >= EPISODES, c.name
        assert c.axis == "friction" or c.mus == MUS
    assert v2.episodes_per_mu(Condition("friction", "mu 0.1", mus=(0.1,))) == 76
    assert v2.pooled_episodes(CONDITIONS[0], 2) == 8  # (fewer episodes: not the protocol, but still pooled)
    # version 1 stays defined as it ran: 0.3, 0.5, 0.8 x 10 per mu, a friction condition 10
    v1 = PROTOCOLS["robustness", 1]
    assert v1.mus == (0.3, 0.5, 0.8) and v1.episodes == 10 and v1.conditions == CONDITIONS_V1
    # version 2 adds the lift tracker's conditions (the v2 task reads the lift from it); the rest are version 1's
    lift = {"lift tracker noise 1 mm", "lift tracker 3 frames late", "lift not tracked"}
    assert [c.name for c in CONDITIONS_V1] == [c.name for c in CONDITIONS if c.name not in lift]
    assert lift <= {c.name for c in CONDITIONS}
    assert {c.name: v1.pooled_episodes(c) for c in CONDITIONS_V1 if c.axis == "friction"} == {
        "mu 0.1": 10, "mu 0.15": 10, "mu 1.2": 10, "mu 1.5": 10}
    assert {v1.pooled_episodes(c) for c in CONDITIONS_V1 if c.axis != "friction"} == {30}


def test_a_condition_is_inside_the_training_ranges_where_every_level_it_sets_was_trained():
    from pathlib import Path

    robust = TrainConfig.load(Path(__file__).parents[1] / "configs/train/experiments/R-robust.yaml")
    inside = {c.name for c in CONDITIONS if robustness.inside_ranges(c, robust.training_task().randomization)}
    assert inside == {"nominal", "force noise 0.05 N", "force noise 0.08 N", "force bias up to 0.05 N",
                      "latency 1 step", "force-loop gain error up to 20%",
                      "grasp up to 3 mm off, 5 deg tilt, 5 deg turn", "grasp up to 5 mm off, 10 deg tilt, 10 deg turn"}
    nominal = TrainConfig().training_task().randomization  # (1 mm / 1 deg / 1.5 deg of pose jitter, no other axis)
    assert {c.name for c in CONDITIONS if robustness.inside_ranges(c, nominal)} == {"nominal"}


def test_the_suite_writes_its_leaderboard_with_the_baselines_and_refuses_the_grid_options(tmp_path, monkeypatch):
    stand_in = (Condition("nominal", "nominal", mus=(0.5,)),
                Condition("actuation", "latency 3 steps", {"latency_steps": (3, 3)}, mus=(0.5,)))
    monkeypatch.setitem(robustness.SUITES, "robustness", stand_in)
    monkeypatch.setattr(evaluation_jobs, "minimal_force_job", lambda cfg, mu: 1.25)  # (the bisection: minutes)
    from msdgrasp.agents import controllers

    monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)  # (the oracle's own bisection)
    rc, out, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--episodes", "1",
                              "--out", str(tmp_path), "--quiet"])
    assert rc == 0, err
    data = json.loads((tmp_path / "suite_robustness.json").read_text())
    assert data["version"] == SUITE_VERSION and data["episodes"] == 1 and data["damage_pressure_kPa"] == 330.0
    # one episode per mu of the grid's four: a condition at one mu pools four; fewer than the protocol's 19
    assert data["protocol"] is False and data["protocol_episodes"] == EPISODES
    assert [c["pooled_episodes"] for c in data["conditions"]] == [len(MUS)] * 2
    # the sealed evaluation seeds by default, recorded as such
    assert data["seeds"] == {"first": EVALUATION_SEED, "count": len(MUS), "sealed": True}
    assert data["seed"] == EVALUATION_SEED == SEALED_SEEDS.start
    # (the slip-feedback controller too: the default training's task has its interface)
    assert {r["spec"] for r in data["leaderboard"]} == {"fixed", "reactive", "oracle", "slipfeedback"}
    scores = [r["score"] for r in data["leaderboard"]]
    assert scores == sorted(scores, reverse=True)
    for res in data["results"]:
        for cell in res["cells"]:
            [row] = cell["rows"]
            assert cell["success_rate"] == row["success_rate"] and row["mu"] == 0.5
            assert row["episodes"] == cell["episodes"] == 4
            # the Wilson interval and its lower bound over the pooled episodes
            wins = sum(row["per_episode"]["success"])
            assert cell["successes"] == wins and cell["success_lower_bound"] == wilson_lower_bound(wins, 4)
            lo, hi = cell["success_ci95"]
            assert lo == cell["success_lower_bound"] <= cell["success_rate"] <= hi
            # the force ratio reads against the shipped reference table of the task (a slower pull cannot lower it)
            assert data["reference"]["kind"] == "reference"
            assert math.isclose(cell["force_ratio"], row["mean_peak_pinch_N"] / data["reference_force_N"]["0.5"])
            assert math.isclose(data["reference_force_N"]["0.5"], reference_force_N(TrainConfig().env, 0.5))
            lifted = [t for t in row["per_episode"]["time_to_lift_s"] if t is not None and math.isfinite(t)]
            if lifted:
                assert math.isclose(cell["mean_time_to_lift_s"], np.mean(lifted))
            else:
                assert cell["mean_time_to_lift_s"] is None
            assert cell["mean_time_above_damage_s"] >= 0.0 and cell["max_peak_pressure_kPa"] >= 0.0
    assert data["inside_training_ranges"] == [True, False]  # (the default training: nominal, no latency)
    for row in data["leaderboard"]:
        assert row["in_range_worst_success_rate"] == row_of(data, row["spec"], "nominal")["success_rate"]
        # the score's bootstrap interval brackets it; the lowest lower bound is the worst condition's
        lo, hi = row["score_ci95"]
        assert 0.0 <= lo <= row["score"] <= hi <= 1.0
        res = [r for r in data["results"] if r["spec"] == row["spec"]][0]
        assert row["worst_lower_bound"] == min(c["success_lower_bound"] for c in res["cells"])
    board = (tmp_path / "leaderboard_robustness.md").read_text()
    assert "| rank | policy | score |" in board and "latency 3 steps" in board and board in out
    assert "| nominal * | 4 |" in board and "| latency 3 steps | 4 |" in board
    assert "mean time to lift" in board
    assert "**Not the protocol**: 1 episodes per mu where the protocol runs 19" in board
    assert "not sealed" not in board.lower()
    oracle = row_of(data, "oracle", "nominal")
    assert f"{oracle['success_rate']:.2f} [{oracle['success_ci95'][0]:.2f}, {oracle['success_ci95'][1]:.2f}]" in board
    # a version 1 result (no intervals, no seeds record, no time to lift) still reads
    old = json.loads(json.dumps(data))
    old.update(version=1, seed=0)
    for key in ("protocol", "protocol_episodes", "mu_grid", "seeds"):
        old.pop(key)
    for cond in old["conditions"]:
        del cond["episodes_per_mu"], cond["pooled_episodes"]
    for res in old["results"]:
        for cell in res["cells"]:
            for key in ("success_ci95", "success_lower_bound", "successes", "episodes", "mean_time_to_lift_s"):
                del cell[key]
    for row in old["leaderboard"]:
        for key in ("worst_lower_bound", "in_range_worst_lower_bound", "mean_time_to_lift_s"):
            del row[key]
    v1 = robustness.leaderboard_markdown(old)
    assert v1.startswith("# Robustness suite `robustness` v1") and "mu 0.3, 0.5, 0.8" in v1 and "seeds 0..0" in v1
    assert "**Seeds not sealed**" in v1 and f"| nominal * | 1 | {oracle['success_rate']:.2f} / " in v1
    rc, _, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--mu-grid", "0.5",
                            "--out", str(tmp_path / "x")])
    assert rc == 2 and "the suite fixes its conditions, mu and batches; drop --mu-grid" in err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("suite", ["robust", "nominal"])
def test_an_unknown_suite_is_refused(suite, capsys):
    assert main(["evaluate", "--suite", suite, "--policy", "fixed"]) == 2
    assert "invalid choice" in capsys.readouterr().err


def test_the_hindsight_oracle_finds_each_episodes_own_minimal_force():
    """An episode's minimal fixed force: the fixed-force controller holds that very episode (its seed, its grasp
    placed up to 5 mm off) at it and not one tolerance below."""
    from msdgrasp.agents.controllers import _fixed_force_success, episode_minimal_forces
    from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv

    config = TrainConfig().env
    off = {"pose_offset_m": 0.005}
    [f] = episode_minimal_forces(config, [0.5], [3], off, tolerance_N=0.1)
    env = GraspLiftVectorEnv(2, config)
    held = _fixed_force_success(env, np.array([f, f - 0.1]), 0.5, seed=[3, 3], options={"mu": [0.5, 0.5], **off})
    assert held.tolist() == [True, False]


def test_a_fixed_grip_holds_the_share_of_episodes_whose_own_minimal_force_it_reaches():
    """Of 20 episodes needing 1..20 N, a grip of 19 N holds 19 (95 %) and 18 N only 18; an episode no fixed force
    holds counts as needing more than any, and where more than 5 % are such, no fixed grip holds 95 %."""
    from msdgrasp.agents.robustness import fixed_grip_force

    needs = [float(k) for k in range(20, 0, -1)]
    assert fixed_grip_force(needs) == 19.0
    assert fixed_grip_force(needs, share=0.5) == 10.0 and fixed_grip_force(needs, share=1.0) == 20.0
    assert fixed_grip_force(needs[1:] + [None]) == 19.0  # 1..19 N and one unheld: 19 N holds 19 of 20
    assert math.isnan(fixed_grip_force(needs[2:] + [None, None]))
    assert fixed_grip_force([None] * 3 + [0.5] * 57) == 0.5  # 57 of 60 is 95 %
    with pytest.raises(ValueError, match="share"):
        fixed_grip_force(needs, share=0.0)


def test_the_reward_prefers_the_fixed_grip_where_its_charge_meets_the_failures_it_avoids():
    """Episodes needing 1..20 N, success +50, failure -10, c points per N: the expected return of a grip of k N is
    (60 k - c k^2) / 20 - 10, best at k = 30 / c; a cap on the charge makes the grip that holds every episode best,
    a gentler slope beyond a knee a grip between."""
    from msdgrasp.agents.robustness import fixed_grip_return, reward_fixed_grip, reward_fixed_grip_table
    from msdgrasp.envs.core import RewardConfig

    needs = [float(k) for k in range(20, 0, -1)] + [None]  # and one episode no fixed force holds
    plain = RewardConfig(peak_force=10.0)  # 2 points per N of a 5 N reference
    grip, held, ret = reward_fixed_grip(needs[:-1], 0.5, plain, 5.0)
    assert (grip, held, ret) == (15.0, 0.75, pytest.approx(12.5))
    scaled = RewardConfig(peak_force=10.0, peak_force_mu_ref=0.4)  # at mu 0.6: 3 points per N
    assert reward_fixed_grip(needs[:-1], 0.6, scaled, 5.0)[:2] == (10.0, 0.5)
    capped = RewardConfig(peak_force=10.0, peak_force_knee=20.0, peak_force_beyond_knee=0.0)  # 2 per N up to 10 N
    assert reward_fixed_grip(needs[:-1], 0.5, capped, 5.0) == (20.0, 1.0, pytest.approx(30.0))
    held, ret = fixed_grip_return(needs, 20.0, 0.5, capped, 5.0)  # the unheld episode fails at any grip
    assert held == pytest.approx(20 / 21) and ret == pytest.approx(20 / 21 * 30.0 - 10 / 21)
    assert reward_fixed_grip([None, None], 0.5, plain, 5.0) == (0.0, 0.0, -10.0)
    # 4 points per N up to 5 N (20 points), 2 per N beyond: above 5 N the return is (50 k - 2 k^2) / 20 - 10, best at
    # 12.5 N (12 and 13 tie), where 4 points per N throughout would be best at 7.5 N
    kneed = RewardConfig(peak_force=20.0, peak_force_knee=20.0, peak_force_beyond_knee=0.5)
    grip, held, ret = reward_fixed_grip(needs[:-1], 0.5, kneed, 5.0)
    assert grip in (12.0, 13.0) and ret == pytest.approx(5.6)
    assert fixed_grip_return(needs, 10.0, 0.5, kneed, 5.0)[1] == pytest.approx(10 / 21 * 20.0 - 11 / 21 * 10.0)
    # the table over a suite result's hindsight cells, the oracle's minimal force 10 N at mu 0.5: 15 N is 1.5x
    suite = {"oracle_minimal_force_N": {"0.5": 10.0}, "conditions": [{"name": "nominal"}, {"name": "latency"}],
             "hindsight": [{"episode_minimal_force_N": {"0.5": needs[:-1]}}, None]}
    table = reward_fixed_grip_table(suite, plain, 5.0)
    assert table.splitlines()[2] == "| nominal | 0.5 | 1.50 | 0.75 | 12.5 | 12.5 |" and len(table.splitlines()) == 3


def test_the_suite_reports_the_hindsight_oracle_where_the_placement_changes(tmp_path, monkeypatch):
    stand_in = (Condition("nominal", "nominal", mus=(0.5,)),
                Condition("actuation", "latency 3 steps", {"latency_steps": (3, 3)}, mus=(0.5,)))
    monkeypatch.setitem(robustness.SUITES, "robustness", stand_in)
    monkeypatch.setattr(evaluation_jobs, "minimal_force_job", lambda cfg, mu: 1.25)
    monkeypatch.setattr(robustness, "_hindsight_job", lambda cfg, mus, n, seed, opts: {"0.5": [1.5, None]})
    from msdgrasp.agents import controllers

    monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)
    rc, out, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--episodes", "1",
                              "--hindsight", "--out", str(tmp_path), "--quiet"])
    assert rc == 0, err
    data = json.loads((tmp_path / "suite_robustness.json").read_text())
    nominal, latency = data["hindsight"]
    assert latency is None  # (latency changes no placement)
    assert nominal["held_rate"] == 0.5 and math.isclose(nominal["force_ratio"], 1.5 / 1.25)
    board = (tmp_path / "leaderboard_robustness.md").read_text()
    # one episode of two held: no fixed grip holds 95 % of them
    assert nominal["fixed_grip_ratio"] is None  # (NaN, written as null)
    assert "| hindsight |" in board and "| 0.50 / 1.20 / - |" in board
    rc, _, err = _run_main(["evaluate", "--policy", "fixed", "--hindsight", "--out", str(tmp_path / "y")])
    assert rc == 2 and "--hindsight needs --suite" in err


def test_a_subset_of_the_conditions_runs_alone_and_says_so(tmp_path, monkeypatch):
    """--condition picks conditions by axis or by name; the result and its leaderboard say it is a subset, and a
    name the suite does not have is refused (exit 2) before anything is written."""
    stand_in = (Condition("nominal", "nominal", mus=(0.5,)),
                Condition("actuation", "latency 3 steps", {"latency_steps": (3, 3)}, mus=(0.5,)),
                Condition("actuation", "pinch ceiling 3 N", {"pinch_ceiling_N": 3.0}, mus=(0.5,)))
    monkeypatch.setitem(robustness.SUITES, "robustness", stand_in)
    assert [c.name for c in robustness.select_conditions("robustness", ["actuation"])] == [
        "latency 3 steps", "pinch ceiling 3 N"]
    assert [c.name for c in robustness.select_conditions("robustness", ["pinch ceiling 3 N", "nominal"])] == [
        "nominal", "pinch ceiling 3 N"]  # (the protocol's order)
    monkeypatch.setattr(evaluation_jobs, "minimal_force_job", lambda cfg, mu: 1.25)
    from msdgrasp.agents import controllers

    monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)
    rc, out, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--episodes", "1",
                              "--condition", "latency 3 steps", "--out", str(tmp_path), "--quiet"])
    assert rc == 0, err
    data = json.loads((tmp_path / "suite_robustness.json").read_text())
    assert data["subset"] is True and [c["name"] for c in data["conditions"]] == ["latency 3 steps"]
    assert all(len(r["cells"]) == 1 for r in data["results"])
    assert "a subset of the protocol: 1 of 3 conditions" in (tmp_path / "leaderboard_robustness.md").read_text()
    rc, _, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--condition", "latency",
                            "--out", str(tmp_path / "x")])
    assert rc == 2 and "condition 'latency' is not in suite 'robustness'" in err and "actuation" in err
    assert not (tmp_path / "x").exists()
    rc, _, err = _run_main(["evaluate", "--policy", "fixed", "--condition", "nominal", "--out", str(tmp_path / "y")])
    assert rc == 2 and "--condition needs --suite" in err


def test_a_run_with_the_protocols_episodes_is_the_protocol_and_a_seed_outside_the_sealed_range_says_so(
        tmp_path, monkeypatch):
    """Without --episodes the suite runs its protocol's episodes ("protocol": true); --seed 0 runs, but its result
    records unsealed seeds and its leaderboard says so. (A one-condition protocol of one episode keeps it short.)"""
    stand_in = (Condition("nominal", "nominal", mus=(0.5,)),)
    monkeypatch.setitem(robustness.SUITES, "robustness", stand_in)
    monkeypatch.setitem(robustness.PROTOCOLS, ("robustness", SUITE_VERSION),
                        robustness.SuiteProtocol(SUITE_VERSION, (0.5,), 1, stand_in, pooled=True))
    monkeypatch.setattr(evaluation_jobs, "minimal_force_job", lambda cfg, mu: 1.25)
    from msdgrasp.agents import controllers

    monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)
    rc, _, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--seed", "0",
                            "--out", str(tmp_path), "--quiet"])
    assert rc == 0, err
    data = json.loads((tmp_path / "suite_robustness.json").read_text())
    assert data["protocol"] is True and data["episodes"] == 1
    assert data["seeds"] == {"first": 0, "count": 1, "sealed": False}
    board = (tmp_path / "leaderboard_robustness.md").read_text()
    assert "**Seeds not sealed**" in board and "Not the protocol" not in board
    rc, _, err = _run_main(["evaluate", "--suite", "robustness", "--policy", "fixed", "--seed", "-1",
                            "--out", str(tmp_path / "x")])
    assert rc == 2 and "--seed: must be an integer >= 0" in err and not (tmp_path / "x").exists()
