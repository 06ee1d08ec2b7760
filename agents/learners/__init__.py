"""The learners behind one small interface, and their registry (docs/learners.md).

A learner trains a policy into a run folder and reads back what it wrote: the shipped model, its
checkpoints, its summary, and the task each model was trained on. Everything that differs between
learners (file names, config class, how a model is loaded) lives in the learner's module; the rest of the
package (the CLI, evaluation, selection, seeds, sweep) asks the registry by NAME:

* :func:`get_learner` (``"ppo"``, ``"sac"``: Stable-Baselines3, :mod:`.sb3`; ``"rsl"``: rsl-rl's
  torch-native PPO, :mod:`.rsl`; ``"recurrent"``: a GRU actor beside a privileged critic, taught by DAgger and
  fine-tuned by PPO, :mod:`.recurrent`);
* :func:`learner_of_run` / :func:`learner_of_model`: the learner NAME RECORDED in a run's or a model's
  files (an SB3 config's ``algo``, a torch policy's ``policy.json``), never found by trying loaders;
* :func:`learner_of_config`: the learner a training config belongs to.

Modules: :mod:`.base` (the interface and the registry), and per learner a layout module (its file names
and how to read a saved model: :mod:`.sb3_layout`, :mod:`.rsl_layout`, which its training code and its
policy class use too) and the learner itself (:mod:`.sb3`, :mod:`.rsl`, registered here on import; it
calls the training code). Lower modules (controllers, evaluation, training) import only :mod:`.base` and
the layouts, so the import graph stays one-way. Nothing heavy loads at import time (torch, SB3, rsl-rl and
numba load inside the methods), so the command line can list the learners without loading them.
"""

from __future__ import annotations

from .base import (  # noqa: F401 (the package's interface)
    DEFAULT, Learner, Policy, RunLayout, RunSummary, TrainOverrides, default_learner, get_learner, learner_names,
    learner_of_config, learner_of_model, learner_of_run, model_kinds, numbered_files, register,
)

# the learners, registered on import in this order (adding one: its module here, docs/learners.md)
from . import sb3  # noqa: E402,F401
from . import rsl  # noqa: E402,F401
from . import recurrent  # noqa: E402,F401

__all__ = ["DEFAULT", "Learner", "Policy", "RunLayout", "RunSummary", "TrainOverrides", "default_learner",
           "get_learner", "learner_names", "learner_of_config", "learner_of_model", "learner_of_run", "model_kinds",
           "numbered_files", "register"]
