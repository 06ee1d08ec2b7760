"""The reference force of the force ratios (agents/reference.py) and its shipped table (configs/reference/spleen.json).

Without simulation: a table assembled from given searches is its definition (per pull the least grip that holds 95 %,
R the least of them, its pull recorded), and its lookup refuses another task's physics and a mu off the grid.

On the shipped table, at one friction, MU, on its reference episodes:

* (a) gripping at R(MU) at its pull, the fixed-force controller scores 1.0 (peak pinch / R within the table's
  tolerance) and holds at least ceil(0.95 n) of the n reference episodes;
* (b) gripping at R(MU) - 3 x tolerance, it holds fewer than ceil(0.95 n) of them at every pull of the grid and at a
  pull between R's and the next slower one: no pull speed reaches a lower score at the same success.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from msdgrasp.agents.reference import (
    FORMAT, assemble_reference, compute_reference, default_reference_path, fingerprint_digest, force_score,
    held_needed, hold_quantile, load_reference, reference_force_N, reference_table, run_fixed_grips, task_fingerprint,
    write_reference,
)
from msdgrasp.cli.main import main
from msdgrasp.envs.core import RewardConfig, benchmark_config
from msdgrasp.physics.config import ConfigError

CONFIG = benchmark_config("spleen")
MU = 0.5
SHIPPED = default_reference_path(CONFIG)
needs_shipped = pytest.mark.skipif(not SHIPPED.is_file(), reason=f"no shipped reference table at {SHIPPED}; compute it "
                                                                 f"with msdgrasp reference --out {SHIPPED}")


def _row(table, mu=MU):
    return next(r for r in table["mu"] if math.isclose(r["mu"], mu))


def _seeds(table, episodes):
    return [table["seeds"]["first"] + int(i) for i in episodes]


# ------------------------------------------------------------------------------------------------
# the definition and the lookup, on a table assembled from given minimal forces
# ------------------------------------------------------------------------------------------------

MUS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
PULLS = (0.18, 0.2, 0.25, 0.5)


def _synthetic(n=40):
    """Least grips ~ 0.45 / mu, less at slower pulls; at 0.18 and 0.2 no grip holds 95 %."""
    rng = np.random.default_rng(0)
    cells = {}
    for mu in MUS:
        base = 0.45 / mu * (1.0 + 0.04 * rng.standard_normal())
        for p in PULLS:
            q = None if p in (0.18, 0.2) else float(base * (0.8 + 0.4 * p))
            cells[(mu, p)] = {"quantile_N": q, "probes": [{"force_N": 1.0, "held": n if q else 0}]}
    return cells


@pytest.fixture
def synthetic(tmp_path):
    cells = _synthetic()
    path = tmp_path / "table.json"
    write_reference(assemble_reference(CONFIG, cells, 3_000_000, 0.01, 40), path)
    return cells, path


def test_a_table_is_its_definition(synthetic):
    cells, path = synthetic
    table = load_reference(path)
    assert table["format"] == FORMAT and table["held_needed"] == 38 and table["pulls"] == list(PULLS)
    for row in table["mu"]:
        mu = row["mu"]
        by_pull = {c["pull"]: c for c in row["per_pull"]}
        assert by_pull[0.18]["quantile_N"] is None and by_pull[0.2]["quantile_N"] is None
        # the least grip of the pulls that hold 95 %: the slowest of them here
        assert row["pull"] == 0.25
        assert row["reference_force_N"] == cells[(mu, 0.25)]["quantile_N"] == by_pull[0.25]["quantile_N"]
        assert row["reference_force_N"] < by_pull[0.5]["quantile_N"]
        assert row["pull_speed_m_s"] == pytest.approx(0.25 * 0.02)
    assert hold_quantile([1.0, None, 2.0], share=0.5) == 2.0 and hold_quantile([None, 1.0], share=1.0) == math.inf
    assert held_needed(48) == 46 and held_needed(40) == 38 and held_needed(60) == 57
    # on a tie the faster pull
    tie = {(0.5, 0.25): {"quantile_N": 1.0, "probes": []}, (0.5, 0.5): {"quantile_N": 1.0, "probes": []}}
    assert assemble_reference(CONFIG, tie, 3_000_000, 0.01, 4)["mu"][0]["pull"] == 0.5


def test_the_search_scans_up_then_bisects(monkeypatch):
    """The least grip that holds 95 %, to the tolerance, where a heavier grip (that runs out of time) holds fewer: a
    bisection over the whole range would miss it; a scan that finds the count falling gives up."""
    from msdgrasp.agents import reference

    def fake(config, mu, seeds, force, pull):  # holds from 1.234 N up to 2 N, nothing above (out of time)
        n = len(seeds)
        k = n if 1.234 <= force <= 2.0 else (n // 2 if force < 1.234 else 0)
        return {"success": np.arange(n) < k}

    monkeypatch.setattr(reference, "run_fixed_grips", fake)
    out = reference.search_quantile(CONFIG, 0.2, 0.25, list(range(40)), 0.01)
    assert 1.234 <= out["quantile_N"] <= 1.234 + 0.01 and all(p["force_N"] <= 2.0 for p in out["probes"])
    monkeypatch.setattr(reference, "run_fixed_grips", lambda c, mu, seeds, force, pull: {
        "success": np.arange(len(seeds)) < (20 if force < 1.5 else 5)})
    out = reference.search_quantile(CONFIG, 0.2, 0.2, list(range(40)), 0.01)
    assert out["quantile_N"] is None and len(out["probes"]) <= 4  # (gave up once the count fell)
    # a count that falls by chance far below the share (1, then 0) does not end the scan
    monkeypatch.setattr(reference, "run_fixed_grips", lambda c, mu, seeds, force, pull: {
        "success": np.arange(len(seeds)) < (1 if force < 0.45 else 0 if force < 0.55 else 40)})
    out = reference.search_quantile(CONFIG, 0.7, 0.22, list(range(40)), 0.01)
    assert out["quantile_N"] is not None and 0.55 <= out["quantile_N"] <= 0.56


def test_lookup_refuses_other_physics_and_mu_off_the_grid(synthetic):
    """(c) a task with other physics, pose draws or time limit is refused (one line naming the field); observation,
    sensing and reward do not enter; a mu off the grid's range is refused; between grid points R x mu is linear."""
    _, path = synthetic
    R = {r["mu"]: r["reference_force_N"] for r in load_reference(path)["mu"]}
    assert reference_force_N(CONFIG, MU, path) == R[MU]
    rnd = CONFIG.randomization
    same = dataclasses.replace(CONFIG, obs_history=3, privileged_obs=True, reward=RewardConfig(), reference_force_N=4.0,
                               randomization=dataclasses.replace(rnd, sensor_noise_N=0.1, slip_sensing="binary"))
    assert reference_force_N(same, MU, path) == R[MU]
    for other, field in ((dataclasses.replace(CONFIG, anchor_stiffness_n_per_m=4.0), "anchor_stiffness_n_per_m"),
                         (dataclasses.replace(CONFIG, randomization=dataclasses.replace(rnd, pose_offset_m=0.003)),
                          "randomization.pose_offset_m"),
                         (dataclasses.replace(CONFIG, time_limit_s=12.0), "time_limit_s is 10.0 there, 12.0 here"),
                         (dataclasses.replace(CONFIG, pull_action_exponent=2.0), "pull_action_exponent")):
        with pytest.raises(ConfigError, match=f"another task.*{field}") as err:
            reference_force_N(other, MU, path)
        assert "\n" not in str(err.value)
    for mu in (0.1, 0.95, float("nan")):
        with pytest.raises(ConfigError, match=r"mu = .* outside .* allowed \[0.2, 0.9\]"):
            reference_force_N(CONFIG, mu, path)
    expected = 0.5 * (R[0.5] * 0.5 + R[0.6] * 0.6) / 0.55
    assert reference_force_N(CONFIG, 0.55, path) == pytest.approx(expected, rel=1e-12)
    assert force_score(2 * R[0.3], 0.3, CONFIG, path) == pytest.approx(2.0)
    with pytest.raises(ConfigError, match="peak_pinch_N"):
        force_score(-1.0, MU, CONFIG, path)


def test_lookup_refuses_broken_or_missing_tables(synthetic, tmp_path):
    _, path = synthetic
    record = json.loads(path.read_text())
    edited = {**record, "task": {**record["task"], "time_limit_s": 5.0}}
    edited["task_digest"] = fingerprint_digest(edited["task"])
    write_reference(edited, path)
    with pytest.raises(ConfigError, match="time_limit_s is 5.0 there, 10.0 here"):
        reference_force_N(CONFIG, 0.7, path)
    path.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ConfigError, match="not a reference table"):
        load_reference(path)
    with pytest.raises(ConfigError, match="no reference table"):
        reference_force_N(CONFIG, MU, tmp_path / "none.json")
    with pytest.raises(ConfigError, match="no reference table"):
        reference_force_N(benchmark_config("sphere"), MU)  # (none shipped for the sphere)
    assert "sensor_noise_N" not in task_fingerprint(CONFIG)["randomization"]


def test_a_stopped_computation_goes_on_from_its_journal(tmp_path, monkeypatch):
    """Searches in the journal are taken, not run again (here every one: nothing is simulated but the check)."""
    from msdgrasp.agents import reference

    journal = tmp_path / "cells.jsonl"
    digest = fingerprint_digest(task_fingerprint(CONFIG))
    lines = [json.dumps({"key": reference._journal_key(digest, 0.5, p, 3_000_000, 2, 0.01),
                         "quantile_N": 1.0 if p == 0.3 else 1.2, "probes": []}) for p in (0.3, 0.5)]
    journal.write_text("\n".join([*lines, "{broken"]) + "\n")
    monkeypatch.setattr(reference, "_search_job", lambda *a: pytest.fail("searched again"))
    monkeypatch.setattr(reference, "_check_job", lambda cfg, mu, pull, force, seed, n: {
        "held": 2, "mean_time_to_lift_s": 6.0})
    record = compute_reference(CONFIG, (0.5,), (0.3, 0.5), 2, journal=journal, progress=False)
    assert record["mu"][0]["reference_force_N"] == 1.0 and record["mu"][0]["pull"] == 0.3
    assert record["mu"][0]["time_to_lift_s"] == 6.0


def test_compute_checks_its_inputs():
    for kwargs, field in (({"pulls": (0.0,)}, "pull"), ({"mus": (0.0,)}, "mu"), ({"tolerance_N": 0.5}, "tolerance_N"),
                          ({"seed": 0}, "seed"), ({"seed": 3_999_990, "episodes": 48}, "seed"),
                          ({"episodes": 0}, "episodes")):
        with pytest.raises(ConfigError, match=field):
            compute_reference(CONFIG, **kwargs)
    with pytest.raises(ConfigError, match="pull_action"):
        compute_reference(dataclasses.replace(CONFIG, pull_action="travel"))


@pytest.mark.parametrize("argv, field", [
    (["--out", "x.txt"], "--out"),
    (["--out", "x.json", "--seed", "0"], "--seed"),
    (["--out", "x.json", "--pulls", "0.3,1.5"], "--pulls"),
    (["--out", "x.json", "--pulls", "slow"], "--pulls"),
    (["--out", "x.json", "--tolerance", "0"], "--tolerance"),
    (["--out", "x.json", "--episodes", "0"], "--episodes"),
    (["--out", "x.json", "--mu-grid", "0,0.5"], "--mu-grid"),
    (["--out", "x.json", "--scene", "spleen", "--config", "c.yaml"], "--scene"),
])
def test_cli_refuses_bad_input(argv, field, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["reference", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert field in err and "\n" not in err
    assert not (tmp_path / "x.json").exists()


# ------------------------------------------------------------------------------------------------
# the shipped table, run again
# ------------------------------------------------------------------------------------------------


def check_reference_grip(table, path: Path, mu=MU):
    """(a) on ``table``: R(mu) at its pull on the reference episodes scores 1 within the tolerance and holds 95 %."""
    row = _row(table, mu)
    R, pull, tol = row["reference_force_N"], row["pull"], table["tolerance_N"]
    ep = run_fixed_grips(CONFIG, mu, _seeds(table, range(table["episodes"])), R, pull)
    assert int(ep["success"].sum()) >= held_needed(table["episodes"]), ep["success"]
    peak = float(ep["peak_pinch_N"].mean())
    assert abs(peak - R) <= tol, (peak, R)
    assert force_score(peak, mu, CONFIG, path) == pytest.approx(1.0, abs=tol / R)


def check_no_pull_undercuts(table, mu=MU):
    """(b) on ``table``: R(mu) - 3 x tolerance holds fewer than 95 % of the reference episodes at every pull of the
    grid and at the pull halfway between R's and the next slower one."""
    row = _row(table, mu)
    R, tol, pulls, n = row["reference_force_N"], table["tolerance_N"], table["pulls"], table["episodes"]
    slower = [p for p in pulls if p < row["pull"]]
    between = round(0.5 * (row["pull"] + slower[-1]), 4) if slower else round(0.9 * row["pull"], 4)
    runs = [*pulls, between]
    ep = run_fixed_grips(CONFIG, mu, _seeds(table, [i for _ in runs for i in range(n)]), R - 3 * tol,
                         [p for p in runs for _ in range(n)])
    for k, p in enumerate(runs):
        held = int(ep["success"][k * n:(k + 1) * n].sum())
        assert held < held_needed(n), f"pull {p:g}: {R - 3 * tol:.3f} N held {held} of {n} (95 %: {held_needed(n)})"


@needs_shipped
def test_shipped_table_is_its_definition():
    table = reference_table(CONFIG)
    assert [r["mu"] for r in table["mu"]] == pytest.approx(MUS)
    assert table["episodes"] >= 40 and table["tolerance_N"] <= 0.02
    for row in table["mu"]:
        quantiles = [c["quantile_N"] for c in row["per_pull"] if c["quantile_N"] is not None]
        assert row["reference_force_N"] == min(quantiles)
        assert row["check"]["held"] >= table["held_needed"]  # run again at R and its pull: 95 % held


@needs_shipped
def test_reference_grip_scores_one_and_holds():
    check_reference_grip(reference_table(CONFIG), SHIPPED)


@needs_shipped
def test_no_pull_speed_undercuts_the_reference():
    check_no_pull_undercuts(reference_table(CONFIG))
