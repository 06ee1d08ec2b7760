"""The teacher-student route: a privileged teacher told mu, a student with memory, DAgger, selection that keeps grasps.

What it must be: the teacher sets the grip the friction needs from the true mu and no further; the student reads
only the sensed entries and remembers per batch slot (a batch of episodes acts as the same episodes one by one);
saved students run wherever a policy runs, recognised by the learner recorded beside them; the loss aims at the
quantile it names; a checkpoint that loses a low-friction grasp never wins on force; a run never draws sealed seeds.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torch")

from msdgrasp.agents.controllers import make_policy  # noqa: E402
from msdgrasp.agents.recurrent_training import RecurrentConfig, student_columns, train_recurrent  # noqa: E402
from msdgrasp.agents.friction import FrictionEstimator, estimator_path  # noqa: E402
from msdgrasp.agents.learners import learner_of_model, learner_of_run  # noqa: E402
from msdgrasp.agents.recurrent import StudentPolicy, make_student_net, pinball, save_student  # noqa: E402
from msdgrasp.agents.training import BestModel  # noqa: E402
from msdgrasp.envs.task import N_OBS, OBS, obs_group  # noqa: E402
from msdgrasp.physics.config import ConfigError, replace  # noqa: E402

TEACHER = "slipfeedback:estimator=builtin,told=1,gate=0.9,gain=0.5,pull=0.3"


# ---- the teacher ------------------------------------------------------------------------------------------------


def test_the_told_teacher_sets_the_grip_of_the_true_mu_and_probes_no_further_than_it_needs():
    cfg = RecurrentConfig()
    est = FrictionEstimator.load(estimator_path("builtin"))
    pol = make_policy(TEACHER, cfg.env)
    mus = [0.2, 0.3, 0.8]
    pol.reset([{"mu": m} for m in mus])
    needed = np.array([1.2 * est.grip_N(m) for m in mus])
    assert pol.start == pytest.approx(np.minimum(est.probe_force_N, needed))  # the closing grip
    # the jaws touch and the pinch reaches the gate: the grip rises to what the told mu needs
    obs = np.zeros((3, N_OBS), dtype=np.float32)
    obs[:, obs_group("contact_fraction")] = 0.5
    obs[:, obs_group("normal_force")] = 4.0 / cfg.env.reference_force_N  # (well above any gate)
    for _ in range(10):
        pol.act(obs)
    assert pol.mu_estimate == pytest.approx(mus)
    assert pol.start == pytest.approx(np.maximum(np.minimum(est.probe_force_N, needed), needed))


@pytest.mark.parametrize("spec, words", [
    ("slipfeedback:told=1", "friction_estimator"),
    ("slipfeedback:estimator=builtin,told=2", "told_mu must be 0 or 1"),
])
def test_a_bad_told_setting_is_refused_naming_it(spec, words):
    with pytest.raises((ValueError, ConfigError), match=words):
        make_policy(spec, RecurrentConfig().env)


def test_the_told_teacher_needs_the_episodes_mu():
    pol = make_policy(TEACHER, RecurrentConfig().env)
    with pytest.raises(ValueError, match="mu in the reset info"):
        pol.reset([{}])


# ---- the student ------------------------------------------------------------------------------------------------


def _student(memory: str = "gru", seed: int = 0) -> StudentPolicy:
    import torch

    torch.manual_seed(seed)
    return StudentPolicy(make_student_net(N_OBS, 16, memory), np.arange(N_OBS))


def _histories(T: int = 12, B: int = 3, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(T, B, N_OBS + 5)).astype(np.float32)  # (privileged tail)


def test_a_batch_of_episodes_acts_as_the_same_episodes_one_by_one():
    xs = _histories()
    batch, alone = _student(), _student()
    batch.reset([{}] * 3)
    together = np.stack([batch.act(x) for x in xs])
    for b in range(3):
        alone.reset([{}])
        one = np.stack([alone.act(x[b:b + 1]) for x in xs])
        assert one[:, 0] == pytest.approx(together[:, b], abs=1e-5)
    assert np.all(np.abs(together) <= 1.0)


def test_the_student_remembers_and_reset_forgets_one_slot_only():
    xs = _histories(B=2)
    pol = _student()
    pol.reset([{}] * 2)
    for x in xs:
        pol.act(x)
    probe = xs[0]
    remembered = pol.act(probe)
    pol.reset_one(1, {})
    after = pol.act(probe)
    fresh = _student()
    fresh.reset([{}] * 2)
    first = fresh.act(probe)
    assert not np.allclose(remembered[1], first[1], atol=1e-4)  # (its history changed what it does)
    assert after[1] == pytest.approx(first[1], abs=1e-5)  # slot 1 forgot its history
    assert not np.allclose(after[0], first[0], atol=1e-4)  # slot 0 did not


def test_without_memory_the_action_reads_the_current_frame_only():
    xs = _histories()
    pol = _student("none")
    pol.reset([{}] * 3)
    for x in xs:
        pol.act(x)
    last = pol.act(xs[0])
    pol.reset([{}] * 3)
    assert last == pytest.approx(pol.act(xs[0]), abs=1e-6)


def test_the_student_reads_no_privileged_entry():
    from msdgrasp.envs.core import GraspLiftCore

    core = GraspLiftCore(RecurrentConfig().env, 1)
    columns = student_columns(core)
    assert columns.tolist() == list(range(N_OBS))
    assert core.obs_dim > N_OBS  # (the privileged block is there, for the teacher)


def test_a_saved_student_acts_as_it_did_and_is_recognised_by_its_recorded_learner(tmp_path):
    from msdgrasp.agents.learners import get_learner

    pol = _student()
    cfg = RecurrentConfig()
    from msdgrasp.physics.config import to_dict

    path = save_student(pol.net, tmp_path / "student.pt", {"learner": "recurrent", "n_in": N_OBS, "hidden": 16,
                                                          "memory": "gru", "actor_columns": list(range(N_OBS)),
                                                          "config": to_dict(cfg)})
    xs = _histories()
    back = learner_of_model(path).load_policy(path)
    assert learner_of_model(path) is get_learner("recurrent")
    pol.reset([{}] * 3)
    back.reset([{}] * 3)
    for x in xs:
        assert back.act(x) == pytest.approx(pol.act(x), abs=1e-6)
    (tmp_path / "student.json").unlink()
    with pytest.raises(ConfigError, match="student.json is missing"):
        learner_of_model(path)


# ---- the loss and the selection ---------------------------------------------------------------------------------


@pytest.mark.parametrize("q", [0.25, 0.5, 0.75])
def test_the_pinball_loss_is_least_at_the_quantile_it_names(q):
    import torch

    target = torch.linspace(0.0, 1.0, 101).reshape(1, 101, 1).repeat(1, 1, 2)
    mask = torch.ones(1, 101)
    quantiles = torch.tensor([q, q])
    grid = np.linspace(0.0, 1.0, 201)
    losses = [float(pinball(torch.full_like(target, c), target, mask, quantiles)) for c in grid]
    assert grid[int(np.argmin(losses))] == pytest.approx(q, abs=0.011)


def test_selection_by_grasps_never_trades_a_low_friction_grasp_for_force(tmp_path):
    cfg = RecurrentConfig()
    sel = BestModel(cfg, tmp_path)
    n = cfg.validation_episodes
    holds_all = {"success_rate": 1.0, "force_cost_N": 2.0, "mean_peak_pinch_N": 2.0,
                 "success_by_mu": {"0.2": 1.0, "0.3": 1.0, "0.5": 1.0, "0.8": 1.0}}
    lighter = {"success_rate": 1 - 0.25 / n, "force_cost_N": 1.0, "mean_peak_pinch_N": 1.0,
               "success_by_mu": {"0.2": 1 - 1 / n, "0.3": 1.0, "0.5": 1.0, "0.8": 1.0}}
    assert sel._key(holds_all) > sel._key(lighter)
    equal = dict(holds_all, force_cost_N=1.5)
    assert sel._key(equal) > sel._key(holds_all)  # (the grasps equal, force decides)
    by_success = BestModel(replace(cfg, selection="success"), tmp_path)
    assert by_success._key(holds_all) > by_success._key(lighter)


# ---- the config ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("change, words", [
    ({"episodes_per_iteration": 100}, "multiple of n_envs"),
    ({"teacher": "slipfeedback:estimator=builtin,gate=0.9"}, "told mu"),
    ({"seed": 999_999_990}, "sealed"),
    ({"memory": "lstm"}, "memory"),
])
def test_a_bad_config_is_refused_naming_the_field(change, words):
    from msdgrasp.agents.learners import get_learner
    from msdgrasp.physics.config import to_dict

    with pytest.raises(ConfigError, match=words):
        get_learner("recurrent").config_from_dict({**to_dict(RecurrentConfig()), **change}, where="recurrent.yaml")


def test_a_tiny_run_writes_its_student_and_the_evaluation_runs_it(tmp_path):
    from msdgrasp.agents.evaluation import build_policy, evaluate_policy

    cfg = replace(RecurrentConfig(), iterations=2, episodes_per_iteration=4, n_envs=4, grad_steps=3, batch_episodes=4,
                  hidden=8, validation_episodes=1, validation_mu=(0.5,), ppo_waves=1, ppo_minibatch_episodes=2)
    summary = train_recurrent(cfg, tmp_path / "run", progress=False)
    run = tmp_path / "run"
    assert learner_of_run(run).name == "recurrent"
    dagger = [h for h in summary["history"] if h["stage"] == "dagger"]
    assert [h["teacher_share"] for h in dagger] == [1.0, 0.0]  # the teacher drives, then the student
    assert [h["stage"] for h in summary["history"]] == ["dagger", "dagger", "ppo"]
    assert len(list((run / "checkpoints").glob("student_*.pt"))) == 3
    from msdgrasp.agents.selection import plan_selection

    # the DAgger stage alone can be selected again (msdgrasp select --checkpoints 0-1)
    assert [k for k, _ in plan_selection(run, numbers=(0, 1)).checkpoints] == [0, 1]
    with pytest.raises(ConfigError, match="numbered 5-9"):
        plan_selection(run, numbers=(5, 9))
    assert summary["agent_steps"] > 0 and (run / "student.pt").is_file()
    assert json.loads((run / "student.json").read_text())["learner"] == "recurrent"
    pol = build_policy(str(run / "student.pt"), cfg.env)
    rows = evaluate_policy(pol, [0.5], 2, config=cfg.env, seed=123)
    assert rows[0]["episodes"] == 2 and 0.0 <= rows[0]["success_rate"] <= 1.0
    assert OBS["lift_slip"] < N_OBS


# ---- PPO on the recurrent actor -----------------------------------------------------------------------------------


def test_gae_without_discount_or_smoothing_is_the_return_to_go_less_the_value():
    from msdgrasp.agents.recurrent_ppo import gae

    rewards = np.array([1.0, 0.0, 2.0, -1.0])
    values = np.array([0.5, 0.2, 0.1, 0.0])
    togo = np.cumsum(rewards[::-1])[::-1]
    assert gae(rewards, values, 1.0, 1.0) == pytest.approx(togo - values)
    # lam 0: the one-step error, the episode ending after its last step
    assert gae(rewards, values, 0.9, 0.0) == pytest.approx(rewards + 0.9 * np.r_[values[1:], 0.0] - values)


def test_the_anchor_pulls_the_actor_towards_the_teachers_labels():
    import torch

    from msdgrasp.agents.recurrent_ppo import RecurrentPPO
    from msdgrasp.agents.recurrent_ppo import Wave

    torch.manual_seed(0)
    cfg = replace(RecurrentConfig(), ppo_epochs=20, ppo_minibatch_episodes=4, ppo_learning_rate=3e-3,
                  ppo_value_coef=0.0)
    net = make_student_net(N_OBS, 16, "gru")
    ppo = RecurrentPPO(net, np.arange(N_OBS), N_OBS, cfg)
    rng = np.random.default_rng(0)
    obs = [rng.normal(size=(30, N_OBS)).astype(np.float32) for _ in range(4)]
    labels = [np.full((30, 2), 0.6, dtype=np.float32) for _ in range(4)]
    with torch.no_grad():
        before = net(torch.from_numpy(np.stack(obs)))[0]
    # rewards equal for every action: no advantage to follow, only the anchor
    wave = Wave(obs, [np.asarray(before[k].numpy()) for k in range(4)], labels, [np.zeros(30, np.float32)] * 4,
                np.ones(4, bool), np.ones(4))
    ppo.update(wave, bc_coef=10.0, rng=rng)
    with torch.no_grad():
        after = net(torch.from_numpy(np.stack(obs)))[0]
    assert float((after - 0.6).abs().mean()) < 0.5 * float((before - 0.6).abs().mean())


def test_ppo_from_scratch_never_reads_the_teacher():
    cfg = replace(RecurrentConfig(), iterations=0, ppo_waves=2, bc_coef=(0.0, 0.0))
    assert not cfg.reads_teacher
    assert replace(cfg, bc_coef=(1.0, 0.0)).reads_teacher and RecurrentConfig().reads_teacher
    with pytest.raises(ConfigError, match="nothing would train"):
        from msdgrasp.physics.config import to_dict

        from msdgrasp.agents.learners import get_learner

        get_learner("recurrent").config_from_dict({**to_dict(cfg), "ppo_waves": 0}, where="x.yaml")
