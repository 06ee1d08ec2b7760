"""The leaderboard: tracks (a training's seeds, or a controller) compared on one suite run's episodes.

``msdgrasp leaderboard SUITE.json --track NAME=PATTERN ... --baseline NAME --out DIR`` reads a suite result
(``msdgrasp evaluate --suite in_range``: every policy on the same sealed episodes) and groups its policies into tracks
by their spec (``fnmatch`` patterns: ``"default training=logs/train/seed_*/best_model.zip"``). Per track it reports:

* per condition, over the track's runs (seeds) and episodes pooled: the success rate with its Wilson 95 % lower bound
  (:func:`~.stats.wilson_lower_bound`; a track of 5 seeds pools 5 x 76 episodes per condition), the mean force ratio
  (each episode's peak pinch over the reference force at its mu: :mod:`.reference`, the least fixed grip that holds
  95 % of the reference episodes at the pull speed that needs least, so a slower pull cannot lower it), and the mean
  time to lift (s);
* aggregates as Agarwal et al. (2021) compute them (``rliable``'s definitions, :mod:`.stats`): the mean and the
  interquartile mean (IQM) over runs x conditions of the success rate (the IQM trims the worst quarter, where the
  failures sit, so the mean leads) and the IQM of the force ratio, each with a 95 % stratified bootstrap
  interval (runs resampled within each condition, then episodes within each run); the probability of improvement over
  the baseline track on the same episodes (per episode: a failure ranks below every success, successes rank by a
  lower force ratio; ties count one half); the performance profile of the force ratio (the share of episodes that
  succeed at a ratio <= tau).

Outputs (atomically): ``leaderboard.json`` and ``leaderboard.md`` in ``--out``.
"""

from __future__ import annotations

import fnmatch
import json
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..physics.config import ConfigError, atomic_write_text, nan_to_none
from .stats import (
    iqm_of_runs, mean_of_runs, performance_profile_at_most, probability_of_improvement_ci, stratified_bootstrap_ci,
    wilson_lower_bound,
)

#: the force ratios at which the performance profile is read
PROFILE_TAUS = (1.0, 1.1, 1.25, 1.5, 2.0)
#: an episode score below every success's (a failure), for the probability of improvement
_FAILURE_SCORE = -1e6


def parse_track(text: str) -> tuple[str, str]:
    """``"NAME=PATTERN"`` -> (name, pattern); ConfigError on anything else. A pattern may join several with ``|``
    (a track whose runs lie in more than one folder)."""
    name, sep, pattern = str(text).partition("=")
    if not sep or not name.strip() or not pattern.strip():
        raise ConfigError(f"--track {text!r}: expected NAME=PATTERN (a policy spec or a glob of specs, e.g. "
                          "'default training=logs/train/seed_*/best_model.zip')")
    return name.strip(), pattern.strip()


def _episodes(result: dict[str, Any], spec: str, references: dict[str, float | None]) -> list[dict[str, np.ndarray]]:
    """Per condition of ``result``, the policy ``spec``'s episodes: success, force ratio, time to lift (NaN: none)."""
    entry = next(r for r in result["results"] if r["spec"] == spec)
    out = []
    for cell in entry["cells"]:
        success, ratio, lift, pinch = [], [], [], []
        for row in cell["rows"]:
            ref = references.get(f"{row['mu']:g}")
            ep = row["per_episode"]
            success += [bool(v) for v in ep["success"]]
            ratio += [(p / ref) if ref else math.nan for p in ep["peak_pinch_N"]]
            pinch += [float(p) for p in ep["peak_pinch_N"]]
            lift += [math.nan if t is None else float(t) for t in ep["time_to_lift_s"]]
        out.append({"success": np.array(success), "ratio": np.array(ratio, dtype=float),
                    "lift": np.array(lift, dtype=float), "pinch": np.array(pinch, dtype=float)})
    return out


def _score(ep: dict[str, np.ndarray]) -> np.ndarray:
    """Per episode, higher is better: minus the force ratio where the episode succeeded, a failure below all."""
    return np.where(ep["success"] & np.isfinite(ep["ratio"]), -np.nan_to_num(ep["ratio"], nan=0.0), _FAILURE_SCORE)


def _mean(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if len(x) else math.nan


def reference_forces(result: dict[str, Any]) -> dict[str, float | None]:
    """The reference force (N) at each mu of a suite result's episodes, from the reference table of its task
    (:func:`.reference.references_at`; a one-line ConfigError where the task has none); None at a mu off its grid."""
    from ..envs.core import GraspLiftConfig
    from ..physics.config import from_dict
    from .reference import references_at

    config = from_dict(GraspLiftConfig, result["config"], where="suite result config")
    mus = sorted({float(row["mu"]) for r in result["results"] for cell in r["cells"] for row in cell["rows"]})
    forces, what = references_at(config, mus)
    if what["kind"] != "reference":
        raise ConfigError(f"no reference forces for the suite result's task: {what['why']}")
    return forces


#: task fields a training chooses for itself, not the episodes: its reward and what its critic or its frame stack reads
_TRAINING_FIELDS = ("reward", "privileged_obs", "privileged_nodes", "privileged_perturbations", "obs_history")


def _task_of(result: dict[str, Any]) -> dict[str, Any]:
    """What of a suite result's task makes its episodes and its actor's sensing: its config less _TRAINING_FIELDS."""
    return {k: v for k, v in (result.get("config") or {}).items() if k not in _TRAINING_FIELDS}


def merge_results(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One suite result of several run on the same episodes (the same suite, version, seeds and task); a policy in
    several keeps its first run. Where the results ran different conditions of the suite (``--condition``), the merge
    keeps the conditions every one of them ran, in the first's order. ConfigError naming what differs."""
    first = results[0]
    for other in results[1:]:
        for key in ("suite", "version", "seeds", "episodes"):
            if other.get(key) != first.get(key):
                raise ConfigError(f"the suite results differ in {key!r}: not the same episodes; merge only runs of one "
                                  "suite, version, seeds, episodes and task")
        a, b = _task_of(first), _task_of(other)
        if a != b:
            field = next(k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k))
            raise ConfigError(f"the suite results' tasks differ in {field!r}: not the same episodes; merge only runs "
                              "of one task (policies trained on it may differ in their reward and critic's inputs)")
    common = [c["name"] for c in first["conditions"]
              if all(c["name"] in {o["name"] for o in other["conditions"]} for other in results[1:])]
    if not common:
        raise ConfigError("the suite results share no condition: nothing to compare")
    merged, seen = [], set()
    for res in results:
        names = [c["name"] for c in res["conditions"]]
        for r in res["results"]:
            if r["spec"] not in seen:
                seen.add(r["spec"])
                merged.append({**r, "cells": [r["cells"][names.index(n)] for n in common]})
    conditions = [next(c for c in first["conditions"] if c["name"] == n) for n in common]
    return {**first, "conditions": conditions, "results": merged,
            "protocol": all(r.get("protocol") for r in results)}


def build_leaderboard(result: dict[str, Any], tracks: Sequence[tuple[str, str]], baseline: str | None = None,
                      references: dict[str, float | None] | None = None,
                      against: str | None = None) -> dict[str, Any]:
    """The leaderboard record of suite result ``result`` for ``tracks`` ((name, spec pattern) pairs); ``baseline``:
    the track the probability of improvement compares with (None: no comparison); ``references``: the reference force
    per mu (default: :func:`reference_forces`, from the table of the result's task); ``against``: a track every run of
    the others is compared with per condition (its successes against that track's pooled success rate, its mean peak
    pinch over that track's: the question "does each seed hold as much as X, with less force?")."""
    if references is None:
        references = reference_forces(result)
    conditions = [c["name"] for c in result["conditions"]]
    members = _track_members([r["spec"] for r in result["results"]], tracks, baseline, against)
    runs = {name: [_episodes(result, s, references) for s in hits] for name, hits in members.items()}
    rows = []
    for name, per_run in runs.items():
        row = _track_row(name, members[name], per_run, conditions)
        if baseline is not None and name != baseline:
            p, lo, hi = probability_of_improvement_ci(*(
                [np.concatenate([_score(r[c]) for r in side]) for c in range(len(conditions))]
                for side in (per_run, runs[baseline])))
            row["p_improvement"] = {"over": baseline, "value": float(p), "ci95": [float(lo), float(hi)]}
        rows.append(row)
    if against is not None:
        _compare_runs_against(rows, against, runs[against], len(conditions))
    return {"suite": result["suite"], "version": result["version"], "protocol": result.get("protocol"),
            "seeds": result.get("seeds"), "conditions": conditions, "baseline": baseline, "against": against,
            "reference_force_N": references, "task_from": result.get("task_from"), "tracks": rows}


def _track_members(specs: Sequence[str], tracks: Sequence[tuple[str, str]], baseline: str | None,
                   against: str | None) -> dict[str, list[str]]:
    """Each track's policies (its pattern's alternatives joined by ``|``, fnmatch); every track matches one at least,
    and the baseline and the against track are tracks."""
    members: dict[str, list[str]] = {}
    for name, pattern in tracks:
        hits = [s for s in specs if any(fnmatch.fnmatchcase(s, p) for p in pattern.split("|"))]
        if not hits:
            raise ConfigError(f"track {name!r}: pattern {pattern!r} matches no policy of the suite result; its "
                              f"policies: {', '.join(specs)}")
        members[name] = hits
    for flag, name in (("--baseline", baseline), ("--against", against)):
        if name is not None and name not in members:
            raise ConfigError(f"{flag} {name!r} is no track; tracks: {', '.join(members)}")
    return members


def _condition_cell(per_run: list, c: int, condition: str) -> dict[str, Any]:
    """A track's pooled cell of one condition: successes, Wilson bound, worst run, force ratio, time to lift."""
    success = np.concatenate([r[c]["success"] for r in per_run])
    k, n = int(success.sum()), int(len(success))
    return {"condition": condition, "successes": k, "episodes": n, "success_rate": k / n,
            "success_lower_bound": wilson_lower_bound(k, n),
            "worst_run_success_rate": min(float(r[c]["success"].mean()) for r in per_run),
            "force_ratio": _mean(np.concatenate([r[c]["ratio"] for r in per_run])),
            "time_to_lift_s": _mean(np.concatenate([r[c]["lift"] for r in per_run]))}


def _track_row(name: str, policies: list[str], per_run: list, conditions: list[str]) -> dict[str, Any]:
    """A track's row: its cells, its runs' cells, rliable's aggregates (tasks = conditions, runs = the track's
    seeds, episodes within each run) and its performance profile."""
    n = len(conditions)
    cells = [_condition_cell(per_run, c, cond) for c, cond in enumerate(conditions)]
    succ = [np.stack([r[c]["success"].astype(float) for r in per_run]) for c in range(n)]
    ratio_tasks = [np.stack([np.nan_to_num(r[c]["ratio"], nan=0.0) for r in per_run]) for c in range(n)]
    s_point, s_lo, s_hi = stratified_bootstrap_ci(succ, iqm_of_runs)
    # (the IQM trims the worst quarter of runs x conditions, where a success rate's failures sit: the mean beside)
    m_point, m_lo, m_hi = stratified_bootstrap_ci(succ, mean_of_runs)
    f_point, f_lo, f_hi = stratified_bootstrap_ci(ratio_tasks, iqm_of_runs)
    ratios = np.concatenate([np.where(r[c]["success"], r[c]["ratio"], np.inf) for r in per_run for c in range(n)])
    profile = performance_profile_at_most(np.where(np.isfinite(ratios), ratios, 1e9), PROFILE_TAUS)
    per_policy = [{"policy": spec, "cells": [{"successes": int(r[c]["success"].sum()),
                                               "episodes": int(len(r[c]["success"])),
                                               "mean_peak_pinch_N": _mean(r[c]["pinch"]),
                                               "force_ratio": _mean(r[c]["ratio"])} for c in range(n)]}
                  for spec, r in zip(policies, per_run)]
    return {"track": name, "policies": policies, "runs": len(per_run), "cells": cells, "per_run": per_policy,
            "success_iqm": float(s_point), "success_iqm_ci95": [float(s_lo), float(s_hi)],
            "success_mean": float(m_point), "success_mean_ci95": [float(m_lo), float(m_hi)],
            "force_ratio_iqm": float(f_point), "force_ratio_iqm_ci95": [float(f_lo), float(f_hi)],
            "lowest_lower_bound": min(c["success_lower_bound"] for c in cells),
            "time_to_lift_s": _mean(np.array([c["time_to_lift_s"] for c in cells])),
            "profile": {f"{t:g}": float(v) for t, v in zip(PROFILE_TAUS, profile)}}


def _compare_runs_against(rows: list[dict], against: str, ref: list, n: int) -> None:
    """Marks every run of the other tracks per condition: does it hold as many as the ``against`` track's pooled
    success rate, and its mean peak pinch over that track's."""
    rate = [float(np.mean(np.concatenate([r[c]["success"] for r in ref]))) for c in range(n)]
    pinch = [_mean(np.concatenate([r[c]["pinch"] for r in ref])) for c in range(n)]
    for row in rows:
        if row["track"] == against:
            continue
        for run in row["per_run"]:
            run["against"] = [{"holds_as_many": x["successes"] >= rate[c] * x["episodes"] - 1e-9,
                               "pinch_over_against": x["mean_peak_pinch_N"] / pinch[c] if pinch[c] else math.nan}
                              for c, x in enumerate(run["cells"])]


def _n(x: float | None, fmt: str) -> str:
    return "-" if x is None or not math.isfinite(x) else format(x, fmt)


def leaderboard_markdown(board: dict[str, Any]) -> str:
    """The leaderboard record as markdown: the aggregate table, then success / lower bound / force ratio / time to
    lift per condition and track."""
    seeds = board.get("seeds") or {}
    lines = [f"# Leaderboard: suite `{board['suite']}` v{board['version']}", ""]
    if not board.get("protocol") or not seeds.get("sealed"):
        why = ("not the protocol's episodes; " if not board.get("protocol") else "") + (
            "seeds not sealed." if not seeds.get("sealed") else "")
        lines += ["**Not a certified result**: " + why, ""]
    lines += [f"{len(board['conditions'])} conditions; episodes from seed {seeds.get('first')} "
              f"({'sealed' if seeds.get('sealed') else 'not sealed'}). Force ratio: peak pinch over the reference "
              "force at the episode's mu (the least fixed grip that holds 95 % of the reference episodes at the pull "
              "speed that needs least). IQM over runs x conditions with 95 % stratified bootstrap intervals (runs, "
              "then episodes); P(improvement): over the baseline on the same episodes, a failure ranking below every "
              "success; profile: the share of episodes that succeed at a force ratio <= tau.", "",
              "| track | runs | success mean [95% CI] | success IQM | lowest lower bound | force ratio IQM [95% CI] | "
              f"time to lift | P(improvement) over {board.get('baseline') or '-'} | profile " +
              " / ".join(f"<={t:g}" for t in PROFILE_TAUS) + " |",
              "|---|---|---|---|---|---|---|---|---|"]
    for t in board["tracks"]:
        pi = t.get("p_improvement")
        lines.append(
            f"| {t['track']} | {t['runs']} | {t['success_mean']:.3f} [{t['success_mean_ci95'][0]:.3f}, "
            f"{t['success_mean_ci95'][1]:.3f}] | {t['success_iqm']:.3f} | {t['lowest_lower_bound']:.3f} | "
            f"{_n(t['force_ratio_iqm'], '.2f')} "
            f"[{_n(t['force_ratio_iqm_ci95'][0], '.2f')}, {_n(t['force_ratio_iqm_ci95'][1], '.2f')}] | "
            f"{_n(t['time_to_lift_s'], '.2f')} s | "
            + (f"{pi['value']:.2f} [{pi['ci95'][0]:.2f}, {pi['ci95'][1]:.2f}]" if pi else "-") + " | "
            + " / ".join(f"{t['profile'][f'{tau:g}']:.2f}" for tau in PROFILE_TAUS) + " |")
    lines += ["", "Per condition: success (pooled episodes) / Wilson 95 % lower bound / force ratio / time to lift (s)",
              "", "| condition | " + " | ".join(t["track"] for t in board["tracks"]) + " |",
              "|---|" + "---|" * len(board["tracks"])]
    for c, cond in enumerate(board["conditions"]):
        cells = []
        for t in board["tracks"]:
            x = t["cells"][c]
            cells.append(f"{x['successes']}/{x['episodes']} / {x['success_lower_bound']:.3f} / "
                         f"{_n(x['force_ratio'], '.2f')} / {_n(x['time_to_lift_s'], '.1f')}")
        lines.append(f"| {cond} | " + " | ".join(cells) + " |")
    lines += _per_run_markdown(board)
    return "\n".join(lines) + "\n"


def _per_run_markdown(board: dict[str, Any]) -> list[str]:
    """Per run (seed) and condition: successes and mean peak pinch; with ``against``, that pinch over the against
    track's and a mark where the run holds fewer episodes than the against track's success rate."""
    against = board.get("against")
    head = "successes / mean peak pinch (N)" + (f" / over {against}'s (! holds fewer than {against})" if against
                                                 else "")
    lines = ["", f"Per run: {head}", "", "| track | run | " + " | ".join(board["conditions"]) + " |",
             "|---|---|" + "---|" * len(board["conditions"])]
    for t in board["tracks"]:
        for run in t.get("per_run", []):
            cells = []
            for c, x in enumerate(run["cells"]):
                text = f"{x['successes']}/{x['episodes']} / {_n(x['mean_peak_pinch_N'], '.2f')}"
                if "against" in run:
                    a = run["against"][c]
                    text += f" / {_n(a['pinch_over_against'], '.2f')}x" + ("" if a["holds_as_many"] else " !")
                cells.append(text)
            lines.append(f"| {t['track']} | {run['policy']} | " + " | ".join(cells) + " |")
    return lines


def read_result(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(f"suite result {path} is not a file (msdgrasp evaluate --suite in_range writes one)")
    try:
        result = json.loads(path.read_text())
    except ValueError as exc:
        raise ConfigError(f"{path}: not a suite result (not JSON: {exc})") from None
    if not isinstance(result, dict) or "results" not in result or "conditions" not in result:
        raise ConfigError(f"{path}: not a suite result (no results / conditions)")
    conditions, results = result["conditions"], result["results"]
    if not (isinstance(conditions, list) and isinstance(results, list) and all(
            isinstance(r, dict) and "spec" in r and isinstance(r.get("cells"), list)
            and len(r["cells"]) == len(conditions) for r in results)):
        raise ConfigError(f"{path}: not a suite result (each of its results needs a spec and one cell per condition)")
    return result


def write_leaderboard(suite_json: str | Path | Sequence[str | Path], tracks: Sequence[str], baseline: str | None,
                      out_dir: str | Path, references: dict[str, float | None] | None = None,
                      against: str | None = None) -> dict[str, Any]:
    """Read suite results (one, or several on the same episodes: :func:`merge_results`), build their leaderboard for
    the ``NAME=PATTERN`` tracks, write leaderboard.json/.md."""
    paths = [suite_json] if isinstance(suite_json, (str, Path)) else list(suite_json)
    result = merge_results([read_result(Path(p)) for p in paths])
    parsed = [parse_track(t) for t in tracks]
    names = [name for name, _ in parsed]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"--track {twice!r} is given twice; name each track once (join patterns with |)")
    board = build_leaderboard(result, parsed, baseline, references, against)
    out = Path(out_dir)
    atomic_write_text(out / "leaderboard.json", json.dumps(nan_to_none(board), indent=2) + "\n")
    atomic_write_text(out / "leaderboard.md", leaderboard_markdown(board))
    return board
