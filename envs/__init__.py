"""Gymnasium environments (GraspLift), the batched core, SB3 adapter and rerun recording."""

from .registration import register_envs

register_envs()
