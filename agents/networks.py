"""Policy networks for Stable-Baselines3: an asymmetric actor-critic (privileged critic).

The GraspLift task randomises friction, stiffness and mass per episode; the actor cannot see them and must
infer them from touch (slip, friction use). The *critic* is only needed during training, so it may see
them: with ``env.privileged_obs`` the observation carries mu, the two scales and node displacements after
the task observations of every frame, and :class:`AsymmetricActorCriticPolicy` zeroes those entries before
the actor's network while the critic gets the whole vector. The value of a state then no longer averages
over unseen frictions, which takes most of the noise out of PPO's advantages on low-friction episodes
(asymmetric actor-critic: Pinto et al., RSS 2018). The deployed actor is blind to the privileged entries by
construction (a fixed mask inside the network; a test perturbs them and checks the action is unchanged).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from gymnasium import spaces

from ..physics.config import needs_extra

with needs_extra("train", "the SB3 policy networks"):
    import torch
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, get_flattened_obs_dim


class MaskedFlatten(BaseFeaturesExtractor):
    """Flatten the observation and zero the entries where ``keep`` is False (no trainable parameters)."""

    def __init__(self, observation_space: spaces.Box, keep: Sequence[bool]) -> None:
        dim = get_flattened_obs_dim(observation_space)
        if len(keep) != dim:
            raise ValueError(f"keep: {len(keep)} entries for an observation of {dim}")
        super().__init__(observation_space, dim)
        self.register_buffer("keep", torch.as_tensor(np.asarray(keep, dtype=np.float32)))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return torch.flatten(observations, start_dim=1) * self.keep


class AsymmetricActorCriticPolicy(ActorCriticPolicy):
    """``MlpPolicy`` whose actor sees only the entries where ``actor_mask`` is True; the critic sees all.

    Pass ``policy_kwargs={"actor_mask": mask, "net_arch": [...]}``; :func:`~msdgrasp.envs.core.actor_mask` builds the
    mask of a GraspLift observation. Actor and critic get separate networks (``share_features_extractor`` is off).
    """

    def __init__(self, *args: Any, actor_mask: Sequence[bool], **kwargs: Any) -> None:
        kwargs["share_features_extractor"] = False
        self.actor_mask = [bool(k) for k in actor_mask]
        super().__init__(*args, **kwargs)
        # the actor's extractor masks; the critic's (built by SB3) flattens everything. Neither has weights,
        # so the optimizer SB3 already built covers every trainable parameter.
        self.pi_features_extractor = MaskedFlatten(self.observation_space, self.actor_mask)
        self.features_extractor = self.pi_features_extractor

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data["actor_mask"] = self.actor_mask
        return data
