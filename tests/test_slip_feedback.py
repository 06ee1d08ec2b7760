"""The slip-feedback controller: a light grip tightened in proportion to the slip since lifting began.

What it must be: blind to the force readings (so force-sensor noise and bias cannot cost it force), monotone in
its grip, and on the benchmark task a lighter grip than the slip-reactive controller that still lifts.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msdgrasp.agents.controllers import SlipFeedbackPolicy, make_policy
from msdgrasp.agents.evaluation import check_policy_spec, evaluate_policy
from msdgrasp.envs.core import GraspLiftConfig, benchmark_config
from msdgrasp.envs.task import OBS, obs_group
from msdgrasp.physics.config import ConfigError

TASK = benchmark_config()


def _frame(n: int = 1) -> np.ndarray:
    return np.zeros((n, len(OBS)), dtype=np.float32)


def test_its_actions_do_not_read_the_force_readings():
    rng = np.random.default_rng(0)
    a, b = SlipFeedbackPolicy(TASK), SlipFeedbackPolicy(TASK)
    a.reset([{}] * 4)
    b.reset([{}] * 4)
    for t in range(40):
        obs = _frame(4)
        obs[:, obs_group("contact_fraction")] = 0.5 if t > 3 else 0.0
        obs[:, OBS["lift_slip"]] = max(0.0, (t - 20) * 0.02)
        noisy = obs.copy()
        for group in ("normal_force", "tangential_force", "friction_use"):
            noisy[:, obs_group(group)] = rng.normal(0.0, 1.0, size=(4, 3))
        assert np.array_equal(a.act(obs), b.act(noisy))


def test_the_grip_follows_the_slip_and_never_eases():
    pol = SlipFeedbackPolicy(TASK, initial_force_N=0.5, gain_N_per_mm=1.0, max_force_N=2.0)
    pol.reset([{}])
    tol_mm = TASK.lift_slip_tolerance_m * 1e3
    forces = []
    for slip_mm in (0.0, 0.3, 0.8, 0.4, 0.0, 5.0):
        obs = _frame()
        obs[0, OBS["lift_slip"]] = slip_mm / tol_mm
        pol.act(obs)
        forces.append(float(pol.force[0]))
    assert forces == pytest.approx([0.5, 0.8, 1.3, 1.3, 1.3, 2.0])  # 0.5 N + 1 N/mm, the peak kept, capped


def test_it_pulls_only_once_the_jaws_have_held_for_the_settling_steps():
    pol = SlipFeedbackPolicy(TASK, contact_jaws=2, settle_steps=3)
    pol.reset([{}])
    pulls = []
    for t in range(8):
        obs = _frame()
        obs[0, obs_group("contact_fraction")] = [0.4, 0.3, 0.0] if t >= 2 else [0.4, 0.0, 0.0]
        pulls.append(float(pol.act(obs)[0, 1]))
    assert pulls[:5] == [-1.0] * 5 and pulls[5:] == [0.0] * 3  # two jaws touch from step 2; pull (10 mm/s) after 3


def _held_frame(pinch_N: float) -> np.ndarray:
    """Three jaws touching, the pinch reading ``pinch_N`` in all (a third on each jaw)."""
    obs = _frame()
    obs[0, obs_group("contact_fraction")] = 0.5
    obs[0, obs_group("normal_force")] = pinch_N / 3 / TASK.reference_force_N
    return obs


def test_a_pinch_gated_pull_waits_for_the_grip_and_then_keeps_pulling():
    """With pinch_gate the pull starts only once the pinch reading reaches that share of the set-point (the
    contact rule met too), and a later dip of the reading does not stop it."""
    pol = SlipFeedbackPolicy(TASK, initial_force_N=1.0, pinch_gate=0.9, settle_steps=2)
    pol.reset([{}])
    readings = [0.2, 0.5, 0.7, 0.85, 0.92, 0.6, 0.3]
    pulls = [float(pol.act(_held_frame(p))[0, 1]) for p in readings]
    assert pulls == [-1.0] * 4 + [0.0] * 3


def test_a_pinch_gate_delays_the_pull_but_a_reading_that_stays_low_cannot_stall_it():
    """A sensor that reads low (a negative bias) holds the pull back at most GATE_WAIT_STEPS steps."""
    from msdgrasp.agents.controller_settings import GATE_WAIT_STEPS

    pol = SlipFeedbackPolicy(TASK, initial_force_N=1.0, pinch_gate=0.9, settle_steps=2)
    pol.reset([{}])
    pulls = [float(pol.act(_held_frame(0.5))[0, 1]) for _ in range(2 + GATE_WAIT_STEPS + 3)]
    first = pulls.index(0.0)
    assert first == 2 + GATE_WAIT_STEPS and all(p == 0.0 for p in pulls[first:])


def test_told_mu_it_starts_each_episode_at_a_margin_over_the_oracle_s_force(monkeypatch):
    """oracle_margin: each episode's initial grip is that multiple of the minimal fixed force at the episode's mu
    and the controller's own pull speed (capped at its largest grip); an episode without mu is refused."""
    import msdgrasp.agents.controllers as controllers

    asked = []

    def fake_minimal_force(config, mu, pull, tolerance_N):
        asked.append((mu, pull, tolerance_N))
        return 0.5 / mu

    monkeypatch.setattr(controllers, "minimal_force", fake_minimal_force)
    pol = SlipFeedbackPolicy(TASK, oracle_margin=1.2, pull=0.3, max_force_N=3.0)
    pol.reset([{"mu": 0.5}, {"mu": 0.25}, {"mu": 0.1}])
    assert pol.force == pytest.approx([1.2, 2.4, 3.0])
    assert asked[0] == (0.5, 0.3, controllers.ORACLE_TOLERANCE_N)
    pol.reset_one(2, {"mu": 1.0})
    assert pol.force == pytest.approx([1.2, 2.4, 0.6])
    obs = _frame(3)
    obs[:, OBS["lift_slip"]] = 1.0 / (TASK.lift_slip_tolerance_m * 1e3)  # 1 mm of slip: + gain x 1 mm on each start
    pol.act(obs)
    assert pol.force == pytest.approx([2.2, 3.0, 1.6])
    with pytest.raises(ValueError, match="needs the episode's mu"):
        pol.reset([{}])


@pytest.mark.parametrize("kwargs, needle", [
    ({"initial_force_N": 0.0}, "initial_force_N"),
    ({"initial_force_N": 5.0, "max_force_N": 4.0}, "initial_force_N"),
    ({"gain_N_per_mm": -1.0}, "gain_N_per_mm"),
    ({"pull": 0.0}, "pull"),
    ({"contact_jaws": 4}, "contact_jaws"),
    ({"settle_steps": -1}, "settle_steps"),
    ({"pinch_gate": 1.5}, "pinch_gate"),
    ({"pinch_gate": -0.1}, "pinch_gate"),
    ({"oracle_margin": 0.2}, "oracle_margin"),
    ({"oracle_margin": 4.0}, "oracle_margin"),
])
def test_bad_parameters_are_refused_naming_the_field(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        SlipFeedbackPolicy(TASK, **kwargs)


def test_it_needs_the_force_set_point_and_pull_speed_interface():
    with pytest.raises(ValueError, match="jaw_action: force and pull_action: forward_speed"):
        SlipFeedbackPolicy(GraspLiftConfig())  # version 0: a travel set-point


def _lifts_lighter(ours: str, theirs: str, task, mus=(0.4, 0.7)) -> list[tuple[dict, dict]]:
    """Two episodes per mu of policy ``ours`` and ``theirs`` on ``task``: ours lifts every one, with a lighter mean
    peak grip at every mu. Returns their rows, mu by mu."""
    rows = [evaluate_policy(make_policy(spec, task), list(mus), 2, task) for spec in (ours, theirs)]
    for a, b in zip(*rows):
        assert a["success_rate"] == 1.0, a["outcomes"]
        assert a["mean_peak_pinch_N"] < b["mean_peak_pinch_N"]
    return list(zip(*rows))


def test_it_lifts_with_a_lighter_grip_than_the_slip_reactive_controller_under_force_noise():
    noisy = dataclasses.replace(TASK, randomization=dataclasses.replace(TASK.randomization, sensor_noise_N=0.08))
    for a, _ in _lifts_lighter("slipfeedback", "reactive", noisy):
        # before it pulls it holds its initial 0.55 N set-point: the evaluation's grip before the pull is the
        # jaws' force on it (the force loop settles from below; 5 % for the loop's overshoot), not zero
        before = a["per_episode"]["peak_pinch_before_pull_N"]
        assert all(0.0 < f <= 0.55 * 1.05 for f in before), before
        assert all(f <= p for f, p in zip(before, a["per_episode"]["peak_pinch_N"]))


def test_a_spec_sets_its_parameters_and_a_bad_one_is_refused_naming_the_key():
    pol = make_policy("slipfeedback:initial=0.7,gain=0.8,pull=0.25", TASK)
    assert (pol.initial, pol.gain, pol.pull) == (0.7, 0.8, 0.25)
    assert pol.name == "slipfeedback:initial=0.7,gain=0.8,pull=0.25"
    check_policy_spec("slipfeedback:pull=0.25")
    for spec, needle in (("slipfeedback:speed=0.2", "takes keys initial, gain, pull, max, gate, oracle"),
                         ("slipfeedback:pull=fast", "pull expects a number"),
                         ("slipfeedback:pull=0", "pull must be in"), ("slipfeedback:gain=-1", "gain_N_per_mm")):
        with pytest.raises(ConfigError, match=needle):
            check_policy_spec(spec)


def test_a_slower_pull_lifts_with_less_grip():
    """At 5 mm/s instead of 10 mm/s the tissue's load on the grasp is smaller, and the same feedback law holds it
    with a lighter grip (the oracle's minimal fixed force: 0.81-0.83x at mu 0.3-0.8, docs/design.md)."""
    for a, b in _lifts_lighter("slipfeedback:pull=0.25", "slipfeedback", TASK):
        assert a["mean_time_to_lift_s"] > b["mean_time_to_lift_s"]


def test_a_spec_runs_as_a_controller_in_evaluations_and_the_suite():
    """A parameterised spec is a controller (no model file is looked for) and travels to a worker as its spec."""
    from msdgrasp.agents.evaluation import is_controller
    from msdgrasp.agents.evaluation_jobs import policy_of, policy_payload

    spec = "slipfeedback:initial=0.7,gain=0.8,pull=0.25"
    assert is_controller(spec) and not is_controller("logs/train/seed_0/best_model.zip")
    payload = policy_payload(spec, spec)
    assert payload[2] is None
    assert policy_of(payload, TASK).gain == 0.8


def test_evaluate_runs_controllers_alone_on_the_default_training_s_task(tmp_path):
    """`msdgrasp evaluate --policy slipfeedback` (controllers only, no model to take the task from) runs on the
    default training's task, as the suite does: the slip-feedback controller needs its interface."""
    from msdgrasp.agents.evaluation import evaluate
    from msdgrasp.agents.models import TrainConfig

    result = evaluate(["slipfeedback:pull=0.25"], [0.5], 1, tmp_path, progress=False, conditions=())
    assert result["config"] == TrainConfig().env
    ours = result["results"][0]
    assert ours["name"] == "slipfeedback:pull=0.25" and ours["rows"][0]["success_rate"] == 1.0
