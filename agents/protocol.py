"""The evaluation protocol's seeds: a sealed range that only evaluations draw from.

An environment's episode is fixed by its reset seed. Training envs (``seed .. seed + n_envs - 1``), the validation
episodes that select a model (``seed + VALIDATION_SEED_OFFSET + i``), behaviour cloning's demonstrations
(``seed + DEMONSTRATION_SEED_OFFSET + i``), friction-estimator fits, collected datasets and sweeps all reset envs with
small seeds, and settings are tuned on what they show. A result on those episodes certifies nothing, so the benchmark's
evaluations draw from :data:`SEALED_SEEDS`, far from every seed a training uses, and everything that trains, fits,
collects, sweeps or selects refuses a seed set that reaches into it (:func:`check_not_sealed`, a one-line
:class:`~..physics.config.ConfigError`; exit status 2 on the command line).

``msdgrasp evaluate`` (the mu grid and ``--suite robustness``), the multi-seed report after ``train --seeds`` and
``msdgrasp report`` start at :data:`EVALUATION_SEED`, the range's first seed, and every result file they write records
``"seeds": {"first", "count", "sealed"}`` (:func:`seeds_record`): ``sealed`` is true where every episode's seed lies
inside the range, so a table of results can refuse the others.
"""

from __future__ import annotations

from numbers import Integral
from typing import Any

from ..physics.config import ConfigError

#: the sealed evaluation seeds, half-open: [1_000_000_000, 1_100_000_000)
SEALED_SEEDS = range(1_000_000_000, 1_100_000_000)
#: where evaluations start by default: the sealed range's first seed
EVALUATION_SEED = SEALED_SEEDS.start
#: validation episode i of a training with seed s is reset with s + VALIDATION_SEED_OFFSET + i
VALIDATION_SEED_OFFSET = 100_000
#: behaviour cloning's demonstration env i of a training with seed s is reset with s + DEMONSTRATION_SEED_OFFSET + i
DEMONSTRATION_SEED_OFFSET = 10_000


def _integer(x: Any) -> bool:
    return isinstance(x, Integral) and not isinstance(x, bool)


def _check_count(first: int, count: int, field: str) -> None:
    if not _integer(first) or first < 0:
        raise ConfigError(f"{field} = {first!r}: seeds must be integers >= 0")
    if not _integer(count) or count < 0:
        raise ConfigError(f"{field}: the number of seeds must be an integer >= 0, got {count!r}")


def overlaps_sealed(first: int, count: int) -> bool:
    """Whether any of the seeds ``first .. first + count - 1`` lies in :data:`SEALED_SEEDS`."""
    return count > 0 and first < SEALED_SEEDS.stop and first + count > SEALED_SEEDS.start


def is_sealed(first: int, count: int) -> bool:
    """Whether every one of the seeds ``first .. first + count - 1`` (at least one) lies in :data:`SEALED_SEEDS`:
    an evaluation on them is one the protocol certifies."""
    return count > 0 and SEALED_SEEDS.start <= first and first + count <= SEALED_SEEDS.stop


def sealed_range_text() -> str:
    """``[1000000000, 1100000000)``: the sealed range as the error messages write it."""
    return f"[{SEALED_SEEDS.start}, {SEALED_SEEDS.stop})"


def check_not_sealed(first: int, count: int, field: str, *, value: int | None = None,
                     via: str | None = None) -> None:
    """ConfigError (one line: the field, the seeds it would use, the allowed range) where the seeds
    ``first .. first + count - 1`` of a training, validation, fit, dataset, sweep or selection reach into
    :data:`SEALED_SEEDS`; also where ``first`` is not an integer >= 0. ``value``: the field's own value where the
    seeds derive from it (default ``first``); ``via``: how they derive (``"validation episodes: seed + 100000 +
    i"``)."""
    _check_count(first, count, field)
    if overlaps_sealed(int(first), int(count)):
        first, count = int(first), int(count)
        seeds = f"seed {first}" if count == 1 else f"seeds {first}..{first + count - 1}"
        how = f" ({via})" if via else ""
        raise ConfigError(
            f"{field} = {first if value is None else value}{how} would use {seeds}, in the sealed evaluation "
            f"seeds {sealed_range_text()} (evaluations only); allowed: seeds below {SEALED_SEEDS.start} or from "
            f"{SEALED_SEEDS.stop} on")


def check_evaluation_seeds(first: int, count: int, field: str = "seed") -> None:
    """ConfigError where an evaluation's first seed is not an integer >= 0, or where its seeds ``first .. first +
    count - 1`` straddle an end of :data:`SEALED_SEEDS` (a result is sealed, all of them inside, or not, all outside;
    one partly inside would be recorded as neither)."""
    _check_count(first, count, field)
    if overlaps_sealed(int(first), int(count)) and not is_sealed(int(first), int(count)):
        first, count = int(first), int(count)
        raise ConfigError(
            f"{field} = {first}: the episodes' seeds {first}..{first + count - 1} straddle the sealed evaluation seeds "
            f"{sealed_range_text()}; allowed: all of them inside (a sealed result) or all outside (a development one)")


def seeds_record(first: int, count: int) -> dict[str, Any]:
    """What a result file records of its episodes' seeds ``first .. first + count - 1``: ``{"first", "count",
    "sealed"}``, sealed where all of them lie in :data:`SEALED_SEEDS`."""
    return {"first": int(first), "count": int(count), "sealed": is_sealed(int(first), int(count))}


__all__ = ["DEMONSTRATION_SEED_OFFSET", "EVALUATION_SEED", "SEALED_SEEDS", "VALIDATION_SEED_OFFSET",
           "check_evaluation_seeds", "check_not_sealed", "is_sealed", "overlaps_sealed", "seeds_record",
           "sealed_range_text"]
