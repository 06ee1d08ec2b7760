"""The leaderboard groups a suite result's policies into tracks and aggregates them as rliable does.

A synthetic suite result (two conditions, two mu, 40 episodes each) with known outcomes: the numbers a track gets are
those counted by hand, and the comparisons go the way the outcomes say.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from msdgrasp.agents.leaderboard import build_leaderboard, leaderboard_markdown, parse_track, write_leaderboard
from msdgrasp.agents.robustness import MUS, SUITES, inside_ranges
from msdgrasp.agents.models import default_training
from msdgrasp.agents.stats import wilson_lower_bound
from msdgrasp.physics.config import ConfigError

REF = {"0.3": 1.0, "0.5": 0.8}


def _row(mu: float, success: list[bool], peak: float, lift: float) -> dict:
    n = len(success)
    return {"mu": mu, "episodes": n, "per_episode": {
        "success": success, "peak_pinch_N": [peak] * n,
        "time_to_lift_s": [lift if s else None for s in success]}}


def _policy(spec: str, fail_every: int, force_scale: float) -> dict:
    cells = []
    for cond in ("nominal", "force noise 0.05 N"):
        rows = [_row(mu, [(i % fail_every) != 0 if fail_every else True for i in range(40)],
                     force_scale * REF[f"{mu:g}"], 5.0) for mu in (0.3, 0.5)]
        cells.append({"condition": cond, "rows": rows})
    return {"spec": spec, "policy": spec, "cells": cells}


def _result() -> dict:
    results = [_policy(f"runs/seed_{k}/best_model.zip", 0, 1.2) for k in range(3)]
    results += [_policy("reactive", 10, 1.8)]
    return {"suite": "in_range", "version": 2, "protocol": True, "seeds": {"first": 10**9, "count": 40, "sealed": True},
            "episodes": 19, "config": {}, "conditions": [{"name": "nominal"}, {"name": "force noise 0.05 N"}],
            "results": results}


def test_tracks_pool_their_seeds_and_count_as_by_hand():
    board = build_leaderboard(_result(), [parse_track("trained=runs/seed_*/best_model.zip"),
                                          parse_track("slip-reactive=reactive")], baseline="slip-reactive",
                              references=REF)
    trained, reactive = board["tracks"]
    assert trained["runs"] == 3 and reactive["runs"] == 1
    cell = trained["cells"][0]
    assert (cell["successes"], cell["episodes"]) == (240, 240)  # 3 seeds x 2 mu x 40
    assert cell["success_lower_bound"] == pytest.approx(wilson_lower_bound(240, 240))
    assert cell["force_ratio"] == pytest.approx(1.2) and cell["time_to_lift_s"] == pytest.approx(5.0)
    r = reactive["cells"][1]
    assert (r["successes"], r["episodes"]) == (72, 80)  # one in ten fails
    assert r["force_ratio"] == pytest.approx(1.8)
    assert trained["success_iqm"] == pytest.approx(1.0) and reactive["success_iqm"] == pytest.approx(0.9)
    assert reactive["success_mean"] == pytest.approx(0.9) and reactive["success_mean_ci95"][0] < 0.9
    # lighter and never failing: it beats the reactive controller on every pair of episodes
    assert trained["p_improvement"]["value"] == pytest.approx(1.0)
    assert trained["profile"]["1.25"] == pytest.approx(1.0) and trained["profile"]["1.1"] == pytest.approx(0.0)
    assert reactive["profile"]["2"] == pytest.approx(0.9)
    text = leaderboard_markdown(board)
    assert "240/240" in text and "Not a certified" not in text


def test_unsealed_or_partial_results_say_so(tmp_path):
    result = _result()
    result["seeds"]["sealed"] = False
    path = tmp_path / "suite.json"
    path.write_text(json.dumps(result))
    board = write_leaderboard(path, ["t=reactive"], None, tmp_path / "out", references=REF)
    assert "Not a certified result" in (tmp_path / "out" / "leaderboard.md").read_text()
    assert board["tracks"][0]["track"] == "t"


@pytest.mark.parametrize("tracks, baseline, needle", [
    (["nothing=nomatch*"], None, "matches no policy"),
    (["t=reactive"], "other", "--baseline"),
    (["no-equals-sign"], None, "NAME=PATTERN"),
])
def test_bad_tracks_are_one_line_errors(tmp_path, tracks, baseline, needle):
    path = tmp_path / "suite.json"
    path.write_text(json.dumps(_result()))
    with pytest.raises(ConfigError, match=needle):
        write_leaderboard(path, tracks, baseline, tmp_path / "out", references=REF)
    assert not (tmp_path / "out").exists()


def test_results_of_other_episodes_do_not_merge(tmp_path):
    a, b = _result(), _result()
    b["seeds"] = {**b["seeds"], "first": 0, "sealed": False}
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for p, r in zip(paths, (a, b)):
        p.write_text(json.dumps(r))
    with pytest.raises(ConfigError, match="seeds"):
        write_leaderboard(paths, ["t=reactive"], None, tmp_path / "out", references=REF)
    b = _result()
    b["config"] = {"sensed_task_state": False}
    paths[1].write_text(json.dumps(b))
    with pytest.raises(ConfigError, match="sensed_task_state"):
        write_leaderboard(paths, ["t=reactive"], None, tmp_path / "out", references=REF)
    b = _result()
    b["config"] = {"reward": {"peak_force": 1.0}, "privileged_obs": True}  # (a training's own choices: the same task)
    b["results"] = [_policy("fixed", 0, 2.0), _policy("reactive", 1, 9.0)]
    paths[1].write_text(json.dumps(b))
    board = write_leaderboard(paths, ["r=reactive", "f=fixed"], None, tmp_path / "out", references=REF)
    assert board["tracks"][0]["cells"][0]["force_ratio"] == pytest.approx(1.8)  # the first run's reactive
    assert board["tracks"][1]["runs"] == 1


def test_the_in_range_suite_is_the_conditions_inside_the_benchmark_ranges():
    ranges = default_training().train_randomization
    names = [c.name for c in SUITES["in_range"]]
    assert names and all(inside_ranges(c, ranges) for c in SUITES["in_range"])
    assert not any(inside_ranges(c, ranges) for c in SUITES["robustness"] if c.name not in names)
    assert "nominal" in names and all(c.mus == MUS for c in SUITES["in_range"])
    assert np.isclose(min(MUS), 0.2)  # the low-friction end is in the grid


def test_each_run_is_compared_with_the_against_track_per_condition():
    result = _result()
    # one seed loses one episode of 40 at mu 0.3 in the nominal condition, and grips 10 % lighter there
    cell = result["results"][1]["cells"][0]["rows"][0]
    cell["per_episode"]["success"][0] = False
    cell["per_episode"]["peak_pinch_N"] = [0.9 * p for p in cell["per_episode"]["peak_pinch_N"]]
    board = build_leaderboard(result, [parse_track("trained=runs/seed_*/best_model.zip"),
                                       parse_track("slip-reactive=reactive")], references=REF, against="trained")
    trained, reactive = board["tracks"]
    assert [r["policy"] for r in trained["per_run"]] == [f"runs/seed_{k}/best_model.zip" for k in range(3)]
    assert "against" not in trained["per_run"][0]  # (the against track is not compared with itself)
    (ours,) = reactive["per_run"]
    assert [a["holds_as_many"] for a in ours["against"]] == [False, False]  # (one in ten fails)
    # the reactive controller's peak pinch 1.8 x REF against the trained track's (1.2 x REF, one seed lighter at mu 0.3)
    trained_pinch = (2 * 40 * 1.2 * 1.0 + 40 * 1.08 * 1.0 + 3 * 40 * 1.2 * 0.8) / 240
    reactive_pinch = (40 * 1.8 * 1.0 + 40 * 1.8 * 0.8) / 80
    assert ours["against"][0]["pinch_over_against"] == pytest.approx(reactive_pinch / trained_pinch)
    assert ours["cells"][1]["successes"] == 72
    text = leaderboard_markdown(board)
    assert "Per run" in text and " !" in text


def test_a_track_may_join_patterns():
    board = build_leaderboard(_result(), [parse_track("two=runs/seed_0/best_model.zip|runs/seed_2/best_model.zip")],
                              references=REF)
    assert board["tracks"][0]["policies"] == ["runs/seed_0/best_model.zip", "runs/seed_2/best_model.zip"]


def test_results_of_some_of_the_conditions_merge_on_the_conditions_they_share(tmp_path):
    full = _result()
    part = _result()
    part["conditions"] = [{"name": "force noise 0.05 N"}]
    part["results"] = [dict(_policy("other", 0, 1.1), cells=_policy("other", 0, 1.1)["cells"][1:])]
    paths = []
    for k, res in enumerate((full, part)):
        paths.append(tmp_path / f"s{k}.json")
        paths[-1].write_text(json.dumps(res))
    board = write_leaderboard(paths, ["trained=runs/seed_*/best_model.zip", "other=other"], None, tmp_path / "b",
                              references=REF)
    assert board["conditions"] == ["force noise 0.05 N"]
    assert [t["cells"][0]["force_ratio"] for t in board["tracks"]] == pytest.approx([1.2, 1.1])
    part["conditions"] = [{"name": "latency 1 step"}]
    paths[1].write_text(json.dumps(part))
    with pytest.raises(ConfigError, match="share no condition"):
        write_leaderboard(paths, ["trained=runs/seed_*/best_model.zip"], None, tmp_path / "b", references=REF)
