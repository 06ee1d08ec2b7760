"""The task's perturbations, each declared once: its config fields, its draw, its privileged entries and its suite
conditions.

A :class:`Perturbation` names

* ``fields``: the :class:`~.core.RandomizationConfig` fields that set it (every field belongs to one perturbation;
  tests/test_perturbations.py checks it), with the rule that says whether a level lies inside a trained range
  (``within``: at most the trained level unless it says otherwise);
* ``columns``: its per-episode draw columns (``TaskState.draws``), each a raw variate (uniform on [0, 1) or
  standard normal) turned into its value by a law (:data:`LAWS`, the kernel's :func:`.task.draw_value`) whose
  parameters ``law(randomization)`` gives per column. A column whose law is ``CONSTANT`` draws nothing (an axis that
  is off leaves the nominal task's random stream as it was before the axis existed); a ``DERIVED`` column is set by
  the perturbation's effect when the episode starts (the grasp pose's error);
* ``privileged``: the entries it adds to the privileged observation (``privileged_perturbations``), each a column
  scaled to about 1 at the suite's largest level: ``(value - centre) / scale``;
* ``levels``: the conditions the robustness suite runs it at (:func:`suite_conditions`).

Its effect on the task (where the latency delays the action, where a bias offsets a reading) is the task's code in
:mod:`.task`, which reads the perturbation's columns by name (``column_index``). Adding a perturbation: one
declaration (with its RandomizationConfig field, where a config sets its level) plus its test; the draw kernel, the
privileged block, the observation's size and the suite's conditions follow from the declarations, on both backends.

The declarations' order is the draws' order (the random stream): a new perturbation goes last.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, Callable, Iterator, Sequence

import numpy as np

#: the laws a draw column's raw variate ``u`` is turned into its value by (parameters ``a``, ``b``):
#: IDENTITY u; UNIFORM a + (b - a) u; LOG_UNIFORM uniform in log on [a, b]; SYMMETRIC a + b (2u - 1) (centre a,
#: half-width b); CUBE_ROOT u^(1/3) (a radius uniform in a ball); STEPS an integer uniform in a..b; CONSTANT a (not
#: drawn); DERIVED set by the perturbation's effect at the episode's start (not drawn)
LAWS = ("identity", "uniform", "log_uniform", "symmetric", "cube_root", "steps", "constant", "derived")
IDENTITY, UNIFORM, LOG_UNIFORM, SYMMETRIC, CUBE_ROOT, STEPS, CONSTANT, DERIVED = range(len(LAWS))
#: the longest action latency, agent steps (the length of the action queue less one)
MAX_LATENCY_STEPS = 3
#: the axes of the robustness suite, in the order it runs them (after the nominal task)
AXES = ("sensing", "actuation", "placement", "friction", "tissue")

Law = tuple[int, float, float]


@dataclasses.dataclass(frozen=True)
class Column:
    """One draw column: its name and its raw variate (standard normal, else uniform on [0, 1))."""

    name: str
    normal: bool = False


@dataclasses.dataclass(frozen=True)
class Privileged:
    """One privileged entry: draw column ``column``'s value as ``(value - centre) / scale``."""

    name: str
    column: str
    centre: float
    scale: float


@dataclasses.dataclass(frozen=True)
class Condition:
    """One condition of the robustness suite: the nominal task with one change."""

    axis: str  # sensing, actuation, placement, friction, tissue (or nominal)
    name: str  # what changed, with its level
    randomization: dict[str, Any] = dataclasses.field(default_factory=dict)  # RandomizationConfig fields
    options: dict[str, float] = dataclasses.field(default_factory=dict)  # reset pins
    mus: tuple[float, ...] = ()  # the friction grid (empty: the suite's)


@dataclasses.dataclass(frozen=True)
class Level:
    """A level a perturbation is run at in the suite: a condition's name and change; ``mus`` its own friction grid
    (empty: the suite's); ``since``: the suite version that added it."""

    name: str
    randomization: dict[str, Any] = dataclasses.field(default_factory=dict)
    options: dict[str, float] = dataclasses.field(default_factory=dict)
    mus: tuple[float, ...] = ()
    since: int = 1


def at_most(level: Any, trained: Any) -> bool:
    """A level inside a trained range: no larger than the trained level."""
    return level <= trained + 1e-12


def same(level: Any, trained: Any) -> bool:
    """A choice inside a trained range: the trained choice."""
    return level == trained


def steps_within(level: Any, trained: Any) -> bool:
    """A range of steps inside a trained range of steps."""
    return trained[0] <= level[0] and level[1] <= trained[1]


def ceiling_at_least(level: Any, trained: Any) -> bool:
    """A force ceiling inside a trained one: a trained ceiling, no higher than the level."""
    return trained is not None and level >= trained


@dataclasses.dataclass(frozen=True)
class Perturbation:
    """One perturbation of the task (see the module docstring)."""

    name: str
    axis: str  # one of AXES
    fields: tuple[str, ...]  # RandomizationConfig fields that set it
    columns: tuple[Column, ...] = ()
    law: Callable[[Any], Sequence[Law]] | None = None  # randomization -> (law, a, b) per column
    privileged: tuple[Privileged, ...] = ()
    levels: tuple[Level, ...] = ()
    within: dict[str, Callable[[Any, Any], bool]] = dataclasses.field(default_factory=dict)  # field -> rule

    def laws(self, randomization: Any) -> list[Law]:
        """Each column's (law, a, b) under ``randomization``."""
        laws = list(self.law(randomization)) if self.law is not None else []
        if len(laws) != len(self.columns):
            raise ValueError(f"perturbation {self.name!r}: {len(laws)} laws for {len(self.columns)} columns")
        return laws


def _uniform_or_off(drawn: bool, law: Law, off: float) -> Law:
    return law if drawn else (CONSTANT, off, off)


def _pose_laws(r: Any) -> list[Law]:
    normal, derived = (IDENTITY, 0.0, 0.0), (DERIVED, 0.0, 0.0)
    return [normal] * 3 + [(CUBE_ROOT, 0.0, 0.0)] + [normal] * 3 + [(SYMMETRIC, 0.0, 1.0)] * 2 + [derived] * 9


def _xyz(prefix: str) -> tuple[str, str, str]:
    return tuple(f"{prefix}_{c}" for c in "xyz")  # type: ignore[return-value]


def _placement(offset_mm: float, tilt_deg: float, azimuth_deg: float) -> Level:
    return Level(f"grasp up to {offset_mm:g} mm off, {tilt_deg:g} deg tilt, {azimuth_deg:g} deg turn",
                 {"pose_offset_m": offset_mm * 1e-3, "pose_tilt_deg": tilt_deg, "pose_azimuth_deg": azimuth_deg})


#: the built-in perturbations, in draw order
BUILTIN: tuple[Perturbation, ...] = (
    Perturbation(
        "friction", "friction", ("mu_range", "mu_distribution"), (Column("mu"),),
        lambda r: [(LOG_UNIFORM if r.mu_distribution == "log_uniform" else UNIFORM, *r.mu_range)],
        levels=tuple(Level(f"mu {m:g}", mus=(m,)) for m in (0.1, 0.15, 1.2, 1.5))),
    Perturbation(
        "tissue", "tissue", ("stiffness_scale_range", "mass_scale_range"),
        (Column("stiffness_scale"), Column("mass_scale")),
        lambda r: [(UNIFORM, *r.stiffness_scale_range), (UNIFORM, *r.mass_scale_range)],
        levels=(*(Level(f"stiffness x{k:g}", options={"stiffness_scale": k}) for k in (0.5, 2.0)),
                *(Level(f"mass x{k:g}", options={"mass_scale": k}) for k in (0.7, 1.5)))),
    # the grasp pose: the tip moves up to pose_offset_m normal to the axis (a direction and a radius), the axis tilts
    # up to pose_tilt_deg about a random normal, the jaws turn up to pose_azimuth_deg; the derived columns hold the
    # pose's error from the planned one (set by .task.begin_episode)
    Perturbation(
        "placement", "placement", ("pose_offset_m", "pose_tilt_deg", "pose_azimuth_deg"),
        (*(Column(n, True) for n in _xyz("offset_dir")), Column("offset_r"),
         *(Column(n, True) for n in _xyz("tilt_axis")), Column("tilt"), Column("azimuth"),
         *(Column(n) for n in (*_xyz("tip_offset"), *_xyz("axis_change"), *_xyz("jaw_dir_change")))),
        _pose_laws,
        privileged=(*(Privileged(n, n, 0.0, 0.005) for n in _xyz("tip_offset")),  # (5 mm)
                    *(Privileged(n, n, 0.0, 0.1745) for n in (*_xyz("axis_change"), *_xyz("jaw_dir_change")))),
        levels=(_placement(3.0, 5.0, 5.0), _placement(5.0, 10.0, 10.0))),  # (unit vectors' change; 10 deg in rad)
    # each jaw's normal-force reading offset by a constant drawn per episode in [-force_bias_N, force_bias_N]
    Perturbation(
        "force_bias", "sensing", ("force_bias_N",), tuple(Column(f"force_bias_{k}") for k in range(3)),
        lambda r: [_uniform_or_off(r.force_bias_N > 0.0, (SYMMETRIC, 0.0, r.force_bias_N), 0.0)] * 3,
        privileged=tuple(Privileged(f"force_bias_{k}", f"force_bias_{k}", 0.0, 0.1) for k in range(3)),
        levels=tuple(Level(f"force bias up to {b:g} N", {"force_bias_N": b}) for b in (0.05, 0.1))),
    # an action takes effect latency steps after it was sent (drawn per episode in latency_steps)
    Perturbation(
        "latency", "actuation", ("latency_steps",), (Column("latency"),),
        lambda r: [_uniform_or_off(r.latency_steps[1] > r.latency_steps[0],
                                   (STEPS, float(r.latency_steps[0]), float(r.latency_steps[1])),
                                   float(r.latency_steps[0]))],
        privileged=(Privileged("latency", "latency", 0.0, MAX_LATENCY_STEPS),),
        levels=tuple(Level(f"latency {k} step{'s' if k > 1 else ''}", {"latency_steps": (k, k)}) for k in (1, 2, 3)),
        within={"latency_steps": steps_within}),
    # the jaw force loop's gain x a factor drawn per episode in [1 - e, 1 + e]
    Perturbation(
        "force_loop_gain", "actuation", ("force_loop_gain_error",), (Column("force_loop_gain"),),
        lambda r: [_uniform_or_off(r.force_loop_gain_error > 0.0, (SYMMETRIC, 1.0, r.force_loop_gain_error), 1.0)],
        privileged=(Privileged("force_loop_gain_error", "force_loop_gain", 1.0, 0.2),),
        levels=tuple(Level(f"force-loop gain error up to {e:.0%}", {"force_loop_gain_error": e}) for e in (0.2, 0.4))),
    # the force readings' noise: its standard deviation, per episode in [sensor_noise_low_N, sensor_noise_N] where a
    # low end is set; how it enters the tangential reading; the readings' low-pass filter
    Perturbation(
        "force_noise", "sensing", ("sensor_noise_N", "sensor_noise_low_N", "force_noise", "force_filter_s"),
        (Column("sensor_noise"),),
        lambda r: [_uniform_or_off(r.sensor_noise_low_N is not None and r.sensor_noise_low_N < r.sensor_noise_N,
                                   (UNIFORM, r.sensor_noise_low_N or 0.0, r.sensor_noise_N), r.sensor_noise_N)],
        levels=tuple(Level(f"force noise {n:g} N", {"sensor_noise_N": n}) for n in (0.05, 0.08, 0.1)),
        within={"force_noise": same}),
    Perturbation(
        "slip_sensing", "sensing", ("slip_sensing", "slip_noise"),
        levels=(Level("slip sensed as a detector (binary)", {"slip_sensing": "binary"}),
                Level("slip not sensed", {"slip_sensing": "absent"}),
                Level("slip speed noise 0.1", {"slip_noise": 0.1})),
        within={"slip_sensing": same}),
    Perturbation(
        "lift_tracker", "sensing", ("lift_sensing", "lift_noise_m", "lift_delay_steps"),
        levels=(Level("lift tracker noise 1 mm", {"lift_noise_m": 0.001}, since=2),
                Level("lift tracker 3 frames late", {"lift_delay_steps": 3}, since=2),
                Level("lift not tracked", {"lift_sensing": "absent"}, since=2)),
        within={"lift_sensing": same}),
    Perturbation(
        "pinch_ceiling", "actuation", ("pinch_ceiling_N",),
        levels=(Level("pinch ceiling 3 N", {"pinch_ceiling_N": 3.0}),), within={"pinch_ceiling_N": ceiling_at_least}),
)

_REGISTRY: list[Perturbation] = list(BUILTIN)


def perturbations() -> tuple[Perturbation, ...]:
    """The declared perturbations, in draw order (the built-ins, then any registered)."""
    return tuple(_REGISTRY)


def register_perturbation(perturbation: Perturbation) -> None:
    """Declare a perturbation after the built-ins (its columns are drawn after theirs). Tasks built afterwards draw
    it, observe it (privileged) and the suite runs its levels; a name or column already declared is refused."""
    names = {p.name for p in _REGISTRY}
    columns = set(draw_columns())
    if perturbation.name in names:
        raise ValueError(f"perturbation {perturbation.name!r} is already declared")
    if clash := columns & {c.name for c in perturbation.columns}:
        raise ValueError(f"perturbation {perturbation.name!r}: column(s) {sorted(clash)} already declared")
    if perturbation.axis not in AXES:
        raise ValueError(f"perturbation {perturbation.name!r}: axis {perturbation.axis!r}; allowed: {', '.join(AXES)}")
    _REGISTRY.append(perturbation)


def unregister_perturbation(name: str) -> None:
    """Remove a registered perturbation (the built-ins stay)."""
    if name in {p.name for p in BUILTIN}:
        raise ValueError(f"perturbation {name!r} is built in")
    _REGISTRY[:] = [p for p in _REGISTRY if p.name != name]


@contextlib.contextmanager
def registered(perturbation: Perturbation) -> Iterator[Perturbation]:
    """``register_perturbation`` for the duration of a ``with`` block."""
    register_perturbation(perturbation)
    try:
        yield perturbation
    finally:
        unregister_perturbation(perturbation.name)


def draw_columns() -> tuple[str, ...]:
    """The draw columns of every declared perturbation, in draw order (``TaskState.draws``)."""
    return tuple(c.name for p in _REGISTRY for c in p.columns)


def column_index(name: str) -> int:
    """The position of draw column ``name``."""
    return draw_columns().index(name)


def privileged_names() -> tuple[str, ...]:
    """The privileged perturbation entries (``privileged_perturbations``), in order."""
    return tuple(e.name for p in _REGISTRY for e in p.privileged)


def draw_plan(randomization: Any) -> dict[str, np.ndarray]:
    """The kernel's arrays of the declared draws under ``randomization``: per column its raw variate's kind
    (``draw_is_normal``), its law and parameters (``draw_law``, ``draw_a``, ``draw_b``); per privileged entry its
    column, centre and scale (``priv_col``, ``priv_centre``, ``priv_scale``)."""
    columns = [c for p in _REGISTRY for c in p.columns]
    laws = [law for p in _REGISTRY for law in p.laws(randomization)]
    index = {c.name: k for k, c in enumerate(columns)}
    entries = [e for p in _REGISTRY for e in p.privileged]
    return {
        "draw_is_normal": np.array([c.normal for c in columns], dtype=np.bool_),
        "draw_law": np.array([law[0] for law in laws], dtype=np.int64),
        "draw_a": np.array([law[1] for law in laws], dtype=np.float64),
        "draw_b": np.array([law[2] for law in laws], dtype=np.float64),
        "priv_col": np.array([index[e.column] for e in entries], dtype=np.int64),
        "priv_centre": np.array([e.centre for e in entries], dtype=np.float64),
        "priv_scale": np.array([e.scale for e in entries], dtype=np.float64),
    }


def suite_conditions(mus: tuple[float, ...], version: int) -> tuple[Condition, ...]:
    """The robustness suite's conditions at ``version`` on the friction grid ``mus``: the nominal task, then each
    axis's perturbations' levels (AXES order; declaration order within an axis)."""
    out = [Condition("nominal", "nominal", mus=mus)]
    for axis in AXES:
        out += [Condition(axis, lv.name, dict(lv.randomization), dict(lv.options), lv.mus or mus)
                for p in _REGISTRY if p.axis == axis for lv in p.levels if lv.since <= version]
    return tuple(out)


def rule_of(field: str) -> Callable[[Any, Any], bool]:
    """The rule that says whether a level of RandomizationConfig field ``field`` lies inside a trained one."""
    for p in _REGISTRY:
        if field in p.fields:
            return p.within.get(field, at_most)
    raise KeyError(f"no perturbation declares the randomization field {field!r}")


__all__ = ["AXES", "BUILTIN", "CONSTANT", "CUBE_ROOT", "Column", "Condition", "DERIVED", "IDENTITY", "LAWS",
           "LOG_UNIFORM", "Level", "MAX_LATENCY_STEPS", "Perturbation", "Privileged", "STEPS", "SYMMETRIC", "UNIFORM",
           "at_most", "ceiling_at_least", "column_index", "draw_columns", "draw_plan", "perturbations",
           "privileged_names", "register_perturbation", "registered", "rule_of", "same", "steps_within",
           "suite_conditions", "unregister_perturbation"]
