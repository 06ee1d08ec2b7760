"""msdgrasp headroom: what predicts each episode's holding grip, and what a grip that knows it is worth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msdgrasp.agents.headroom import (
    HOLD_SHARE, SOURCES, format_headroom, headroom_verdict, leave_one_out_quantiles, loo_ridge_residuals,
    measure_headroom, privileged_draws, source_grips,
)
from msdgrasp.cli.main import main
from msdgrasp.envs.core import benchmark_config
from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv
from msdgrasp.envs.perturbations import privileged_names


def test_the_closed_form_residuals_are_those_of_refitting_without_each_episode():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(30, 4)), rng.normal(size=30)
    ridge = 2.0
    fast = loo_ridge_residuals(x, y, ridge)
    a = np.c_[(x - x.mean(0)) / x.std(0), np.ones(30)]  # (standardised on all episodes, as the closed form is)
    penalty = np.diag([ridge] * 4 + [0.0])
    for i in range(30):
        keep = np.arange(30) != i
        w = np.linalg.solve(a[keep].T @ a[keep] + penalty, a[keep].T @ y[keep])
        assert fast[i] == pytest.approx(y[i] - a[i] @ w, abs=1e-10)


def test_no_episode_sizes_its_own_margin():
    values = np.array([1.0, 2.0, 3.0, 4.0, 100.0])
    assert leave_one_out_quantiles(values, 1.0).tolist() == [100.0, 100.0, 100.0, 100.0, 4.0]


def test_the_draws_are_the_current_frames_perturbation_block_and_the_scales():
    import dataclasses

    from msdgrasp.agents.models import default_training

    task = dataclasses.replace(default_training().training_task(), privileged_obs=True, privileged_perturbations=True)
    seen = []
    for history in (1, 3):
        env = GraspLiftVectorEnv(2, dataclasses.replace(task, obs_history=history))
        obs, info = env.reset(seed=[11, 12], options={"mu": [0.3, 0.5]})
        draws = privileged_draws(obs, info)
        assert draws.shape == (2, 2 + len(privileged_names()))
        assert draws[:, 0] == pytest.approx(np.log(info["stiffness_scale"]))
        seen.append(draws)
    assert seen[0] == pytest.approx(seen[1])  # (the current frame's block, however many frames are stacked)
    assert not np.allclose(seen[0][0, 2:], seen[0][1, 2:])  # two seeds, two poses, biases, ...


def _synthetic(n_per_mu: int = 60, seed: int = 1) -> dict[str, np.ndarray]:
    """Holding grips Coulomb-like in mu, scattered by one privileged draw the closing does not see; the controller's
    estimate is the true mu with noise."""
    rng = np.random.default_rng(seed)
    mu = np.repeat([0.2, 0.3, 0.5, 0.8], n_per_mu)
    draws = rng.normal(size=(len(mu), 16))
    hold = 0.35 / mu * np.exp(0.2 * draws[:, 3])
    hold[0] = np.nan  # an episode no grip holds: it gets a grip, it is not fitted
    estimate, features = mu * np.exp(0.3 * rng.normal(size=len(mu))), rng.normal(size=(len(mu), 55))
    estimate[5], features[5] = np.nan, np.nan  # one the controller made no estimate in: the mean grip
    return {"mu": mu, "hold_N": hold, "draws": draws, "mu_estimate": estimate, "features": features}


def test_a_source_that_knows_what_scatters_the_grip_needs_no_margin_and_one_that_guesses_needs_more():
    grips = source_grips(_synthetic())
    assert set(grips) == set(SOURCES)
    assert grips["mu_draws"]["residual_sd"] < 0.02 and max(grips["mu_draws"]["margins"]) == pytest.approx(1.0, abs=0.05)
    assert grips["mu"]["residual_sd"] == pytest.approx(0.2, rel=0.2)  # the draw's scatter, which mu does not know
    assert grips["estimate"]["residual_sd"] > grips["mu"]["residual_sd"]  # the estimate's own error adds to it
    for g in grips.values():
        assert np.all(np.isfinite(g["grip_N"])) and np.all(g["grip_N"] > 0)


def test_the_margin_holds_the_share_of_the_holdable_episodes_it_is_sized_for():
    data = _synthetic()
    holdable = np.isfinite(data["hold_N"])
    for g in source_grips(data).values():
        held = np.mean(g["grip_N"][holdable] >= data["hold_N"][holdable] * (1 - 1e-9))
        assert held >= HOLD_SHARE - 0.02  # (the LOO predictions are not those of the full fit: a hair either way)


def test_a_source_that_knows_mu_holds_the_share_at_every_mu_and_one_margin_for_all_does_not():
    data = _synthetic(n_per_mu=100)
    scatter = np.repeat([0.4, 0.2, 0.1, 0.05], 100)  # (the grip scatters more where the tissue is slipperier)
    data["hold_N"] = 0.35 / data["mu"] * np.exp(scatter * data["draws"][:, 3])
    data["mu_estimate"] = data["mu"].copy()  # (an estimate as good as the truth, but not told it is: one margin)
    grips = source_grips(data)
    assert len(grips["mu"]["margins"]) == 4 and len(grips["estimate"]["margins"]) == 1
    for name, low, high in (("mu", 0.9, 1.0), ("estimate", 0.0, 0.85)):
        held = grips[name]["grip_N"] >= data["hold_N"]
        assert low <= held[:100].mean() <= high, name  # at mu 0.2
    assert held[300:].mean() == 1.0  # one margin sized by the slippery tissue over-grips the rough one


def _record(successes: dict[str, list[float]], forces: dict[str, list[float]]) -> dict:
    per_mu = lambda s, f: [{"mu": m, "success_rate": a, "force_vs_controller": b, "mean_peak_pinch_N": b}  # noqa: E731
                           for m, a, b in zip((0.2, 0.8), s, f)]
    return {"controller_per_mu": per_mu([0.8, 1.0], [1.0, 1.0]),
            "sources": {k: {"per_mu": per_mu(successes[k], forces[k])} for k in successes}}


def test_the_verdict_takes_the_lightest_source_that_loses_no_grasp():
    rec = _record({"mu": [0.8, 1.0], "closing": [0.7, 1.0]}, {"mu": [0.9, 0.97], "closing": [0.5, 0.5]})
    assert "mu, at most 0.97x" in headroom_verdict(rec) and "above 0.95x" in headroom_verdict(rec)
    rec = _record({"mu": [0.7, 1.0]}, {"mu": [0.5, 0.5]})
    assert headroom_verdict(rec).startswith("no source")


def test_a_tiny_run_measures_every_source_on_the_task(tmp_path):
    record = measure_headroom(benchmark_config("spleen"), mus=(0.3, 0.8), episodes=3)
    assert set(record["sources"]) == set(SOURCES)
    for s in record["sources"].values():
        assert [r["mu"] for r in s["per_mu"]] == [0.3, 0.8] and all(r["episodes"] == 3 for r in s["per_mu"])
        assert all(0 <= r["success_rate"] <= 1 and r["mean_peak_pinch_N"] > 0 for r in s["per_mu"])
    # every held episode got the controller's estimate and closing features: each source fits as many episodes
    held = round(sum(h["held_share"] for h in record["hindsight"]) * 3)
    assert held >= 3 and {s["fitted"] for s in record["sources"].values()} == {held}
    assert "| the controller" in format_headroom(record)
    episodes = record["per_episode"]  # (each episode, to run another policy on the same ones)
    assert episodes["mu"] == [0.3] * 3 + [0.8] * 3 and len(set(episodes["seed"])) == 6
    assert all(h is None or h > 0 for h in episodes["hold_N"])
    json.dumps(record, allow_nan=False)  # (strict JSON: no NaN)


@pytest.mark.parametrize("argv, field", [
    (["--out", "x.txt"], "--out"),
    (["--out", "x.json", "--seed", "0"], "--seed"),
    (["--out", "x.json", "--episodes", "2"], "--episodes"),
    (["--out", "x.json", "--mu-grid", "0,0.5"], "--mu-grid"),
    (["--out", "x.json", "--mu-grid", "abc"], "--mu-grid"),
    (["--out", "x.json", "--episodes", "300000"], "--episodes"),
    (["--out", "x.json", "--config", "missing.yaml"], "--config"),
    (["--out", "x.json", "--controller", "fixed:force=1"], "--controller"),
    (["--out", "x.json", "--controller", "fixed:1"], "--controller"),
])
def test_cli_refuses_bad_input(argv, field, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["headroom", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert field in err and "\n" not in err
    assert not (tmp_path / "x.json").exists()
