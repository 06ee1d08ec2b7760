"""The actor's observation comes from named sensors (envs/sensors.py), entry by entry.

Two sub-envs with the same physics seed and different sensor seeds are driven by the same open-loop actions, so their
tissues move alike (the physics never reads a sensor) and only the readings can differ:
* an entry whose sensor is noisy differs somewhere in the episode; an entry of exact sensors never does;
* with a sensor absent, every entry derived from it is constant over the episode;
* the truth behind the sensed task-state entries is in the privileged block, the same for both.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from msdgrasp.envs.core import benchmark_config
from msdgrasp.envs.grasp_lift import GraspLiftEnv, GraspLiftVectorEnv
from msdgrasp.envs.sensors import ENTRY_SENSORS, SENSORS, absent_entries, entry_sensors, noisy_entries
from msdgrasp.envs.task import N_OBS, OBS, OBS_NAMES, PRIVILEGED_TRUTH
from msdgrasp.physics.config import ConfigError

#: close to a 1.8 N set-point, then pull at 10 mm/s from step 40: lifts the nominal spleen to its target and holds
STEPS = 200


def _actions(k: int) -> np.ndarray:
    return np.array([[0.2, -1.0 if k < 40 else 0.0]] * 2)


def _run(config, seed: int = 3) -> tuple[np.ndarray, list[dict]]:
    """Observations (T, 2, obs_dim) of two sub-envs with physics seed ``seed`` and sensor seeds 0 and 1, up to the
    step the first episode ends; and the infos."""
    env = GraspLiftVectorEnv(2, config)
    obs, _ = env.reset(seed=[seed, seed], options={"sensor_seed": [0, 1], "mu": 0.6})
    frames, infos = [obs], []
    for k in range(STEPS):
        obs, _, term, trunc, info = env.step(_actions(k))
        frames.append(obs)
        infos.append(info)
        if (term | trunc).any():
            break
    return np.stack(frames), infos


def _noisy(**randomization) -> object:
    """The v2 task with every noisy sensor noisy (and the critic's privileged entries)."""
    cfg = benchmark_config(version=2)
    return replace(cfg, privileged_obs=True,
                   randomization=replace(cfg.randomization, sensor_noise_N=0.05, **randomization))


@pytest.fixture(scope="module")
def v2_run():
    cfg = _noisy()
    return cfg, *_run(cfg)


@pytest.fixture(scope="module")
def absent_run():
    cfg = _noisy(slip_sensing="absent", lift_sensing="absent")
    return cfg, *_run(cfg)


def test_every_entry_names_its_sensors():
    assert tuple(ENTRY_SENSORS) == OBS_NAMES
    for entry, names in ENTRY_SENSORS.items():
        assert names and all(n in SENSORS and n != "truth" for n in names), entry
    # before v2 the task-state entries are the truth; from v2 none is
    assert any("truth" in v for v in entry_sensors(benchmark_config(version=1)).values())
    assert not any("truth" in v for v in entry_sensors(benchmark_config(version=2)).values())


@pytest.mark.parametrize("entry", OBS_NAMES)
def test_noisy_sensor_entries_differ_between_sensor_seeds(v2_run, entry):
    cfg, obs, infos = v2_run
    # the physics is the same in both (the same draws, the same actions): only readings can differ
    assert infos[-1]["lifted_m"][0] == infos[-1]["lifted_m"][1]
    assert infos[-1]["lifted_m"][0] > cfg.lift_target_m  # (the run reaches the hold: its entries are exercised)
    a, b = obs[:, 0, OBS[entry]], obs[:, 1, OBS[entry]]
    if entry in noisy_entries(cfg):
        assert np.any(a != b), f"{entry} reads a noisy sensor yet is the same under two sensor seeds"
    else:
        np.testing.assert_array_equal(a, b, err_msg=f"{entry} reads exact sensors yet differs between sensor seeds")


@pytest.mark.parametrize("entry", OBS_NAMES)
def test_absent_sensor_entries_are_constant(absent_run, entry):
    cfg, obs, _ = absent_run
    series = obs[:, 0, OBS[entry]]
    if entry in absent_entries(cfg):
        assert np.all(series == series[0]), f"{entry} derives from an absent sensor yet changes"
    elif entry in ("lift_progress", "pull_distance", "normal_force_0", "jaw_opening"):
        assert np.ptp(series) > 0.0  # (a present sensor does read the episode)


def test_absent_sensors_cover_the_derived_entries():
    cfg = _noisy(slip_sensing="absent", lift_sensing="absent")
    assert set(absent_entries(cfg)) == {
        "slip_speed_0", "slip_speed_1", "slip_speed_2", "slipping_fraction_0", "slipping_fraction_1",
        "slipping_fraction_2", "lift_slip", "hold_slip", "lift_progress", "hold_progress", "lift_lag", "best_lift"}


def test_truth_is_privileged_and_matches_the_simulation(v2_run):
    cfg, obs, infos = v2_run
    truth = obs[1:, :, N_OBS + 3 + 3 * cfg.privileged_nodes:][:, :, :len(PRIVILEGED_TRUTH)]
    np.testing.assert_array_equal(truth[:, 0], truth[:, 1])  # the truth does not depend on the sensor seed
    lift = np.array([i["lifted_m"][0] for i in infos]) / cfg.lift_target_m
    np.testing.assert_allclose(truth[:, 0, PRIVILEGED_TRUTH.index("true_lift_progress")], lift, rtol=1e-5, atol=1e-7)
    peak = np.array([i["peak_pinch_N"][0] for i in infos]) / cfg.reference_force_N
    np.testing.assert_allclose(truth[:, 0, PRIVILEGED_TRUTH.index("true_peak_pinch")], peak, rtol=1e-5, atol=1e-7)


def test_tracked_lift_is_the_truth_delayed_with_its_noise(v2_run):
    """The tracker's reading is the true lift of ``lift_delay_steps`` frames before, within a few noise sigmas."""
    cfg, obs, infos = v2_run
    delay, sigma = cfg.randomization.lift_delay_steps, cfg.randomization.lift_noise_m
    true = np.array([i["lifted_m"][0] for i in infos])
    sensed = obs[1:, 0, OBS["lift_progress"]] * cfg.lift_target_m
    err = sensed[delay:] - true[:len(true) - delay]
    assert abs(np.mean(err)) < 4 * sigma / np.sqrt(len(err))  # unbiased
    assert 0.7 * sigma < np.std(err) < 1.3 * sigma  # its noise model


def test_v1_task_state_entries_are_the_truth():
    cfg = replace(benchmark_config(version=1), randomization=replace(benchmark_config(version=1).randomization,
                                                                     sensor_noise_N=0.05))
    obs, infos = _run(cfg)
    lift = np.array([i["lifted_m"][0] for i in infos]) / cfg.lift_target_m
    np.testing.assert_allclose(obs[1:, 0, OBS["lift_progress"]], lift, rtol=1e-5, atol=1e-7)
    # v1 draws its sensor noise from the physics stream: the sensor seed changes nothing
    np.testing.assert_array_equal(obs[:, 0], obs[:, 1])


def test_sensor_seed_needs_a_seed_and_a_count():
    env = GraspLiftEnv(benchmark_config(version=2))
    with pytest.raises(ConfigError, match="sensor_seed"):
        env.reset(options={"sensor_seed": 2})
    with pytest.raises(ConfigError, match="sensor_seed"):
        env.reset(seed=1, options={"sensor_seed": -1})


def test_docstring_table_names_each_entrys_sensors():
    """GraspLiftEnv's observation table gives every entry (0-31) with the sensors ENTRY_SENSORS declares."""
    rows = {}
    for line in GraspLiftEnv.__doc__.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0][:1].isdigit():
            lo, _, hi = cells[0].partition("-")
            if hi and not hi.isdigit():
                continue
            for i in range(int(lo), int(hi or lo) + 1):
                rows[i] = tuple(n.strip() for n in cells[2].split(","))
    assert sorted(i for i in rows if i < len(OBS_NAMES)) == list(range(len(OBS_NAMES)))
    for i, name in enumerate(OBS_NAMES):
        assert set(rows[i]) == set(ENTRY_SENSORS[name]), name


def test_default_training_meets_the_v2_sensors():
    """The default training draws its episodes under the benchmark task's sensors at least (a field left out of
    train_randomization would fall back to no noise)."""
    from msdgrasp.agents.models import TrainConfig
    from msdgrasp.envs.core import V2_SENSING
    from msdgrasp.physics.config import builtin_config

    cfg = TrainConfig.load(builtin_config("train/ppo.yaml"))
    assert cfg.env.sensed_task_state
    for name, level in V2_SENSING.items():
        assert getattr(cfg.training_task().randomization, name) >= level, name
