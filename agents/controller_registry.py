"""The controller registry: every hand-written controller by name, with what the rest of the package asks of it
(docs/learners.md, "Adding a controller").

A policy spec names a controller (``reactive``), a controller with a value (``fixed:2.5``) or with settings
(``slipfeedback:gain=0.8,pull=0.25``); any other spec is a saved model's path. Evaluation, the robustness suite, the
training config, seeds, sweeps and the command line ask this registry, never a name of their own:

* :func:`register_controller` / :func:`unregister_controller`, :func:`controller_names`, :func:`get_controller`;
* :func:`controller_of` (the entry a spec names, None for a model), :func:`parse_controller_spec` (its options,
  checked through the entry's settings record), :func:`check_controller_spec`, :func:`make_controller`;
* :func:`baselines`, :func:`suite_baselines`, :func:`residual_bases`: the entries with that flag;
* :func:`display_name`, :func:`spec_forms`, :func:`policy_usage`, :func:`controllers_help`: names for people.

The built-in controllers register in :mod:`.controllers`, beside their classes: import the registry from there (this
module holds the machinery and imports no controller, so that it stays below them in the import graph).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from ..envs.core import setpoint_interface
from ..physics.config import ConfigError

if TYPE_CHECKING:
    from ..envs.core import GraspLiftConfig


@dataclasses.dataclass(frozen=True)
class SpecOptions:
    """What a spec ``name:...`` may give after the name: ``key=value`` settings (``keys``: spec key -> settings field,
    the factory's keyword) or one bare value (``positional``: the field it sets). ``usage``: the part after the colon
    as the help writes it (``<N>``, ``initial=N,gain=N``); ``path_keys``: keys whose value is a file path, not a
    number."""

    keys: Mapping[str, str] = dataclasses.field(default_factory=dict)
    positional: str | None = None
    usage: str = "key=value,..."
    path_keys: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if bool(self.keys) == (self.positional is not None):
            raise ValueError("spec options take either keys or one positional field")


@dataclasses.dataclass(frozen=True)
class Controller:
    """One registered controller.

    ``factory(config, **options)`` builds its policy for the task ``config`` (a class whose ``__init__`` takes the
    task first serves). ``settings``: its parameter record (a dataclass whose ``__post_init__`` raises ValueError
    naming a bad field); a spec's options are checked by building it. ``display``: its name in tables and plots (or
    a function from a policy's name to it, None where the name is not this controller's). ``options``: what its
    spec may give after the name (None: nothing). ``resolve``: turns the checked options into the factory's keywords
    (loads the files they name: a missing one is refused when the spec is checked). Flags: ``baseline``, evaluated
    beside every policy (evaluations, the suite, seeds, sweeps); ``suite_baseline``, beside every policy in the
    robustness suite too; ``residual_base``, may be the base of a residual policy; ``needs_setpoint_interface``, runs
    on a force set-point jaw and a forward-speed pull only; ``reports_pull``, its policy says per episode whether its
    pull has started (``policy.pulling``)."""

    name: str
    factory: Callable[..., Any]
    settings: type | None = None
    display: str | Callable[[str], str | None] | None = None
    options: SpecOptions | None = None
    resolve: Callable[[dict[str, Any]], dict[str, Any]] | None = None
    help: str = ""
    baseline: bool = False
    suite_baseline: bool = False
    residual_base: bool = False
    needs_setpoint_interface: bool = False
    reports_pull: bool = False

    @property
    def shown(self) -> str:
        """The display name of the bare controller."""
        return self.display if isinstance(self.display, str) else self.name

    def display_of(self, name: str) -> str | None:
        """How a policy named ``name`` is shown, where the name is this controller's (None elsewhere)."""
        if callable(self.display):
            return self.display(name)
        if name == self.name:
            return self.shown
        if name.startswith(self.name + ":"):  # a spec with settings names its policy
            return f"{self.shown} ({name.split(':', 1)[1]})"
        return None

    def runs_on(self, config: GraspLiftConfig) -> bool:
        """Whether the task ``config`` has the interface this controller drives."""
        return not self.needs_setpoint_interface or setpoint_interface(config)

    def spec_forms(self) -> list[str]:
        """Its spec's forms for an error message: the name, and the name with its options."""
        if self.options is None:
            return [self.name]
        tail = self.options.usage if self.options.positional is not None else "key=value,..."
        return [self.name, f"{self.name}:{tail}"]


_REGISTRY: dict[str, Controller] = {}


def register_controller(name: str, factory: Callable[..., Any], **fields: Any) -> Controller:
    """Make the controller ``name`` known (the :class:`Controller` fields as keywords); ValueError for a name taken
    or unusable in a spec."""
    if not name or ":" in name or any(c in name for c in "*?[/\\") or name != name.strip():
        raise ValueError(f"controller name {name!r} cannot be a policy spec (no ':', '/', wildcards or spaces)")
    if name in _REGISTRY:
        raise ValueError(f"controller {name!r} is registered twice")
    entry = Controller(name, factory, **fields)
    _REGISTRY[name] = entry
    return entry


def unregister_controller(name: str) -> None:
    """Forget the controller ``name`` (ConfigError for one not registered)."""
    get_controller(name)
    del _REGISTRY[name]


def controller_names() -> tuple[str, ...]:
    """The registered controllers' names, in registration order."""
    return tuple(_REGISTRY)


def get_controller(name: str) -> Controller:
    """The controller ``name``; ConfigError naming the known ones for another."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ConfigError(f"unknown controller {name!r}; known controllers: {', '.join(_REGISTRY)}") from None


def controller_of(spec: str) -> Controller | None:
    """The controller a policy spec names (``name`` or ``name:...``), None where the spec is a model's path."""
    if not isinstance(spec, str):
        return None
    return _REGISTRY.get(spec.split(":", 1)[0])


def is_controller(spec: str) -> bool:
    """Whether a policy spec names a registered controller (with options too), not a saved model."""
    return controller_of(spec) is not None


def _number(spec: str, key: str, value: str) -> float:
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number):
        raise ConfigError(f"policy {spec!r}: {key} expects a number, got {value!r}")
    return number


def _keyed(spec: str, entry: Controller, body: str) -> dict[str, Any]:
    """The options of ``name:key=value,...``; ConfigError naming the spec and the key, with the keys allowed."""
    opts = entry.options
    options: dict[str, Any] = {}
    for part in body.split(","):
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in opts.keys:
            raise ConfigError(f"policy {spec!r}: '{entry.name}:key=value,...' takes keys {', '.join(opts.keys)}; "
                              f"got {part!r}")
        if opts.keys[key] in options:
            raise ConfigError(f"policy {spec!r}: {key} is given twice; give each key once")
        if key in opts.path_keys:
            if not value.strip():
                raise ConfigError(f"policy {spec!r}: {key} expects a file path, got {value!r}")
            options[opts.keys[key]] = value.strip()
        else:
            options[opts.keys[key]] = _number(spec, key, value)
    return options


def parse_controller_spec(spec: str) -> tuple[Controller, dict[str, Any]]:
    """The controller a spec names and its options (settings field -> value, file paths as text), checked through
    the controller's settings record; ConfigError naming the spec, and the key or field, on a bad one."""
    entry = controller_of(spec)
    if entry is None:
        raise ConfigError(f"policy {spec!r} names no controller; known controllers: {', '.join(_REGISTRY)}")
    name, sep, body = spec.partition(":")
    if not sep:
        return entry, {}
    if entry.options is None:
        raise ConfigError(f"policy {spec!r}: {name} takes no options; give {name!r} alone")
    if entry.options.positional is not None:
        options = {entry.options.positional: _number(spec, f"'{name}:{entry.options.usage}'", body)}
    else:
        options = _keyed(spec, entry, body)
    if entry.settings is not None:
        paths = {entry.options.keys[k] for k in entry.options.path_keys}
        try:
            entry.settings(**{k: v for k, v in options.items() if k not in paths})
        except ValueError as exc:
            raise ConfigError(f"policy {spec!r}: {exc}") from None
    return entry, options


def _resolved(spec: str) -> tuple[Controller, dict[str, Any]]:
    entry, options = parse_controller_spec(spec)
    if entry.resolve is not None:
        try:
            options = entry.resolve(options)
        except ValueError as exc:  # (ConfigError too: a file the options name is missing or broken)
            raise ConfigError(str(exc) if isinstance(exc, ConfigError) else f"policy {spec!r}: {exc}") from None
    return entry, options


def _check_forces(spec: str, options: dict[str, Any], config: GraspLiftConfig) -> None:
    """ConfigError where a force setting of ``spec`` (a field named ``*_N``, in newtons) is beyond what the task's jaw
    can command (``max_pinch_force_N``): it would be clamped, and the spec would name a grip it never had."""
    for field, value in options.items():
        if field.endswith("_N") and isinstance(value, float) and value > config.max_pinch_force_N:
            raise ConfigError(f"policy {spec!r}: {field} = {value:g} N is beyond the task's max_pinch_force_N; "
                              f"allowed (0, {config.max_pinch_force_N:g}] N")


def check_controller_spec(spec: str, config: GraspLiftConfig | None = None) -> Controller:
    """The controller of ``spec`` once its options are checked and the files they name load, and, given the task
    ``config``, its force settings are within the task's jaw (ConfigError else)."""
    entry, options = _resolved(spec)
    if config is not None:
        _check_forces(spec, options, config)
    return entry


def make_controller(spec: str, config: GraspLiftConfig) -> Any:
    """The policy of the controller spec ``spec`` on the task ``config``. A spec with ``key=value`` settings names
    its policy (two settings of one controller stay apart in a table); a bare name or value leaves the name to the
    controller."""
    entry, options = _resolved(spec)
    if not entry.runs_on(config):
        raise ConfigError(f"policy {spec!r}: {entry.name} needs jaw_action: force and pull_action: forward_speed, "
                          f"got {config.jaw_action!r} / {config.pull_action!r}")
    _check_forces(spec, options, config)
    policy = entry.factory(config, **options)
    if entry.options is not None and entry.options.keys and ":" in spec:
        policy.name = spec
    return policy


def baselines() -> tuple[str, ...]:
    """The controllers evaluated beside every policy, in registration order."""
    return tuple(n for n, e in _REGISTRY.items() if e.baseline)


def suite_baselines(config: GraspLiftConfig) -> tuple[str, ...]:
    """The robustness suite's baselines on the task ``config``: every evaluation's first, then the suite's own, each
    where the task has the interface it drives."""
    own = tuple(n for n, e in _REGISTRY.items() if e.suite_baseline and not e.baseline)
    return tuple(n for n in (*baselines(), *own) if _REGISTRY[n].runs_on(config))


def residual_bases() -> tuple[Controller, ...]:
    """The controllers a residual policy may correct."""
    return tuple(e for e in _REGISTRY.values() if e.residual_base)


def display_name(name: str) -> str:
    """What a policy is, for plots and tables: 'reactive' -> 'slip-reactive', 'fixed2.5N' -> 'fixed 2.5 N'; a
    model's name stays as it is."""
    for entry in _REGISTRY.values():
        shown = entry.display_of(name)
        if shown is not None:
            return shown
    return name


def spec_forms(entries: tuple[Controller, ...] | None = None) -> list[str]:
    """Every controller spec's forms (``fixed``, ``fixed:<N>``, ...), for an error message."""
    return [form for e in (_REGISTRY.values() if entries is None else entries) for form in e.spec_forms()]


def policy_usage() -> str:
    """The controller specs as the help writes them: ``fixed[:<N>] | reactive | ...``."""
    return " | ".join(e.name if e.options is None else f"{e.name}[:{e.options.usage}]" for e in _REGISTRY.values())


def controllers_help() -> str:
    """One line per controller: its name and help."""
    return "\n".join(f"  {e.name:<13} {e.help}" for e in _REGISTRY.values())
