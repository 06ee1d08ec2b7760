"""A tanh-squashed Gaussian action distribution for rsl-rl's PPO (``TorchPPOConfig.squash_actions``).

rsl-rl's :class:`~rsl_rl.modules.distribution.GaussianDistribution` samples unbounded actions and the env
clips them to [-1, 1]. A clipped pinch set-point whose mean drifts past +1 acts at full force whatever the
mean, so nothing pulls the mean back; the SB3 training squashes instead (``squash_output``,
docs/design.md). This is the same squash for rsl-rl: ``a = tanh(u)``, ``u ~ N(mean, std)``.

Actions are stored squashed, as SB3 stores them, so the rollout's and the update's log-probabilities come
from the same ``a`` (``u = atanh(a)``, clamped 1e-6 inside the bounds); the change-of-variables term,
``-sum log(1 - a^2)``, is included, and cancels in PPO's ratio. The KL of the adaptive learning rate is the
Gaussian's (the squash is one-to-one, so the KL of the squashed pair is the same). The exported policy
(``as_deterministic_output_module``) is ``tanh(mean)``.

Tested on four seeds against the clipped Gaussian (docs/design.md): lighter grips at high
friction on two, heavier at low friction on all four; an option, off by default.

Only imported where rsl-rl is installed (the ``gpu`` extra); rsl-rl resolves it by name.
"""

from __future__ import annotations

from ..physics.config import needs_extra

with needs_extra("gpu", "the torch-native PPO's squashed actions"):
    import torch
    from rsl_rl.modules.distribution import GaussianDistribution
    from torch import nn

#: distance kept from the bounds where squashed actions are mapped back (float32 tanh reaches 1.0 at |u| ~ 9)
EPS = 1e-6


class SquashedGaussianDistribution(GaussianDistribution):
    """``tanh`` of a Gaussian with a state-independent, learnt std (rsl-rl's Gaussian, squashed)."""

    def sample(self) -> torch.Tensor:
        return torch.tanh(super().sample())

    def deterministic_output(self, mlp_output: torch.Tensor) -> torch.Tensor:
        return torch.tanh(mlp_output)

    def as_deterministic_output_module(self) -> nn.Module:
        return nn.Tanh()

    def log_prob(self, outputs: torch.Tensor) -> torch.Tensor:
        a = outputs.clamp(-1.0 + EPS, 1.0 - EPS)
        u = torch.atanh(a)
        return (self._distribution.log_prob(u) - torch.log1p(-a * a)).sum(dim=-1)  # type: ignore[union-attr]
