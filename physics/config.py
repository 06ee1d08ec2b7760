"""Strict configuration loading and atomic file writes, shared by every layer.

Configs are YAML files mapping onto dataclasses. Loading is strict: an unknown key, a wrong type or an
out-of-range value raises :class:`ConfigError` naming the field (dotted path) and what is allowed.
Results are written atomically (temp file in the same folder + ``os.replace``) so an interrupted or
failed write never leaves a half-written file behind.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


# ----------------------------------------------------------------------------------------------
# validation helpers (used in dataclass __post_init__)
# ----------------------------------------------------------------------------------------------


def check_range(
    name: str,
    value: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_inclusive: bool = True,
    hi_inclusive: bool = True,
) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a finite number in the given interval."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    lo_ok = lo is None or (value >= lo if lo_inclusive else value > lo)
    hi_ok = hi is None or (value <= hi if hi_inclusive else value < hi)
    if not (lo_ok and hi_ok):
        left = "(-inf" if lo is None else ("[" if lo_inclusive else "(") + f"{lo:g}"
        right = "inf)" if hi is None else f"{hi:g}" + ("]" if hi_inclusive else ")")
        raise ConfigError(f"{name} = {value!r} is out of range; allowed {left}, {right}")


def check_choice(name: str, value: Any, choices: typing.Iterable[Any]) -> None:
    choices = tuple(choices)
    if value not in choices:
        raise ConfigError(f"{name} = {value!r} is not allowed; choose one of {', '.join(map(repr, choices))}")


def check_vector(name: str, value: Any, length: int = 3) -> tuple[float, ...]:
    try:
        vec = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a list of {length} numbers, got {value!r}") from None
    if len(vec) != length or not all(math.isfinite(v) for v in vec):
        raise ConfigError(f"{name} must be a list of {length} finite numbers, got {value!r}")
    return vec


# ----------------------------------------------------------------------------------------------
# dataclass <-> dict
# ----------------------------------------------------------------------------------------------


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{where}: {value!r} matches none of {tp}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a mapping, got {type(value).__name__}")
        return from_dict(tp, value, where)
    if origin is typing.Literal:
        check_choice(where, value, args)
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where} must be a list, got {value!r}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            items = [_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value)]
        elif origin is tuple and args:
            if len(value) != len(args):
                raise ConfigError(f"{where} must have {len(args)} entries, got {len(value)}")
            items = [_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args))]
        else:
            inner = args[0] if args else Any
            items = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where} must be a mapping, got {value!r}")
        return dict(value)
    return value


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str | None = None) -> T:
    """Build dataclass ``cls`` from a mapping, strictly (unknown keys and wrong types raise)."""
    where = where or cls.__name__
    data = dict(data or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; allowed keys: {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {name: _coerce(val, hints[name], f"{where}.{name}") for name, val in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith(where) else f"{where}.{msg}") from None


def to_dict(obj: Any) -> Any:
    """Dataclass -> plain dict/list/float tree (YAML-safe)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalar
        return obj.item()
    return obj


def replace(obj: T, **changes: Any) -> T:
    """``dataclasses.replace`` that re-runs validation and reports ConfigError with the class name."""
    return from_dict(type(obj), {**to_dict(obj), **changes})


def read_yaml(path: str | os.PathLike) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must contain a mapping at the top level")
    return data


def load_config(cls: type[T], path: str | os.PathLike, section: str | None = None) -> T:
    data = read_yaml(path)
    if section is not None:
        data = data.get(section, {})
    return from_dict(cls, data, where=f"{Path(path).name}" + (f":{section}" if section else ""))


CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"


def builtin_config(relpath: str) -> Path:
    """Path of a config shipped with the package (``configs/<relpath>``)."""
    path = CONFIG_DIR / relpath
    if not path.is_file():
        raise ConfigError(f"no built-in config {relpath!r} in {CONFIG_DIR}")
    return path


# ----------------------------------------------------------------------------------------------
# atomic writes
# ----------------------------------------------------------------------------------------------


def atomic_write(path: str | os.PathLike, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` then atomically move the result to ``path``.

    The temp file lives in the destination folder (same filesystem, so the rename is atomic) and keeps
    the destination's suffix (writers such as matplotlib or meshio pick the format from it). On any
    failure the temp file is removed and the destination is left untouched.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot create output folder {path.parent}: {exc.strerror or exc}") from None
    tmp_path = temp_beside(path)
    try:
        writer(tmp_path)
        publish(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
    return path


def temp_beside(path: str | os.PathLike, suffix: str | None = None) -> Path:
    """A new, empty temp file in ``path``'s folder (same file system, so :func:`publish` is atomic)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    return Path(tmp)


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Give a finished temp file the permissions of a normally created file and move it onto ``path``
    atomically. (mkstemp creates files 0600: without this, outputs would not be readable like any other.)"""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, path)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write(path, lambda p: p.write_text(text))


def save_figure(fig, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Lay out a matplotlib figure, write it atomically (format from the suffix), and close it."""
    import matplotlib.pyplot as plt

    try:
        fig.tight_layout()
        return atomic_write(path, lambda p: fig.savefig(p, dpi=dpi))
    finally:
        plt.close(fig)


def write_yaml(path: str | os.PathLike, data: dict[str, Any]) -> Path:
    return atomic_write_text(path, yaml.safe_dump(to_dict(data), sort_keys=False))
