"""``msdgrasp collect``: demonstrations as Minari datasets that ``minari.load_dataset`` reads back in a fresh process,
whose episodes replay in the recovered env to the same observations (same seeds)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import textwrap

import pytest

from msdgrasp.cli.main import main

pytest.importorskip("minari")  # (a test dependency: msdgrasp[test] installs it)

DATASET = "msdgrasp/grasplift/reactive-v0"

REPLAY = textwrap.dedent("""
    import json, sys
    import minari
    import numpy as np

    ds = minari.load_dataset(sys.argv[1])
    env = ds.recover_environment()
    seeds = [m["seed"] for m in ds.storage.get_episode_metadata(range(ds.total_episodes))]
    same = []
    for ep, seed in zip(ds.iterate_episodes(), seeds):
        obs, _ = env.reset(seed=seed)
        ok = np.array_equal(obs, ep.observations[0])
        for k, action in enumerate(ep.actions):
            obs, *_ = env.step(action)
            ok = ok and np.array_equal(obs, ep.observations[k + 1])
        same.append(bool(ok))
    print(json.dumps({"episodes": ds.total_episodes, "steps": ds.total_steps, "seeds": seeds, "same": same,
                      "env": ds.spec.env_spec.id}))
""")


def _run_main(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def test_a_collected_dataset_loads_in_a_fresh_process_and_replays_to_the_same_observations(tmp_path):
    rc, out, err = _run_main(["collect", "--policy", "reactive", "--episodes", "2", "--seed", "5",
                              "--out", str(tmp_path), "--quiet"])
    assert rc == 0, err
    summary = json.loads(out)
    assert summary["dataset_id"] == DATASET and summary["episodes"] == 2
    card = json.loads((tmp_path / DATASET / "card.json").read_text())
    assert card["env_id"] == "msdgrasp/GraspLift-v0" and card["env_version"] == 0 and card["seeds"] == [5, 6]
    assert card["steps"] == sum(e["steps"] for e in card["per_episode"]) and "# " + DATASET in (
        tmp_path / DATASET / "card.md").read_text()
    env = {**os.environ, "MINARI_DATASETS_PATH": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", REPLAY, DATASET], env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"episodes": 2, "steps": card["steps"], "seeds": [5, 6], "same": [True, True],
                   "env": "msdgrasp/GraspLift-v0"}
    # a second collection into the same id is refused before anything runs
    rc, _, err = _run_main(["collect", "--policy", "reactive", "--episodes", "1", "--out", str(tmp_path)])
    assert rc == 2 and "exists: remove it or give another --dataset-id" in err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".collect-")]  # no temporary folder left


@pytest.mark.parametrize("argv, message", [
    (["--episodes", "0"], "--episodes must be >= 1, got 0"),
    (["--dataset-id", "no version"], "is not a Minari id"),
    (["--policy", "nosuch.zip"], "nosuch.zip"),
])
def test_bad_collect_arguments_are_one_line_errors(tmp_path, argv, message):
    args = ["collect", "--policy", "fixed", "--out", str(tmp_path / "d"), *argv]
    rc, _, err = _run_main(args)
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "d").exists()


def test_a_clone_of_a_dataset_imitates_its_teacher_and_runs_as_a_policy_on_the_benchmark_task(tmp_path, monkeypatch):
    pytest.importorskip("stable_baselines3")
    monkeypatch.chdir(tmp_path)  # (relative folders, as the command line's defaults are)
    from msdgrasp.agents.evaluation import build_policy, evaluate_policy, trained_task_of
    from msdgrasp.agents.models import TrainConfig

    rc, _, err = _run_main(["collect", "--policy", "reactive", "--episodes", "3", "--out", "d", "--quiet"])
    assert rc == 0, err
    rc, out, err = _run_main(["clone", DATASET, "--datasets", "d", "--out", "bc", "--epochs", "60"])
    assert rc == 0, err
    summary = json.loads(out)
    model = str(tmp_path / "bc" / "best_model.zip")
    config, _ = trained_task_of([model])
    assert config == TrainConfig().env  # evaluated on the benchmark task, as every trained model
    clone = build_policy(model, config)
    assert clone.name == f"BC of {DATASET}"
    # it fits its teacher's actions (in [-1, 1]: an error of 0.05 is a few percent of the range) and, run on its
    # own, lifts as its teacher does at a friction where the teacher always lifts
    assert summary["demo_steps"] > 300 and summary["final_mse"] < 0.05, summary
    rows = evaluate_policy(clone, [0.6], 2, config, seed=3)
    assert rows[0]["success_rate"] >= 0.5


def test_clone_of_a_missing_dataset_is_a_one_line_error(tmp_path):
    rc, _, err = _run_main(["clone", "msdgrasp/none-v0", "--datasets", str(tmp_path), "--out", str(tmp_path / "o")])
    assert rc == 2 and "card.json" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()
