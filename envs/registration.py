"""Gymnasium registration of the msdgrasp environments.

Gymnasium 1.x has no plugin entry points: ``import msdgrasp`` (or ``import msdgrasp.envs``) registers
the ids, after which::

    import gymnasium as gym
    import msdgrasp  # noqa: F401  (registers the ids)

    env = gym.make("msdgrasp/GraspLift-v0")
    envs = gym.make_vec("msdgrasp/GraspLift-v0", num_envs=16, vectorization_mode="vector_entry_point")

or, without the explicit import, ``gym.make("msdgrasp:msdgrasp/GraspLift-v0")`` (Gymnasium imports the
module named before the colon).
"""

from __future__ import annotations

import gymnasium as gym

IDS = {
    "msdgrasp/GraspLift-v0": {},
    "msdgrasp/GraspLiftSphere-v0": {"scene": "sphere"},
}


def register_envs() -> None:
    for env_id, kwargs in IDS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point="msdgrasp.envs.grasp_lift:GraspLiftEnv",
            vector_entry_point="msdgrasp.envs.grasp_lift:GraspLiftVectorEnv",
            kwargs=dict(kwargs),
            max_episode_steps=None,  # the env truncates itself at its time limit
            disable_env_checker=False,
        )
