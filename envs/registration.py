"""Gymnasium registration of the msdgrasp environments.

Gymnasium 1.x has no plugin entry points: ``import msdgrasp`` (or ``import msdgrasp.envs``) registers
the ids, after which::

    import gymnasium as gym
    import msdgrasp  # noqa: F401  (registers the ids)

    env = gym.make("msdgrasp/GraspLift-v2")
    envs = gym.make_vec("msdgrasp/GraspLift-v2", num_envs=16, vectorization_mode="vector_entry_point")

or, without the explicit import, ``gym.make("msdgrasp:msdgrasp/GraspLift-v2")`` (Gymnasium imports the
module named before the colon).

``-v2`` is the benchmark task (:func:`.core.benchmark_config`), the one the results are about: every observation
entry from a named sensor. ``-v1`` is the same task whose actor reads the simulation's truth for lift, slip and peak
pinch (kept loadable for its published results); ``-v0`` is the first interface (GraspLiftConfig's defaults). The
version history is in :class:`.grasp_lift.GraspLiftEnv`.
"""

from __future__ import annotations

import gymnasium as gym

#: the episode limit of the v1 and v2 tasks, agent steps (their time limit, 10 s at 33 ms; tests/test_env_api.py checks
#: it against benchmark_config().max_episode_steps: written here so that registering imports no physics)
V1_MAX_EPISODE_STEPS = 304

#: id -> (entry point, vector entry point, kwargs, spec's max_episode_steps)
IDS = {
    "msdgrasp/GraspLift-v0": ("GraspLiftEnv", "GraspLiftVectorEnv", {}, None),
    "msdgrasp/GraspLiftSphere-v0": ("GraspLiftEnv", "GraspLiftVectorEnv", {"scene": "sphere"}, None),
    "msdgrasp/GraspLift-v1": ("make_benchmark_env", "make_benchmark_vector_env", {"scene": "spleen", "version": 1},
                              V1_MAX_EPISODE_STEPS),
    "msdgrasp/GraspLiftSphere-v1": ("make_benchmark_env", "make_benchmark_vector_env", {"scene": "sphere",
                                                                                        "version": 1},
                                    V1_MAX_EPISODE_STEPS),
    "msdgrasp/GraspLift-v2": ("make_benchmark_env", "make_benchmark_vector_env", {"scene": "spleen", "version": 2},
                              V1_MAX_EPISODE_STEPS),
    "msdgrasp/GraspLiftSphere-v2": ("make_benchmark_env", "make_benchmark_vector_env", {"scene": "sphere",
                                                                                        "version": 2},
                                    V1_MAX_EPISODE_STEPS),
}


def register_envs() -> None:
    for env_id, (entry, vector_entry, kwargs, max_steps) in IDS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=f"msdgrasp.envs.grasp_lift:{entry}",
            vector_entry_point=f"msdgrasp.envs.grasp_lift:{vector_entry}",
            kwargs=dict(kwargs),
            max_episode_steps=max_steps,  # (the env also truncates itself at its time limit, on the same step)
            disable_env_checker=False,
        )
