"""Settings of the built-in controllers, checked where they are given: in a policy spec (``fixed:<N>``,
``slipfeedback:key=value,...``, parsed by :mod:`.controller_registry` through these records), in a training config
(``residual_base``) or in code. Imports nothing of the package: a record is plain data with its checks."""

from __future__ import annotations

import dataclasses

#: the longest a pinch-gated pull waits for the pinch reading beyond the contact rule, agent steps (1 s at 30 Hz): a
#: force sensor that reads low (bias, a weak force loop) delays the pull, never stalls it
GATE_WAIT_STEPS = 30

#: the settings a ``slipfeedback:key=value,...`` spec may give (initial=N, gain=N per mm, pull=fraction of the top
#: speed, max=N, gate=share of the set-point, oracle=multiple of the oracle's minimal force at the episode's mu,
#: estimator=a friction estimator's file or ``builtin``, margin=multiple of the minimal force at the estimate, told=1:
#: the estimate replaced by the episode's mu), and the SlipFeedbackPolicy argument each sets
SLIPFEEDBACK_KEYS = {"initial": "initial_force_N", "gain": "gain_N_per_mm", "pull": "pull", "max": "max_force_N",
                     "gate": "pinch_gate", "oracle": "oracle_margin", "margin": "estimate_margin",
                     "estimator": "friction_estimator", "told": "told_mu"}
#: the spec keys whose value is a path, not a number
PATH_KEYS = ("estimator",)


@dataclasses.dataclass(frozen=True)
class FixedForceSettings:
    """The fixed-force controller's settings (``agents.controllers.FixedForcePolicy``); ValueError naming the field
    on a bad one."""

    force_N: float = 2.5  # the pinch force it closes to and holds, N
    pull: float = 0.5  # pull speed, a fraction of the arm's top speed

    def __post_init__(self) -> None:
        if not self.force_N > 0:
            raise ValueError(f"force_N must be > 0 (a force in newtons), got {self.force_N!r}")
        if not 0 < self.pull <= 1:
            raise ValueError(f"pull must be in (0, 1], got {self.pull!r}")


#: the steepest slip feedback: 100 N per mm of slip reaches any grip the jaw has within 0.05 mm
MAX_GAIN_N_PER_MM = 100.0


@dataclasses.dataclass(frozen=True)
class SlipFeedbackSettings:
    """The slip-feedback controller's settings (``agents.controllers.SlipFeedbackPolicy``); ValueError naming the
    field on a bad one."""

    initial_force_N: float = 0.55  # the grip until the tissue slips, N
    gain_N_per_mm: float = 1.0  # the grip added per mm of slip since lifting began
    max_force_N: float = 4.0  # the largest grip, N
    pull: float = 0.5  # pull speed, a fraction of the arm's top speed
    contact_jaws: int = 2  # jaws touching before the pull may start
    settle_steps: int = 6  # agent steps the jaws hold before the pull starts
    # the pull also waits until the pinch reading reaches this fraction of the set-point (0: it does not wait), at
    # most GATE_WAIT_STEPS agent steps beyond settle_steps
    pinch_gate: float = 0.0
    # > 0: the initial grip is this multiple of the oracle's minimal fixed force at the episode's friction and this
    # pull speed (the controller is told mu, as the oracle is); 0: initial_force_N
    oracle_margin: float = 0.0
    # with a friction estimator: the grip set before the pull is this multiple of the minimal fixed force at the
    # estimated friction
    estimate_margin: float = 1.2
    # with a friction estimator: 1, the estimate is replaced by the episode's mu (the controller is told it, as the
    # oracle is: a privileged teacher that closes, probes and pulls as the estimating controller does); 0: estimated
    told_mu: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.initial_force_N <= self.max_force_N:
            raise ValueError(f"initial_force_N must be in (0, max_force_N={self.max_force_N}], "
                             f"got {self.initial_force_N!r}")
        if not 0 <= self.gain_N_per_mm <= MAX_GAIN_N_PER_MM:
            raise ValueError(f"gain_N_per_mm must be in [0, {MAX_GAIN_N_PER_MM:g}], got {self.gain_N_per_mm!r}")
        if not 0 < self.pull <= 1:
            raise ValueError(f"pull must be in (0, 1], got {self.pull!r}")
        if self.contact_jaws not in (1, 2, 3):
            raise ValueError(f"contact_jaws must be 1, 2 or 3, got {self.contact_jaws!r}")
        if not (isinstance(self.settle_steps, int) and self.settle_steps >= 0):
            raise ValueError(f"settle_steps must be an integer >= 0, got {self.settle_steps!r}")
        if not 0 <= self.pinch_gate <= 1:
            raise ValueError(f"pinch_gate must be in [0, 1], got {self.pinch_gate!r}")
        if not (self.oracle_margin == 0 or 0.5 <= self.oracle_margin <= 3):
            raise ValueError(f"oracle_margin must be 0 (off) or in [0.5, 3], got {self.oracle_margin!r}")
        if not 0.5 <= self.estimate_margin <= 3:
            raise ValueError(f"estimate_margin must be in [0.5, 3], got {self.estimate_margin!r}")
        if self.told_mu not in (0, 1):
            raise ValueError(f"told_mu must be 0 or 1, got {self.told_mu!r}")
