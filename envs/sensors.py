"""The grasper's sensors, declared once: what each one measures, its noise model, the config fields that set it, and
which observation entries come from it.

The kernels (:func:`.task.observe`, :func:`.task.noise_scale`, :func:`.task.sense_task_state`) compute the readings;
this module is their declaration, read by the env's documentation, the robustness suite's sensing conditions and the
tests (tests/test_sensors.py checks every entry against it: a noisy sensor makes its entries differ between two
sensor seeds of one physics seed; an absent one leaves every entry derived from it constant).

From version 2 of the benchmark task (``sensed_task_state``) every entry of the actor's observation comes from these
sensors; the simulation's truth behind the task-state entries is privileged (:data:`.task.PRIVILEGED_TRUTH`), for
critics and teachers.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from .task import OBS_NAMES


@dataclasses.dataclass(frozen=True)
class Sensor:
    """One sensor of the grasper (or of the scene: the laparoscope's tracker)."""

    name: str
    #: what it is, in a grasper's terms
    device: str
    #: its noise model, with the config fields (RandomizationConfig unless named otherwise) that set it
    noise: str
    #: whether it adds noise to its readings under a task config (then two sensor seeds read differently)
    noisy: Callable[[Any], bool] = lambda config: False
    #: whether it is absent under a task config (then every entry derived from it is constant)
    absent: Callable[[Any], bool] = lambda config: False


def _r(config: Any) -> Any:
    return config.randomization


#: the sensors, by name
SENSORS: dict[str, Sensor] = {s.name: s for s in (
    Sensor("jaw_encoder", "the jaw drive's encoder (opening, closing speed)",
           "exact (an encoder's resolution is far below the 0.1 mm the task resolves)"),
    Sensor("arm_encoder", "the arm's joint encoders (pull distance, pull speed along the pull direction)",
           "exact"),
    Sensor("force", "a load cell in each jaw (normal force, tangential force magnitude)",
           "white Gaussian noise of sensor_noise_N (per episode uniform from sensor_noise_low_N where set), a bias per "
           "jaw and episode uniform in +-force_bias_N, a first-order low-pass of force_filter_s; tangential: "
           "force_noise (magnitude or vector)",
           noisy=lambda c: _r(c).sensor_noise_N > 0.0),
    Sensor("contact", "the jaw face's pressure taxels (share of the jaw's footprint in contact)",
           "exact (a taxel per contact node)"),
    Sensor("slip", "a tactile slip sensor in each jaw (slip speed, share of the contact that slips)",
           "slip_sensing: exact (white noise of slip_noise on the speed; from v2 also on the share, clipped to "
           "[0, 1]), binary (a detector: 1 while any of the jaw slips) or absent (zeros)",
           noisy=lambda c: _r(c).slip_sensing == "exact" and _r(c).slip_noise > 0.0,
           absent=lambda c: _r(c).slip_sensing == "absent"),
    Sensor("lift", "a point of the grasped region tracked in the laparoscope's image (its lift along the pull)",
           "lift_sensing: tracked (white noise of lift_noise_m per frame, lift_delay_steps frames late) or absent; "
           "before v2 the region's true mean lift",
           noisy=lambda c: c.sensed_task_state and _r(c).lift_sensing == "tracked" and _r(c).lift_noise_m > 0.0,
           absent=lambda c: c.sensed_task_state and _r(c).lift_sensing == "absent"),
    Sensor("command", "the agent's own previous action", "exact"),
    Sensor("clock", "the episode's clock", "exact"),
    Sensor("truth", "no sensor: the simulation's state (the task-state entries before v2)", "none"),
)}


def _per_jaw(prefix: str, *sensors: str) -> dict[str, tuple[str, ...]]:
    return {f"{prefix}_{k}": sensors for k in range(3)}


#: each observation entry (envs.task.OBS_NAMES) and the sensors it is computed from (v2; before v2 the task-state
#: entries lift_progress ... lift_slip are the simulation's truth)
ENTRY_SENSORS: dict[str, tuple[str, ...]] = {
    "jaw_opening": ("jaw_encoder",), "jaw_speed": ("jaw_encoder",),
    "pull_distance": ("arm_encoder",), "pull_speed": ("arm_encoder",),
    **_per_jaw("normal_force", "force"), **_per_jaw("tangential_force", "force"),
    **_per_jaw("contact_fraction", "contact"),
    **_per_jaw("slip_speed", "slip"), **_per_jaw("slipping_fraction", "slip"),
    "prev_action_jaw": ("command",), "prev_action_pull": ("command",), "time_fraction": ("clock",),
    # the task state: tracked lift (m), time at the target by the tracker, slip there, lag behind the arm, the
    # highest pinch reading, the highest tracked lift, the slip since the arm's travel passed lift_started_m
    "lift_progress": ("lift",), "hold_progress": ("lift",), "hold_slip": ("lift", "slip"),
    "lift_lag": ("lift", "arm_encoder"), "peak_pinch": ("force",), "best_lift": ("lift",),
    **_per_jaw("friction_use", "force"), "lift_slip": ("slip", "arm_encoder"),
}
assert tuple(ENTRY_SENSORS) == OBS_NAMES, "ENTRY_SENSORS must list OBS_NAMES in order"
assert all(s in SENSORS for names in ENTRY_SENSORS.values() for s in names)


#: the entries that are the simulation's truth without ``sensed_task_state`` (v0, v1)
TASK_STATE_ENTRIES = ("lift_progress", "hold_progress", "hold_slip", "lift_lag", "peak_pinch", "best_lift", "lift_slip")


def entry_sensors(config: Any) -> dict[str, tuple[str, ...]]:
    """Each observation entry's sensors under ``config`` (a GraspLiftConfig): :data:`ENTRY_SENSORS`, with the
    task-state entries the truth where the task does not sense them (before v2)."""
    if config.sensed_task_state:
        return dict(ENTRY_SENSORS)
    return {e: (("truth",) if e in TASK_STATE_ENTRIES else names) for e, names in ENTRY_SENSORS.items()}


def noisy_entries(config: Any) -> list[str]:
    """The observation entries that read a noisy sensor under ``config``."""
    return [e for e, names in entry_sensors(config).items() if any(SENSORS[n].noisy(config) for n in names)]


def absent_entries(config: Any) -> list[str]:
    """The observation entries derived from a sensor that is absent under ``config`` (constant over an episode)."""
    return [e for e, names in entry_sensors(config).items() if any(SENSORS[n].absent(config) for n in names)]
