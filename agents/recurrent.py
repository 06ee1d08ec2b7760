"""A policy with memory: a GRU over the actor's sensed entries, and the policy that runs it step by step.

The actor of the recurrent learner (:mod:`.recurrent_training`) is a :class:`StudentNet`: the actor's observation
entries (the task's sensed entries, never the privileged ones) normalised by the training data's statistics, a GRU
(``memory: gru``) or nothing (``memory: none``, the ablation without memory: an MLP on the current frame), then a
two-layer head to the two actions. Its hidden state is what the policy remembers of the episode: the friction it
has inferred from the closing, whether the grip is set, how far the pull has gone. :class:`StudentPolicy` keeps
that state per batch slot: ``reset`` zeroes it for a new batch of episodes, ``reset_one`` for one slot, ``act``
carries it from step to step, so evaluation, the suites, ``record`` and ``collect`` run it like any policy.

A saved student is ``<name>.pt`` (the network's tensors, ``torch.save`` of a state dict, loaded with
``weights_only``) with ``<name>.json`` beside it (learner, architecture, actor columns, training config).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..physics.config import ConfigError, atomic_write, atomic_write_text, needs_extra

#: what a student remembers: a GRU over the episode, or nothing (the current frame only)
MEMORIES = ("gru", "none")


def _torch():
    with needs_extra("train", "a student policy"):
        import torch
    return torch


def make_student_net(n_in: int, hidden: int, memory: str):
    """A :class:`StudentNet` (built here so that torch loads only when a student is made or run)."""
    torch = _torch()
    nn = torch.nn

    class StudentNet(nn.Module):
        """Normalised actor entries -> (GRU) -> MLP head -> 2 actions (unclipped; the policy clips to [-1, 1])."""

        def __init__(self) -> None:
            super().__init__()
            if memory not in MEMORIES:
                raise ConfigError(f"memory must be one of {', '.join(MEMORIES)}, got {memory!r}")
            self.memory = memory
            self.hidden = int(hidden)
            self.register_buffer("obs_mean", torch.zeros(n_in))
            self.register_buffer("obs_std", torch.ones(n_in))
            self.inp = nn.Linear(n_in, hidden)
            self.gru = nn.GRU(hidden, hidden, batch_first=True) if memory == "gru" else None
            self.head = nn.Sequential(nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, 2))

        def forward(self, x, h=None):
            """x (B, T, n_in) raw entries, h (1, B, hidden) or None (a new episode) -> (actions (B, T, 2), h)."""
            z = torch.tanh(self.inp((x - self.obs_mean) / self.obs_std))
            if self.gru is not None:
                z, h = self.gru(z, h)
            return self.head(z), h

    return StudentNet()


def meta_path(model: str | Path) -> Path:
    """The ``.json`` beside a saved student (``student.pt`` -> ``student.json``)."""
    return Path(model).with_suffix(".json")


def save_student(net, path: str | Path, meta: dict[str, Any]) -> Path:
    """Write the network's tensors to ``path`` and ``meta`` (learner, architecture, columns, config) beside it,
    each atomically."""
    torch = _torch()
    path = Path(path)
    for key in ("learner", "n_in", "hidden", "memory", "actor_columns", "config"):
        if key not in meta:
            raise ValueError(f"a student's description needs {key!r}")
    atomic_write(path, lambda p: torch.save(net.state_dict(), p))
    atomic_write_text(meta_path(path), json.dumps(meta, indent=1) + "\n")
    return path


def read_student_meta(model: str | Path, learner: str | None = None) -> dict[str, Any]:
    """The description beside a saved student (ConfigError naming the missing or broken file, or one recording a
    learner other than ``learner``; default: the learner recorded there, whichever it is)."""
    from .learners.base import read_model_record

    return read_model_record(model, learner, ("config.env", "actor_columns", "memory", "hidden", "n_in"), "student")


def load_student_net(model: str | Path):
    """The saved student's network (eval mode) and its description."""
    torch = _torch()
    meta = read_student_meta(model)
    net = make_student_net(int(meta["n_in"]), int(meta["hidden"]), str(meta["memory"]))
    try:
        net.load_state_dict(torch.load(str(model), map_location="cpu", weights_only=True))
    except (OSError, RuntimeError, ValueError) as exc:
        raise ConfigError(f"model {model}: not a student's tensors ({exc})") from None
    net.eval()
    return net, meta


class StudentPolicy:
    """A student network run step by step with its hidden state per batch slot (deterministic)."""

    def __init__(self, net, columns: Sequence[int], name: str = "student") -> None:
        self.net = net
        self.columns = np.asarray(columns, dtype=np.int64)
        self.name = name
        self._h = None  # (1, B, hidden); None: every slot starts an episode

    @classmethod
    def load(cls, model: str | Path, name: str | None = None) -> "StudentPolicy":
        net, meta = load_student_net(model)
        return cls(net, meta["actor_columns"], name or meta.get("name", Path(model).stem))

    def reset(self, infos: Sequence[dict[str, Any]]) -> None:
        self._h = None

    def reset_one(self, index: int, info: dict[str, Any]) -> None:
        """Start a new episode in batch slot ``index`` only (the others keep their memory)."""
        if self._h is not None:
            self._h[:, index] = 0.0

    def mean(self, obs: np.ndarray) -> np.ndarray:
        """The network's actions for a batch of observations, unclipped, its memory carried to the next call."""
        torch = _torch()
        x = torch.as_tensor(np.atleast_2d(obs)[:, self.columns], dtype=torch.float32)[:, None, :]
        with torch.no_grad():
            y, h = self.net(x, self._h)
        if h is not None:
            self._h = h.clone()
        return y[:, 0].numpy()

    def act(self, obs: np.ndarray) -> np.ndarray:
        return np.clip(self.mean(obs), -1.0, 1.0).astype(np.float32)


def pad_episodes(seqs: Sequence[np.ndarray], T: int) -> np.ndarray:
    """Episodes of different lengths (each (t, ...)) as one zero-padded float32 batch (B, T, ...)."""
    out = np.zeros((len(seqs), T, *seqs[0].shape[1:]), dtype=np.float32)
    for j, seq in enumerate(seqs):
        out[j, :len(seq)] = seq
    return out


def pinball(pred, target, mask, quantiles):
    """Mean pinball loss over the masked steps, per action its quantile (torch tensors (B, T, 2), (B, T), (2,))."""
    err = target - pred
    loss = (quantiles * err).maximum((quantiles - 1.0) * err)
    return (loss.sum(-1) * mask).sum() / mask.sum().clamp(min=1.0)
