"""The controller registry (agents/controller_registry.py): a controller registered in one entry, with its class, runs
through ``msdgrasp evaluate`` and the robustness suite without a change anywhere else; its spec's options are checked
through its settings record; the built-in controllers keep their names, flags and display names."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json

import numpy as np
import pytest

from msdgrasp.agents import controllers
from msdgrasp.agents.controllers import (
    SpecOptions, baselines, check_controller_spec, controller_names, display_name, get_controller, is_controller,
    make_policy, register_controller, residual_bases, spec_forms, suite_baselines, unregister_controller,
)
from msdgrasp.agents.evaluation import check_policy_spec
from msdgrasp.agents.models import TrainConfig
from msdgrasp.cli.main import main
from msdgrasp.envs.core import pinch_action, pull_action
from msdgrasp.physics.config import ConfigError, from_dict, replace

TOY = "constgrip"


@dataclasses.dataclass(frozen=True)
class ConstantGripSettings:
    force_N: float = 2.0  # the pinch set-point held from the first step, N

    def __post_init__(self) -> None:
        if not 0 < self.force_N <= 5:
            raise ValueError(f"force_N must be in (0, 5], got {self.force_N!r}")


class ConstantGrip:
    """A toy controller: the same pinch set-point every step; the pull starts after HOLD_STEPS steps."""

    HOLD_STEPS = 20

    def __init__(self, config, force_N: float = 2.0) -> None:
        ConstantGripSettings(force_N)
        self.config, self.force_N, self.name = config, float(force_N), TOY
        self._steps = 0

    def reset(self, infos) -> None:
        self._steps = 0

    def act(self, obs: np.ndarray) -> np.ndarray:
        self._steps += 1
        pull = float(pull_action(0.5, self.config)) if self._steps > self.HOLD_STEPS else -1.0
        action = [float(pinch_action(self.force_N, self.config)), pull]
        return np.tile(np.asarray(action, dtype=np.float32), (np.atleast_2d(obs).shape[0], 1))


@pytest.fixture
def toy():
    entry = register_controller(TOY, ConstantGrip, settings=ConstantGripSettings, display="constant grip",
                                options=SpecOptions(keys={"force": "force_N"}, usage="force=N"),
                                needs_setpoint_interface=True, help="a constant pinch set-point (a test's toy)")
    try:
        yield entry
    finally:
        unregister_controller(TOY)


@pytest.fixture
def stub_oracle(monkeypatch):
    monkeypatch.setattr(controllers, "_minimal_force_cached", lambda *args: 1.25)  # (the oracle's bisection: minutes)


def _run_main(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def test_a_registered_controller_runs_through_msdgrasp_evaluate(toy, stub_oracle, tmp_path):
    rc, stdout, stderr = _run_main(["evaluate", "--policy", f"{TOY}:force=1", "--policy", f"{TOY}:force=2.5",
                                    "--mu-grid", "0.5", "--episodes", "2", "--no-unseen", "--out", str(tmp_path),
                                    "--quiet"])
    assert rc == 0, stderr
    data = json.loads((tmp_path / "evaluation.json").read_text())
    by_spec = {r["spec"]: r for r in data["results"]}
    # beside the registry's baselines; a spec with settings names its policy
    assert set(by_spec) == {f"{TOY}:force=1", f"{TOY}:force=2.5", "reactive", "oracle"}
    assert by_spec[f"{TOY}:force=1"]["name"] == f"{TOY}:force=1"
    light, firm = (by_spec[f"{TOY}:force={f}"]["rows"][0]["mean_peak_pinch_N"] for f in ("1", "2.5"))
    assert 0 < light < firm  # (the option reached the controller: a firmer set-point, a firmer grip)
    assert display_name(f"{TOY}:force=2.5") == "constant grip (force=2.5)"


def test_a_registered_controller_runs_through_the_robustness_suite(toy, stub_oracle, tmp_path):
    from msdgrasp.agents.robustness import run_suite

    result = run_suite([f"{TOY}:force=2"], tmp_path, episodes=1, only=["nominal"], progress=False, baselines=False)
    [res] = result["results"]
    assert res["spec"] == f"{TOY}:force=2" and [c["condition"] for c in res["cells"]] == ["nominal"]
    assert res["cells"][0]["episodes"] == len(result["mu_grid"])
    assert f"| {TOY}:force=2 |" in (tmp_path / "leaderboard_robustness.md").read_text()


def test_bad_options_of_a_registered_controller_are_one_line_config_errors(toy, tmp_path):
    for spec, needle in ((f"{TOY}:speed=1", "takes keys force; got 'speed=1'"),
                         (f"{TOY}:force=fast", "force expects a number"),
                         (f"{TOY}:force=9", "force_N must be in (0, 5]"),
                         (f"{TOY}:2", "takes keys force")):
        with pytest.raises(ConfigError) as info:
            check_policy_spec(spec)
        assert needle in str(info.value) and spec in str(info.value) and "\n" not in str(info.value)
    rc, _, stderr = _run_main(["evaluate", "--policy", f"{TOY}:force=9", "--out", str(tmp_path / "x"), "--quiet"])
    assert rc == 2 and "force_N must be in (0, 5]" in stderr and stderr.count("\n") == 1
    assert not (tmp_path / "x").exists()
    # (it needs the set-point interface: refused on a travel pull, naming both settings)
    travel = replace(TrainConfig().env, pull_action="travel")
    with pytest.raises(ConfigError, match=f"{TOY} needs jaw_action: force and pull_action: forward_speed"):
        make_policy(TOY, travel)


def test_unregistering_forgets_the_controller_and_names_stay_unique(toy):
    assert is_controller(f"{TOY}:force=1") and TOY in controller_names() and get_controller(TOY) is toy
    with pytest.raises(ValueError, match="registered twice"):
        register_controller(TOY, ConstantGrip)
    for bad in ("a:b", "", "dir/x", "x*"):
        with pytest.raises(ValueError, match="cannot be a policy spec"):
            register_controller(bad, ConstantGrip)
    unregister_controller(TOY)
    try:
        assert not is_controller(TOY) and TOY not in controller_names()
        with pytest.raises(ConfigError, match=f"unknown policy '{TOY}'"):
            check_policy_spec(TOY)
        with pytest.raises(ConfigError, match="unknown controller"):
            unregister_controller(TOY)
    finally:  # (the fixture unregisters it again)
        register_controller(TOY, ConstantGrip)


def test_a_residual_base_is_what_the_registry_flags(toy):
    """The training config asks the registry: a controller not flagged as a residual base is refused, naming those
    that are; a flagged one is taken with its settings."""
    short = {"total_timesteps": 64, "n_envs": 2}
    with pytest.raises(ConfigError, match="residual_base = 'constgrip' is not a controller a residual may correct"):
        from_dict(TrainConfig, {**short, "residual_base": TOY})
    assert {e.name for e in residual_bases()} == {"slipfeedback", "reactive", "fixed"}
    assert from_dict(TrainConfig, {**short, "residual_base": "fixed:2"}).residual_base == "fixed:2"


def test_the_built_in_controllers_keep_their_specs_flags_and_display_names():
    assert controller_names()[:6] == ("fixed", "reactive", "slipfeedback", "oracle", "zero", "idle")
    assert spec_forms()[:3] == ["fixed", "fixed:<N>", "reactive"]
    assert baselines() == ("reactive", "oracle")
    bench = TrainConfig().env  # (a force set-point and a forward pull: the slip-feedback controller's interface)
    assert suite_baselines(bench) == ("reactive", "oracle", "fixed", "slipfeedback")
    assert "slipfeedback" not in suite_baselines(replace(bench, pull_action="travel"))
    assert make_policy("fixed:2", bench).name == "fixed2N" and display_name("fixed2N") == "fixed 2 N"
    assert display_name("reactive") == "slip-reactive" and display_name("slipfeedback") == "slip-feedback"
    assert display_name("PPO (seed 3)") == "PPO (seed 3)"
    assert check_controller_spec("slipfeedback:gain=0.8").name == "slipfeedback"
    with pytest.raises(ConfigError, match="reactive takes no options"):
        check_policy_spec("reactive:gain=1")
