"""What choosing a policy per mu could do on a suite's episodes: the told-mu frontier (``msdgrasp frontier``).

A family of policies run on the same episodes (a suite result: fixed grips, or the estimating controller told mu at
several margins) bounds what a policy that knows the episode's friction could reach by picking one member per mu:

* **per member**, in every condition: its successes less the reference policy's (``against``) and its mean peak pinch
  over the reference's (the acceptance's force measure);
* **the best schedule** (one member per mu, the same in every condition, as a policy told mu would act): the one
  whose mean peak pinch is at most ``cap`` x the reference's in every condition and whose successes trail the
  reference's least in its worst condition (then the most successes in all, then the least force), found by trying
  every schedule; beside it the best schedule with no force cap;
* **per-episode hindsight**: the episodes some member holds, per condition, and the Wilson lower bound of each count.

Every pick is made on the episodes it is scored on, so each number is an upper bound on what that knowledge gives
(for development episodes only: the command refuses a result on sealed evaluation seeds). Reasons and the measured
frontiers: docs/design.md, "Learned control with memory".
"""

from __future__ import annotations

import fnmatch
import itertools
import math
from typing import Any, Sequence

import numpy as np

from ..physics.config import ConfigError
from .stats import wilson_lower_bound

#: the acceptance's force cap: mean peak pinch at most this multiple of the reference policy's in every condition
DEFAULT_CAP = 0.95
#: relative slack of the cap test, so that a schedule at the cap is not dropped by rounding
CAP_RTOL = 1e-9
#: schedules tried at most (members ** mu values): an exhaustive search held in memory, so the family is kept small
MAX_SCHEDULES = 500_000


def _table(result: dict[str, Any], spec: str) -> tuple[list[float], np.ndarray, np.ndarray]:
    """A policy's episodes: its mu grid, and success and peak pinch (N) shaped (condition, mu, episode)."""
    try:
        entry = next(r for r in result["results"] if r["spec"] == spec)
        mus = [float(row["mu"]) for row in entry["cells"][0]["rows"]]
        success, pinch = [], []
        for cell in entry["cells"]:
            if [float(row["mu"]) for row in cell["rows"]] != mus:
                raise ConfigError(f"{spec}: its conditions differ in their mu grid; the frontier needs one (an "
                                  "in_range suite's)")
            success.append([row["per_episode"]["success"] for row in cell["rows"]])
            pinch.append([row["per_episode"]["peak_pinch_N"] for row in cell["rows"]])
            if any(len(a) != len(b) for a, b in zip(success[-1], pinch[-1])):
                raise ConfigError(f"{spec}: its success and peak pinch lists differ in length; a suite result has "
                                  "one entry per episode in each")
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise ConfigError(f"{spec}: not a suite result's policy (cells of rows with mu and per_episode success and "
                          f"peak_pinch_N: {type(exc).__name__} {exc})") from None
    try:
        ok, force = np.array(success, dtype=bool), np.array(pinch, dtype=float)
    except (ValueError, TypeError):
        raise ConfigError(f"{spec}: its mu values ran different numbers of episodes; the frontier needs the same "
                          "episodes per mu") from None
    if ok.ndim != 3 or force.shape != ok.shape:
        raise ConfigError(f"{spec}: not a suite result's policy (its episodes are not one list per condition and mu)")
    if not np.isfinite(force).all():
        raise ConfigError(f"{spec}: a peak pinch that is not a number (null or NaN); the frontier needs every "
                          "episode's")
    return mus, ok, force


def family_specs(result: dict[str, Any], patterns: Sequence[str], against: str) -> list[str]:
    """The specs of ``result`` other than ``against`` that match any glob of ``patterns`` (all of them where none is
    given), in the result's order; ConfigError where none does."""
    specs = [r["spec"] for r in result["results"] if r["spec"] != against]
    family = [s for s in specs if not patterns or any(fnmatch.fnmatchcase(s, p) for p in patterns)]
    if not family:
        raise ConfigError(f"--family {list(patterns)!r} matches none of the result's other policies: {specs}")
    return family


def check_development(result: dict[str, Any]) -> None:
    """ConfigError where a suite result ran on sealed evaluation seeds: picks made on them would tune on them."""
    from .protocol import check_not_sealed

    seeds = result.get("seeds") or {}
    if not isinstance(seeds, dict) or "first" not in seeds or "count" not in seeds:
        raise ConfigError("the suite result names no seeds (msdgrasp evaluate --suite writes them); the frontier "
                          "runs only on development episodes")
    if seeds.get("sealed"):
        raise ConfigError(f"the suite result ran on sealed evaluation seeds (from {seeds['first']}); the frontier "
                          "picks on the episodes it scores, so it runs only on development episodes (--seed below "
                          "the sealed seeds)")
    check_not_sealed(seeds["first"], seeds["count"], "the suite result's seeds")


def mu_frontier(result: dict[str, Any], against: str, family: Sequence[str], cap: float = DEFAULT_CAP
                ) -> dict[str, Any]:
    """The told-mu frontier of ``family`` (policy specs of the suite result ``result``) against the policy ``against``
    (module docstring); ``cap`` > 0 bounds each condition's mean peak pinch over the reference's."""
    specs = [r["spec"] for r in result["results"]]
    if against not in specs:
        raise ConfigError(f"--against {against!r} is not a policy of the suite result; it has: {specs}")
    missing = [s for s in family if s not in specs or s == against]
    if missing or not family:
        raise ConfigError(f"the family must be policies of the suite result other than the reference, got "
                          f"{list(family)!r}; it has {specs}")
    check_development(result)
    if not (math.isfinite(cap) and cap > 0):
        raise ConfigError(f"--cap must be a finite multiple > 0 of the reference's mean peak pinch, got {cap!r}")
    mus, ref_ok, ref_pinch = _table(result, against)
    tables = [_table(result, s) for s in family]
    for spec, (m, ok, _) in zip(family, tables):
        if m != mus or ok.shape != ref_ok.shape:
            raise ConfigError(f"{spec} ran other episodes than {against} (mu grid {m} against {mus}, shape "
                              f"{ok.shape} against {ref_ok.shape}); the frontier needs the same episodes")
    n_schedules = len(family) ** len(mus)
    if n_schedules > MAX_SCHEDULES:
        raise ConfigError(f"{len(family)} members over {len(mus)} mu values make {n_schedules} schedules, more than "
                          f"the {MAX_SCHEDULES} tried; narrow --family")
    conditions = [c["name"] for c in result["conditions"]]
    ok = np.stack([t[1] for t in tables])  # (member, condition, mu, episode)
    pinch = np.stack([t[2] for t in tables])
    held = ok.sum(axis=3)  # (member, condition, mu)
    pinch_sum = pinch.sum(axis=3)
    episodes = ref_ok.shape[1] * ref_ok.shape[2]  # per condition
    ref_held = ref_ok.sum(axis=(1, 2))  # (condition,)
    ref_force = ref_pinch.sum(axis=2).sum(axis=1) / episodes  # (summed as the members are: a copy is 1.0x)
    if not (ref_force > 0).all():
        raise ConfigError(f"{against}: a condition with no pinch at all; the force ratio needs a reference that grips")

    members = []
    for f, spec in enumerate(family):
        force = pinch_sum[f].sum(axis=1) / episodes
        members.append({"spec": spec, "held": held[f].sum(axis=1).tolist(),
                        "held_less_reference": (held[f].sum(axis=1) - ref_held).tolist(),
                        "force_ratio": (force / ref_force).tolist(), "held_per_mu": held[f].tolist()})

    # every schedule (one member per mu) at once: (schedule, condition)
    combos = np.array(list(itertools.product(range(len(family)), repeat=len(mus))), dtype=np.int64)
    cols = np.arange(len(mus))
    s_held = held[combos, :, cols].sum(axis=1)  # (schedule, condition)
    s_force = pinch_sum[combos, :, cols].sum(axis=1) / episodes / ref_force
    worst_gap = (s_held - ref_held).min(axis=1)
    worst_force = s_force.max(axis=1)
    within = worst_force <= cap * (1 + CAP_RTOL)
    total = s_held.sum(axis=1)

    def best(mask: np.ndarray) -> dict[str, Any] | None:
        idx = np.flatnonzero(mask)
        if not len(idx):
            return None
        k = idx[np.lexsort((worst_force[idx], -total[idx], -worst_gap[idx]))[0]]
        return {"members": {f"{mu:g}": family[c] for mu, c in zip(mus, combos[k])},
                "held": s_held[k].tolist(), "held_less_reference": (s_held[k] - ref_held).tolist(),
                "force_ratio": s_force[k].tolist(), "worst_held_less_reference": int(worst_gap[k]),
                "worst_force_ratio": float(worst_force[k]),
                "lower_bound": [wilson_lower_bound(int(h), episodes) for h in s_held[k]]}

    any_held = ok.any(axis=0).sum(axis=(1, 2))  # (condition,)
    return {
        "against": against, "family": list(family), "cap": cap, "conditions": conditions, "mu": mus,
        "episodes_per_condition": episodes,
        "reference": {"held": ref_held.tolist(), "mean_peak_pinch_N": ref_force.tolist(),
                      "lower_bound": [wilson_lower_bound(int(h), episodes) for h in ref_held]},
        "members": members,
        "best_within_cap": best(within),
        "best_uncapped": best(np.ones(len(combos), dtype=bool)),
        "hindsight": {"held": any_held.tolist(),
                      "lower_bound": [wilson_lower_bound(int(h), episodes) for h in any_held]},
    }


def frontier_verdict(record: dict[str, Any]) -> str:
    """One line: whether some schedule within the cap holds the reference's grasps in every condition."""
    best, cap = record["best_within_cap"], record["cap"]
    if best is None:
        return f"No schedule of the family stays within {cap:g}x the reference's mean peak pinch in every condition."
    gaps = best["held_less_reference"]
    force = f"{min(best['force_ratio']):.2f}-{max(best['force_ratio']):.2f}x"
    short = [(c, g) for c, g in zip(record["conditions"], gaps) if g < 0]
    if not short:
        return (f"Within {cap:g}x, one member per mu holds at least the reference's grasps in every condition, at "
                f"{force} its mean peak pinch.")
    worst = min(short, key=lambda cg: cg[1])
    return (f"Within {cap:g}x, the best schedule holds fewer grasps than the reference in {len(short)} of "
            f"{len(gaps)} conditions ({-worst[1]} fewer {worst[0]}), at {force} its mean peak pinch.")


def frontier_markdown(record: dict[str, Any]) -> str:
    """The frontier as markdown: per condition the reference, each member, the best schedules and hindsight."""
    conds, n = record["conditions"], record["episodes_per_condition"]
    ref = record["reference"]
    lines = [f"Told-mu frontier against `{record['against']}` ({n} episodes per condition; every pick made on the "
             "episodes it is scored on: an upper bound)", "", frontier_verdict(record), "",
             "| policy | " + " | ".join(conds) + " |", "|---|" + "---|" * len(conds),
             "| reference: held (Wilson lower bound), mean peak pinch | " + " | ".join(
                 f"{h} ({lb:.2f}), {f:.2f} N" for h, lb, f in zip(ref["held"], ref["lower_bound"],
                                                                   ref["mean_peak_pinch_N"])) + " |"]
    for m in record["members"]:
        lines.append(f"| `{m['spec']}` | " + " | ".join(
            f"{d:+d}, {r:.2f}x" for d, r in zip(m["held_less_reference"], m["force_ratio"])) + " |")
    for key, label in (("best_within_cap", f"best schedule at <= {record['cap']:g}x"),
                       ("best_uncapped", "best schedule, no cap")):
        b = record[key]
        if b is None:
            lines.append(f"| {label} | " + " | ".join("none" for _ in conds) + " |")
            continue
        lines.append(f"| {label} | " + " | ".join(
            f"{d:+d}, {r:.2f}x (lb {lb:.2f})" for d, r, lb in zip(b["held_less_reference"], b["force_ratio"],
                                                                   b["lower_bound"])) + " |")
    hs = record["hindsight"]
    lines.append("| per-episode hindsight: held (lb) | " + " | ".join(
        f"{h} ({lb:.2f})" for h, lb in zip(hs["held"], hs["lower_bound"])) + " |")
    lines += ["", "Cells: successes less the reference's, mean peak pinch over the reference's. Schedules (one "
              "member per mu):"]
    for key in ("best_within_cap", "best_uncapped"):
        if record[key] is not None:
            lines.append(f"* {key}: " + ", ".join(f"mu {mu}: `{s}`" for mu, s in record[key]["members"].items()))
    return "\n".join(lines) + "\n"
