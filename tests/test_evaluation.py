"""Evaluation across friction (``msdgrasp evaluate``), the RL subcommands' wiring, and ``msdgrasp record``.

Runtime: the oracle's bisection costs ~10 s per mu (cached per process), so the oracle runs at two mu
values only and the CLI run at two more; episodes are few.
"""

from __future__ import annotations

import contextlib
import dataclasses
import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from msdgrasp.cli.main import build_parser, main
from msdgrasp.agents.controllers import FixedForcePolicy, OraclePolicy, minimal_force
from msdgrasp.agents.evaluation import CSV_COLUMNS, PULL_STARTED_M, evaluate_policy, parse_mu_grid
from msdgrasp.agents.protocol import EVALUATION_SEED
from msdgrasp.envs.core import GraspLiftConfig
from msdgrasp.envs.grasp_lift import GraspLiftEnv
from msdgrasp.physics.config import ConfigError, from_dict

CONFIG = GraspLiftConfig()
ORACLE_MUS = (0.3, 0.9)
FIXED_NAME = FixedForcePolicy(CONFIG).name  # the default fixed force ('fixed' spec), e.g. 'fixed2.5N'
OUTPUTS = ("evaluation.json", "evaluation.csv", "success_vs_mu.png", "pinch_vs_mu.png")


def _run_main(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


# ------------------------------------------------------------------------------------------------
# mu grid
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, expected", [
    ("0.2:1.0:0.1", [0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]),
    ("0.5:0.6:0.1", [0.5, 0.6]),
    ("0.2:1.0:0.3", [0.2, 0.5, 0.8]),  # stop not on the grid: not added
    ("0.4:0.4:0.1", [0.4]),
    ("0.3,0.5", [0.3, 0.5]),
    (" 0.9 , 0.3 ", [0.3, 0.9]),
    ("0.5", [0.5]),
    ("0", [0.0]),
])
def test_parse_mu_grid_good(text, expected):
    got = parse_mu_grid(text)
    assert isinstance(got, np.ndarray)
    assert got.tolist() == pytest.approx(expected, abs=1e-12)
    assert len(got) == len(expected)


def test_parse_mu_grid_default_is_inclusive_and_exact():
    got = parse_mu_grid("0.2:1.0:0.1")
    assert len(got) == 9 and got[0] == 0.2 and got[-1] == 1.0
    assert got[1] == 0.3  # rounded: no 0.30000000000000004 (recording names, oracle cache keys)
    assert len(parse_mu_grid("0:1:0.01")) == 101  # the largest grid allowed


@pytest.mark.parametrize("text, rule", [
    ("a:1:0.1", "not a number"),
    ("0.3,abc", "not a number"),
    ("0.2:1.0:0", "step must be > 0"),
    ("0.2:1.0:-0.1", "step must be > 0"),
    ("1.0:0.2:0.1", "start (1) must be <= stop (0.2)"),
    ("-0.1:0.5:0.1", "negative"),
    ("0.3,-0.5", "negative"),
    ("0:1:0.001", "at most 101"),
    ("0.2:1.0", "three fields"),
    ("0.3,,0.5", "empty entry"),
    ("0.2:nan:0.1", "finite"),
])
def test_parse_mu_grid_malformed(text, rule):
    with pytest.raises(ConfigError) as exc:
        parse_mu_grid(text)
    msg = str(exc.value)
    assert repr(text) in msg, msg  # names the grid
    assert rule in msg, msg  # and the rule


def test_parse_mu_grid_empty():
    with pytest.raises(ConfigError, match="empty"):
        parse_mu_grid("  ")


# ------------------------------------------------------------------------------------------------
# policies across mu
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def envs():
    """Shared vector envs (keyed by config and batch size) for evaluate_policy."""
    return {}


@pytest.fixture(scope="module")
def fixed_default_rows(envs):
    """The default fixed-force baseline (FixedForcePolicy(), what the 'fixed' spec runs) at the oracle's mu values."""
    return evaluate_policy(FixedForcePolicy(CONFIG), ORACLE_MUS, episodes=4, config=CONFIG, seed=0, _envs=envs)


def test_fixed_high_force_succeeds_at_high_friction(envs):
    (row,) = evaluate_policy(FixedForcePolicy(CONFIG, force_N=2.5), [0.8], episodes=4, config=CONFIG, seed=0,
                             _envs=envs)
    assert row["episodes"] == 4 and row["mu"] == 0.8
    assert row["success_rate"] >= 0.75, row
    # the controller regulates the pinch force at its set-point
    assert 2.3 < row["mean_peak_pinch_N"] < 2.8, row
    assert row["max_peak_pinch_N"] >= row["mean_peak_pinch_N"]
    assert 0 < row["mean_pinch_N"] < row["mean_peak_pinch_N"]
    assert math.isfinite(row["mean_time_to_lift_s"]) and 0 < row["mean_time_to_lift_s"] < CONFIG.time_limit_s


def test_oracle_succeeds_with_less_force_than_fixed_baseline(envs, fixed_default_rows):
    rows = evaluate_policy(OraclePolicy(CONFIG), ORACLE_MUS, episodes=4, config=CONFIG, seed=0, _envs=envs)
    for row, base in zip(rows, fixed_default_rows):
        assert row["mu"] == base["mu"]
        assert row["success_rate"] >= 0.75, row
        assert row["mean_peak_pinch_N"] < base["mean_peak_pinch_N"], (row, base)
        # the oracle holds about (1 + margin) x the minimal slip-free force of this mu
        fmin = minimal_force(CONFIG, row["mu"])
        assert fmin <= row["mean_peak_pinch_N"] <= 1.35 * fmin, (row, fmin)
    # slipperier tissue needs more force
    assert rows[0]["mean_peak_pinch_N"] > rows[1]["mean_peak_pinch_N"]


# ------------------------------------------------------------------------------------------------
# the evaluate CLI
# ------------------------------------------------------------------------------------------------

CLI_MU = "0.5:0.6:0.1"


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate")
    rc, stdout, stderr = _run_main(["evaluate", "--policy", "fixed", "--mu-grid", CLI_MU, "--episodes", "2",
                                    "--out", str(out), "--quiet", "--no-unseen"])
    return rc, stdout, stderr, out


def test_cli_evaluate_writes_the_four_files(cli_run):
    rc, stdout, stderr, out = cli_run
    assert rc == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(OUTPUTS)  # no temp files left behind
    for name in OUTPUTS:
        assert (out / name).stat().st_size > 0
        assert str(out / name) in stdout
    for name in ("success_vs_mu.png", "pinch_vs_mu.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(out / "evaluation.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == CSV_COLUMNS
    # the slip-reactive controller and the oracle are always evaluated beside the asked-for policy
    assert [(r["policy"], float(r["mu"]), int(r["episodes"])) for r in rows] == [
        (name, mu, 2) for name in (FIXED_NAME, "reactive", "oracle") for mu in (0.5, 0.6)]
    data = json.loads((out / "evaluation.json").read_text())
    assert data["config"]["randomization"]["mu_range"] == list(CONFIG.randomization.mu_range)
    assert data["evaluation"]["mu_grid"] == [0.5, 0.6]
    # the sealed evaluation seeds by default, and the result says so
    assert data["evaluation"]["seeds"] == [EVALUATION_SEED, EVALUATION_SEED + 1]
    assert data["seeds"] == {"first": EVALUATION_SEED, "count": 2, "sealed": True}
    assert f"evaluation seeds {EVALUATION_SEED}..{EVALUATION_SEED + 1}: sealed" in stdout
    pol = data["results"][0]
    assert [p["spec"] for p in data["results"]] == ["fixed", "reactive", "oracle"]
    assert pol["spec"] == "fixed" and pol["name"] == FIXED_NAME and len(pol["rows"]) == 2
    curve = data["oracle_minimal_force"]
    assert curve["mu"] == [0.5, 0.6]
    assert curve["minimal_force_N"] == pytest.approx([minimal_force(CONFIG, 0.5), minimal_force(CONFIG, 0.6)])
    # csv and json agree
    for r, j in zip(rows, pol["rows"]):
        for col in CSV_COLUMNS[2:-1]:  # (NaN, e.g. no reference force here, is null in the JSON)
            expected = float("nan") if j[col] is None else j[col]
            assert float(r[col]) == pytest.approx(expected, rel=1e-5, nan_ok=True), col
    assert FIXED_NAME in stdout and "success" in stdout  # the table


def _hand_episode(env: GraspLiftEnv, seed: int, mu: float) -> dict[str, float]:
    """One episode of the default fixed-force policy on a single env (on its task), metrics from the infos alone."""
    config = env.config
    policy = FixedForcePolicy(config)
    obs, info = env.reset(seed=seed, options={"mu": mu})
    policy.reset([info])
    pinches, stresses, ttl, before_pull, setpoints = [], [], float("nan"), 0.0, []
    for step in range(1, config.max_episode_steps + 1):
        action = policy.act(obs[None])[0]
        setpoints.append((0.5 * (np.clip(action[0], -1, 1) + 1)) ** config.pinch_action_exponent
                         * config.max_pinch_force_N)
        obs, _, terminated, truncated, info = env.step(action)
        pinches.append(info["pinch_force_N"])
        if info["travel_m"] < PULL_STARTED_M:  # the grasper has not started pulling yet
            before_pull = max(before_pull, info["pinch_force_N"])
        stresses.append(info["peak_stress_pa"])
        if math.isnan(ttl) and info["lifted_m"] >= config.lift_target_m:
            ttl = step * config.agent_dt_s
        if terminated or truncated:
            break
    return {"success": bool(info["is_success"]), "peak_pinch_N": max(pinches), "mean_pinch_N": float(np.mean(pinches)),
            "peak_pinch_before_pull_N": before_pull, "setpoint_change_N": float(np.mean(np.abs(np.diff(setpoints)))),
            "slip_mm": info["slip_distance_m"] * 1e3, "peak_stress_kPa": max(stresses) * 1e-3, "time_to_lift_s": ttl,
            "steps": step}


def test_json_values_match_episodes_run_by_hand(cli_run):
    rc, _, stderr, out = cli_run
    assert rc == 0, stderr
    data = json.loads((out / "evaluation.json").read_text())
    row = next(r for r in data["results"][0]["rows"] if r["mu"] == 0.5)
    # (the task the command evaluates controllers on: the benchmark task)
    env = GraspLiftEnv(from_dict(GraspLiftConfig, data["config"], where="evaluation.json"))
    hand = [_hand_episode(env, seed, 0.5) for seed in (EVALUATION_SEED, EVALUATION_SEED + 1)]
    per = row["per_episode"]
    assert per["success"] == [h["success"] for h in hand]
    assert per["steps"] == [h["steps"] for h in hand]
    for key in ("peak_pinch_N", "peak_pinch_before_pull_N", "mean_pinch_N", "setpoint_change_N", "slip_mm",
                "peak_stress_kPa", "time_to_lift_s"):
        assert per[key] == pytest.approx([h[key] for h in hand], rel=1e-6, nan_ok=True), key
    assert row["success_rate"] == pytest.approx(np.mean([h["success"] for h in hand]))
    assert row["mean_peak_pinch_N"] == pytest.approx(np.mean([h["peak_pinch_N"] for h in hand]), rel=1e-6)
    assert row["max_peak_pinch_N"] == pytest.approx(max(h["peak_pinch_N"] for h in hand), rel=1e-6)
    assert row["mean_pinch_N"] == pytest.approx(np.mean([h["mean_pinch_N"] for h in hand]), rel=1e-6)
    assert row["mean_slip_mm"] == pytest.approx(np.mean([h["slip_mm"] for h in hand]), rel=1e-6)
    assert row["mean_peak_stress_kPa"] == pytest.approx(np.mean([h["peak_stress_kPa"] for h in hand]), rel=1e-6)
    lifted = [h["time_to_lift_s"] for h in hand if not math.isnan(h["time_to_lift_s"])]
    if lifted:
        assert row["mean_time_to_lift_s"] == pytest.approx(np.mean(lifted), rel=1e-6)
    else:
        assert row["mean_time_to_lift_s"] is None
    assert row["episodes"] == 2


@pytest.mark.parametrize("extra, needle", [
    (["--policy", "fixed", "--mu-grid", "0.6:0.2:0.1"], "'0.6:0.2:0.1'"),
    (["--policy", "fixed", "--mu-grid", "0.2,x"], "not a number"),
    (["--policy", "nonexistent.zip"], "nonexistent.zip"),
    (["--policy", "fixed", "--policy", "nonexistent.zip"], "model file not found"),
    (["--policy", "bogus"], "unknown policy 'bogus'"),
    (["--policy", "fixed:-1"], "fixed:-1"),
])
def test_cli_evaluate_bad_input_exits_2_and_writes_nothing(tmp_path, monkeypatch, extra, needle):
    import msdgrasp.agents.evaluation as evaluation

    def must_not_run(*args, **kwargs):
        raise AssertionError("episodes ran before every input was validated")

    monkeypatch.setattr(evaluation, "evaluate_policy", must_not_run)
    out = tmp_path / "out"
    out.mkdir()
    rc, stdout, stderr = _run_main(["evaluate", *extra, "--episodes", "1", "--out", str(out), "--quiet"])
    assert rc == 2, (stdout, stderr)
    assert needle in stderr, stderr
    assert stderr.startswith("msdgrasp evaluate: error:") and stderr.count("\n") == 1  # one line, no traceback
    assert list(out.iterdir()) == []


def test_rl_subcommands_are_wired():
    parser = build_parser()
    a = parser.parse_args(["train", "--algo", "sac", "--total-timesteps", "100", "--n-envs", "2", "--seed", "3",
                           "--resume", "runs/x", "--quiet"])  # (--algo: the old name of --learner)
    assert (a.learner, a.total_timesteps, a.n_envs, a.seed, a.resume, a.quiet) == (
        "sac", 100, 2, 3, Path("runs/x"), True)
    # (--out defaults in the handler: logs/train for SB3, logs/train_torch for the torch PPO)
    assert a.config is None and a.out is None and a.backend is None
    assert parser.parse_args(["train", "--learner", "rsl"]).learner == "rsl"
    e = parser.parse_args(["evaluate"])
    # (--episodes: 10 on the mu grid, the protocol's with --suite; --seed: the first sealed evaluation seed)
    assert (e.policy, e.mu_grid, e.episodes, e.seed, e.out, e.record) == (
        None, None, None, EVALUATION_SEED, Path("logs/evaluate"), False)
    r = parser.parse_args(["record", "--policy", "fixed"])
    assert (r.mu, r.out) == (0.5, Path("logs/record/episode.rrd"))
    s = parser.parse_args(["soak"])
    assert (s.steps, s.n_envs, s.out) == (1_000_000, 16, Path("logs/soak"))
    p = parser.parse_args(["replay", "x.rrd", "--print-command"])
    assert p.file == Path("x.rrd") and p.print_command
    for args in (a, e, r, s, p):
        assert callable(args.func)


# ------------------------------------------------------------------------------------------------
# record
# ------------------------------------------------------------------------------------------------


def test_cli_record_writes_a_recording(tmp_path, monkeypatch):
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    for var in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_CACHE_HOME", "XDG_STATE_HOME"):
        monkeypatch.setenv(var, str(home / var.lower()))
    path = tmp_path / "rec" / "episode.rrd"
    rc, stdout, stderr = _run_main(["record", "--policy", "fixed:2.5", "--mu", "0.8", "--seed", "1",
                                    "--out", str(path)])
    assert rc == 0, stderr
    assert path.is_file() and path.stat().st_size > 1000
    assert path.read_bytes()[:3] == b"RRF"
    summary = json.loads(stdout)
    assert summary["path"] == str(path) and summary["size_bytes"] == path.stat().st_size
    assert summary["policy"] == "fixed:2.5" and summary["mu"] == 0.8 and summary["steps"] > 0
    assert summary["success"] is True  # fixed 2.5 N lifts at mu 0.8 (see the test above)
    assert [p.name for p in path.parent.iterdir()] == ["episode.rrd"]  # no temp files left


def test_cli_record_bad_policy_exits_2(tmp_path):
    path = tmp_path / "rec" / "episode.rrd"
    rc, _, stderr = _run_main(["record", "--policy", "nonexistent.zip", "--out", str(path)])
    assert rc == 2 and "nonexistent.zip" in stderr
    assert not path.exists()


def test_unseen_tissue_options_build_an_env_for_them():
    """Pinning a stiffness above the training range evaluates on that tissue (the env gets the substeps it
    needs), and the pinned scale is what the episode runs with."""
    from msdgrasp.agents.controllers import FixedForcePolicy

    pol = FixedForcePolicy(CONFIG, 2.5)
    envs: dict = {}
    (row,) = evaluate_policy(pol, [0.5], 2, CONFIG, _envs=envs, options={"stiffness_scale": 1.5})
    ((cfg, _), env), = envs.items()
    assert cfg.randomization.stiffness_scale_range[1] == 1.5 and env.core.sim.kscale[0] == 1.5
    assert row["success_rate"] == 1.0  # the cautious 2.5 N grip also holds a stiffer spleen


def test_policy_patterns_expand_or_fail(tmp_path):
    from msdgrasp.agents.evaluation import expand_policy_specs
    from msdgrasp.physics.config import ConfigError

    for k in (1, 0):
        (tmp_path / f"seed_{k}").mkdir()
        (tmp_path / f"seed_{k}" / "best_model.zip").write_bytes(b"")
    got = expand_policy_specs([str(tmp_path / "seed_*" / "best_model.zip"), "fixed"])
    assert got == [str(tmp_path / "seed_0" / "best_model.zip"), str(tmp_path / "seed_1" / "best_model.zip"), "fixed"]
    with pytest.raises(ConfigError, match="no saved model matches"):
        expand_policy_specs([str(tmp_path / "nothing_*.zip")])


def test_an_episodes_result_does_not_depend_on_the_batch_it_runs_in():
    """Every (mu, episode) pair runs in one batch by default (SIMD lanes from 16 tissues); capped at 4 envs the
    same episodes run in chunks, tissue by tissue: the results are the same, number for number."""
    import dataclasses

    cfg = dataclasses.replace(CONFIG, time_limit_s=0.5)
    pol = FixedForcePolicy(cfg, force_N=2.0)
    together = evaluate_policy(pol, [0.3, 0.6, 0.9], episodes=6, config=cfg, seed=3)
    apart = evaluate_policy(pol, [0.3, 0.6, 0.9], episodes=6, config=cfg, seed=3, n_envs=4)
    assert [r["mu"] for r in together] == [0.3, 0.6, 0.9] and all(r["episodes"] == 6 for r in together)
    assert json.dumps(together, sort_keys=True) == json.dumps(apart, sort_keys=True)


class _BangBang:
    """Pinch set-point 5 N and 0 N in turn (the force loop then runs at its speed limit both ways), no pull."""

    name = "bangbang"

    def reset(self, infos):
        self.k = 0

    def act(self, obs):
        self.k += 1
        return np.tile([1.0 if self.k % 2 else -1.0, -1.0], (len(obs), 1))


def test_the_setpoint_change_measures_how_far_the_policy_moves_its_pinch_setpoint_each_step():
    """A policy that commands 5 N and 0 N in turn moves its set-point by 5 N every step; a fixed force by none."""
    cfg = dataclasses.replace(CONFIG, time_limit_s=0.2)
    (row,) = evaluate_policy(_BangBang(), [0.5], episodes=2, config=cfg)
    assert row["mean_setpoint_change_N"] == pytest.approx(cfg.max_pinch_force_N)
    assert row["per_episode"]["setpoint_change_N"] == pytest.approx([cfg.max_pinch_force_N] * 2)
    (row,) = evaluate_policy(FixedForcePolicy(cfg), [0.5], episodes=2, config=cfg)
    assert row["mean_setpoint_change_N"] == 0.0


ROBUST_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "train" / "experiments" / "R-robust-privileged.yaml"


def test_cli_evaluate_training_task_runs_controllers_on_the_episodes_that_training_draws(tmp_path):
    from msdgrasp.agents.models import TrainConfig

    rc, stdout, stderr = _run_main(["evaluate", "--training-task", str(ROBUST_CONFIG), "--policy", "fixed",
                                    "--mu-grid", "0.5", "--episodes", "1", "--out", str(tmp_path), "--quiet",
                                    "--no-unseen"])
    assert rc == 0, stderr
    drawn = TrainConfig.load(ROBUST_CONFIG).training_task().randomization
    assert drawn.sensor_noise_N > TrainConfig().env.randomization.sensor_noise_N  # the perturbations, not the task's
    data = json.loads((tmp_path / "evaluation.json").read_text())
    assert data["config"]["randomization"]["sensor_noise_N"] == drawn.sensor_noise_N
    assert data["config"]["randomization"]["pose_offset_m"] == drawn.pose_offset_m
    # the table shows what the training's reward makes of each controller
    assert "return" in stdout.splitlines()[0]
    assert all(math.isfinite(r["rows"][0]["mean_return"]) for r in data["results"])


def test_cli_evaluate_training_task_refuses_models_and_the_suite(tmp_path):
    rc, _, err = _run_main(["evaluate", "--training-task", str(ROBUST_CONFIG), "--policy", str(tmp_path / "m.zip"),
                            "--out", str(tmp_path / "x")])
    assert rc == 2 and "--training-task runs controllers only" in err and len(err.strip().splitlines()) == 1
    rc, _, err = _run_main(["evaluate", "--suite", "robustness", "--training-task", str(ROBUST_CONFIG),
                            "--out", str(tmp_path / "y")])
    assert rc == 2 and "drop --training-task" in err
    rc, _, err = _run_main(["evaluate", "--training-task", str(tmp_path / "none.yaml"), "--policy", "fixed",
                            "--out", str(tmp_path / "z")])
    assert rc == 2 and "no such file" in err
    assert not (tmp_path / "x").exists() and not (tmp_path / "z").exists()
