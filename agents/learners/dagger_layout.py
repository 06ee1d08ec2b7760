"""The teacher-student learner's run layout (what :mod:`.dagger`, the training (:mod:`msdgrasp.agents.dagger`) and the
student policy share; no training here)."""

from __future__ import annotations

from .base import RunLayout

NAME = "dagger"
LAYOUT = RunLayout(model="student.pt", fallback_model=None, summary="summary.json", config="config.json",
                   checkpoint="checkpoints/student_{}.pt",
                   model_description="<name>.pt with <name>.json beside it recording learner dagger")
#: the built-in config (``msdgrasp train --learner dagger`` without ``--config``)
CONFIG = "train/dagger.yaml"
