"""The GraspLift task on a CUDA GPU: the whole agent step (commands, physics, readouts, observation, reward,
termination and autoreset with domain randomisation) on the device, for thousands of tissues at once.

:class:`CudaGraspLiftCore` runs :mod:`.task`'s per-env functions, compiled for the device from the CPU core's
own source (:func:`~msdgrasp.physics.cuda_step.device_twin`), on :class:`~msdgrasp.physics.cuda_step.CudaBatch`.
This module holds only what the GPU adds: device memory, the launches, the block-parallel finiteness / smallest
tet volume and settled-state restore, and the random numbers. One agent step is four launches, no transfer:
``_command_kernel`` (a thread per env: :func:`.task.command`), the physics (a block per tissue),
``_task_kernel`` (a block per env: the reductions, then :func:`.task.update`) and ``_reset_kernel`` (a block
per env that is done: the settled tissue back, then :func:`.task.draw_episode` and :func:`.task.begin_episode`).

Observations, rewards and flags stay in device arrays (:meth:`CudaGraspLiftCore.arrays`); a torch learner
reads them without a copy (:func:`as_torch`). The tests compare both cores step by step in numba's simulator.

Differences from the CPU core, by design: the random numbers come from xoroshiro128+ streams on the device
(one per env, seeded by ``seed``) instead of NumPy's per-env generators, so a GPU batch is reproducible by
its own seed but does not replay the CPU's episodes; both turn the same kinds of variates (uniform, normal)
into the draws by the same function, so the distributions agree (tests/test_task_backends.py). A done env is
reset in the same step (the observation returned for it is its new episode's first; the last one of the old
episode is in ``terminal_obs``, and ``truncated`` says which ends were time limits, for bootstrapping);
``reset(options)`` pins friction and scales (``mu``, ``stiffness_scale``, ``mass_scale``) for every later
episode until the next ``reset``.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np
from numba import cuda
from numba.core.registry import CPUDispatcher
from numba.cuda.random import create_xoroshiro128p_states, xoroshiro128p_normal_float64, xoroshiro128p_uniform_float64

from ..physics.config import ConfigError, check_choice, check_range
from ..physics.cuda_step import PRECISIONS, THREADS_PER_BLOCK, CudaBatch, _tet_edges, device_twin, to_device
from ..physics.viscoelastic import elongations
from . import task
from .core import GraspLiftConfig, GraspLiftCore
from .task import PINNABLE, TaskState, task_state

#: what ``reset(options=...)`` may pin (for every later episode)
GPU_PINNABLE = ("mu", "stiffness_scale", "mass_scale")


def _twins(module) -> dict:
    """The GPU twins of a module's numba functions, each calling the twins of the ones defined before it."""
    twins: dict = {}
    for name, f in vars(module).items():
        if isinstance(f, CPUDispatcher) and f.py_func.__module__ == module.__name__:
            late = [n for n in f.py_func.__code__.co_names if isinstance(vars(module).get(n), CPUDispatcher)
                    and n not in twins]
            if late:
                raise ImportError(f"{module.__name__}.{name} calls {late}, defined after it")
            twins[name] = device_twin(f, **twins)
    return twins


_task = _twins(task)
_command, _update, _draw_episode, _begin_episode = (_task[n] for n in ("command", "update", "draw_episode",
                                                                       "begin_episode"))


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
    lo_sh = cuda.shared.array(THREADS_PER_BLOCK, np.float64)
    ok_sh = cuda.shared.array(THREADS_PER_BLOCK, np.int32)
    ok = 1
    for i in range(tid, s.x.shape[1], cuda.blockDim.x):
        for c in range(3):
            if not (math.isfinite(s.x[b, i, c]) and math.isfinite(s.v[b, i, c])):
                ok = 0
    lo = math.inf
    for t in range(tid, m.tets.shape[0], cuda.blockDim.x):
        r = _tet_edges(s.x[b], m.tets, t)[9] / m.rest_volume[t]
        if r < lo:  # (as forces.min_volume_ratios compares)
            lo = r
    lo_sh[tid] = lo
    ok_sh[tid] = ok
    cuda.syncthreads()
    if tid == 0:
        for k in range(1, cuda.blockDim.x):
            lo = lo_sh[k] if lo_sh[k] < lo else lo
            ok = ok & ok_sh[k]
        for c in range(3):
            ts.noise[b, c] = p.env.randomization.sensor_noise_N * xoroshiro128p_normal_float64(rng, b)
        _update(p, s, out, ts, b, ok == 1, lo)


@cuda.jit
def _reset_kernel(s, out, p, ts, rng, mask, fv_start, dl_start):
    """New episodes for the envs where ``mask``: the settled tissue (block-parallel), then the draws."""
    b = cuda.blockIdx.x
    if b >= s.x.shape[0] or not mask[b]:
        return
    tid = cuda.threadIdx.x
    for i in range(tid, s.x.shape[1], cuda.blockDim.x):
        for c in range(3):
            s.x[b, i, c] = p.x_start[i, c]
            s.v[b, i, c] = 0.0
            s.f_ext[b, i, c] = 0.0
            out.contact_force[b, i, c] = 0.0
        out.contact_state[b, i] = 0
    for e in range(tid, s.fv.shape[1], cuda.blockDim.x):
        s.fv[b, e] = fv_start[e]
        s.dl_prev[b, e] = dl_start[e]
    cuda.syncthreads()
    if tid == 0:
        for k in range(ts.draws.shape[1]):  # the raw variates, in column order
            normal = p.draw_is_normal[k]
            ts.draws[b, k] = xoroshiro128p_normal_float64(rng, b) if normal else xoroshiro128p_uniform_float64(rng, b)
        _draw_episode(p, ts, b)
        _begin_episode(p, s, out, ts, b)


def as_torch(array):
    """A torch tensor of a device array: a zero-copy view on a GPU (``__cuda_array_interface__``), a copy
    on the host under numba's CUDA simulator (which has no device memory to share)."""
    import torch

    if hasattr(array, "__cuda_array_interface__") and torch.cuda.is_available():
        return torch.as_tensor(array, device="cuda")
    return torch.from_numpy(array.copy_to_host())


class CudaGraspLiftCore:
    """The GraspLift task for ``num_envs`` tissues resident on the GPU (see the module docstring).

    ``precision="float32"`` keeps the tissue's per-node, per-spring and per-tet arrays in float32
    (:data:`~msdgrasp.physics.cuda_step.FLOAT32_FIELDS`); the task's own state stays float64.
    ``reset()`` starts every env; ``step(actions)`` advances all of them by one agent step and resets the ones
    that ended. Both return the device arrays ``(obs, reward, terminated, truncated)``, updated in place; every
    other output is a field of :meth:`arrays`; :meth:`download` copies named fields to the host.
    """

    def __init__(self, config: GraspLiftConfig | None = None, num_envs: int = 1, seed: int = 0,
                 threads: int = THREADS_PER_BLOCK, precision: str = "float64") -> None:
        check_range("threads", threads, 1, THREADS_PER_BLOCK)
        check_choice("precision", precision, PRECISIONS)
        self.host = host = GraspLiftCore(config, num_envs)  # builds the scene, host arrays and task constants once
        self.config, self.num_envs, self.frame_dim, self.obs_dim = host.config, host.num_envs, host.frame_dim, host.obs_dim
        self.threads, self.precision = int(threads), precision
        sim, scene = host.sim, host.scene
        self.physics = CudaBatch(sim.kernel_model(), sim.kernel_state(), sim.kernel_readout(), threads=self.threads,
                                 precision=precision)
        self.params = to_device(host.params)
        self.state = to_device(task_state(self.num_envs, self.config.obs_history, self.frame_dim, np.float32))
        self._settled = [cuda.to_device(a) for a in (scene.fv_start, elongations(scene.x_start, scene.model.edges,
                                                                                  scene.model.rest_length))]
        with warnings.catch_warnings():  # the simulator compiles the state set-up in object mode, noisily
            warnings.simplefilter("ignore")
            self.rng = create_xoroshiro128p_states(self.num_envs, seed=int(seed))
        self._all = cuda.to_device(np.ones(self.num_envs, dtype=np.bool_))
        self._blocks = (self.num_envs + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK

    def reset(self, options: dict[str, Any] | None = None):
        """Start a new episode in every env. ``options`` pins ``mu``, ``stiffness_scale`` and ``mass_scale``
        (a number or one per env) for this and every later episode until the next ``reset``."""
        options = dict(options or {})
        unknown = sorted(set(options) - set(GPU_PINNABLE))
        if unknown:
            raise ConfigError(f"reset options: unknown key(s) {unknown}; allowed on the GPU: {list(GPU_PINNABLE)}")
        sim = self.host.sim
        bounds = {"mu": (0.0, 10.0), "stiffness_scale": (0.0, sim.max_stiffness_scale), "mass_scale": (sim.min_mass_scale, None)}
        pin = np.full((self.num_envs, len(PINNABLE)), np.nan)
        for name in set(options):
            values = np.broadcast_to(np.asarray(options[name], dtype=np.float64), (self.num_envs,))
            for v in np.unique(values):
                check_range(f"options[{name!r}]", float(v), *bounds[name], lo_inclusive=name != "stiffness_scale")
            pin[:, PINNABLE.index(name)] = values
        self.state.pin.copy_to_device(pin)
        self._reset(self._all)
        return self.state.obs

    def _reset(self, mask) -> None:
        s, out = self.physics.state, self.physics.out
        _reset_kernel[self.num_envs, self.threads](s, out, self.params, self.state, self.rng, mask, *self._settled)

    def step(self, actions):
        """Advance every env by one agent step; ``actions`` (B,2) in [-1, 1] (clipped): a host array, a
        device array or a CUDA tensor (read in place). Envs that end are reset in the same call."""
        shape = tuple(getattr(actions, "shape", np.shape(actions)))
        if shape != (self.num_envs, 2):
            raise ConfigError(f"actions must have shape ({self.num_envs}, 2), got {shape}")
        if hasattr(actions, "__cuda_array_interface__"):
            dev = cuda.as_cuda_array(actions)
        else:
            host = actions.numpy() if hasattr(actions, "numpy") else np.asarray(actions)
            dev = cuda.to_device(np.ascontiguousarray(host, dtype=np.float64))
        m, s, out, st = self.physics.model, self.physics.state, self.physics.out, self.state
        _command_kernel[self._blocks, THREADS_PER_BLOCK](self.params, s, st, dev)
        self.physics.step(self.config.physics_steps_per_action)
        _task_kernel[self.num_envs, self.threads](m, s, out, self.params, st, self.rng)
        self._reset(st.done)
        return st.obs, st.reward, st.terminated, st.truncated

    def arrays(self) -> dict[str, object]:
        """Every device array of the task, the physics state and the readouts, by field name (no copy)."""
        return {**self.physics.arrays(), **{name: getattr(self.state, name) for name in TaskState._fields}}

    def download(self, *names: str) -> dict[str, np.ndarray]:
        """Host copies of the named fields of :meth:`arrays`."""
        arrays = self.arrays()
        unknown = [n for n in names if n not in arrays]
        if unknown:
            raise ConfigError(f"unknown field(s) {unknown}; allowed: {sorted(arrays)}")
        return {n: arrays[n].copy_to_host() for n in names}
