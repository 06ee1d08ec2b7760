"""The told-mu frontier: what picking one policy per mu could do on a suite's development episodes.

A synthetic suite result (three conditions, two mu, 10 episodes each) with outcomes set by hand: a reference, a light
member that loses grasps at the low mu placed off, a heavy member that holds everything, a member that holds other
episodes than the light one. Pinch differs per condition. The schedule the frontier picks, its counts and force
ratios are those worked out by hand, and it refuses what it must.
"""

from __future__ import annotations

import json

import pytest

from msdgrasp.agents.frontier import family_specs, frontier_markdown, mu_frontier
from msdgrasp.agents.protocol import SEALED_SEEDS
from msdgrasp.agents.stats import wilson_lower_bound
from msdgrasp.cli.main import main
from msdgrasp.physics.config import ConfigError

MUS = (0.2, 0.8)
CONDITIONS = ("nominal", "force noise 0.08 N", "grasp up to 5 mm off")
OFF = "grasp up to 5 mm off"
N = 10
#: the conditions' pinch scale: each condition's pinch differs, so that a ratio mixing conditions is caught
SCALE = {"nominal": 1.0, "force noise 0.08 N": 1.5, OFF: 2.0}


def _policy(spec: str, lost: dict, pinch: dict) -> dict:
    """The episodes of ``lost[(condition, mu)]`` (indices) fail, the others succeed; each at ``pinch[mu]`` x the
    condition's scale (N)."""
    cells = [{"condition": c, "rows": [
        {"mu": mu, "per_episode": {"success": [i not in lost.get((c, mu), ()) for i in range(N)],
                                   "peak_pinch_N": [pinch[mu] * SCALE[c]] * N}}
        for mu in MUS]} for c in CONDITIONS]
    return {"spec": spec, "policy": spec, "cells": cells}


def _result(first: int = 7_100_000, sealed: bool = False) -> dict:
    results = [
        _policy("controller", {(OFF, 0.2): {0, 1}}, {0.2: 2.0, 0.8: 1.0}),
        _policy("light", {(OFF, 0.2): {0, 1, 2, 3}}, {0.2: 1.6, 0.8: 0.6}),
        _policy("heavy", {}, {0.2: 2.4, 0.8: 1.2}),
        _policy("other", {(OFF, 0.2): {4, 5, 6, 7}}, {0.2: 1.6, 0.8: 0.6}),  # as light, losing other episodes
    ]
    return {"suite": "in_range", "version": 2, "seeds": {"first": first, "count": N, "sealed": sealed},
            "episodes": N, "config": {}, "conditions": [{"name": c} for c in CONDITIONS], "results": results}


def test_members_are_counted_against_the_reference_per_condition():
    record = mu_frontier(_result(), "controller", ["light", "heavy"])
    light, heavy = record["members"]
    assert record["reference"]["held"] == [20, 20, 18]
    assert record["reference"]["mean_peak_pinch_N"] == pytest.approx([1.5, 2.25, 3.0])
    assert light["held_less_reference"] == [0, 0, -2] and heavy["held_less_reference"] == [0, 0, 2]
    # mean peak pinch over the reference's, the same in every condition: (1.6 + 0.6) / (2.0 + 1.0), (2.4 + 1.2) / 3
    assert light["force_ratio"] == pytest.approx([2.2 / 3] * 3)
    assert heavy["force_ratio"] == pytest.approx([1.2] * 3)
    assert record["hindsight"]["held"] == [20, 20, 20]


def test_the_best_schedule_keeps_the_grasps_within_the_force_cap():
    record = mu_frontier(_result(), "controller", ["light", "heavy"], cap=0.95)
    best = record["best_within_cap"]
    # heavy at mu 0.2 and light at 0.8 would hold everything at (2.4 + 0.6) / 3 = 1.0x: over the cap. Within it,
    # light / light (0.73x) and light / heavy (0.93x) both trail the reference by 2 placed off; the lighter wins
    assert best["members"] == {"0.2": "light", "0.8": "light"}
    assert best["worst_held_less_reference"] == -2 and best["held"] == [20, 20, 16]
    assert best["lower_bound"][2] == pytest.approx(wilson_lower_bound(16, 20))
    # a cap of exactly 1.0x admits the schedule at 1.0x: it holds everything and is lighter than heavy throughout
    mixed = mu_frontier(_result(), "controller", ["light", "heavy"], cap=1.0)["best_within_cap"]
    assert mixed["members"] == {"0.2": "heavy", "0.8": "light"}
    assert mixed["held_less_reference"] == [0, 0, 2] and mixed["worst_force_ratio"] == pytest.approx(1.0)
    assert record["best_uncapped"]["members"] == mixed["members"]
    assert "fewer grasps than the reference in 1 of 3 conditions (2 fewer grasp up to 5 mm off)" in frontier_markdown(
        record)
    assert "at least the reference's grasps in every condition" in frontier_markdown(
        mu_frontier(_result(), "controller", ["light", "heavy"], cap=1.0))
    assert mu_frontier(_result(), "controller", ["heavy"], cap=0.5)["best_within_cap"] is None
    assert "best schedule at <= 0.5x | none" in frontier_markdown(
        mu_frontier(_result(), "controller", ["heavy"], cap=0.5))


def test_a_tie_in_the_worst_condition_goes_to_more_grasps_before_less_force():
    result = _result()
    # light now also loses one episode under force noise at mu 0.8: within 0.95x, light / light (0.73x) and
    # light / heavy (0.93x) both trail by 2 placed off, but light / heavy holds one grasp more in all
    result["results"][1] = _policy("light", {(OFF, 0.2): {0, 1, 2, 3}, ("force noise 0.08 N", 0.8): {0}},
                                   {0.2: 1.6, 0.8: 0.6})
    best = mu_frontier(result, "controller", ["light", "heavy"], cap=0.95)["best_within_cap"]
    assert best["members"] == {"0.2": "light", "0.8": "heavy"}
    assert best["worst_held_less_reference"] == -2 and sum(best["held"]) == 56
    # with no cap the schedule that trails nowhere wins, however heavy
    free = mu_frontier(result, "controller", ["light", "heavy"], cap=10)["best_within_cap"]
    assert free["members"] == {"0.2": "heavy", "0.8": "heavy"} and free["worst_held_less_reference"] == 0


def test_the_cap_holds_in_every_condition_not_on_average():
    result = _result()
    for row in result["results"][3]["cells"][2]["rows"]:  # other grips 1.7x as hard placed off: 1.24x there
        row["per_episode"]["peak_pinch_N"] = [p * 1.7 for p in row["per_episode"]["peak_pinch_N"]]
    record = mu_frontier(result, "controller", ["other"], cap=0.95)
    assert record["members"][0]["force_ratio"] == pytest.approx([2.2 / 3, 2.2 / 3, 1.7 * 2.2 / 3])
    assert record["best_within_cap"] is None  # its mean over the conditions, 0.90x, is not what counts


def test_hindsight_pools_the_episodes_any_member_holds():
    record = mu_frontier(_result(), "controller", ["light", "other"])
    # light loses episodes 0-3 placed off at mu 0.2, other 4-7: between them every episode is held by one
    assert record["hindsight"]["held"] == [20, 20, 20]
    assert max(m["held"][2] for m in record["members"]) == 16


def test_it_refuses_sealed_episodes_and_unknown_policies():
    with pytest.raises(ConfigError, match="sealed"):
        mu_frontier(_result(first=SEALED_SEEDS.start, sealed=True), "controller", ["light"])
    with pytest.raises(ConfigError, match="sealed"):  # reaching into them, though not flagged
        mu_frontier(_result(first=SEALED_SEEDS.start - 5), "controller", ["light"])
    with pytest.raises(ConfigError, match="--against 'nope'"):
        mu_frontier(_result(), "nope", ["light"])
    with pytest.raises(ConfigError, match="other than the reference"):
        mu_frontier(_result(), "controller", ["controller", "light"])
    with pytest.raises(ConfigError, match="--cap"):
        mu_frontier(_result(), "controller", ["light"], cap=0.0)
    with pytest.raises(ConfigError, match="--family"):
        family_specs(_result(), ["zzz*"], "controller")
    assert family_specs(_result(), [], "controller") == ["light", "heavy", "other"]
    assert family_specs(_result(), ["*"], "controller") == ["light", "heavy", "other"]


@pytest.mark.parametrize("break_it, needle", [
    (lambda ep: (ep["success"].append(True), ep["peak_pinch_N"].append(1.0)), "different numbers of episodes"),
    (lambda ep: ep["peak_pinch_N"].append(1.0), "differ in length"),
    (lambda ep: ep["peak_pinch_N"].__setitem__(0, None), "not a number"),
    (lambda ep: ep.pop("peak_pinch_N"), "not a suite result's policy"),
])
def test_malformed_episodes_are_one_line_errors(break_it, needle):
    result = _result()
    break_it(result["results"][1]["cells"][0]["rows"][0]["per_episode"])
    with pytest.raises(ConfigError, match=needle):
        mu_frontier(result, "controller", ["light"])


def test_the_command_writes_both_files_and_nothing_on_bad_input(tmp_path, capsys):
    suite = tmp_path / "suite.json"
    suite.write_text(json.dumps(_result()))
    assert main(["frontier", str(suite), "--against", "controller", "--cap", "1", "--out", str(tmp_path / "f")]) == 0
    record = json.loads((tmp_path / "f" / "frontier.json").read_text())
    assert record["best_within_cap"]["members"] == {"0.2": "heavy", "0.8": "light"}
    assert "per-episode hindsight" in (tmp_path / "f" / "frontier.md").read_text()
    sealed = tmp_path / "sealed.json"
    sealed.write_text(json.dumps(_result(first=SEALED_SEEDS.start, sealed=True)))
    assert main(["frontier", str(sealed), "--against", "controller", "--out", str(tmp_path / "g")]) == 2
    assert main(["frontier", str(suite), "--family", "zzz", "--out", str(tmp_path / "g")]) == 2
    short = _result()
    short["results"][1]["cells"].pop()  # a result with a cell missing
    (tmp_path / "short.json").write_text(json.dumps(short))
    args = ["--against", "controller", "--out", str(tmp_path / "g")]
    assert main(["frontier", str(tmp_path / "short.json"), *args]) == 2
    assert main(["frontier", str(suite), "--against", "controller", "--out", str(suite)]) == 2
    assert not (tmp_path / "g").exists()
    err = capsys.readouterr().err
    assert "sealed" in err and "one cell per condition" in err and "must be a folder" in err
