"""Specs of the task design: the force / travel control interface, the observation of success state,
and a reward under which success dominates, not touching is no haven and less force is better.

Each test runs short batched episodes of the coarse spleen (one numba call per step for the batch).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from msdgrasp.agents.controllers import FixedForcePolicy
from msdgrasp.envs.core import OBS_NAMES, GraspLiftConfig, GraspLiftCore, RewardConfig, pinch_action, pull_action
from msdgrasp.envs.grasp_lift import GraspLiftVectorEnv
from msdgrasp.physics.config import ConfigError

NOMINAL = {"stiffness_scale": 1.0, "mass_scale": 1.0, "pose_offset_m": 0.0, "pose_tilt_deg": 0.0,
           "pose_azimuth_deg": 0.0}


def _episodes(env: GraspLiftVectorEnv, policy, mus, seed: int = 0) -> dict[str, np.ndarray]:
    """Run one episode per sub-env (sub-env i at mu[i]); returns, outcomes and per-step traces."""
    core = env.core
    env.reset(seed=seed)
    infos = [core.reset(i, {**NOMINAL, "mu": float(m)}) for i, m in enumerate(mus)]
    obs = core.obs.astype(np.float32)
    if hasattr(policy, "reset"):
        policy.reset(infos)
    B = env.num_envs
    ret = np.zeros(B)
    done = np.zeros(B, dtype=bool)
    success = np.zeros(B, dtype=bool)
    peak = np.zeros(B)
    peak_charge = np.zeros(B)  # the summed peak_force reward term
    pinch, travel, target = [], [], []
    for _ in range(env.config.max_episode_steps):
        act = policy.act(obs) if hasattr(policy, "act") else policy(obs)
        obs, r, term, trunc, info = core.step(act)
        ret += np.where(done, 0.0, r)
        peak_charge += np.where(done, 0.0, info["reward_terms"]["peak_force"])
        pinch.append(info["pinch_force_N"].copy())
        travel.append(info["travel_m"].copy())
        target.append(core.travel_target.copy())
        ended = ~done & (term | trunc)
        success |= ended & info["is_success"]
        peak = np.where(ended, info["peak_pinch_N"], peak)
        done |= term | trunc
        if done.all():
            break
    return {"return": ret, "success": success, "peak": peak, "peak_force": peak_charge, "pinch": np.array(pinch),
            "travel": np.array(travel), "target": np.array(target)}


# -- the control interface ---------------------------------------------------------------------------
def test_force_loop_holds_the_pinch_set_point():
    """A constant set-point (jaw_action = force) is tracked by the 1 kHz loop: within 3% once settled."""
    env = GraspLiftVectorEnv(3)
    setpoints = np.array([0.8, 1.5, 3.0])
    a_jaw = 2.0 * setpoints / env.config.max_pinch_force_N - 1.0
    run = _episodes(env, lambda obs: np.stack([a_jaw, np.full(3, -1.0)], axis=1), [0.5, 0.5, 0.5])
    settled = run["pinch"][150:]  # 5 s in: the jaws have closed on the tissue (no pull: travel set-point 0)
    np.testing.assert_allclose(settled.mean(axis=0), setpoints, rtol=0.03)
    assert np.all(np.abs(run["travel"]) < 1e-9)


@pytest.mark.parametrize("limit_m_s, speed_mm_s", [(None, 20.0), (0.01, 10.0)])
def test_travel_set_point_is_reached_at_the_speed_limit(limit_m_s, speed_mm_s):
    """pull_action = travel: the arm reaches a set-point within one step when the speed limit allows it, and
    moves at the limit otherwise (the grasper's 20 mm/s, or max_pull_speed_m_s)."""
    env = GraspLiftVectorEnv(1, GraspLiftConfig(max_pull_speed_m_s=limit_m_s))
    cfg = env.config
    run = _episodes(env, lambda obs: np.array([[-1.0, 2 * 0.03 / cfg.max_travel_m - 1.0]]), [0.5])
    step_mm = speed_mm_s * cfg.agent_dt_s
    travel_mm = run["travel"][:, 0] * 1e3
    np.testing.assert_allclose(np.diff(travel_mm[:40]), step_mm, rtol=1e-6)  # speed limited on the way
    assert travel_mm[-1] == pytest.approx(30.0, abs=1e-6)  # then exactly at the 30 mm set-point


def test_speed_mode_is_still_available():
    """jaw_action = speed / pull_action = speed: the fixed-force controller still lifts at mu 0.5."""
    cfg = GraspLiftConfig(jaw_action="speed", pull_action="speed")
    env = GraspLiftVectorEnv(2, cfg)
    run = _episodes(env, FixedForcePolicy(cfg, 2.5), [0.5, 0.8])
    assert run["success"].all()
    assert np.all(run["peak"] > 2.4) and np.all(run["peak"] < 3.0)


@pytest.mark.parametrize("exponent, force_at_zero_N", [(1.0, 2.5), (2.0, 1.25)])
def test_pinch_action_exponent_shapes_the_set_point(exponent, force_at_zero_N):
    """set-point = ((a + 1) / 2) ** p x 5 N: the ends stay 0 and 5 N, action 0 gives 5 / 2**p N, and
    pinch_action (what the controllers use) inverts it."""
    core = GraspLiftCore(GraspLiftConfig(pinch_action_exponent=exponent))
    a = np.linspace(-1.0, 1.0, 9)
    sp = core.pinch_setpoint(a)
    assert sp[0] == 0.0 and sp[-1] == pytest.approx(5.0) and sp[4] == pytest.approx(force_at_zero_N)
    assert np.all(np.diff(sp) > 0)
    np.testing.assert_allclose(pinch_action(sp, core.config), a, atol=1e-12)


def test_forward_speed_pull_maps_the_action_to_zero_to_top_speed():
    """pull_action = forward_speed: action -1 stands still, 0 pulls at half the arm's top speed (10 mm/s),
    and the fixed-force controller still lifts with it."""
    cfg = GraspLiftConfig(pull_action="forward_speed")
    env = GraspLiftVectorEnv(2, cfg)
    run = _episodes(env, lambda obs: np.array([[-1.0, -1.0], [-1.0, 0.0]]), [0.5, 0.5])
    step_mm = np.diff(run["travel"][:20], axis=0) * 1e3
    np.testing.assert_allclose(step_mm[:, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(step_mm[:, 1], 10.0 * cfg.agent_dt_s, rtol=1e-6)
    lift = _episodes(env, FixedForcePolicy(cfg, 2.5), [0.5, 0.8])
    assert lift["success"].all()


@pytest.mark.parametrize("exponent, speed_at_zero_mm_s", [(1.0, 10.0), (2.0, 5.0)])
def test_pull_action_exponent_shapes_the_pull_speed(exponent, speed_at_zero_mm_s):
    """pull_action = forward_speed: speed = ((a + 1) / 2) ** q x 20 mm/s. The grasper moves by that speed each step
    (action 0: 20 / 2**q mm/s), and pull_action (what the controllers use) inverts it, so a controller's pull speed
    does not depend on q."""
    cfg = GraspLiftConfig(pull_action="forward_speed", pull_action_exponent=exponent)
    env = GraspLiftVectorEnv(2, cfg)
    run = _episodes(env, lambda obs: np.array([[-1.0, 0.0], [-1.0, 1.0]]), [0.5, 0.5])
    step_mm = np.diff(run["travel"][:20], axis=0) * 1e3
    np.testing.assert_allclose(step_mm[:, 0], speed_at_zero_mm_s * cfg.agent_dt_s, rtol=1e-6)
    np.testing.assert_allclose(step_mm[:, 1], 20.0 * cfg.agent_dt_s, rtol=1e-6)
    fractions = np.linspace(0.0, 1.0, 9)
    np.testing.assert_allclose((0.5 * (pull_action(fractions, cfg) + 1.0)) ** exponent, fractions, atol=1e-12)
    assert pull_action(0.25, cfg) == pytest.approx(0.0 if exponent == 2.0 else -0.5)


@pytest.mark.parametrize("field, value, match", [
    ("pinch_action_exponent", 0.5, "pinch_action_exponent"), ("pull_action_exponent", 0.9, "pull_action_exponent"),
    ("pull_action_exponent", 5.0, "pull_action_exponent"),
    ("jaw_action", "torque", "jaw_action"), ("pull_action", "position", "pull_action"),
    ("max_pinch_force_N", 0.0, "max_pinch_force_N"), ("max_travel_m", 0.5, "max_travel_m"),
    ("obs_history", 0, "obs_history"), ("force_loop_gain_m_s_per_N", -1.0, "force_loop_gain"),
    ("max_pull_speed_m_s", 0.0, "max_pull_speed_m_s"), ("max_pull_speed_m_s", 0.5, "max_pull_speed_m_s"),
    ("substep_safety", 0.0, r"substep_safety.*\(0(\.0)?, 1(\.0)?\]"), ("substep_safety", 1.5, "substep_safety"),
])
def test_bad_control_config_names_the_field(field, value, match):
    with pytest.raises(ConfigError, match=match):
        GraspLiftConfig(**{field: value})


# -- observations ------------------------------------------------------------------------------------
def test_observation_history_stacks_frames_oldest_first():
    one = GraspLiftVectorEnv(1)
    three = GraspLiftVectorEnv(1, GraspLiftConfig(obs_history=3))
    n = len(OBS_NAMES)
    assert three.single_observation_space.shape == (3 * n,)
    o1, _ = one.reset(seed=4)
    o3, _ = three.reset(seed=4)
    np.testing.assert_array_equal(o3[0], np.tile(o1[0], 3))  # at reset: the first frame three times
    frames = [o1[0]]
    for a in ([0.2, -1.0], [0.4, -1.0], [0.6, -0.5]):
        o1, *_ = one.step(np.array([a]))
        o3, *_ = three.step(np.array([a]))
        frames.append(o1[0])
    np.testing.assert_array_equal(o3[0], np.concatenate(frames[-3:]))


def test_success_state_is_observed():
    """Lift progress, hold progress and the tissue lag behind the grasper are in the observation, and they
    move as the episode does: hold progress reaches ~1 at success."""
    env = GraspLiftVectorEnv(1)
    pol = FixedForcePolicy(env.config, 2.0)
    core = env.core
    env.reset(seed=1)
    core.reset(0, {**NOMINAL, "mu": 0.6})
    pol.reset([{}])
    obs = core.obs.astype(np.float32)
    lift_i, hold_i, lag_i = (OBS_NAMES.index(k) for k in ("lift_progress", "hold_progress", "lift_lag"))
    for _ in range(env.config.max_episode_steps):
        prev = obs
        obs, r, term, trunc, info = core.step(pol.act(obs))
        if term[0] or trunc[0]:
            break
    assert info["is_success"][0]
    assert prev[0, lift_i] >= 1.0 and prev[0, hold_i] > 0.9
    assert abs(prev[0, lag_i]) < 0.05  # held: the tissue follows the grasper (< 1.5 mm of 30 mm)


# -- reward ------------------------------------------------------------------------------------------
def test_reward_scale_success_dominates_and_no_touch_is_no_haven():
    """Returns on the nominal tissue: never touching < a weak grip that lifts then slips (mu 0.2) <
    any success; among successes, less peak pinch earns more (mu 0.8: 1.0 N > 2.5 N)."""
    w = RewardConfig()
    env = GraspLiftVectorEnv(4)
    never = _episodes(env, lambda obs: np.full((4, 2), -1.0), [0.8] * 4)
    np.testing.assert_allclose(never["return"], -w.failure_penalty, atol=0.01)  # the failure penalty alone
    pol = FixedForcePolicy(env.config, 1.0)
    runs = _episodes(env, pol, [0.2, 0.8, 0.8, 0.8])
    pol2 = FixedForcePolicy(env.config, 2.5)
    strong = _episodes(env, pol2, [0.8] * 4)
    weak_low_mu, weak_ok = runs["return"][0], runs["return"][1]
    assert not runs["success"][0] and runs["success"][1] and strong["success"][0]
    assert never["return"][0] < weak_low_mu < strong["return"][0] < weak_ok
    # the force discount is the documented one: 10 points per newton of peak pinch
    gap = weak_ok - strong["return"][0]
    expected = w.peak_force * (strong["peak"][0] - runs["peak"][1]) / env.config.reference_force_N
    assert gap == pytest.approx(expected, abs=0.5)  # slip differs a little between the two
    # success dominates: a success at the cautious 2.5 N still nets more than the best possible failure
    # (full progress and hold shaping, then the failure penalty)
    assert w.success_bonus - w.peak_force * 2.5 / env.config.reference_force_N > w.progress + w.hold - w.failure_penalty


def test_peak_force_scaled_by_mu_charges_the_same_grip_more_where_friction_needs_less():
    """reward.peak_force_mu_ref: the charge per N is w / reference force x mu / mu_ref, so the same
    1.5 N grip costs 2.25x as much at mu 0.9 as at mu 0.4, and at mu = mu_ref what the plain charge costs."""
    scaled = GraspLiftConfig(reward=RewardConfig(peak_force_mu_ref=0.4))
    mus = [0.4, 0.9]
    runs = _episodes(GraspLiftVectorEnv(2, scaled), FixedForcePolicy(scaled, 1.5), mus)
    plain = _episodes(GraspLiftVectorEnv(2), FixedForcePolicy(GraspLiftConfig(), 1.5), mus)
    assert list(runs["success"]) == list(plain["success"]) == [True, True]
    w = scaled.reward
    for k, mu in enumerate(mus):
        expected = w.peak_force * runs["peak"][k] / scaled.reference_force_N * mu / 0.4
        assert -runs["peak_force"][k] == pytest.approx(expected, rel=1e-9)
    assert runs["peak_force"][0] == pytest.approx(plain["peak_force"][0], rel=1e-6)  # mu = mu_ref
    assert runs["peak_force"][1] / runs["peak_force"][0] == pytest.approx(0.9 / 0.4 * runs["peak"][1] / runs["peak"][0])
    with pytest.raises(ConfigError, match="peak_force_mu_ref"):
        RewardConfig(peak_force_mu_ref=0.0)


def test_peak_force_knee_bends_the_charge_so_a_steep_charge_need_not_make_failing_pay():
    """reward.peak_force_knee: a success is charged min(x, knee) + beyond x max(x - knee, 0) for the plain charge x
    (0: a cap, keeping the success above the failure); a charge below the knee is the plain one to the bit; charged
    as made, the bent charge is paid as the peak rises and refunded without success."""
    mus = [0.2, 0.8]  # a 1 N grip fails at mu 0.2 and succeeds at 0.8
    steep = dict(peak_force=500.0, peak_force_mu_ref=0.4)  # 100 points per N at mu 0.4, 200 at mu 0.8
    configs = {"plain": {}, "capped": {"peak_force_knee": 55.0, "peak_force_beyond_knee": 0.0},
               "bent": {"peak_force_knee": 55.0, "peak_force_beyond_knee": 0.1}, "loose": {"peak_force_knee": 1e6}}
    runs = {}
    for name, knee in configs.items():
        cfg = GraspLiftConfig(reward=RewardConfig(**steep, **knee))
        runs[name] = _episodes(GraspLiftVectorEnv(2, cfg), FixedForcePolicy(cfg, 1.0), mus)
    assert list(runs["plain"]["success"]) == list(runs["capped"]["success"]) == [False, True]
    charge = -runs["plain"]["peak_force"][1]
    assert charge > 60.0  # the steep charge makes this success worth less than a failure...
    assert runs["plain"]["return"][1] < runs["plain"]["return"][0]
    assert runs["capped"]["peak_force"][1] == -55.0  # ...the cap keeps it above
    assert runs["capped"]["return"][1] > runs["capped"]["return"][0]
    assert -runs["bent"]["peak_force"][1] == pytest.approx(55.0 + 0.1 * (charge - 55.0), rel=1e-12)
    np.testing.assert_array_equal(runs["loose"]["return"], runs["plain"]["return"])  # below the knee: unchanged
    made = GraspLiftConfig(reward=RewardConfig(**steep, **configs["bent"], peak_force_timing="as_made"))
    as_made = _episodes(GraspLiftVectorEnv(2, made), FixedForcePolicy(made, 1.0), mus)
    np.testing.assert_allclose(as_made["return"], runs["bent"]["return"], atol=1e-9)
    with pytest.raises(ConfigError, match="peak_force_knee"):
        RewardConfig(peak_force_knee=-1.0)


def test_setpoint_change_charges_each_move_of_the_pinch_setpoint_and_nothing_for_a_steady_one():
    """reward.setpoint_change: w per N the commanded pinch set-point moves from one step to the next of the same
    episode: 5 N and 0 N in turn pay 5 w a step from the second step on, a fixed set-point nothing."""
    cfg = GraspLiftConfig(reward=RewardConfig(setpoint_change=0.1), time_limit_s=0.2)
    env = GraspLiftVectorEnv(2, cfg)
    env.reset(seed=0)
    for k in range(6):
        jaw = 1.0 if k % 2 else -1.0
        _, _, _, _, info = env.core.step(np.array([[jaw, -1.0], [0.3, -1.0]]))
        charged = info["reward_terms"]["setpoint_change"]
        assert charged[0] == pytest.approx(0.0 if k == 0 else -0.1 * cfg.max_pinch_force_N, abs=1e-12)
        assert charged[1] == 0.0
    plain = GraspLiftVectorEnv(2, dataclasses.replace(cfg, reward=RewardConfig()))
    plain.reset(seed=0)
    _, _, _, _, info = plain.core.step(np.array([[1.0, -1.0], [-1.0, -1.0]]))
    assert np.all(info["reward_terms"]["setpoint_change"] == 0.0)


def test_peak_force_charged_as_made_has_the_same_returns_and_pays_when_the_force_rises():
    """reward.peak_force_timing = as_made: each rise of the peak pinch is charged in its step and the sum is
    refunded without success, so every episode's return equals the at_success one (within float sums),
    while the charge of a success is paid by the time the grip is closed, long before the success."""
    mus = [0.2, 0.8]  # a 1 N grip fails at mu 0.2 and succeeds at 0.8
    made = GraspLiftConfig(reward=RewardConfig(peak_force_timing="as_made"))
    at_end = _episodes(GraspLiftVectorEnv(2), FixedForcePolicy(GraspLiftConfig(), 1.0), mus)
    env = GraspLiftVectorEnv(2, made)
    as_made = _episodes(env, FixedForcePolicy(made, 1.0), mus)
    assert list(as_made["success"]) == list(at_end["success"]) == [False, True]
    np.testing.assert_allclose(as_made["return"], at_end["return"], atol=1e-9)
    # timing: run the successful episode again and sum the charge paid before the lift begins
    env.reset(seed=0)
    env.core.reset(0, {**NOMINAL, "mu": 0.8})
    pol = FixedForcePolicy(made, 1.0)
    pol.reset([{}])
    obs = env.core.obs.astype(np.float32)
    charged_before_lift = 0.0
    for _ in range(made.max_episode_steps):
        obs, _, term, trunc, info = env.core.step(pol.act(obs[:1]).repeat(2, axis=0))
        if info["lifted_m"][0] < made.lift_started_m:
            charged_before_lift += info["reward_terms"]["peak_force"][0]
        if term[0] or trunc[0]:
            break
    full = made.reward.peak_force * info["peak_pinch_N"][0] / made.reference_force_N
    assert -charged_before_lift == pytest.approx(full, rel=0.1)
