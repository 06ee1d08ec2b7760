"""The recurrent learner's run layout (what :mod:`.recurrent`, the training (:mod:`msdgrasp.agents.recurrent_training`)
and the student policy share; no training here)."""

from __future__ import annotations

from .base import RunLayout

NAME = "recurrent"
LAYOUT = RunLayout(model="student.pt", fallback_model=None, summary="summary.json", config="config.json",
                   checkpoint="checkpoints/student_{}.pt",
                   model_description="<name>.pt with <name>.json beside it recording learner recurrent")
#: the built-in config (``msdgrasp train --learner recurrent`` without ``--config``)
CONFIG = "train/recurrent.yaml"
