"""Where the time goes (``msdgrasp bench profile``): per physics substep, per agent step, per training.

substep
    The coarse spleen with the jaws closed on it (the bench's grasp set-up, contact active), one tissue and a
    batch of 64 (one lane block). Every figure times the real kernel, :func:`~msdgrasp.physics.integrator.simulate`,
    on the Simulation's own records, one call per agent step (33 outer steps) from the same saved state, restored
    before each call: a part's cost is what the call saves when the model record switches that part off
    (:data:`SWITCHES`). The parts come off in turn, each from the step without the ones before it, so that a part
    switched off cannot make one still on work harder (released jaws let the compressed tissue spring back and
    the volume barrier remake its watch list on every substep): ``barrier`` (``kvol`` empty), then ``contacts``
    (``jaw_active`` False), then ``springs`` (a model without springs); ``base`` is what is left, the step with all
    three off (gravity and external forces, node update, the contacts' bookkeeping, the loop), less the restore
    timed alone. The parts add up to ``whole``, the call less the restore. Beside them, from the same rounds: the
    springs' Maxwell branch (``use_sls``) and dashpots (``use_dashpot``), switched off from the springs' step; the
    cost of a full barrier flag pass on every substep (``watch_delta`` 0) over the watch list the kernel keeps; the
    springs of ``Simulation(precision="float32")``; and the springs' divider floor (their square roots and
    divisions alone: :func:`_divider_floor`).
agent step
    Per agent step of the default training env (``TrainConfig().env``): the physics (``sim.step`` of the
    env's outer steps), the task (``command_batch`` + ``update_batch``), the whole core step (the rest is the
    env's Python: readouts, sensor noise, the info dict) and the SB3 vector env's whole step (adds autoreset
    and per-env info dicts); policy inference of the default PPO policy (untrained) on one observation and on
    a batch of 64.
training
    A short SB3 PPO run of the default config (``--quick``: fewer steps): wall time split into rollouts (env
    stepping and the policy's forward passes), PPO updates and validation, measured with an SB3 callback.

Substep times are the fastest process CPU time (``time.process_time``) of each timing over
:data:`PROFILE_ROUNDS` interleaved rounds (a busy machine only adds time, and every timing sees the same stretch of
it); agent-step and training times are wall clock (``time.perf_counter``), medians of repeated measurements.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from ..physics.jit import kernel

from ..physics.config import needs_extra
from ..physics.integrator import LANE_MIN, batch_lanes, simulate
from ..physics.records import SimModel, SimState
from ..physics.reference import DT_OUTER
from .harness import clone, grasped, out_paths, round_sig, time_per_unit

#: batch of the lane-layout rows (one lane block)
PROFILE_BATCH = 64
#: the parts of a substep, in the order they are switched off (base: what is left with all of them off)
PHASES = ("barrier", "contacts", "springs", "base")
#: outer steps per timed kernel call: one agent step of the env, so the call's set-up weighs as it does there
STEPS_PER_CALL = 33
#: interleaved rounds of every substep timing
PROFILE_ROUNDS = 5
#: the model fields of the springs (a model without springs has them empty)
SPRING_FIELDS = ("edges", "rest_length", "k1", "k2", "dlc", "cdash", "kv")


def _without_springs(model: SimModel, state: SimState) -> tuple[SimModel, SimState]:
    # the springs' state goes too (E = 0), so that model and state agree on the spring count
    empty = np.empty((state.fv.shape[0], 0), dtype=state.fv.dtype)
    return model._replace(**{k: getattr(model, k)[:0] for k in SPRING_FIELDS}), \
        state._replace(fv=empty, dl_prev=empty.copy())


#: how each part is switched off, by the kernel's records alone: (model, state) -> (model, state). The values keep
#: their types (an empty slice of the same array, the field's own scalar type), so the kernel is not recompiled
SWITCHES: dict[str, Callable[[SimModel, SimState], tuple[SimModel, SimState]]] = {
    "barrier": lambda m, s: (m._replace(kvol=m.kvol[:0]), s),
    "contacts": lambda m, s: (m._replace(jaw_active=False), s),
    "springs": _without_springs,
    "maxwell_branch": lambda m, s: (m._replace(use_sls=False), s),
    "dashpots": lambda m, s: (m._replace(use_dashpot=False), s),
    "watch_list": lambda m, s: (m._replace(watch_delta=type(m.watch_delta)(0.0)), s),  # a full pass every substep
}


def switched_off(model: SimModel, state: SimState, *parts: str) -> tuple[SimModel, SimState]:
    """The kernel's records with ``parts`` (keys of :data:`SWITCHES`) switched off."""
    for part in parts:
        model, state = SWITCHES[part](model, state)
    return model, state


class Restored:
    """Kernel calls from one saved state of a Simulation: :meth:`run` restores every state and readout array
    before each call, so each call meets the same state whatever the last one did."""

    def __init__(self, sim) -> None:
        self.model, self.state, self.out = sim.kernel_model(), sim.kernel_state(), sim.kernel_readout()
        self.n_sub = int(self.model.n_sub)
        self._arrays = [*self.state, *self.out]
        self._saved = [a.copy() for a in self._arrays]

    def restore(self) -> None:
        for a, saved in zip(self._arrays, self._saved):
            np.copyto(a, saved)

    def run(self, *parts: str) -> Callable[[int], None]:
        """k restored calls of :data:`STEPS_PER_CALL` outer steps with ``parts`` switched off."""
        model, state = switched_off(self.model, self.state, *parts)
        lanes = batch_lanes(state.x.shape[0])

        def run(k: int) -> None:
            for _ in range(k):
                self.restore()
                simulate(model, state, self.out, STEPS_PER_CALL, lanes)
        return run

    def restores(self, k: int) -> None:
        for _ in range(k):
            self.restore()


def fastest_us(runs: dict[str, Callable[[int], Any]], min_time: float, repeats: int,
               rounds: int = PROFILE_ROUNDS) -> dict[str, float]:
    """us per unit of each of ``runs`` (``run(k)`` does k units): the fastest process CPU time of its repetitions
    over ``rounds`` interleaved rounds (``min_time`` s each in all). A cost is what it takes undisturbed: a busy
    machine only adds to it, and interleaving lets every run see the same machine, where timings taken one after
    the other differ by the machine's drift."""
    for run in runs.values():
        run(1)  # compile / load the cache
    best = dict.fromkeys(runs, math.inf)
    for _ in range(rounds):
        for name, run in runs.items():
            t = time_per_unit(run, min_time / rounds, repeats, max_units=10**7)["best_cpu_s"] * 1e6
            best[name] = min(best[name], t)
    return best


# ------------------------------------------------------------------------------------------------
# the springs' divider floor
# ------------------------------------------------------------------------------------------------


@kernel
def _rep_divider(l2, out, one, reps):
    """A square root and a division per entry of ``l2`` (contiguous), in ``one``'s type: the two operations every spring
    of every tissue needs per substep (its length and the inverse that makes its direction), with nothing else."""
    for _ in range(reps):
        for k in range(l2.shape[0]):
            out[k] = one / math.sqrt(l2[k])


def _divider_floor(x: np.ndarray, edges: np.ndarray, min_time: float, repeats: int) -> dict:
    """us per substep that the springs' square roots and divisions alone take (float64 and float32), on the
    squared spring lengths of every tissue of the batch x (B,N,3): the vector divider's floor under any float64
    spring pass that keeps the spring law's arithmetic (the spring loops compute exactly these two per spring and
    tissue)."""
    d = x[:, edges[:, 1]] - x[:, edges[:, 0]]  # (B, E, 3)
    l2 = np.ascontiguousarray((d * d).sum(axis=2)).reshape(-1)
    runs = {}
    for name, typ in (("float64", np.float64), ("float32", np.float32)):
        a = l2.astype(typ)
        runs[name] = lambda k, a=a, out=np.empty_like(a), one=typ(1.0): _rep_divider(a, out, one, k)
    return {name: round_sig(us) for name, us in fastest_us(runs, min_time, repeats).items()}


# ------------------------------------------------------------------------------------------------
# per substep
# ------------------------------------------------------------------------------------------------


def volume_ratios(x: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray) -> np.ndarray:
    """(B,T) current / rest volume of every tet of every tissue of the batch x (B,N,3) (signed: <= 0 inverted)."""
    a = x[:, tets[:, 0]]
    e1, e2, e3 = (x[:, tets[:, k]] - a for k in (1, 2, 3))
    return np.einsum("btc,btc->bt", e1, np.cross(e2, e3)) / 6.0 / rest_volume


def _springs_float32(sim, min_time: float, repeats: int) -> dict:
    """The springs' part of a float32 copy of ``sim`` (``Simulation(precision="float32")``, the same grasp), timed
    as the float64 one is: the springs' step without barrier and contacts, with and without springs."""
    from ..physics.simulation import Simulation

    sim32 = Simulation(sim.model, sim.batch_size, dt=sim.dt, substeps=sim.n_sub, grasper=sim.grasper,
                       plates=sim.plates, precision="float32")
    clone(sim, sim32)
    calls = Restored(sim32)
    t = fastest_us({"springs": calls.run("barrier", "contacts"), "none": calls.run("barrier", "contacts", "springs")},
                   min_time, repeats)
    calls.restore()
    return {"us_per_substep": round_sig((t["springs"] - t["none"]) / (STEPS_PER_CALL * calls.n_sub))}


def profile_substep(sim, min_time: float, repeats: int) -> dict:
    """us per substep of each part (:data:`PHASES`) and of the whole kernel call for ``sim``'s batch, from its
    current state (restored afterwards: ``sim`` is left as it was)."""
    calls = Restored(sim)
    m = calls.model
    nb = sim.batch_size
    chain = ("barrier", "contacts", "springs")
    runs = {"all": calls.run(), "restore": calls.restores, "watch_list_off": calls.run("watch_list")}
    for k in range(1, len(chain) + 1):  # the parts off in turn: barrier; barrier, contacts; all three
        runs["off:" + ",".join(chain[:k])] = calls.run(*chain[:k])
    within = [p for p, on in (("maxwell_branch", m.use_sls), ("dashpots", m.use_dashpot)) if on]
    for part in within:  # switched off from the springs' step (no barrier, no contacts)
        runs[part + "_off"] = calls.run("barrier", "contacts", part)
    us = fastest_us(runs, min_time, repeats)
    calls.run()(1)  # (the contact memory after a call: a batch cloned from one tissue starts without it)
    contact_nodes = int(np.count_nonzero(sim.held > 0))
    calls.restore()
    per_substep = 1.0 / (STEPS_PER_CALL * calls.n_sub)
    before = [us["all"]] + [us["off:" + ",".join(chain[:k])] for k in range(1, len(chain) + 1)]
    phases = {part: (before[k] - before[k + 1]) * per_substep for k, part in enumerate(chain)}
    phases["base"] = (before[-1] - us["restore"]) * per_substep
    whole = (us["all"] - us["restore"]) * per_substep
    springs_on = us["off:barrier,contacts"]
    below = int((volume_ratios(sim.x, m.tets, m.rest_volume) < m.vol_threshold).sum()) if m.kvol.shape[0] else 0
    return {
        "tissues": nb,
        "layout": "lanes" if nb >= LANE_MIN else "one tissue at a time",
        "n_sub": calls.n_sub,
        "steps_per_call": STEPS_PER_CALL,
        "maxwell_branch": bool(m.use_sls),
        "dashpots": bool(m.use_dashpot),
        "contact_nodes": contact_nodes,
        "tets_below_barrier_threshold": below,
        "phases_us_per_substep": {p: round_sig(phases[p]) for p in PHASES},
        "phases_share_of_whole": {p: round_sig(phases[p] / whole) for p in PHASES},
        "whole_us_per_substep": round_sig(whole),
        "per_tissue_whole_us_per_substep": round_sig(whole / nb),
        "springs_within_us": {p: round_sig((springs_on - us[p + "_off"]) * per_substep) for p in within},
        "barrier_full_flag_pass_us": round_sig((us["watch_list_off"] - us["all"]) * per_substep),
        "springs_float32": _springs_float32(sim, min_time, repeats),
        "springs_sqrt_div_us": _divider_floor(sim.x, m.edges, min_time, repeats),
    }


def profile_substeps(quick: bool, progress: Callable[[str], None] = lambda s: None, resolution="coarse") -> dict:
    """:func:`profile_substep` of the grasped coarse spleen, one tissue and a batch of :data:`PROFILE_BATCH`."""
    from ..physics.simulation import Simulation

    min_time = 0.1 if quick else 0.5
    repeats = 1 if quick else 3
    settle_s, close_s = (0.5, 1.0) if quick else (2.0, 2.0)
    progress(f"profile: grasping the {resolution} spleen")
    scene, sim1 = grasped(resolution, settle_s, close_s)
    progress("profile: substep parts, one tissue")
    one = profile_substep(sim1, min_time, repeats)
    simb = Simulation(scene.model, PROFILE_BATCH, dt=DT_OUTER, grasper=scene.grasper)
    clone(sim1, simb)
    progress(f"profile: substep parts, batch of {PROFILE_BATCH}")
    batch = profile_substep(simb, min_time, repeats)
    return {"resolution": resolution, "nodes": scene.model.n_nodes, "springs": int(len(scene.model.edges)),
            "tets": int(len(scene.model.tets)), "surface_nodes": int(len(scene.mesh.surface_nodes)),
            "min_time_per_measurement_s": min_time, "rows": [one, batch]}


# ------------------------------------------------------------------------------------------------
# per agent step
# ------------------------------------------------------------------------------------------------


def _default_train_config():
    # PPO from scratch (configs/train/ppo_scratch.yaml): the learner's own cost; the default run adds a controller's
    # per-step work on top (docs/performance.md)
    from ..agents.models import TrainConfig

    return TrainConfig()


def build_default_ppo(venv, config):
    """An untrained PPO of ``config``'s policy settings on ``venv``, built as agents/training.py's ``train`` does."""
    from ..agents.networks import AsymmetricActorCriticPolicy
    from ..envs.core import OBS_NAMES, actor_mask

    with needs_extra("train", "the PPO profile"):
        from stable_baselines3 import PPO

    kwargs = dict(config.ppo)
    policy, policy_kwargs = "MlpPolicy", {"net_arch": list(config.policy_net),
                                          "log_std_init": float(config.log_std_init)}
    if config.squash_actions:
        policy_kwargs["squash_output"] = True
    if config.asymmetric_critic:
        policy = AsymmetricActorCriticPolicy
        policy_kwargs["actor_mask"] = actor_mask(len(OBS_NAMES), venv.core.frame_dim, config.env.obs_history)
    return PPO(policy, venv, seed=config.seed, device="cpu", verbose=0, policy_kwargs=policy_kwargs, **kwargs)


def profile_agent_step(quick: bool, progress: Callable[[str], None] = lambda s: None) -> dict:
    """ms per agent step of the default env's parts (batch of 1 and of the default n_envs) and of the policy."""
    with needs_extra("train", "the agent-step profile"):
        import torch

    from ..envs import core as core_module
    from ..envs.sb3 import GraspLiftSB3VecEnv
    from ..envs.task import command_batch, update_batch

    config = _default_train_config()
    torch.set_num_threads(config.torch_threads)
    min_time = 0.2 if quick else 1.0
    repeats = 1 if quick else 3
    rows = []
    for n_envs in (1, config.n_envs):
        progress(f"profile: agent step, {n_envs} env(s)")
        venv = GraspLiftSB3VecEnv(n_envs, config.env, seed=config.seed)
        venv.reset()
        core = venv.core
        rng = np.random.default_rng(0)
        for _ in range(5):  # into the episode: the jaws move towards the tissue
            venv.step(rng.uniform(-1.0, 1.0, (n_envs, 2)).astype(np.float32))
        # the parts are timed inside real vector-env steps (random actions, autoreset), by timers around
        # the physics call, the task's two functions and the blow-up/volume readouts, restored afterwards
        spent = {"physics": 0.0, "task": 0.0, "readouts": 0.0}

        def timed(fn: Callable, part: str) -> Callable:
            def wrapper(*args: Any, **kwargs: Any) -> Any:
                t0 = time.perf_counter()
                try:
                    return fn(*args, **kwargs)
                finally:
                    spent[part] += time.perf_counter() - t0
            return wrapper

        sim = core.sim
        sim.step = timed(sim.step, "physics")
        sim.finite = timed(sim.finite, "readouts")
        sim.min_volume_ratio = timed(sim.min_volume_ratio, "readouts")
        core_module.command_batch = timed(command_batch, "task")
        core_module.update_batch = timed(update_batch, "task")
        try:
            n_steps, t0 = 0, time.perf_counter()
            while n_steps < 3 or time.perf_counter() - t0 < min_time:
                venv.step(rng.uniform(-1.0, 1.0, (n_envs, 2)).astype(np.float32))
                n_steps += 1
            wall = time.perf_counter() - t0
        finally:
            core_module.command_batch, core_module.update_batch = command_batch, update_batch
            for name in ("step", "finite", "min_volume_ratio"):
                delattr(sim, name)
        vec = wall / n_steps * 1e3
        physics, task_ms, readouts = (spent[k] / n_steps * 1e3 for k in ("physics", "task", "readouts"))
        steps = core.config.physics_steps_per_action
        rows.append({
            "n_envs": n_envs,
            "physics_ms_per_agent_step": steps,
            "agent_steps_timed": n_steps,
            "ms": {"physics": round_sig(physics), "task": round_sig(task_ms),
                   "readouts_finite_volume": round_sig(readouts),
                   "python_rest": round_sig(vec - physics - task_ms - readouts), "sb3_vec_env_step": round_sig(vec)},
            "share_of_sb3_step": {"physics": round_sig(physics / vec), "task": round_sig(task_ms / vec),
                                  "readouts_finite_volume": round_sig(readouts / vec),
                                  "python_rest": round_sig((vec - physics - task_ms - readouts) / vec)},
            "agent_steps_per_s": round_sig(n_envs / vec * 1e3),
        })
        if n_envs == config.n_envs:
            progress("profile: policy inference")
            model = build_default_ppo(venv, config)
            policy = model.policy

            def ms(run: Callable[[int], Any]) -> float:
                run(1)
                return time_per_unit(run, min_time, repeats, max_units=10**6)["median_s"] * 1e3

            obs = venv.reset()
            inference = {"policy": type(policy).__name__, "net_arch": list(config.policy_net),
                         "obs_dim": int(obs.shape[1]), "torch_threads": config.torch_threads}
            for batch in (1, PROFILE_BATCH):
                o = np.resize(obs, (batch, obs.shape[1])).astype(np.float32)
                t = torch.as_tensor(o)

                def predict(k: int, o=o) -> None:
                    for _ in range(k):
                        policy.predict(o, deterministic=True)

                def forward(k: int, t=t) -> None:
                    with torch.no_grad():
                        for _ in range(k):
                            policy(t)  # what the rollout calls: actions, values, log-probabilities

                inference[f"predict_batch{batch}_ms"] = round_sig(ms(predict))
                inference[f"forward_batch{batch}_ms"] = round_sig(ms(forward))
            del model
        venv.close()
    return {"resolution": config.env.resolution, "min_time_per_measurement_s": min_time, "rows": rows,
            "policy_inference": inference}


# ------------------------------------------------------------------------------------------------
# per training
# ------------------------------------------------------------------------------------------------


def profile_training(quick: bool, progress: Callable[[str], None] = lambda s: None) -> dict:
    """A short SB3 PPO run of the default config (default n_envs and rollout length; ``--quick``: one rollout
    of 4 envs): wall time of rollouts, PPO updates and one validation (:class:`~..agents.training.BestModel`,
    as at a checkpoint), with an SB3 callback. Nothing is written outside a temporary folder."""
    import tempfile

    with needs_extra("train", "the training profile"):
        import torch
        from stable_baselines3.common.callbacks import BaseCallback

    from ..agents.training import BestModel
    from ..envs.sb3 import GraspLiftSB3VecEnv
    from ..physics.config import replace

    config = _default_train_config()
    if quick:
        config = replace(config, n_envs=4, validation_episodes=1, validation_mu=(0.5,),
                         ppo={**dict(config.ppo), "n_steps": 32, "batch_size": 64, "n_epochs": 2})
    torch.set_num_threads(config.torch_threads)
    total = config.n_envs * config.ppo["n_steps"]  # one rollout and one update
    progress(f"profile: training {total} steps ({config.n_envs} envs)")
    venv = GraspLiftSB3VecEnv(config.n_envs, config.env, seed=config.seed)
    model = build_default_ppo(venv, config)
    times = {"rollout": 0.0, "update": 0.0}
    marks: dict[str, float] = {}

    class Timer(BaseCallback):
        def _on_rollout_start(self) -> None:
            now = time.perf_counter()
            if "rollout_end" in marks:
                times["update"] += now - marks["rollout_end"]
            marks["rollout_start"] = now

        def _on_rollout_end(self) -> None:
            now = time.perf_counter()
            times["rollout"] += now - marks["rollout_start"]
            marks["rollout_end"] = now

        def _on_step(self) -> bool:
            return True

    t0 = time.perf_counter()
    model.learn(total, callback=Timer())
    end = time.perf_counter()
    learn = end - t0
    if "rollout_end" in marks:  # the last update runs after the last rollout, before learn returns
        times["update"] += end - marks["rollout_end"]
    with tempfile.TemporaryDirectory() as tmp:
        from pathlib import Path

        selector = BestModel(config, Path(tmp))
        path = Path(tmp) / "model.zip"
        model.save(path)
        progress("profile: one validation")
        t1 = time.perf_counter()
        selector.consider(model, path)
        validation = time.perf_counter() - t1
    venv.close()
    checkpoints = config.total_timesteps / config.checkpoint_every
    full_s = {"rollout": times["rollout"] / total * config.total_timesteps,
              "update": times["update"] / total * config.total_timesteps, "validation": validation * checkpoints}
    full_total = sum(full_s.values())
    return {
        "n_envs": config.n_envs, "n_steps": config.ppo["n_steps"], "agent_steps": total,
        "n_epochs": config.ppo["n_epochs"], "batch_size": config.ppo["batch_size"],
        "validation_episodes": config.validation_episodes, "validation_mu": list(config.validation_mu),
        "seconds": {"learn": round_sig(learn), "rollout": round_sig(times["rollout"]),
                    "update": round_sig(times["update"]),
                    "learn_rest": round_sig(learn - times["rollout"] - times["update"]),
                    "one_validation": round_sig(validation)},
        "rollout_agent_steps_per_s": round_sig(total / times["rollout"]) if times["rollout"] > 0 else None,
        "extrapolated_default_run": {"total_timesteps": config.total_timesteps, "checkpoints": round_sig(checkpoints),
                                     "hours": {k: round_sig(s / 3600.0) for k, s in full_s.items()},
                                     "share": {k: round_sig(s / full_total) for k, s in full_s.items()}},
    }


# ------------------------------------------------------------------------------------------------
# report
# ------------------------------------------------------------------------------------------------


def run_profile(quick: bool = False, progress: Callable[[str], None] = lambda s: None, training: bool = True) -> dict:
    from .report import machine_info

    t0 = time.perf_counter()
    report: dict[str, Any] = {"what": "profile", "quick": bool(quick), "machine": machine_info()}
    report["substep"] = profile_substeps(quick, progress)
    report["agent_step"] = profile_agent_step(quick, progress)
    if training:
        report["training"] = profile_training(quick, progress)
    report["elapsed_s"] = round_sig(time.perf_counter() - t0)
    return report


def _divider_line(one: dict, batch: dict) -> str:
    """The profile's sentence on the springs' divider floor (:func:`_divider_floor`) of one tissue and the batch."""
    f1, fb, nb = one["springs_sqrt_div_us"], batch["springs_sqrt_div_us"], batch["tissues"]
    return ("The springs' square roots and divisions alone (one of each per spring and tissue, nothing else: the "
            "vector divider's floor under a spring pass that keeps the spring law's arithmetic), us per substep, "
            f"float64 / float32: one tissue {f1['float64']} / {f1['float32']}, batch {fb['float64']} / {fb['float32']} "
            f"({round_sig(fb['float64'] / nb)} / {round_sig(fb['float32'] / nb)} per tissue); float64 at "
            f"{one['n_sub']} substeps per ms: {round_sig(f1['float64'] * one['n_sub'])} us per simulated ms one "
            "tissue, "
            f"{round_sig(fb['float64'] * batch['n_sub'] / nb)} per tissue of the batch.")


#: the parts' rows in the substep table
PHASE_LABELS = {"barrier": "volume barrier", "contacts": "contacts (jaws)", "springs": "springs",
                "base": "base (forces, node update, loop)"}
WITHIN_LABELS = {"maxwell_branch": "Maxwell branch", "dashpots": "dashpots"}


def _substep_table(sub: dict) -> list[str]:
    """The per-substep table and notes (markdown lines)."""
    one, batch = sub["rows"]
    nb = batch["tissues"]
    lines = [f"Per substep, {sub['resolution']} spleen ({sub['nodes']} nodes, {sub['springs']} springs, "
             f"{sub['tets']} tets), jaws closed (contact nodes: {one['contact_nodes']} one tissue), n_sub "
             f"{one['n_sub']}, Maxwell branch {'on' if one['maxwell_branch'] else 'off'}, dashpots "
             f"{'on' if one['dashpots'] else 'off'}; each part is what the kernel call ({one['steps_per_call']} outer "
             "steps) saves with it switched off, after the parts above it:", "",
             f"| part | one tissue us | share | batch {nb} us | per tissue us | share |", "|---|---|---|---|---|---|"]
    for p in PHASES:
        lines.append(f"| {PHASE_LABELS[p]} | {one['phases_us_per_substep'][p]} | {one['phases_share_of_whole'][p]} | "
                     f"{batch['phases_us_per_substep'][p]} | {round_sig(batch['phases_us_per_substep'][p] / nb)} "
                     f"| {batch['phases_share_of_whole'][p]} |")
    lines.append(f"| whole | {one['whole_us_per_substep']} | 1 | {batch['whole_us_per_substep']} | "
                 f"{batch['per_tissue_whole_us_per_substep']} | 1 |")
    for p, us in one["springs_within_us"].items():
        lines += ["", f"Of the springs, the {WITHIN_LABELS[p]}: {us} / {batch['springs_within_us'][p]} us "
                  "(one tissue / batch)."]
    f32 = batch["springs_float32"]["us_per_substep"]
    springs = one["phases_us_per_substep"]["springs"], batch["phases_us_per_substep"]["springs"]
    lines += ["", f"Volume barrier: {one['tets_below_barrier_threshold']} / {batch['tets_below_barrier_threshold']} "
              f"tets below its threshold (one tissue / batch); a full flag pass on every substep instead of the watch "
              f"list would add {one['barrier_full_flag_pass_us']} / {batch['barrier_full_flag_pass_us']} us.",
              "", f"The springs in float32 (`Simulation(precision=\"float32\")`, the same grasp): "
              f"{one['springs_float32']['us_per_substep']} us one tissue, {f32} the batch ({round_sig(f32 / nb)} per "
              f"tissue), against {springs[0]} / {springs[1]} in float64 (its error against float64: "
              "`msdgrasp bench physics`).",
              "", _divider_line(one, batch)]
    return lines


def _agent_step_table(agent: dict) -> list[str]:
    """The per-agent-step table and the policy's inference (markdown lines)."""
    lines = ["Per agent step, ms (share of the SB3 vector env's step):", "",
             "| n_envs | physics | task | finite + volume | Python rest | SB3 vec step | agent steps/s |",
             "|---|---|---|---|---|---|---|"]
    for r in agent["rows"]:
        t, sh = r["ms"], r["share_of_sb3_step"]
        lines.append(f"| {r['n_envs']} | {t['physics']} ({sh['physics']}) | {t['task']} ({sh['task']}) | "
                     f"{t['readouts_finite_volume']} ({sh['readouts_finite_volume']}) | {t['python_rest']} "
                     f"({sh['python_rest']}) | {t['sb3_vec_env_step']} | {r['agent_steps_per_s']} |")
    inf = agent["policy_inference"]
    lines += ["", f"Policy inference ({inf['policy']}, net {inf['net_arch']}, obs {inf['obs_dim']}, torch threads "
              f"{inf['torch_threads']}), ms: predict 1 obs {inf['predict_batch1_ms']}, predict {PROFILE_BATCH} obs "
              f"{inf[f'predict_batch{PROFILE_BATCH}_ms']}, forward 1 obs {inf['forward_batch1_ms']}, forward "
              f"{PROFILE_BATCH} obs {inf[f'forward_batch{PROFILE_BATCH}_ms']}"]
    return lines


def _training_line(tr: dict) -> str:
    s, ext = tr["seconds"], tr["extrapolated_default_run"]
    return (f"Training ({tr['agent_steps']} agent steps, {tr['n_envs']} envs, {tr['n_epochs']} epochs): "
            f"rollout {s['rollout']} s, PPO update {s['update']} s, one validation {s['one_validation']} s; "
            f"extrapolated to the default {ext['total_timesteps']} steps: rollout {ext['hours']['rollout']} h, "
            f"update {ext['hours']['update']} h, validation {ext['hours']['validation']} h (shares "
            f"{ext['share']['rollout']} / {ext['share']['update']} / {ext['share']['validation']})")


def markdown_table(report: dict) -> str:
    """The profile's tables (markdown)."""
    lines = _substep_table(report["substep"]) + [""] + _agent_step_table(report["agent_step"])
    if "training" in report:
        lines += ["", _training_line(report["training"])]
    return "\n".join(lines)


def profile_cli(quick: bool, out) -> int:
    """``msdgrasp bench profile``: print the JSON report (and the tables on stderr); ``out`` also writes it
    (JSON and markdown, atomically)."""
    from ..physics.config import atomic_write_text

    def progress(msg: str) -> None:
        print(f"[bench] {msg}", file=sys.stderr, flush=True)

    report = run_profile(quick, progress=progress)
    table = markdown_table(report)
    if out is not None:
        json_path, md_path, _ = out_paths(out)
        report["files"] = {"json": str(json_path), "markdown": str(md_path)}
        atomic_write_text(json_path, json.dumps(report, indent=2) + "\n")
        atomic_write_text(md_path, table + "\n")
    print(table, file=sys.stderr)
    print(json.dumps(report, indent=2))
    return 0
