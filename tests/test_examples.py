"""The examples in examples/ run, each on a few steps, and print what their docstrings say they print.

Each runs as a user runs it: a fresh interpreter (this one's), the repository root as the working folder."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_example(name: str, *args: str, timeout: float = 600) -> str:
    """Run examples/<name> with ``args``; its stdout, after checking that it exits 0."""
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / name), *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, f"{name} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


def test_single_env_prints_each_step() -> None:
    out = run_example("single_env.py", "--steps", "4")
    assert "observation space (32,)" in out
    steps = [line for line in out.splitlines() if line.startswith("step ")]
    assert len(steps) == 4 and all("reward" in s and "peak" in s for s in steps)
    assert "return over 4 steps" in out and "is_success" in out


def test_vector_env_with_gymnasium_vector_wrappers() -> None:
    # random actions end some of 8 episodes within 150 steps (the seed fixes which): the statistics wrapper reports them
    out = run_example("vector_env.py", "--num-envs", "8", "--steps", "150")
    assert "GraspLiftVectorEnv: 8 envs, autoreset NEXT_STEP, single observation (32,)" in out
    assert "episode return" in out and "episodes finished, success rate" in out
    assert "observation after NormalizeObservation" in out


def test_cleanrl_ppo_runs_its_iterations(tmp_path: Path) -> None:
    saved = tmp_path / "agent.pt"
    out = run_example("cleanrl_ppo.py", "--total-timesteps", "512", "--num-envs", "4", "--num-steps", "64",
                      "--update-epochs", "2", "--save", str(saved))
    assert "iteration 1/2" in out and "iteration 2/2  steps 512" in out
    import torch

    state = torch.load(saved)
    assert state["actor_logstd"].shape == (1, 2) and state["critic.0.weight"].shape == (64, 32)


@pytest.mark.slow
def test_own_policy_through_api_and_command_line(tmp_path: Path) -> None:
    out = run_example("own_policy.py", "--episodes", "1", "--out", str(tmp_path))
    for mu in ("0.3", "0.5", "0.8"):
        assert f"mu {mu}: success" in out
    assert "msdgrasp evaluate exited 0" in out
    suite = json.loads((tmp_path / "suite_in_range.json").read_text())
    assert [r["spec"] for r in suite["results"]] == ["steady"]  # --no-baselines: the own policy alone
    assert [c["name"] for c in suite["conditions"]] == ["nominal"] and suite["results"][0]["cells"][0]["episodes"] == 4


@pytest.mark.slow
def test_plain_sb3_ppo_on_v2() -> None:
    out = run_example("plain_sb3_ppo.py", "--steps", "64", "--eval-episodes", "1")
    assert "deterministic policy: mu 0.3: success" in out and "mu 0.9" in out
