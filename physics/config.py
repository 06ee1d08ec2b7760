"""Strict configuration records, loading and atomic file writes, shared by every layer.

Configs are YAML files mapping onto dataclasses validated by pydantic (:func:`config_dataclass`): every
field's type and allowed range is declared on the field itself (``Annotated[Real, Gt(0), Le(1)]``), and
loading is strict: an unknown key, a wrong type (a bool for a number, a string for a bool) or an
out-of-range value raises :class:`ConfigError`, one line naming the field (dotted path) and what is
allowed. Results are written atomically (temp file in the same folder + ``os.replace``) so an
interrupted or failed write never leaves a half-written file behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import math
import os
import re
import tempfile
import types
import typing
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated, Any, TypeVar

import annotated_types as at
import pydantic
import pydantic.dataclasses
import typing_extensions
import yaml
from pydantic import Strict, StrictBool, StrictInt, StrictStr

T = TypeVar("T")

__all__ = [
    "RECORD_CONFIG", "Bool", "ConfigError", "Int", "NonNegative", "Positive", "Real", "Str", "atomic_write",
    "ConfigFile", "GRASPER_FILE", "TISSUE_FILE", "atomic_write_text", "builtin_config", "check_choice", "check_range",
    "config_dataclass", "from_dict", "load_config", "merge_mappings", "read_config_file", "read_extending_yaml",
    "read_yaml", "replace",
    "save_figure", "to_dict", "write_yaml", "MissingExtraError", "needs_extra", "require_extra",
]


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message names the extra of msdgrasp that installs it."""


@contextlib.contextmanager
def needs_extra(extra: str, purpose: str) -> Iterator[None]:
    """Wrap the imports of an optional dependency (the core install is the env and the physics only).

    A module missing inside the block raises :class:`MissingExtraError`, one line naming ``purpose``, the
    module and the command that installs it: ``pip install 'msdgrasp[<extra>]'``.
    """
    try:
        yield
    except ModuleNotFoundError as exc:
        raise MissingExtraError(f"{purpose}: {exc.name or 'a module'} is not installed; "
                                f"pip install 'msdgrasp[{extra}]'") from None


def require_extra(extra: str, purpose: str, *modules: str) -> None:
    """Import ``modules`` now: a command that uses them only at its end (plots after a run) fails before the run."""
    with needs_extra(extra, purpose):
        for name in modules:
            importlib.import_module(name)


# ----------------------------------------------------------------------------------------------
# field types of config records: strict scalars (YAML's `true` is not a number, "1.5" not a float)
# ----------------------------------------------------------------------------------------------

#: a finite number (an integer is accepted; a bool or a string is not)
Real = Annotated[float, Strict()]
Int = StrictInt
Bool = StrictBool
Str = StrictStr
Positive = Annotated[Real, at.Gt(0)]
NonNegative = Annotated[Real, at.Ge(0)]

#: pydantic settings of every config record: unknown keys are errors, numbers must be finite
RECORD_CONFIG = pydantic.ConfigDict(extra="forbid", allow_inf_nan=False)


def config_dataclass(cls: type[T]) -> type[T]:
    """Make ``cls`` a frozen config record validated by pydantic, whose errors are :class:`ConfigError`.

    Fields are checked on construction (``TissueParams(youngs_modulus_pa=-1)`` raises), by
    :func:`from_dict` (nested mappings become nested records) and by :func:`replace`. Checks that involve
    several fields stay in ``__post_init__`` (raise :class:`ConfigError` there).
    """
    cls = pydantic.dataclasses.dataclass(frozen=True, config=RECORD_CONFIG)(cls)
    init = cls.__init__

    @functools.wraps(init)
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        try:
            init(self, *args, **kwargs)
        except pydantic.ValidationError as exc:
            raise ConfigError(describe_validation_error(exc, cls, cls.__name__)) from None

    cls.__init__ = __init__
    return cls


# ----------------------------------------------------------------------------------------------
# one-line error messages
# ----------------------------------------------------------------------------------------------


def interval_text(lo: float | None, hi: float | None, lo_inclusive: bool = True, hi_inclusive: bool = True) -> str:
    """``[0, 1)``-style text of an interval (None: unbounded)."""
    left = "(-inf" if lo is None else ("[" if lo_inclusive else "(") + f"{lo:g}"
    right = "inf)" if hi is None else f"{hi:g}" + ("]" if hi_inclusive else ")")
    return f"{left}, {right}"


def _bounds(annotation: Any, found: dict[str, float]) -> None:
    """Collect the Gt/Ge/Lt/Le bounds declared in ``annotation`` (through Annotated, unions, FieldInfo)."""
    if isinstance(annotation, pydantic.fields.FieldInfo):
        for meta in annotation.metadata:
            _bounds(meta, found)
        _bounds(annotation.annotation, found)
        return
    for kind in ("gt", "ge", "lt", "le"):
        bound = getattr(annotation, kind, None)
        if isinstance(annotation, (at.Gt, at.Ge, at.Lt, at.Le, at.Interval)) and bound is not None:
            found.setdefault(kind, bound)
    if typing.get_origin(annotation) is Annotated:
        for meta in annotation.__metadata__:
            _bounds(meta, found)
        _bounds(typing.get_args(annotation)[0], found)
    elif typing.get_origin(annotation) in (typing.Union, types.UnionType):
        for arg in typing.get_args(annotation):
            _bounds(arg, found)


def _strip(annotation: Any) -> Any:
    """The type inside Annotated / Optional (the first non-None member of a union)."""
    while True:
        origin = typing.get_origin(annotation)
        if origin is Annotated:
            annotation = typing.get_args(annotation)[0]
        elif origin in (typing.Union, types.UnionType):
            annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
        else:
            return annotation


def _field_at(cls: Any, loc: tuple) -> Any:
    """The annotation (or pydantic FieldInfo) of the field at ``loc`` inside record ``cls`` (None: unknown)."""
    node: Any = cls
    for part in loc:
        raw = node.annotation if isinstance(node, pydantic.fields.FieldInfo) else node
        if isinstance(part, int) and typing.get_origin(raw) in (typing.Union, types.UnionType):
            raw = next((a for a in typing.get_args(raw) if typing.get_origin(_strip(a)) in (tuple, list)), raw)
        tp = _strip(raw)
        if isinstance(part, int):
            args = typing.get_args(tp)
            if not args:
                return None
            node = args[0] if (len(args) == 2 and args[1] is Ellipsis) or part >= len(args) else args[part]
        elif hasattr(tp, "__pydantic_fields__") and part in tp.__pydantic_fields__:
            node = tp.__pydantic_fields__[part]
        elif typing_extensions.is_typeddict(tp) and part in typing.get_type_hints(tp, include_extras=True):
            node = typing.get_type_hints(tp, include_extras=True)[part]
        else:
            return None
    return node


def _allowed_keys(cls: Any, loc: tuple) -> list[str]:
    node = _field_at(cls, loc) if loc else cls
    tp = _strip(node.annotation if isinstance(node, pydantic.fields.FieldInfo) else node)
    if hasattr(tp, "__pydantic_fields__"):
        return sorted(tp.__pydantic_fields__)
    if typing_extensions.is_typeddict(tp):
        return sorted(typing.get_type_hints(tp))
    return []


def _union_tag(part: Any) -> bool:
    """Whether a pydantic error location part names a member of a union (``constrained-float``, ``tuple[...]``), not
    a field: the path a user reads names fields only."""
    return isinstance(part, str) and ("[" in part or re.fullmatch(r"[a-z]+(-[a-z]+)+", part) is not None)


def _reported_error(exc: pydantic.ValidationError) -> Any:
    """The error a message reports: the first (later ones are often its consequences), but where a sequence failed a
    union's members one by one, the sequence member's (its entries are what is wrong, not that it is no number)."""
    errors = exc.errors()
    err = errors[0]
    if not isinstance(err.get("input"), (list, tuple)):
        return err
    sequence = [e for e in errors if e["loc"][:len(err["loc"]) - 1] == err["loc"][:-1]
                and any(isinstance(p, str) and p.startswith(("tuple[", "list[")) for p in e["loc"])]
    return sequence[0] if sequence else err


def describe_validation_error(exc: pydantic.ValidationError, cls: Any, where: str) -> str:
    """One line for a pydantic error: the dotted field path, the value and what is allowed."""
    err = _reported_error(exc)
    loc = tuple(p for p in err["loc"] if not _union_tag(p))
    path = where + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc)
    kind, value, ctx = err["type"], err.get("input"), err.get("ctx") or {}
    if kind in ("extra_forbidden", "unexpected_keyword_argument"):
        parent = path.rsplit(".", 1)[0]
        allowed = _allowed_keys(cls, loc[:-1])
        text = f"{parent}: unknown key {loc[-1]!r}" + (f"; allowed keys: {', '.join(allowed)}" if allowed else "")
    elif kind in ("missing", "missing_argument", "missing_keyword_only_argument"):
        text = f"{path} is required" + (" (too few entries)" if loc and isinstance(loc[-1], int) else "")
    elif kind == "finite_number":
        text = f"{path} must be a finite number, got {value!r}"
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        bounds: dict[str, float] = {}
        field = _field_at(cls, loc)
        if field is not None:
            _bounds(field, bounds)
        lo = bounds.get("gt", bounds.get("ge"))
        hi = bounds.get("lt", bounds.get("le"))
        text = (f"{path} = {value!r} is out of range; allowed "
                f"{interval_text(lo, hi, 'gt' not in bounds, 'lt' not in bounds)}")
    elif kind == "too_short":
        text = (f"{path} must have at least {ctx['min_length']} entr{'y' if ctx['min_length'] == 1 else 'ies'}, "
                f"got {value!r}")
    elif kind == "too_long":
        text = f"{path} must have at most {ctx['max_length']} entries, got {value!r}"
    elif kind == "literal_error":
        text = f"{path} = {value!r} is not allowed; choose {ctx.get('expected', '')}"
    elif kind in ("dict_type", "dataclass_type", "dataclass_args_type", "model_type"):
        text = f"{path} must be a mapping, got {value!r}"
    elif kind == "bool_type":
        text = f"{path} must be true or false, got {value!r}"
    elif kind in ("int_type", "int_from_float"):
        text = f"{path} must be an integer, got {value!r}"
    elif kind == "float_type":
        text = f"{path} must be a number, got {value!r}"
    elif kind == "value_error":
        text = f"{path}: {ctx.get('error', err['msg'])}" if loc else f"{where}: {ctx.get('error', err['msg'])}"
    else:
        text = f"{path} = {value!r}: {err['msg']}"
    return text


# ----------------------------------------------------------------------------------------------
# checks of run-time values (reset options, solver arguments: not config records)
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
        raise ConfigError(f"{name} = {value!r} is out of range; "
                          f"allowed {interval_text(lo, hi, lo_inclusive, hi_inclusive)}")


def check_choice(name: str, value: Any, choices: typing.Iterable[Any]) -> None:
    choices = tuple(choices)
    if value not in choices:
        raise ConfigError(f"{name} = {value!r} is not allowed; choose one of {', '.join(map(repr, choices))}")


# ----------------------------------------------------------------------------------------------
# record <-> dict
# ----------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=None)
def _adapter(cls: type) -> pydantic.TypeAdapter:
    return pydantic.TypeAdapter(cls)


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str | None = None) -> T:
    """Build config record ``cls`` from a mapping, strictly (unknown keys, wrong types and values out of
    range raise :class:`ConfigError` naming ``where`` and the field)."""
    where = where or cls.__name__
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{where} must be a mapping, got {type(data).__name__}")
    try:
        return _adapter(cls).validate_python(dict(data or {}))
    except pydantic.ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, cls, where)) from None


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
    """``dataclasses.replace`` of a config record: the changed record is validated again."""
    return dataclasses.replace(obj, **changes)


class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (YAML keeps the last silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice (line {key_node.start_mark.line + 1})",
                    key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | os.PathLike) -> dict[str, Any]:
    """The top-level mapping of a YAML config file. A missing file, a file not UTF-8, invalid YAML or a key given
    twice in one mapping, an empty file (every
    config needs at least one key: an empty one would silently be all defaults) or a top level that is
    not a mapping raises :class:`ConfigError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {path} is not UTF-8 text (byte {exc.start}); a config is YAML") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {' '.join(str(exc).split())}") from None
    if data is None:
        raise ConfigError(f"config file {path} is empty; a config needs at least one key (an empty file is not "
                          "taken as all defaults)")
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must contain a mapping at the top level")
    return data


#: the most envs one batched env may hold (a training's n_envs, --n-envs): the GPU task's trainings run 4,096; far
#: more is a typo, not a batch
MAX_ENVS = 65_536

#: the top-level key by which a config file builds on another (:func:`read_extending_yaml`)
EXTENDS = "extends"


def merge_mappings(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` deep-merged onto ``base`` (neither is changed): a key whose value is a mapping in both merges key by
    key; any other value of ``over`` (a scalar, a list, null, a mapping over a non-mapping) replaces ``base``'s."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_mappings(out[key], value)
        else:
            out[key] = value
    return out


def _nested_extends(data: Any, where: str) -> str | None:
    """The dotted path of the first ``extends`` key below the top level of ``data`` (None: there is none)."""
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for key, value in items:
        path = f"{where}.{key}" if where else str(key)
        if isinstance(value, dict) and EXTENDS in value:
            return f"{path}.{EXTENDS}"
        found = _nested_extends(value, path)
        if found is not None:
            return found
    return None


def read_extending_yaml(path: str | os.PathLike,
                        prepare: Callable[[dict[str, Any], Path], dict[str, Any]] | None = None,
                        merge: Callable[[dict[str, Any], dict[str, Any]], dict[str, Any]] = merge_mappings
                        ) -> dict[str, Any]:
    """The top-level mapping of a config file that may build on another one (a training, tissue or grasper config).

    A top-level ``extends: <file>`` names the parent, relative to this file's folder; the result is the parent's
    mapping (itself read this way, so a parent may extend another) deep-merged with this file's
    (:func:`merge_mappings`: this file's values win, mappings merge key by key, lists and scalars replace), without
    the ``extends`` key. The merged mapping is then checked by the record's loader as any other file's, so an
    unknown key is refused wherever in the chain it was written. ``prepare(data, file)``, where given, is applied to
    each file's own mapping before it is merged (e.g. to resolve the paths a file names against its own folder);
    ``merge(parent, child)`` merges the two (a kind of file may replace a section whole: :attr:`ConfigFile.merge`).

    Besides :func:`read_yaml`'s errors (naming the file read), a parent that does not exist, a cycle, an ``extends``
    that is not a non-empty string and an ``extends`` below the top level each raise a one-line
    :class:`ConfigError` naming the file and the field; nothing falls back to defaults."""
    return _read_extending(Path(path), prepare, merge, ())


def _read_extending(path: Path, prepare: Callable[[dict[str, Any], Path], dict[str, Any]] | None,
                    merge: Callable[[dict[str, Any], dict[str, Any]], dict[str, Any]],
                    chain: tuple[Path, ...]) -> dict[str, Any]:
    data = read_yaml(path)
    nested = _nested_extends(data, "")
    if nested is not None:
        raise ConfigError(f"{path}: {nested}: '{EXTENDS}' is only allowed at the top level of a config file")
    extends = EXTENDS in data
    parent_name = data.pop(EXTENDS, None)
    if prepare is not None:
        data = prepare(data, path)
    if not extends:
        return data
    if not isinstance(parent_name, str) or not parent_name.strip():
        raise ConfigError(f"{path}: {EXTENDS} must be the path of the config file this one builds on (relative to "
                          f"{path.parent}), got {parent_name!r}")
    parent = path.parent / parent_name
    chain = (*chain, path.resolve())
    if parent.resolve() in chain:
        names = " -> ".join(str(p) for p in (*chain, parent.resolve()))
        raise ConfigError(f"{path}: {EXTENDS}: {parent_name!r} makes a cycle: {names}")
    if not parent.is_file():
        raise ConfigError(f"{path}: {EXTENDS}: config file not found: {parent}")
    return merge(_read_extending(parent, prepare, merge, chain), data)


@dataclasses.dataclass(frozen=True)
class ConfigFile:
    """What one kind of YAML config file holds: its top-level sections, which of them it must have, and what
    to write for each required one (the error of a missing section says what to add)."""

    #: what the file is, for messages ("tissue config")
    kind: str
    #: every allowed top-level section
    sections: tuple[str, ...]
    #: the sections the file must have: a missing one is an error, never a default
    required: tuple[str, ...]
    #: per required section, a one-line example of it
    examples: tuple[tuple[str, str], ...] = ()
    #: how a file that ``extends`` another merges onto it (:func:`read_extending_yaml`)
    merge: Callable[[dict[str, Any], dict[str, Any]], dict[str, Any]] = merge_mappings


def merge_tissue_configs(parent: dict[str, Any], child: dict[str, Any]) -> dict[str, Any]:
    """:func:`merge_mappings`, except that a child's ``mesh`` naming another ``shape`` than its parent's replaces the
    parent's mesh section whole: a mesh's options (``resolution``, a generator's own) belong to its shape, so none
    is inherited by a mesh they may not fit."""
    merged = merge_mappings(parent, child)
    mine, theirs = child.get("mesh"), parent.get("mesh")
    if isinstance(mine, dict) and isinstance(theirs, dict) and "shape" in mine:
        if str(mine["shape"]).strip().lower() != str(theirs.get("shape", "")).strip().lower():
            merged["mesh"] = dict(mine)
    return merged


#: a tissue config (configs/tissue/*.yaml): the mesh, the material, and the record of a calibration that wrote it
TISSUE_FILE = ConfigFile(
    "tissue config", ("mesh", "tissue", "calibration"), ("mesh", "tissue"),
    (("mesh", "mesh: {shape: sphere-even | sphere | spleen | spleen-even | spleen-j1 | <mesh file, relative to this "
              "YAML>, resolution: coarse}"),
     ("tissue", "tissue: {youngs_modulus_pa: 12000.0, mass_kg: 0.15, ...} (see configs/tissue/spleen.yaml)")),
    merge_tissue_configs,
)
#: a grasper config (configs/grasper/*.yaml)
GRASPER_FILE = ConfigFile(
    "grasper config", ("grasper",), ("grasper",),
    (("grasper",
      "grasper: {jaw_length_m: 0.03, jaw_width_m: 0.014, mu: 0.6, ...} (see configs/grasper/default.yaml)"),),
)


def read_config_file(path: str | os.PathLike, spec: ConfigFile,
                     prepare: Callable[[dict[str, Any], Path], dict[str, Any]] | None = None) -> dict[str, Any]:
    """The top-level sections of a config file of kind ``spec``, checked: an unknown section (a misspelt
    one included), a missing required one or a section that is not a mapping raises :class:`ConfigError`
    naming the file and the section. A top-level ``extends: <file>`` builds on another config of the kind
    (:func:`read_extending_yaml`, with ``prepare`` applied to each file's own mapping, merged by ``spec.merge``)."""
    data = read_extending_yaml(path, prepare, spec.merge)
    allowed = ", ".join(spec.sections)
    for name in data:
        if name not in spec.sections:
            raise ConfigError(f"{path}: unknown section {name!r} in a {spec.kind}; allowed sections: {allowed}")
    examples = dict(spec.examples)
    for name in spec.required:
        if name not in data:
            example = f"; add e.g. {examples[name]}" if name in examples else ""
            raise ConfigError(f"{path}: no '{name}:' section (a {spec.kind} must have "
                              f"{', '.join(spec.required)}){example}")
    for name, section in data.items():
        if not isinstance(section, dict):
            raise ConfigError(f"{path}:{name} must be a mapping of keys, got {section!r}")
    return data


def load_config(cls: type[T], path: str | os.PathLike, spec: ConfigFile, section: str) -> T:
    """Config record ``cls`` from section ``section`` of a file of kind ``spec``, strictly: the file's sections
    are checked (:func:`read_config_file`) and the section's keys, types and ranges (:func:`from_dict`), each
    error one line naming the file and the key. A section the file may leave out gives ``cls``'s defaults."""
    if section not in spec.sections:
        raise ValueError(f"{section!r} is not a section of a {spec.kind}")  # (a programming error)
    return from_dict(cls, read_config_file(path, spec).get(section), where=f"{path}:{section}")


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


def nan_to_none(x: Any) -> Any:
    """NaN/inf floats (also nested in dicts and lists) as None: JSON's null instead of invalid NaN."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: nan_to_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [nan_to_none(v) for v in x]
    return x


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
