"""Sweeps on Ray: multi-seed training, hyper-parameter grids and evaluation as jobs on a local Ray (2 CPUs).

The specification: a runner changes where jobs run, never what they compute (the same numbers as local
processes or this process), results land in the driver's output folder from any node, and a bad sweep is a
one-line error before anything runs or is written.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from msdgrasp.agents import parallel  # noqa: E402
from msdgrasp.agents.evaluation import evaluate  # noqa: E402
from msdgrasp.agents.parallel import Runner, land, run_in_folder  # noqa: E402
from msdgrasp.agents.sweep import SweepConfig, run_sweep, sweep_points  # noqa: E402
from msdgrasp.cli.main import main  # noqa: E402
from msdgrasp.physics.config import ConfigError  # noqa: E402

#: a tiny but real training run: 512 PPO steps on 2 envs, one checkpoint, one validation episode
TINY = {"total_timesteps": 512, "n_envs": 2, "checkpoint_every": 256, "validation_episodes": 1,
        "validation_mu": [0.5], "ppo": {"n_steps": 128, "batch_size": 128, "n_epochs": 1, "use_sde": True}}


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray instance with 2 CPUs for the module (a Runner finds it and leaves it running)."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=2, include_dashboard=False, configure_logging=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_runners_return_results_in_job_order_and_report_each_once(local_ray):
    for runner in (Runner.processes(2), Runner.ray()):
        seen = []
        with runner:
            # jobs are module-level functions (pickled by reference): builtins here
            out = runner.run([(pow, (k, 2)) for k in range(6)], on_done=lambda k, r: seen.append((k, r)))
            if runner.is_ray:
                assert runner.capacity() == 2  # the local instance's CPUs
        assert out == [k * k for k in range(6)]
        assert sorted(seen) == [(k, k * k) for k in range(6)]


def test_a_failing_job_raises_in_the_driver(local_ray):
    for runner in (Runner.processes(2), Runner.ray()):
        with runner, pytest.raises(ValueError, match="job 1 failed"):
            runner.run([(pow, (0, 2)), (int, ("job 1 failed",))])


def _write_run(folder: str, text: str) -> dict:
    Path(folder).mkdir(parents=True, exist_ok=True)
    (Path(folder) / "model.txt").write_text(text)
    # a summary that names the model where it was written (as a run's train_summary.json does)
    (Path(folder) / "summary.json").write_text(json.dumps({"best_model": str(Path(folder) / "model.txt")}))
    return {"run": folder, "model": str(Path(folder) / "model.txt"), "nested": [folder + "x"]}


def test_a_job_on_another_node_lands_its_folder_in_the_drivers_output(tmp_path, monkeypatch):
    """A job on a node other than the driver's writes a temporary folder that travels back as an archive;
    the driver unpacks it where the job was told to write, and the result's paths point there."""
    target = tmp_path / "out" / "seed_3"
    monkeypatch.setattr(parallel, "_current_node", lambda: "node-b")
    res = run_in_folder(_write_run, str(target), "node-a", "weights")
    assert not target.exists()  # nothing was written on the driver's disk by the job itself
    assert res["run"] == str(target) and res["model"] == str(target / "model.txt")
    assert res["nested"][0].endswith("x") and not res["nested"][0].startswith(str(target))  # only whole path parts
    landed = land(res, target)
    assert (target / "model.txt").read_text() == "weights"
    # the files it wrote name where they landed, not the other node's temporary folder
    assert json.loads((target / "summary.json").read_text()) == {"best_model": str(target / "model.txt")}
    assert set(landed) == {"run", "model", "nested"}
    # on the driver's own node the job writes in place and nothing is shipped
    monkeypatch.setattr(parallel, "_current_node", lambda: "node-a")
    res = run_in_folder(_write_run, str(tmp_path / "here"), "node-a", "w2")
    assert land(res, tmp_path / "here") == res and (tmp_path / "here" / "model.txt").read_text() == "w2"


@pytest.fixture(scope="module")
def sb3_seeds(tmp_path_factory) -> Path:
    """Two seeds of a TINY finished SB3 run (copies: the same checkpoints) on 0.2 s episodes."""
    import shutil

    from msdgrasp.agents.models import TrainConfig
    from msdgrasp.agents.training import train
    from msdgrasp.physics.config import from_dict, to_dict

    runs = tmp_path_factory.mktemp("sb3_seeds")
    env = {**to_dict(TrainConfig().env), "time_limit_s": 0.2}
    train(from_dict(TrainConfig, {**TINY, "env": env}), runs / "seed_0", progress=False)
    shutil.copytree(runs / "seed_0", runs / "seed_1")
    return runs


def _picked(folder: Path) -> dict:
    """What a selection decided, without the time it took."""
    sel = json.loads((folder / "selection.json").read_text())
    return {"selection": {k: v for k, v in sel.items() if k != "selection_s"},
            "validation": json.loads((folder / "validation.json").read_text())}


def test_select_on_ray_ships_each_runs_checkpoints_and_picks_as_local_processes(sb3_seeds, tmp_path, local_ray,
                                                                               monkeypatch):
    from msdgrasp.agents.selection import _select_job, pack_run, plan_selection, select

    local = select(sb3_seeds, tmp_path / "local", validation_episodes=2, workers=2)
    on_ray = select(sb3_seeds, tmp_path / "ray", validation_episodes=2, runner=Runner.ray())
    assert [r["run"] for r in on_ray] == [r["run"] for r in local] == [str(sb3_seeds / f"seed_{k}") for k in (0, 1)]
    for k in (0, 1):
        a, b = _picked(tmp_path / "local" / f"seed_{k}"), _picked(tmp_path / "ray" / f"seed_{k}")
        assert a == b
        # the history names the run's own checkpoints, not the copy the job validated
        run = sb3_seeds / f"seed_{k}"
        assert [h["model"] for h in b["validation"]["history"]] == [
            str(run / "checkpoints" / "model_256.zip"), str(run / "checkpoints" / "model_512.zip"),
            str(run / "final_model.zip")]
    # a node that cannot read the run: the job validates the archive alone, its pick lands in the driver's folder
    plan = plan_selection(sb3_seeds / "seed_0", validation_episodes=2)
    archive = pack_run(plan)
    away = sb3_seeds.parent / "sb3_seeds_away"
    sb3_seeds.rename(away)
    try:
        monkeypatch.setattr(parallel, "_current_node", lambda: "node-b")
        target = tmp_path / "remote" / "seed_0"
        res = run_in_folder(_select_job, str(target), "node-a", plan, archive)
        assert not target.exists()
        land(res, target)
    finally:
        away.rename(sb3_seeds)
    assert _picked(target) == _picked(tmp_path / "local" / "seed_0")
    summary = json.loads((target / "train_summary.json").read_text())
    assert (summary["best_model"] == str(target / "best_model.zip")
            and summary["selected_from"] == str(sb3_seeds / "seed_0"))


def _sweep(**extra) -> SweepConfig:
    """The shipped smoke sweep (2 learning rates x 2 seeds of TINY runs), with ``extra`` fields changed."""
    from msdgrasp.physics.config import builtin_config, replace

    sweep = SweepConfig.load(builtin_config("sweep/smoke.yaml"))
    assert sweep.set == TINY
    return replace(sweep, **extra)


def test_a_sweep_on_ray_writes_ranked_per_point_multi_seed_reports_equal_to_local_processes(tmp_path, local_ray):
    sweep = _sweep()
    res_ray = run_sweep(sweep, tmp_path / "ray", Runner.ray(), progress=False)
    data = json.loads((tmp_path / "ray" / "sweep.json").read_text())
    assert [p["params"] for p in data["points"]] == [{"ppo.learning_rate": 1.0e-4}, {"ppo.learning_rate": 1.0e-3}]
    for point in data["points"]:
        folder = tmp_path / "ray" / f"point_{point['point']}"
        report = json.loads((folder / "seeds.json").read_text())  # the same report as `train --seeds`
        assert report["config"]["ppo"]["learning_rate"] == point["params"]["ppo.learning_rate"]
        assert [r["seed"] for r in report["per_seed"]] == [0, 1]
        for rec in report["per_seed"]:
            assert (folder / f"seed_{rec['seed']}" / "best_model.zip").is_file()
            assert rec["run"] == str(folder / f"seed_{rec['seed']}")
        # the aggregate is computed from the per-seed numbers it reports
        ratios = [r["peak_pinch_over_oracle_min"] for r in report["per_seed"]]
        assert point["aggregate"]["peak_pinch_over_oracle_min"]["mean"] == pytest.approx(np.mean(ratios))
    # ranked by mean success over mu 0.3-0.9, then by the pinch ratio
    keys = [(-data["points"][k]["aggregate"]["success_ref"]["mean"],
             data["points"][k]["aggregate"]["peak_pinch_over_oracle_min"]["mean"]) for k in data["ranking"]]
    assert keys == sorted(keys) and sorted(data["ranking"]) == [0, 1]
    md = (tmp_path / "ray" / "sweep.md").read_text()
    assert "| 1 |" in md and "ppo.learning_rate" in md and "reactive" in md and "(ray)" in md
    # where the jobs ran does not change what they computed
    res_proc = run_sweep(sweep, tmp_path / "proc", Runner.processes(2), progress=False)
    for a, b in zip(res_ray["points"], res_proc["points"]):
        assert [(s["seed"], s["peak_pinch_ref_N"], s["success_ref"]) for s in a["per_seed"]] == \
               [(s["seed"], s["peak_pinch_ref_N"], s["success_ref"]) for s in b["per_seed"]]


def test_ray_evaluation_equals_the_in_process_evaluation(tmp_path, local_ray):
    kw = dict(mus=[0.3, 0.6], episodes=1, progress=False, conditions=({"stiffness_scale": 1.5},))
    seq = evaluate(["fixed"], out_dir=tmp_path / "seq", **kw)
    par = evaluate(["fixed"], out_dir=tmp_path / "ray", runner=Runner.ray(), **kw)
    assert ([r["name"] for r in par["results"]] == [r["name"] for r in seq["results"]]
            == ["fixed2.5N", "reactive", "oracle"])
    for a, b in zip(seq["results"], par["results"]):
        assert a["rows"] == b["rows"]
    assert seq["oracle_minimal_force"] == par["oracle_minimal_force"]
    assert seq["unseen_conditions"] == par["unseen_conditions"]
    assert json.loads((tmp_path / "ray" / "evaluation.json").read_text())["evaluation"]["runner"] == "ray"


def test_every_point_is_validated_before_anything_runs(tmp_path):
    with pytest.raises(ConfigError, match=r"point 1 \(ppo.learning_rate=fast\).*learning_rate"):
        sweep_points(_sweep(grid={"ppo.learning_rate": [1.0e-4, "fast"]}))
    with pytest.raises(ConfigError, match=r"point 0 \(gamma_typo=0.9\).*unknown key 'gamma_typo'"):
        sweep_points(_sweep(grid={"gamma_typo": [0.9]}))
    with pytest.raises(ConfigError, match="seeds come from"):
        _sweep(grid={"seed": [1, 2]})
    with pytest.raises(ConfigError, match="allowed 1 ... 256"):
        _sweep(grid={"ppo.learning_rate": [1e-4 * (k + 1) for k in range(17)],
                     "log_std_init": [-1.0 - 0.1 * k for k in range(16)]})
    with pytest.raises(ConfigError, match="the value 0.0001 is given twice"):  # (one config trained twice)
        _sweep(grid={"ppo.learning_rate": [1e-4, 1e-4]})
    with pytest.raises(ConfigError, match="both in 'set' and in 'grid'"):
        _sweep(set={**TINY, "ppo.learning_rate": 1e-3})
    with pytest.raises(ConfigError, match="is a value, not a section"):
        sweep_points(_sweep(grid={"n_envs.x": [1]}))
    with pytest.raises(ConfigError, match="grid"):
        _sweep(grid={})
    out = tmp_path / "never"
    with pytest.raises(ConfigError):
        run_sweep(_sweep(grid={"ppo.gamma": [0.9, 1.5]}), out, Runner.processes(1), progress=False)
    assert not out.exists()


def _cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(args))
    return rc, out.getvalue(), err.getvalue()


def test_sweep_and_runner_command_line_errors_are_one_line_with_exit_2(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    good = tmp_path / "sweep.yaml"
    good.write_text(json.dumps({"set": TINY, "grid": {"ppo.learning_rate": [1.0e-4, 3.0e-4]}, "seeds": "0-4"}))
    rc, stdout, stderr = _cli("sweep", str(good), "--dry-run")
    assert rc == 0, stderr
    assert json.loads(stdout)["points"] == [{"ppo.learning_rate": 1.0e-4}, {"ppo.learning_rate": 3.0e-4}]
    bad = tmp_path / "bad.yaml"
    bad.write_text(json.dumps({"grid": {"ppo.gamma": [0.9, 1.5]}}))
    cases = [
        (("sweep", str(bad)), "bad.yaml point 1 (ppo.gamma=1.5)"),
        (("sweep", str(good), "--workers", "0"), "--workers must be >= 1"),
        (("sweep", str(good), "--address", "auto", "--workers", "2"), "the cluster's CPUs decide"),
        (("sweep", str(good), "--address", " "), "--address is empty"),
        (("train", "--ray"), "give --seeds"),
        (("sweep", str(tmp_path / "missing.yaml")), "not found"),
    ]
    for args, message in cases:
        rc, stdout, stderr = _cli(*args, "--out", str(tmp_path / "out"))
        assert rc == 2, (args, stdout, stderr)
        assert message in stderr and len(stderr.strip().splitlines()) == 1, (args, stderr)
    assert not (tmp_path / "out").exists() and not (tmp_path / "logs").exists()


def test_the_shipped_sweep_builds_every_point_on_the_default_training():
    from msdgrasp.agents.models import TrainConfig
    from msdgrasp.physics.config import builtin_config, replace

    points = sweep_points(SweepConfig.load(builtin_config("sweep/learning_rate.yaml")))
    rates = [p["ppo.learning_rate"] for p, _ in points]
    assert len(points) == 3 and 1.0e-3 in rates  # the default's rate is one of the points
    for params, cfg in points:
        # everything but the swept key is the default training
        assert replace(cfg, ppo={**cfg.ppo, "learning_rate": TrainConfig().ppo["learning_rate"]}) == TrainConfig()
