"""The told-mu frontier: what picking one policy per mu could do on a suite's development episodes.

A synthetic suite result (two conditions, two mu, 10 episodes each) with outcomes set by hand: a reference, a light
member that loses grasps at the low mu only, a heavy member that holds everything. The schedule the frontier picks,
its counts and force ratios are those worked out by hand, and it refuses what it must.
"""

from __future__ import annotations

import json

import pytest

from msdgrasp.agents.frontier import family_specs, frontier_markdown, mu_frontier
from msdgrasp.agents.stats import wilson_lower_bound
from msdgrasp.cli.main import main
from msdgrasp.physics.config import ConfigError

MUS = (0.2, 0.8)
CONDITIONS = ("nominal", "grasp up to 5 mm off")
N = 10


def _policy(spec: str, held: dict, pinch: dict) -> dict:
    """``held[(condition, mu)]`` episodes of N succeed (the first ones), each at ``pinch[mu]`` N."""
    cells = [{"condition": c, "rows": [
        {"mu": mu, "per_episode": {"success": [i < held[(c, mu)] for i in range(N)], "peak_pinch_N": [pinch[mu]] * N}}
        for mu in MUS]} for c in CONDITIONS]
    return {"spec": spec, "policy": spec, "cells": cells}


def _result(sealed: bool = False) -> dict:
    all_held = {(c, mu): N for c in CONDITIONS for mu in MUS}
    ref = _policy("controller", {**all_held, ("grasp up to 5 mm off", 0.2): 8}, {0.2: 2.0, 0.8: 1.0})
    light = _policy("light", {**all_held, ("grasp up to 5 mm off", 0.2): 6}, {0.2: 1.6, 0.8: 0.6})
    heavy = _policy("heavy", all_held, {0.2: 2.4, 0.8: 1.2})
    first = 10**9 if sealed else 7_100_000
    return {"suite": "in_range", "version": 2, "seeds": {"first": first, "count": N, "sealed": sealed},
            "episodes": N, "config": {}, "conditions": [{"name": c} for c in CONDITIONS],
            "results": [ref, light, heavy]}


def test_members_are_counted_against_the_reference_per_condition():
    record = mu_frontier(_result(), "controller", ["light", "heavy"])
    light, heavy = record["members"]
    assert record["reference"]["held"] == [20, 18]
    assert light["held_less_reference"] == [0, -2] and heavy["held_less_reference"] == [0, 2]
    # mean peak pinch over the reference's: (1.6 + 0.6) / (2.0 + 1.0) and (2.4 + 1.2) / 3
    assert light["force_ratio"] == pytest.approx([2.2 / 3] * 2)
    assert heavy["force_ratio"] == pytest.approx([1.2] * 2)


def test_the_best_schedule_keeps_the_grasps_within_the_force_cap():
    record = mu_frontier(_result(), "controller", ["light", "heavy"], cap=0.95)
    best = record["best_within_cap"]
    # heavy where the light one loses grasps (mu 0.2), light elsewhere: (2.4 + 0.6) / 3 = 1.0x > 0.95, so over the cap;
    # within it only light everywhere (0.73x) is left, two grasps short of the reference placed off
    assert best["members"] == {"0.2": "light", "0.8": "light"}
    assert best["worst_held_less_reference"] == -2
    assert best["lower_bound"][1] == pytest.approx(wilson_lower_bound(16, 20))
    # with room for 1.0x (1.01) the mixed schedule holds everything, and it is lighter than heavy everywhere
    mixed = mu_frontier(_result(), "controller", ["light", "heavy"], cap=1.01)["best_within_cap"]
    assert mixed["members"] == {"0.2": "heavy", "0.8": "light"}
    assert mixed["held_less_reference"] == [0, 2] and mixed["worst_force_ratio"] == pytest.approx(1.0)
    assert record["best_uncapped"]["members"] == mixed["members"]  # as many grasps, less force than heavy throughout
    assert record["hindsight"]["held"] == [20, 20]
    assert mu_frontier(_result(), "controller", ["heavy"], cap=0.5)["best_within_cap"] is None
    assert "best schedule at <= 0.5x | none" in frontier_markdown(mu_frontier(_result(), "controller", ["heavy"],
                                                                            cap=0.5))


def test_it_refuses_sealed_episodes_and_unknown_policies():
    with pytest.raises(ConfigError, match="sealed"):
        mu_frontier(_result(sealed=True), "controller", ["light"])
    with pytest.raises(ConfigError, match="--against 'nope'"):
        mu_frontier(_result(), "nope", ["light"])
    with pytest.raises(ConfigError, match="--cap"):
        mu_frontier(_result(), "controller", ["light"], cap=0.0)
    with pytest.raises(ConfigError, match="--family"):
        family_specs(_result(), ["zzz*"], "controller")
    assert family_specs(_result(), [], "controller") == ["light", "heavy"]
    other = _result()
    other["results"][1]["cells"][0]["rows"][0]["per_episode"]["success"].append(True)  # one more episode
    other["results"][1]["cells"][0]["rows"][0]["per_episode"]["peak_pinch_N"].append(1.0)
    with pytest.raises(ConfigError, match="light"):
        mu_frontier(other, "controller", ["light"])


def test_the_command_writes_both_files_or_nothing(tmp_path, capsys):
    suite = tmp_path / "suite.json"
    suite.write_text(json.dumps(_result()))
    assert main(["frontier", str(suite), "--against", "controller", "--cap", "1.01", "--out", str(tmp_path / "f")]) == 0
    record = json.loads((tmp_path / "f" / "frontier.json").read_text())
    assert record["best_within_cap"]["members"] == {"0.2": "heavy", "0.8": "light"}
    assert "per-episode hindsight" in (tmp_path / "f" / "frontier.md").read_text()
    sealed = tmp_path / "sealed.json"
    sealed.write_text(json.dumps(_result(sealed=True)))
    assert main(["frontier", str(sealed), "--against", "controller", "--out", str(tmp_path / "g")]) == 2
    assert main(["frontier", str(suite), "--family", "zzz", "--out", str(tmp_path / "g")]) == 2
    assert not (tmp_path / "g").exists()
    assert "sealed" in capsys.readouterr().err
