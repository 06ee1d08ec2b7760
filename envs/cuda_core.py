"""The GraspLift task on a CUDA GPU: the whole agent step (commands, physics, readouts, observation, reward,
termination, autoreset with domain randomisation) on the device, for thousands of tissues at once.

:class:`CudaGraspLiftCore` runs :mod:`.task`'s per-env functions, compiled for the device from the CPU core's
source (:func:`~msdgrasp.physics.cuda_step.device_twin`); this module adds only device memory, the launches,
the block-parallel reductions and the device's random numbers. A step is four launches and no transfer: the
commands (a thread per env), the physics (a block per tissue), the update (a block per env: finiteness and
smallest tet volume, then :func:`.task.update`) and the reset of the done envs (a block each). Outputs stay in
device arrays (:meth:`CudaGraspLiftCore.arrays`; torch reads them in place, :func:`as_torch`).

Differences from the CPU core, by design: the random numbers come from xoroshiro128+ streams (one per env,
seeded by ``seed``), not NumPy's per-env generators, so a batch replays its own seed's episodes, not the CPU's
(both turn uniform and normal variates into draws by one function: the distributions agree,
tests/test_task_backends.py), and one stream per env carries both the physics' draws and the sensors' noise (the
CPU's v2 envs seed their sensors apart); a done env is reset in the same step (``terminal_obs`` holds its episode's last
observation, ``truncated`` marks time limits); ``reset(options)`` pins for every later episode.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
from numba import cuda
from numba.cuda.random import create_xoroshiro128p_states, xoroshiro128p_normal_float64, xoroshiro128p_uniform_float64

from ..physics.config import ConfigError, check_choice, check_range
from ..physics.cuda_step import PRECISIONS, THREADS_PER_BLOCK, CudaBatch, device_twin, tet_edges, to_device
from . import task
from .core import GraspLiftConfig, GraspLiftCore, check_pin
from .task import PINNABLE, TaskState, task_state

#: what ``reset(options=...)`` may pin (for every later episode)
GPU_PINNABLE = ("mu", "stiffness_scale", "mass_scale")

# the GPU twins of task.py's functions (each calling the twins of the numba functions it calls)
_command, _update, _restore_settled, _draw_episode, _begin_episode, _column_drawn, _noise_scale = (
    device_twin(getattr(task, n)) for n in ("command", "update", "restore_settled", "draw_episode", "begin_episode",
                                            "column_drawn", "noise_scale"))


@cuda.jit
def _command_kernel(p, s, ts, actions):
    b = cuda.grid(1)
    if b < ts.mu.shape[0]:
        _command(p, s, ts, b, float(actions[b, 0]), float(actions[b, 1]))


@cuda.jit
def _task_kernel(m, s, out, p, ts, rng):
    """After the physics: finiteness and the smallest tet volume ratio (block-parallel), then env b's update."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0]:
        return
    tid = cuda.threadIdx.x
    lo_sh = cuda.shared.array(THREADS_PER_BLOCK, np.float64)  # (one call a line: the simulator keys them by line)
    ok_sh = cuda.shared.array(THREADS_PER_BLOCK, np.int32)
    ok = 1
    for i in range(tid, s.x.shape[1], cuda.blockDim.x):
        for c in range(3):
            ok = ok if math.isfinite(s.x[b, i, c]) and math.isfinite(s.v[b, i, c]) else 0
    lo = math.inf
    for t in range(tid, m.tets.shape[0], cuda.blockDim.x):
        r = tet_edges(s.x[b], m.tets, t)[9] / m.rest_volume[t]
        lo = r if r < lo else lo  # (as forces.min_volume_ratios compares)
    lo_sh[tid], ok_sh[tid] = lo, ok
    cuda.syncthreads()
    if tid == 0:
        for k in range(1, cuda.blockDim.x):
            lo = lo_sh[k] if lo_sh[k] < lo else lo
            ok = ok & ok_sh[k]
        for c in range(ts.noise.shape[1]):  # the sensors' noise: the drawn columns in order, as on the CPU
            sd = _noise_scale(p, ts, b, c)
            if sd >= 0.0:
                ts.noise[b, c] = sd * xoroshiro128p_normal_float64(rng, b)
        _update(p, s, out, ts, b, ok == 1, lo)


@cuda.jit
def _reset_kernel(s, out, p, ts, rng, mask):
    """New episodes for the envs where ``mask``: the settled tissue (block-parallel), then the draws."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0] or not mask[b]:
        return
    _restore_settled(p, s, out, b, cuda.threadIdx.x, cuda.blockDim.x)
    cuda.syncthreads()
    if cuda.threadIdx.x == 0:
        for k in range(ts.draws.shape[1]):  # the raw variates, in column order (an axis that is off: 0)
            if not _column_drawn(p, k):
                ts.draws[b, k] = 0.0
            elif p.draw_is_normal[k]:
                ts.draws[b, k] = xoroshiro128p_normal_float64(rng, b)
            else:
                ts.draws[b, k] = xoroshiro128p_uniform_float64(rng, b)
        _draw_episode(p, ts, b)
        _begin_episode(p, s, out, ts, b)


def as_torch(array):
    """A torch tensor of a device array: a view on a GPU, a copy under numba's CUDA simulator."""
    import torch
    if hasattr(array, "__cuda_array_interface__") and torch.cuda.is_available():
        return torch.as_tensor(array, device="cuda")
    return torch.from_numpy(array.copy_to_host())


class CudaGraspLiftCore:
    """The GraspLift task for ``num_envs`` tissues on the GPU. ``reset()`` and ``step(actions)`` return the device
    arrays ``(obs, reward, terminated, truncated)``, updated in place; the other outputs are fields of :meth:`arrays`.
    ``precision="float32"``: the tissue's per-node, per-spring and per-tet arrays in float32
    (:data:`~msdgrasp.physics.cuda_step.FLOAT32_FIELDS`); the task's state stays float64."""

    def __init__(self, config: GraspLiftConfig | None = None, num_envs: int = 1, seed: int = 0,
                 threads: int = THREADS_PER_BLOCK, precision: str = "float64") -> None:
        check_range("threads", threads, 1, THREADS_PER_BLOCK)
        check_choice("precision", precision, PRECISIONS)
        self.host = host = GraspLiftCore(config, num_envs)  # builds the scene, host arrays and task constants once
        self.config, self.num_envs, self.frame_dim, self.obs_dim = (host.config, host.num_envs, host.frame_dim,
                                                                    host.obs_dim)
        self.threads, self.precision = int(threads), precision
        self.physics = CudaBatch(host.sim.kernel_model(), host.sim.kernel_state(), host.sim.kernel_readout(),
                                 threads=self.threads, precision=precision)
        self.params = to_device(host.params)
        self.state = to_device(task_state(self.num_envs, self.config.obs_history, self.frame_dim, np.float32))
        with warnings.catch_warnings():  # the simulator compiles the state set-up in object mode, noisily
            warnings.simplefilter("ignore")
            self.rng = create_xoroshiro128p_states(self.num_envs, seed=int(seed))
        self._all = cuda.to_device(np.ones(self.num_envs, dtype=np.bool_))

    def reset(self, options: dict[str, Any] | None = None):
        """Start a new episode in every env. ``options`` pins ``mu``, ``stiffness_scale`` and ``mass_scale``
        (a number or one per env) for this and every later episode until the next ``reset``."""
        options = dict(options or {})
        if unknown := sorted(set(options) - set(GPU_PINNABLE)):
            raise ConfigError(f"reset options: unknown key(s) {unknown}; allowed on the GPU: {list(GPU_PINNABLE)}")
        pin = np.full((self.num_envs, len(PINNABLE)), np.nan)
        for name, value in options.items():
            pin[:, PINNABLE.index(name)] = np.broadcast_to(np.asarray(value, dtype=np.float64), (self.num_envs,))
            for v in np.unique(pin[:, PINNABLE.index(name)]):
                check_pin(name, float(v), self.host.sim)
        self.state.pin.copy_to_device(pin)
        ph = self.physics
        _reset_kernel[self.num_envs, self.threads](ph.state, ph.out, self.params, self.state, self.rng, self._all)
        return self.state.obs

    def step(self, actions):
        """Advance every env by one agent step; ``actions`` (B,2) in [-1, 1] (clipped): a host array, a
        device array or a CUDA tensor (read in place). Envs that end are reset in the same call."""
        shape = tuple(getattr(actions, "shape", np.shape(actions)))
        if shape != (self.num_envs, 2):
            raise ConfigError(f"actions must have shape ({self.num_envs}, 2), got {shape}")
        dev = (cuda.as_cuda_array(actions) if hasattr(actions, "__cuda_array_interface__")  # (a CUDA tensor: in place)
               else cuda.to_device(np.ascontiguousarray(actions, dtype=np.float64)))
        m, s, out, st = self.physics.model, self.physics.state, self.physics.out, self.state
        _command_kernel[-(-self.num_envs // THREADS_PER_BLOCK), THREADS_PER_BLOCK](self.params, s, st, dev)
        self.physics.step(self.config.physics_steps_per_action)
        _task_kernel[self.num_envs, self.threads](m, s, out, self.params, st, self.rng)
        _reset_kernel[self.num_envs, self.threads](s, out, self.params, st, self.rng, st.done)
        return st.obs, st.reward, st.terminated, st.truncated

    def arrays(self) -> dict[str, object]:
        """Every device array of the task, the physics state and the readouts, by field name (no copy)."""
        return {**self.physics.arrays(), **{name: getattr(self.state, name) for name in TaskState._fields}}

    def download(self, *names: str) -> dict[str, np.ndarray]:
        """Host copies of the named fields of :meth:`arrays`."""
        arrays = self.arrays()
        if unknown := [n for n in names if n not in arrays]:
            raise ConfigError(f"unknown field(s) {unknown}; allowed: {sorted(arrays)}")
        return {n: arrays[n].copy_to_host() for n in names}
