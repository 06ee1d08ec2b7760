"""Spec tests of the GraspLift Gymnasium environments, the native vector env and the SB3 adapter.

All on ``msdgrasp/GraspLift-v0`` with the coarse spleen (the settled scene is computed once per process
and cached, so each env construction is cheap after the first).
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.vector import AutoresetMode

import msdgrasp  # noqa: F401  (registers the ids)
from msdgrasp.envs.core import OBS_NAMES, GraspLiftConfig
from msdgrasp.envs.grasp_lift import GraspLiftEnv, GraspLiftVectorEnv
from msdgrasp.physics.config import ConfigError

ENV_ID = "msdgrasp/GraspLift-v0"
SPHERE_ID = "msdgrasp/GraspLiftSphere-v0"


def _actions(n: int, rng_seed: int = 123) -> np.ndarray:
    """A fixed, varied action sequence in [-1, 1]: mostly closing, then pulling."""
    rng = np.random.default_rng(rng_seed)
    a = rng.uniform(-1.0, 1.0, size=(n, 2))
    a[: n // 2, 0] = np.abs(a[: n // 2, 0])
    a[n // 2 :, 1] = np.abs(a[n // 2 :, 1])
    return a.astype(np.float32)


def _rollout(env: gym.Env, seed: int, actions: np.ndarray, options: dict | None = None):
    obs, info = env.reset(seed=seed, options=options)
    obs_seq, rew_seq = [obs], []
    for a in actions:
        obs, r, terminated, truncated, info = env.step(a)
        obs_seq.append(obs)
        rew_seq.append(r)
        if terminated or truncated:
            obs, info = env.reset()
            obs_seq.append(obs)
    return np.array(obs_seq), np.array(rew_seq)


# -- registration, checker, spaces -------------------------------------------------------------------
def test_gym_make_both_ids():
    for env_id, scene in ((ENV_ID, "spleen"), (SPHERE_ID, "sphere")):
        env = gym.make(env_id)
        assert isinstance(env.unwrapped, GraspLiftEnv)
        assert env.unwrapped.config.scene == scene
        obs, info = env.reset(seed=0)
        assert env.observation_space.contains(obs)
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert isinstance(r, float) and isinstance(term, bool) and isinstance(trunc, bool)
        env.close()


@pytest.mark.parametrize("env_id", ["msdgrasp/GraspLift-v0", "msdgrasp/GraspLiftSphere-v0", "msdgrasp/GraspLift-v1",
                                    "msdgrasp/GraspLiftSphere-v1"])
def test_gymnasium_env_checker_passes(env_id):
    from gymnasium.utils.env_checker import check_env

    env = gym.make(env_id)
    with warnings.catch_warnings():
        # unbounded observations are by design (forces); every other checker warning is an error
        warnings.simplefilter("error", UserWarning)
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value.*")
        check_env(env.unwrapped, skip_render_check=False)


def test_spaces():
    env = GraspLiftEnv()
    assert env.action_space == spaces.Box(-1.0, 1.0, (2,), np.float32)
    assert isinstance(env.observation_space, spaces.Box)
    assert env.observation_space.dtype == np.float32
    assert env.observation_space.shape == (len(OBS_NAMES),) == (32,)
    obs, _ = env.reset(seed=1)
    assert obs.dtype == np.float32 and obs.shape == (len(OBS_NAMES),)
    obs, *_ = env.step(np.zeros(2, np.float32))
    assert obs.dtype == np.float32 and obs.shape == (len(OBS_NAMES),)

    priv = GraspLiftEnv(privileged_obs=True)
    n = priv.observation_space.shape[0]
    assert n == len(OBS_NAMES) + 3 + 3 * priv.config.privileged_nodes
    obs, _ = priv.reset(seed=1, options={"mu": 0.42})
    assert obs.shape == (n,) and obs.dtype == np.float32
    n0 = len(OBS_NAMES)
    assert obs[n0] == pytest.approx(0.42, rel=1e-6)  # mu is the first privileged entry
    np.testing.assert_array_equal(obs[:n0], env.reset(seed=1, options={"mu": 0.42})[0])


def test_privileged_perturbations_give_the_critic_the_episodes_robustness_draws():
    """privileged_perturbations appends the episode's pose error, force biases, latency and gain error, each scaled
    to about 1 at the suite's largest levels; the actor's entries are unchanged; all zero on an unperturbed task."""
    from msdgrasp.envs.core import ConfigError, RandomizationConfig
    from msdgrasp.envs.perturbations import privileged_names
    PRIVILEGED_PERTURBATIONS = privileged_names()

    r = RandomizationConfig(force_bias_N=0.05, latency_steps=(2, 2), force_loop_gain_error=0.2, pose_offset_m=0.004,
                            pose_tilt_deg=0.0, pose_azimuth_deg=0.0)
    env = GraspLiftEnv(privileged_obs=True, privileged_perturbations=True, randomization=r)
    plain = GraspLiftEnv(privileged_obs=True, randomization=r)
    n = plain.observation_space.shape[0]
    assert env.observation_space.shape == (n + len(PRIVILEGED_PERTURBATIONS),)
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        np.testing.assert_array_equal(obs[:n], plain.reset(seed=seed)[0])
        x = dict(zip(PRIVILEGED_PERTURBATIONS, obs[n:].astype(float)))
        offset = np.hypot(np.hypot(x["tip_offset_x"], x["tip_offset_y"]), x["tip_offset_z"]) * 5.0  # mm
        assert 0.0 < offset <= 4.0 + 1e-6
        assert all(abs(x[f"{k}_change_{c}"]) < 1e-6 for k in ("axis", "jaw_dir") for c in "xyz")  # no tilt, no turn
        assert all(0.0 < abs(x[f"force_bias_{k}"]) <= 0.5 for k in range(3))  # 0.05 N of 0.1 N
        assert x["latency"] == pytest.approx(2 / 3)
        assert 0.0 < abs(x["force_loop_gain_error"]) <= 1.0
    still = RandomizationConfig(pose_offset_m=0.0, pose_tilt_deg=0.0, pose_azimuth_deg=0.0)
    nominal = GraspLiftEnv(privileged_obs=True, privileged_perturbations=True, randomization=still)
    assert not np.any(nominal.reset(seed=0)[0][n:])
    with pytest.raises(ConfigError, match="privileged_perturbations.*privileged_obs"):
        GraspLiftEnv(privileged_perturbations=True)


# -- determinism -----------------------------------------------------------------------------------
def test_same_seed_same_trajectory_different_seed_different_mu():
    acts = _actions(30)
    env1, env2 = GraspLiftEnv(), GraspLiftEnv()
    o1, r1 = _rollout(env1, 7, acts)
    o2, r2 = _rollout(env2, 7, acts)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(r1, r2)
    assert np.any(o1[-1] != o1[0])  # the state really evolved
    # the same env object re-seeded reproduces too
    o3, r3 = _rollout(env1, 7, acts)
    np.testing.assert_array_equal(o1, o3)
    np.testing.assert_array_equal(r1, r3)

    mus = {GraspLiftEnv.reset(env1, seed=s)[1]["mu"] for s in range(5)}
    assert len(mus) == 5
    lo, hi = env1.config.randomization.mu_range
    assert all(lo <= m <= hi for m in mus)


def _compare_infos(got, want, where):
    """Two vector infos equal key for key: the same keys, ``_key`` masks, dtypes and values (per-env arrays in
    object arrays compared element by element)."""
    assert sorted(got) == sorted(want), where
    for key, w in want.items():
        g = got[key]
        if isinstance(w, dict):
            _compare_infos(g, w, f"{where}/{key}")
        elif w.dtype == object:
            assert g.dtype == object and g.shape == w.shape, (where, key)
            for a, b in zip(g, w):
                assert (a is None and b is None) or np.array_equal(a, b), (where, key)
        else:
            assert g.dtype == w.dtype, (where, key, g.dtype, w.dtype)
            np.testing.assert_array_equal(g, w, err_msg=f"{where}/{key}")


def test_the_batched_info_is_gymnasiums_add_info_of_each_envs_info():
    """The vector env's info of the envs with an ordinary step, built from the core's batch at once, equals
    Gymnasium's _add_info over each env's own info; an env whose info differs (here one with a numerical failure and
    its error message, and one left out, as a reset env is) is added by _add_info on top, as the step does."""
    from msdgrasp.envs.grasp_lift import _batched_info, env_info

    venv = GraspLiftVectorEnv(4)
    venv.reset(seed=0)
    infos = venv.core.step(np.zeros((4, 2)))[4]
    infos["numerical_failure"][2] = True
    want: dict = {}
    for i in (0, 1, 2):
        want = venv._add_info(want, env_info(infos, i), i)
    assert "error" in want and want["_error"].tolist() == [False, False, True, False]
    rows = np.array([True, True, False, False])
    got = venv._add_info(_batched_info(infos, rows), env_info(infos, 2), 2)
    _compare_infos(got, want, "batched")
    assert got["_reward_terms"].tolist() == [True, True, True, False]


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_the_native_vector_env_is_gymnasiums_sync_vector_env_of_single_envs(mode):
    """Same seeds and actions: observations, rewards, flags and infos (keys, masks, dtypes, values) equal those of
    Gymnasium's SyncVectorEnv over single envs in the same autoreset mode, through episode ends at different
    steps (a damage threshold of 100 Pa ends an episode at the first firm contact: the hard pinch first, the lighter
    one later, the open jaws run to the time limit)."""
    cfg = {"time_limit_s": 0.6, "damage_stress_pa": 100.0}
    n, seed = 3, 2
    native = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point",
                          autoreset_mode=mode, config=cfg)
    sync = gym.vector.SyncVectorEnv([lambda: GraspLiftEnv(cfg) for _ in range(n)], autoreset_mode=mode)
    assert isinstance(native.unwrapped, GraspLiftVectorEnv) and native.metadata["autoreset_mode"] == mode
    obs_n, info_n = native.reset(seed=seed)
    obs_s, info_s = sync.reset(seed=seed)
    np.testing.assert_array_equal(obs_n, obs_s)
    _compare_infos(info_n, info_s, "reset")
    actions = np.array([[1.0, -1.0], [0.0, -1.0], [-1.0, -1.0]], np.float32)
    ended_apart = False
    for step in range(45):  # two episodes and more
        got = native.step(actions)
        want = sync.step(actions)
        for k in range(4):
            np.testing.assert_array_equal(got[k], want[k], err_msg=f"step {step} output {k}")
        _compare_infos(got[4], want[4], f"step {step}")
        done = want[2] | want[3]
        ended_apart |= bool(done.any() and not done.all())
    assert ended_apart  # the masks of a partial end were compared
    native.close()
    sync.close()


def test_v2_is_the_default_trainings_task_with_its_episode_limit_in_the_spec():
    """gym.make("msdgrasp/GraspLift-v2") is the task the default training trains on (which adds only the
    privileged entries its critic reads), and its spec states the limit at which the env truncates; v1 stays
    loadable: the same task with the truth in its observation."""
    from msdgrasp.agents.models import TrainConfig
    from msdgrasp.envs.core import benchmark_config
    from msdgrasp.envs.registration import V1_MAX_EPISODE_STEPS
    from msdgrasp.physics.config import replace

    env = gym.make("msdgrasp/GraspLift-v2")
    assert env.unwrapped.config == benchmark_config() == benchmark_config(version=2)
    assert env.unwrapped.config.sensed_task_state
    assert replace(env.unwrapped.config, privileged_obs=True) == TrainConfig().env
    assert env.spec.max_episode_steps == env.unwrapped.config.max_episode_steps == V1_MAX_EPISODE_STEPS
    assert gym.make("msdgrasp/GraspLiftSphere-v2").unwrapped.config == benchmark_config("sphere")
    v1 = gym.make("msdgrasp/GraspLift-v1").unwrapped.config
    assert v1 == benchmark_config(version=1) and not v1.sensed_task_state
    # v2 changes the observation only: physics, actions, reward and success are v1's
    assert replace(v1, sensed_task_state=True, randomization=env.unwrapped.config.randomization) == benchmark_config()
    assert gym.make("msdgrasp/GraspLiftSphere-v1").unwrapped.config == benchmark_config("sphere", version=1)
    with pytest.raises(ValueError, match="fixed task"):
        gym.make("msdgrasp/GraspLift-v2", config={})
    # fields change by name, as for the other ids
    assert gym.make("msdgrasp/GraspLift-v2", time_limit_s=1.0).unwrapped.config.pull_action == "forward_speed"


def test_normalize_observation_steps_the_v1_vector_env_through_episode_ends():
    from gymnasium.wrappers.vector import NormalizeObservation

    env = NormalizeObservation(gym.make_vec("msdgrasp/GraspLift-v1", num_envs=4,
                                            vectorization_mode="vector_entry_point", time_limit_s=0.2,
                                            max_episode_steps=7))
    env.reset(seed=0)
    ends = 0
    for _ in range(16):
        obs, _, term, trunc, _ = env.step(np.zeros((4, 2), np.float32))
        ends += int(np.sum(term | trunc))
        assert np.all(np.isfinite(obs))
    assert ends >= 8


def test_gymnasiums_vector_wrappers_run_on_the_native_vector_env():
    from gymnasium.wrappers.vector import NormalizeObservation, RecordEpisodeStatistics

    env = RecordEpisodeStatistics(NormalizeObservation(gym.make_vec(
        ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", config={"time_limit_s": 0.2})))
    env.reset(seed=0)
    episodes = 0
    for _ in range(16):  # past two time limits of 7 steps
        _, _, term, trunc, info = env.step(np.zeros((2, 2), np.float32))
        episodes += int(np.sum(term | trunc))
    assert episodes >= 2 and "episode" in info or episodes >= 2


def test_vector_env_autoreset_same_step():
    venv = GraspLiftVectorEnv(2, time_limit_s=0.1, autoreset_mode=AutoresetMode.SAME_STEP)  # 4 steps
    obs, _ = venv.reset(seed=3)
    zero = np.zeros((2, 2), np.float32)
    for k in range(venv.config.max_episode_steps):
        obs, r, term, trunc, info = venv.step(zero)
    assert np.all(trunc) and not np.any(term)
    final = np.stack(info["final_obs"])
    assert final.shape == (2, len(OBS_NAMES)) and np.all(info["_final_obs"])
    assert np.all(np.isfinite(final))
    # the returned observation is the first one of the next episode (time fraction 0)
    assert np.all(obs[:, OBS_NAMES.index("time_fraction")] == 0.0)
    assert np.all(final[:, OBS_NAMES.index("time_fraction")] > 0.99)
    with pytest.raises(ConfigError, match=r"autoreset_mode = 'disabled' is not supported"):
        GraspLiftVectorEnv(2, autoreset_mode="disabled")


# -- reset options ---------------------------------------------------------------------------------
def test_reset_options_pin_and_validate():
    env = GraspLiftEnv()
    _, info = env.reset(seed=0, options={"mu": 0.5})
    assert info["mu"] == 0.5
    assert env.core.sim.mu_s[0] == 0.5
    _, info = env.reset(seed=0, options={"mu": 0.5, "mu_kinetic": 0.4, "stiffness_scale": 1.1, "mass_scale": 1.0})
    assert (info["mu_kinetic"], info["stiffness_scale"], info["mass_scale"]) == (0.4, 1.1, 1.0)
    # pinning does not shift the random stream: the same seed gives the same other draws
    _, a = env.reset(seed=5, options={"mu": 0.5})
    _, b = env.reset(seed=5)
    assert a["stiffness_scale"] == b["stiffness_scale"] and a["mass_scale"] == b["mass_scale"]

    with pytest.raises(ConfigError, match="bogus_key"):
        env.reset(seed=0, options={"bogus_key": 1.0})
    for bad in (-0.1, 11.0, float("nan")):
        with pytest.raises(ConfigError, match="mu"):
            env.reset(seed=0, options={"mu": bad})
    with pytest.raises(ConfigError, match="mu_kinetic"):
        env.reset(seed=0, options={"mu": 0.3, "mu_kinetic": 0.6})


# -- actions ---------------------------------------------------------------------------------------
def test_out_of_range_actions_are_clipped():
    env = GraspLiftEnv()
    env.reset(seed=2)
    o_big, r_big, *_ = env.step(np.array([5.0, 5.0]))
    o_big2, *_ = env.step(np.array([-7.0, 3.0]))
    env.reset(seed=2)
    o_one, r_one, *_ = env.step(np.array([1.0, 1.0]))
    o_one2, *_ = env.step(np.array([-1.0, 1.0]))
    np.testing.assert_array_equal(o_big, o_one)
    np.testing.assert_array_equal(o_big2, o_one2)
    assert r_big == r_one
    assert o_one[OBS_NAMES.index("prev_action_jaw")] == 1.0  # the clipped action is what is observed


@pytest.mark.parametrize(
    "action, match",
    [
        ([np.nan, 0.0], "NaN or inf"),
        ([0.0, np.inf], "NaN or inf"),
        ([-np.inf, 0.0], "NaN or inf"),
        ([0.0, 0.0, 0.0], "shape"),
        ([[0.0, 0.0]], "shape"),
        (0.5, "shape"),
    ],
)
def test_invalid_actions_raise(action, match):
    env = GraspLiftEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_vector_env_invalid_actions_raise():
    venv = GraspLiftVectorEnv(3)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="shape"):
        venv.step(np.zeros((2, 2)))
    bad = np.zeros((3, 2))
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        venv.step(bad)


# -- numerical failure -------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["nan_position", "huge_velocity"])
def test_numerical_failure_terminates_with_error_and_finite_obs(how):
    env = GraspLiftEnv()
    env.reset(seed=0)
    env.step(np.array([1.0, 0.0]))
    sim = env.unwrapped.core.sim
    if how == "nan_position":
        sim.x[0, 0, 0] = np.nan
    else:
        sim.v[0, :, :] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        obs, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0]))
    assert terminated is True and truncated is False
    assert "error" in info and "numerical" in info["error"]
    assert info["numerical_failure"] is True
    assert np.all(np.isfinite(obs)) and obs.dtype == np.float32
    assert np.isfinite(reward) and reward < 0
    assert all(np.isfinite(v) for v in info["reward_terms"].values())
    assert sum(info["reward_terms"].values()) == pytest.approx(reward)
    # the env recovers on reset
    obs, _ = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert np.all(np.isfinite(obs)) and "error" not in info and not terminated


def test_an_inverted_tet_is_a_numerical_failure(tmp_path):
    """A tet turned inside out (here by hand, on a tissue without the volume barrier that would undo it)
    ends the episode as a numerical failure: its springs and barrier would push the wrong way."""
    from msdgrasp.physics.config import builtin_config, read_yaml, write_yaml

    cfg = read_yaml(builtin_config("tissue/spleen.yaml"))
    cfg["tissue"]["volume_modulus_pa"] = 0.0
    write_yaml(tmp_path / "spleen_no_barrier.yaml", cfg)
    config = GraspLiftConfig(tissue_config=str(tmp_path / "spleen_no_barrier.yaml"), inverted_tet_is_failure=True)
    env = GraspLiftEnv(config=config)
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert not terminated and 0.0 < info["min_volume_ratio"] <= 1.0
    sim = env.unwrapped.core.sim
    a, b, c, d = sim.model.tets[0]
    p = sim.x[0]
    n = np.cross(p[c] - p[b], p[d] - p[b])
    n /= np.linalg.norm(n)
    p[a] -= 2.0 * ((p[a] - p[b]) @ n) * n  # node a mirrored through the opposite face: volume ratio -1
    obs, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert info["min_volume_ratio"] <= 0.0
    assert terminated is True and info["numerical_failure"] is True
    assert "inverted" in info["error"]
    assert np.all(np.isfinite(obs)) and reward < 0


def test_the_volume_barrier_keeps_every_tet_upright_under_a_5N_pinch(tmp_path):
    """A 5 N force-loop pinch and lift on the softest tissue (stiffness 0.8, mu 0.3): the pure MSD (no barrier)
    crushes surface tets under the jaws through zero; with the spleen's volume barrier no tet comes near it,
    the episode is no numerical failure, and the lift still succeeds."""
    from msdgrasp.agents.controllers import FixedForcePolicy
    from msdgrasp.physics.config import builtin_config, read_yaml, write_yaml

    cfg = read_yaml(builtin_config("tissue/spleen.yaml"))
    assert cfg["tissue"]["volume_modulus_pa"] > 0
    cfg["tissue"]["volume_modulus_pa"] = 0.0
    write_yaml(tmp_path / "spleen_pure_msd.yaml", cfg)
    lowest = {}
    for name, tissue in (("pure MSD", str(tmp_path / "spleen_pure_msd.yaml")), ("barrier", None)):
        # the pure-MSD run goes on past the inversion, to show how far it goes
        config = GraspLiftConfig(tissue_config=tissue, terminate_on_damage=False,
                                 inverted_tet_is_failure=name == "barrier")
        env = GraspLiftEnv(config=config)
        obs, info = env.reset(seed=0, options=dict(mu=0.3, stiffness_scale=0.8, mass_scale=1.0))
        policy = FixedForcePolicy(config, force_N=5.0)
        policy.reset([info])
        lowest[name] = 1.0
        for _ in range(300):
            obs, reward, terminated, truncated, info = env.step(policy.act(obs[None])[0])
            lowest[name] = min(lowest[name], info["min_volume_ratio"])
            if terminated or truncated:
                break
        if name == "barrier":
            assert info["peak_pinch_N"] == pytest.approx(5.0, abs=0.25)  # the loop reached the set-point
            assert info["is_success"] and not info["numerical_failure"]
    assert lowest["pure MSD"] < 0.0, lowest
    assert lowest["barrier"] > 0.1, lowest


@pytest.mark.parametrize("tissue", ["spleen", "spleen-j1"])
def test_a_held_pinch_is_steady_and_every_face_held_node_stays_in_its_friction_cone(tissue):
    """``msdgrasp experiment pinch-hold`` on the coarse spleen (5 N force-loop pinch at mu 0.3, stiffness 0.8,
    a 15 mm/s pull, a hold), shortened: read at every 1 ms step, the pinch changes by at most 0.01 N from step
    to step (standard deviation; the volume floor this barrier replaced chattered at 0.15 N), every node a jaw
    face holds keeps |Ft| <= mu_s |Fn| within 1 % (the contact law's own cone: the barrier's force on a held
    node passes through it), and no tet inverts; on the shipped spleen and on its nodes split as J1."""
    from msdgrasp.experiments.pinch_hold import run_pinch_hold
    from msdgrasp.physics.config import builtin_config

    r = run_pinch_hold("coarse", close_s=2.5, pull_s=1.0, hold_s=0.5,
                       tissue_config=builtin_config(f"tissue/{tissue}.yaml"))
    assert r.hold_pinch_N == pytest.approx(5.0, abs=0.1)  # still gripped after the pull
    assert r.pinch_step_std_pull_N <= 0.01 and r.pinch_step_std_hold_N <= 0.01, r
    assert r.held_node_samples > 1000 and r.max_friction_cone_ratio <= 1.01, r
    assert r.min_volume_ratio > 0.0, r


def test_vector_env_numerical_failure_is_isolated():
    venv = GraspLiftVectorEnv(3)
    venv.reset(seed=0)
    venv.core.sim.x[1, 0, 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        obs, r, term, trunc, info = venv.step(np.zeros((3, 2)))
    assert term.tolist() == [False, True, False]
    assert info["_error"].tolist() == [False, True, False] and "numerical failure" in info["error"][1]
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(r))  # (its last observation: zeros, never NaN)
    obs, r, term, trunc, info = venv.step(np.zeros((3, 2)))  # NEXT_STEP: the failed env starts over
    assert r[1] == 0.0 and not term[1] and np.all(np.isfinite(venv.core.sim.x))


# -- time limit, rewards -----------------------------------------------------------------------------
@pytest.mark.parametrize("make", ["gym.make", "class"])
def test_time_limit_truncates_at_max_episode_steps(make):
    env = gym.make(ENV_ID, time_limit_s=0.5) if make == "gym.make" else GraspLiftEnv(time_limit_s=0.5)
    cfg = env.unwrapped.config
    assert cfg.max_episode_steps == int(np.ceil(0.5 / cfg.agent_dt_s)) == 16
    env.reset(seed=4)
    for k in range(1, cfg.max_episode_steps + 1):
        obs, r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        assert not terminated
        assert truncated == (k == cfg.max_episode_steps), f"step {k}"
    assert obs[OBS_NAMES.index("time_fraction")] == pytest.approx(1.0, abs=0.07)


def test_default_time_limit():
    cfg = GraspLiftConfig()
    assert cfg.max_episode_steps == 304
    assert gym.spec(ENV_ID).max_episode_steps is None  # the env truncates itself


def test_reward_terms_follow_their_definitions_over_a_successful_episode():
    """Each term recomputed from the physics the env reports (slip distance, lift, pinch), not from itself."""
    from msdgrasp.agents.controllers import make_policy

    cfg = GraspLiftConfig()
    env = GraspLiftEnv(cfg)
    policy = make_policy("reactive", cfg)
    obs, info = env.reset(seed=9, options={"mu": 0.6})
    policy.reset([info])
    w = cfg.reward
    sums = dict.fromkeys(("progress", "hold", "grasp", "force", "damage"), 0.0)
    slip_before, best_lift, peak = 0.0, 0.0, 0.0
    for _ in range(cfg.max_episode_steps):
        obs, r, terminated, truncated, info = env.step(policy.act(obs[None])[0])
        terms = info["reward_terms"]
        slip_mm = (info["slip_distance_m"] - slip_before) * 1e3
        slip_before = info["slip_distance_m"]
        assert terms["slip"] == pytest.approx(-w.slip_per_mm * slip_mm, abs=1e-12)
        best_lift = max(best_lift, min(info["lifted_m"], cfg.lift_target_m))
        peak = max(peak, info["pinch_force_N"])
        for k in sums:
            sums[k] += terms[k]
        if terminated or truncated:
            break
    assert info["is_success"], "the slip-reactive controller holds at mu 0.6"
    # progress pays the highest lift once; hold is potential-based from 0 to a full hold
    assert sums["progress"] == pytest.approx(w.progress * best_lift / cfg.lift_target_m, rel=1e-9)
    assert sums["progress"] == pytest.approx(w.progress)
    assert sums["hold"] == pytest.approx(w.hold)
    assert sums["grasp"] == 0.0 and sums["force"] == 0.0 and sums["damage"] == 0.0  # default weights 0 / no damage
    # the episode's end: the bonus, discounted by the peak pinch; no failure penalty
    assert terms["success"] == w.success_bonus and terms["failure"] == 0.0
    assert info["peak_pinch_N"] == pytest.approx(peak)
    assert terms["peak_force"] == pytest.approx(-w.peak_force * peak / cfg.reference_force_N)
    assert 0.5 < peak < 2.0  # the reactive controller's light grip at mu 0.6 (README: 1.19 N)


# -- rendering --------------------------------------------------------------------------------------
def test_render_rgb_array():
    env = gym.make(ENV_ID, render_mode="rgb_array")
    env.reset(seed=0)
    f0 = env.render()
    assert isinstance(f0, np.ndarray) and f0.dtype == np.uint8 and f0.shape == (480, 640, 3)
    for _ in range(25):
        env.step(np.array([1.0, 1.0]))
    f1 = env.render()
    assert f1.shape == f0.shape and f1.dtype == np.uint8
    assert np.count_nonzero(np.any(f0 != f1, axis=2)) > 200  # a different state draws a different image
    assert f1.std() > 5  # not a blank frame
    assert GraspLiftEnv().render() is None  # no render mode: nothing


def test_render_helper_sizes_and_cache():
    from msdgrasp.envs.render import render_rgb

    venv = GraspLiftVectorEnv(2, render_mode="rgb_array")
    venv.reset(seed=0)
    img = render_rgb(venv.core, 1, width=200, height=150, color_by="pressure")
    assert img.shape == (150, 200, 3) and img.dtype == np.uint8
    assert len(venv.core._render_cache) == 1
    render_rgb(venv.core, 0, width=200, height=150)
    assert len(venv.core._render_cache) == 1  # figure reused
    frames = venv.render()
    assert frames.shape == (2, 480, 640, 3) and frames.dtype == np.uint8
    with pytest.raises(IndexError):
        render_rgb(venv.core, 2)
    with pytest.raises(ValueError, match="color_by"):
        render_rgb(venv.core, 0, color_by="temperature")


# -- Stable-Baselines3 adapter ---------------------------------------------------------------------


def test_sb3_adapter_reset_step_shapes_and_terminal_observation():
    from msdgrasp.envs.sb3 import GraspLiftSB3VecEnv, make_sb3_env

    venv = make_sb3_env(3, None, seed=5)
    assert isinstance(venv, GraspLiftSB3VecEnv)
    from stable_baselines3.common.vec_env import VecEnv

    assert isinstance(venv, VecEnv)
    assert venv.observation_space.shape == (len(OBS_NAMES),) and venv.action_space.shape == (2,)
    obs = venv.reset()
    assert obs.shape == (3, len(OBS_NAMES)) and obs.dtype == np.float32
    obs, rew, dones, infos = venv.step(np.zeros((3, 2), np.float32))
    assert obs.shape == (3, len(OBS_NAMES)) and rew.shape == (3,) and dones.shape == (3,) and dones.dtype == bool
    assert isinstance(infos, list) and len(infos) == 3
    assert all("is_success" in i and "TimeLimit.truncated" in i for i in infos)
    with pytest.raises(ValueError):
        venv.step(np.zeros((2, 2)))

    short = GraspLiftSB3VecEnv(2, time_limit_s=0.1, seed=0)  # 4-step episodes
    short.reset()
    for k in range(short.config.max_episode_steps):
        obs, rew, dones, infos = short.step(np.zeros((2, 2), np.float32))
    assert dones.all()
    for info in infos:
        assert info["TimeLimit.truncated"] is True
        term = info["terminal_observation"]
        assert term.shape == (len(OBS_NAMES),) and term[OBS_NAMES.index("time_fraction")] > 0.99
        assert info["episode"]["l"] == short.config.max_episode_steps
    assert np.all(obs[:, OBS_NAMES.index("time_fraction")] == 0.0)  # already reset
    # attributes, methods, wrappers
    assert short.get_attr("render_mode") == ["rgb_array", "rgb_array"]
    assert len(short.get_attr("mu")) == 2 and short.get_attr("mu", indices=[1])[0] == short.core.mu[1]
    assert short.env_is_wrapped(gym.Wrapper) == [False, False]
    frame = short.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    short.close()


def test_sb3_adapter_matches_single_envs_and_seed_conventions():
    from msdgrasp.envs.sb3 import GraspLiftSB3VecEnv

    venv = GraspLiftSB3VecEnv(2)
    assert venv.seed(20) == [20, 21]
    venv.set_options({"mu": 0.5})
    obs = venv.reset()
    assert [d["mu"] for d in venv.reset_infos] == [0.5, 0.5]
    acts = np.stack([_actions(10, 1), _actions(10, 2)], axis=1)
    rews = []
    for a in acts:
        obs, r, dones, infos = venv.step(a)
        rews.append(r)
    for i in range(2):
        env = GraspLiftEnv()
        env.reset(seed=20 + i, options={"mu": 0.5})
        rs = [env.step(a)[1] for a in acts[:, i]]
        np.testing.assert_allclose(np.array(rews)[:, i], rs, rtol=1e-6)  # SB3 rewards are float32
        np.testing.assert_array_equal(obs[i], env.core.obs[0].astype(np.float32))
    # seeds and options are used once: a plain reset() re-randomises mu
    venv.reset()
    assert any(d["mu"] != 0.5 for d in venv.reset_infos)


def test_sb3_ppo_trains_on_the_vec_env_and_sees_episode_stats():
    from stable_baselines3 import PPO

    from msdgrasp.envs.sb3 import make_sb3_env

    venv = make_sb3_env(2, GraspLiftConfig(time_limit_s=0.5), seed=0)
    model = PPO("MlpPolicy", venv, n_steps=32, batch_size=32, n_epochs=1, seed=0, device="cpu", verbose=0)
    model.learn(64)
    assert model.num_timesteps >= 64
    # episode stats reach SB3's logger without a Monitor: 0.5 s episodes are 16 agent steps, and an
    # episode that ends by the time limit without success pays the failure penalty
    assert len(model.ep_info_buffer) > 0 and len(model.ep_success_buffer) > 0
    assert all(ep["l"] == 16 for ep in model.ep_info_buffer)
    assert all(ep["r"] < 0.0 for ep in model.ep_info_buffer)
    action, _ = model.predict(venv.reset(), deterministic=True)
    assert action.shape == (2, 2)
