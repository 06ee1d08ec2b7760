"""The reference force of the benchmark's force ratios: a grip that no pull speed can undercut.

A force ratio divides a policy's mean peak pinch by a reference force at the episode's friction mu. A grasp needs
less grip the slower it pulls (the tissue's viscous drag on the jaws falls with the speed), so a reference taken at
one pull speed rewards any policy that pulls slower than it, and the ratios of policies pulling at different speeds
cannot be compared. The reference here takes the pull speed out:

    R(mu) = min over the pull fractions p of :data:`DEFAULT_PULLS` of Q_p(mu),
    Q_p(mu) = the least fixed pinch force (to ``tolerance_N``) with which the fixed-force controller
              (:class:`.controllers.FixedForcePolicy` at pull p) lifts and holds at least SHARE (95 %) of mu's n
              reference episodes within the time limit (an infinite force where no grip up to the motor's limit does).

Q_p is found by a scan up in steps of x 1.2 from 0.28 N / mu (Coulomb: the least grip times mu is 0.30-0.45 N over the
task's frictions) to the first grip that holds, then bisection, every probe running all n reference episodes at once
(about nine probes of n episodes, where a search per episode costs four times as many). A scan, not a bisection over
the whole range: at a slow pull a heavy grip closes for longer and runs out of time, so the count held falls again
above the least grip that holds. The episodes run on their own draws (stiffness, mass, grasp pose, sensing), not on
the nominal tissue. A pull fraction p is p times the arm's top speed (20 mm/s on the benchmark task: p = 0.5 is 10
mm/s). Pulling slowly is thus part of what the reference optimises, as a policy may: no policy that holds SHARE of the
episodes can reach a lower peak pinch by choosing another pull speed of the grid (tested in tests/test_reference.py).
A pull of 0.2 cannot lift the 30 mm target and hold it 1 s within the 10 s limit in 95 % of the episodes (the lift
itself takes about 1.5 s + 1.5 s / p), so the grid starts at 0.22, and the reference sits at the slowest pull that
can.

The reference episodes are their own: episode i (at every mu and pull) is reset with seed ``seed + i`` from
:data:`REFERENCE_SEED`, inside :data:`REFERENCE_SEEDS`, apart from the seeds evaluations and trainings use; mu is
pinned, everything else drawn as the task's randomisation draws it.

``msdgrasp reference --out FILE`` computes the table (a job per mu and pull, in parallel processes) and writes it as
JSON with the task's fingerprint (:func:`task_fingerprint`: the physics, actions and time limits of the task, not its
observation, sensing or reward). :func:`reference_force_N` and :func:`force_score` read it and refuse, with a one-line
:class:`~..physics.config.ConfigError`, a task whose fingerprint differs or a mu outside the table's grid. Between grid
points R is interpolated so that R x mu is linear in mu: Coulomb friction makes the minimal force nearly proportional to
1 / mu (R x mu varies by a few percent over the grid), so this interpolates the part that is nearly constant.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.core import GraspLiftConfig
from ..physics.config import CONFIG_DIR, ConfigError, atomic_write_text, from_dict, nan_to_none, to_dict
from .parallel import run_jobs

#: the file layout written here
FORMAT = "msdgrasp-reference-force-1"
#: the reference episodes' seeds, half-open: apart from the small seeds that trainings, validations, fits and the
#: evaluations' defaults use, and from the sealed evaluation seeds from 1_000_000_000
REFERENCE_SEEDS = range(3_000_000, 4_000_000)
#: episode i of the reference is reset with REFERENCE_SEED + i
REFERENCE_SEED = REFERENCE_SEEDS.start
#: the friction grid of the shipped table
DEFAULT_MUS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
#: the pull fractions (of the arm's top speed) searched: 0.22, the slowest that can lift 30 mm and hold it 1 s within
#: the 10 s limit in 95 % of the episodes (0.2 cannot: measured at mu 0.2 and 0.3, where no grip up to the scan's end
#: held 38 of the 40 reference episodes, and the lift alone takes about 1.5 s + 1.5 s / pull at any mu), and 0.25 and
#: 0.3 (the default controller's), slower than the oracle's 0.5, where every measured grip was larger
DEFAULT_PULLS = (0.22, 0.25, 0.3)
#: reference episodes per mu (the same episodes at every pull): 40, of which the reference grip may drop 2
DEFAULT_EPISODES = 40
#: the share of a mu's reference episodes the reference grip holds
SHARE = 0.95
#: the bisection's tolerance, N: a quarter or less of the differences it judges (the 95 % quantiles of neighbouring
#: pulls differ by 0.03-0.1 N at mu 0.5; the episodes' minimal forces at one pull spread over about 0.06 N)
TOLERANCE_N = 0.01
#: where the search starts, N x mu (Coulomb: the least grip times mu lies in 0.30-0.45 N over the task's frictions), and
#: its scan's step (a factor)
SCAN_FROM_N_MU = 0.28
SCAN_STEP = 1.2

#: GraspLiftConfig fields that change what an agent observes or how it is paid, not what grip a grasp needs: left out
#: of the fingerprint (the benchmark task's versions that differ only in them share one reference)
OBSERVATION_FIELDS = frozenset({"obs_history", "privileged_obs", "privileged_nodes", "privileged_perturbations",
                                "sensed_task_state", "reference_force_N", "reward"})
#: RandomizationConfig fields of the sensing: they change the readings, not the tissue, the grasper or the commands
#: (the fixed-force controller reads the pinch only to start its pull once the grip is nearly there)
SENSING_FIELDS = frozenset({"sensor_noise_N", "sensor_noise_low_N", "force_noise", "force_filter_s", "force_bias_N",
                            "slip_sensing", "slip_noise", "lift_sensing", "lift_noise_m", "lift_delay_steps"})


# ------------------------------------------------------------------------------------------------
# the task's fingerprint
# ------------------------------------------------------------------------------------------------


def task_fingerprint(config: GraspLiftConfig) -> dict[str, Any]:
    """What of ``config`` the reference forces depend on: its ``to_dict`` without the observation, reward
    (:data:`OBSERVATION_FIELDS`) and sensing (:data:`SENSING_FIELDS`) fields: the scene and its physics, the action
    interface, the time limits and success rule, and the tissue, pose and actuation randomisation."""
    data = {k: v for k, v in to_dict(config).items() if k not in OBSERVATION_FIELDS}
    data["randomization"] = {k: v for k, v in data["randomization"].items() if k not in SENSING_FIELDS}
    return data


def fingerprint_digest(fingerprint: dict[str, Any]) -> str:
    """SHA-256 (hex, first 16 digits) of a fingerprint's canonical JSON."""
    text = json.dumps(fingerprint, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _first_difference(theirs: dict[str, Any], ours: dict[str, Any], where: str = "") -> str:
    """The first field (dotted) whose value differs between two fingerprints, with both values."""
    for key in sorted(set(theirs) | set(ours)):
        name = f"{where}{key}"
        if key not in theirs:
            return f"field {name} is not in the table's task (computed before it existed); here {ours[key]!r}"
        if key not in ours:
            return f"field {name} is {theirs[key]!r} in the table's task and not in this one"
        a, b = theirs[key], ours[key]
        if isinstance(a, dict) and isinstance(b, dict):
            if a != b:
                return _first_difference(a, b, name + ".")
        elif a != b:
            return f"field {name} is {a!r} there, {b!r} here"
    return "no field differs"


# ------------------------------------------------------------------------------------------------
# computing the table
# ------------------------------------------------------------------------------------------------


def hold_quantile(forces: Sequence[float | None], share: float = SHARE) -> float:
    """The least fixed force that holds at least ``share`` of the episodes whose own minimal fixed forces are
    ``forces`` (None or NaN: no force holds that episode): their ceil(share x n)-th smallest; ``inf`` where fewer than
    that many episodes are held by any force."""
    if not len(forces) or not 0.0 < share <= 1.0:
        raise ValueError(f"need episodes and a share in (0, 1], got {len(forces)} episodes and share {share!r}")
    ordered = sorted(math.inf if f is None or not math.isfinite(f) else float(f) for f in forces)
    return ordered[math.ceil(share * len(ordered) - 1e-9) - 1]


def held_needed(episodes: int, share: float = SHARE) -> int:
    """How many of ``episodes`` episodes a grip must hold to hold ``share`` of them: ceil(share x episodes)."""
    return math.ceil(share * episodes - 1e-9)


def run_fixed_grips(config: GraspLiftConfig, mu: float, seeds: Sequence[int], forces: Sequence[float] | float,
                    pulls: Sequence[float] | float) -> dict[str, np.ndarray]:
    """Run the fixed-force controller on the episodes reset with ``seeds`` at friction ``mu`` (everything else drawn
    as ``config`` draws it), episode k gripping at ``forces[k]`` N and pulling at ``pulls[k]`` of the arm's top speed,
    all in one batch. Per episode: ``success`` (lifted and held within the time limit), ``peak_pinch_N`` and
    ``time_to_lift_s`` (NaN where the lift target was never reached)."""
    from ..envs.grasp_lift import GraspLiftVectorEnv
    from .controllers import FixedForcePolicy

    n = len(seeds)
    forces = np.broadcast_to(np.asarray(forces, dtype=np.float64), (n,)).copy()
    pulls = np.broadcast_to(np.asarray(pulls, dtype=np.float64), (n,)).copy()
    if not (np.all(forces > 0) and np.all((pulls > 0) & (pulls <= 1))):
        raise ValueError("forces must be > 0 N and pulls in (0, 1]")
    env = GraspLiftVectorEnv(n, config)
    obs, _ = env.reset(seed=[int(s) for s in seeds], options={"mu": [float(mu)] * n})
    policy = FixedForcePolicy(env.config, 1.0, 0.5)
    policy.reset([{}] * n)
    policy.force, policy.pull = forces, pulls
    core = env.core
    done = np.zeros(n, dtype=bool)
    out = {"success": np.zeros(n, dtype=bool), "peak_pinch_N": np.zeros(n), "time_to_lift_s": np.full(n, np.nan)}
    for _ in range(env.config.max_episode_steps):
        # (ended episodes' tissues stand still, as in the evaluation and the minimal-force search)
        obs, _, term, trunc, info = core.step(policy.act(obs), advance=np.flatnonzero(~done))
        ended = ~done & (term | trunc)
        out["success"][ended] = info["is_success"][ended]
        out["peak_pinch_N"][ended] = core.peak_pinch[ended]
        out["time_to_lift_s"][ended] = core.time_to_lift[ended]
        done |= ended
        if done.all():
            break
    env.close()
    return out


def search_quantile(config: GraspLiftConfig, mu: float, pull: float, seeds: Sequence[int],
                    tolerance_N: float = TOLERANCE_N) -> dict[str, Any]:
    """Q_p(mu): the least fixed grip (N, to ``tolerance_N``) with which the fixed-force controller at pull ``pull``
    holds at least :func:`held_needed` of the episodes reset with ``seeds`` at friction ``mu``.

    The count held is not monotone in the grip over the whole range: at a slow pull a heavy grip takes longer to close
    and runs out of time (measured: at mu 0.2 and pull 0.22, 1.5 N holds every episode, 3 N none). So the search scans
    up from :data:`SCAN_FROM_N_MU` / mu in steps of x :data:`SCAN_STEP` (down first where that already holds) to
    the first grip that holds, up to the motor's limit or until a grip holds fewer than the one below it (which held at
    least half the share), then bisects
    between it and the last that did not.
    Returns ``{"quantile_N": Q or None (no grip of the scan holds that share), "probes": [{"force_N", "held"}]}``."""
    need = held_needed(len(seeds))
    cap = float(config.max_pinch_force_N)
    probes: list[dict[str, Any]] = []

    def held(force: float) -> bool:
        k = int(run_fixed_grips(config, mu, seeds, force, pull)["success"].sum())
        probes.append({"force_N": round(float(force), 6), "held": k})
        return k >= need

    def falling() -> bool:  # (the scan's last grip held fewer than the one before, which held at least half what it
        # must: heavier grips run out of time. Below that, a count of 1 then 0 is chance, not the time limit)
        return len(probes) >= 2 and 2 * probes[-2]["held"] >= need and probes[-1]["held"] < probes[-2]["held"]

    hi = min(SCAN_FROM_N_MU / mu, cap)
    if held(hi):  # (the floor holds already: down until a grip does not)
        lo = hi / SCAN_STEP
        while held(lo):
            hi, lo = lo, lo / SCAN_STEP
    else:
        lo = hi
        while True:
            if lo >= cap or falling():
                return {"quantile_N": None, "probes": probes}
            hi = min(lo * SCAN_STEP, cap)
            if held(hi):
                break
            lo = hi
    while hi - lo > tolerance_N:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if held(mid) else (mid, hi)
    return {"quantile_N": float(hi), "probes": probes}


def _search_job(config_dict: dict[str, Any], mu: float, pull: float, first_seed: int, episodes: int,
                tolerance_N: float) -> dict[str, Any]:
    """One (mu, pull) cell: :func:`search_quantile` on the reference episodes."""
    config = from_dict(GraspLiftConfig, config_dict, where="env")
    return search_quantile(config, float(mu), float(pull), [first_seed + i for i in range(episodes)],
                           float(tolerance_N))


def _check_job(config_dict: dict[str, Any], mu: float, pull: float, force_N: float, first_seed: int,
               episodes: int) -> dict[str, Any]:
    """The reference grip run on the reference episodes at its pull: what it holds, its peak pinch, its lift time."""
    config = from_dict(GraspLiftConfig, config_dict, where="env")
    ep = run_fixed_grips(config, mu, [first_seed + i for i in range(episodes)], force_N, pull)
    lifted = np.isfinite(ep["time_to_lift_s"])
    return {"held": int(ep["success"].sum()), "success_rate": float(ep["success"].mean()),
            "mean_peak_pinch_N": float(ep["peak_pinch_N"].mean()),
            "score": float(ep["peak_pinch_N"].mean() / force_N),
            "mean_time_to_lift_s": float(ep["time_to_lift_s"][lifted].mean()) if lifted.any() else None,
            "max_time_to_lift_s": float(ep["time_to_lift_s"][lifted].max()) if lifted.any() else None}


def _check_seeds(seed: int, episodes: int) -> None:
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ConfigError(f"episodes must be an integer >= 1, got {episodes!r}")
    last = REFERENCE_SEEDS.stop - episodes
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not REFERENCE_SEEDS.start <= seed <= last:
        raise ConfigError(f"seed = {seed!r}: the reference episodes' seeds must lie in the reference seeds "
                          f"[{REFERENCE_SEEDS.start}, {REFERENCE_SEEDS.stop}); allowed {REFERENCE_SEEDS.start}..{last} "
                          f"for {episodes} episodes")


def _check_grid(mus: Sequence[float], pulls: Sequence[float], tolerance_N: float) -> tuple[list[float], list[float]]:
    mus = sorted({round(float(m), 10) for m in mus})
    pulls = sorted({round(float(p), 10) for p in pulls})
    if not mus:
        raise ConfigError("the mu grid is empty")
    for m in mus:
        if not (math.isfinite(m) and 0.0 < m <= 10.0):
            raise ConfigError(f"mu = {m!r} is out of range; allowed (0, 10]")
    if not pulls:
        raise ConfigError("the pull grid is empty")
    for p in pulls:
        if not (math.isfinite(p) and 0.0 < p <= 1.0):
            raise ConfigError(f"pull = {p!r} is out of range; allowed (0, 1] (a fraction of the arm's top speed)")
    if isinstance(tolerance_N, bool) or not isinstance(tolerance_N, (int, float)) or not 0.0 < tolerance_N <= 0.1:
        raise ConfigError(f"tolerance_N = {tolerance_N!r} is out of range; allowed (0, 0.1] N")
    return mus, pulls


def _journal_key(digest: str, mu: float, pull: float, seed: int, episodes: int, tolerance_N: float) -> str:
    return json.dumps([digest, round(mu, 10), round(pull, 10), int(seed), int(episodes), float(tolerance_N)])


def _read_journal(path: Path | None) -> dict[str, dict[str, Any]]:
    """The (mu, pull) cells a journal holds, by key; a line that cannot be read (a run killed while writing it) is
    skipped and its cell searched again."""
    cells: dict[str, dict[str, Any]] = {}
    if path is None or not path.is_file():
        return cells
    for line in path.read_text().splitlines():
        try:
            entry = json.loads(line)
            cells[entry["key"]] = {"quantile_N": entry["quantile_N"], "probes": list(entry["probes"])}
        except (ValueError, KeyError, TypeError):
            continue
    return cells


def compute_reference(config: GraspLiftConfig, mus: Sequence[float] = DEFAULT_MUS,
                      pulls: Sequence[float] = DEFAULT_PULLS, episodes: int = DEFAULT_EPISODES,
                      seed: int = REFERENCE_SEED, tolerance_N: float = TOLERANCE_N, runner=None,
                      progress: bool = True, journal: str | Path | None = None) -> dict[str, Any]:
    """The reference table of ``config`` (see the module docstring) as the JSON record :func:`write_reference` writes.

    Every (mu, pull) search is a job (``runner``: :class:`.parallel.Runner`, local processes or Ray; None: in this
    process, one after the other); then, per mu, the reference grip is run once more on the reference episodes at its
    pull (its held share, peak pinch over R and time to lift are recorded beside it). ``journal``: a file (JSON lines)
    each finished search is appended to, and whose searches of the same task, mu, pull, episodes, seed and tolerance
    are taken instead of run again: a run that was stopped goes on where it stopped."""
    if config.jaw_action != "force":
        raise ConfigError(f"jaw_action = {config.jaw_action!r}: the reference grip is a pinch-force set-point; "
                          "allowed: force")
    if config.pull_action != "forward_speed":
        raise ConfigError(f"pull_action = {config.pull_action!r}: the reference is searched over pull speeds; "
                          "allowed: forward_speed")
    mus, pulls = _check_grid(mus, pulls, tolerance_N)
    _check_seeds(seed, episodes)
    cfg = to_dict(config)
    digest = fingerprint_digest(task_fingerprint(config))
    journal = Path(journal) if journal is not None else None
    done = _read_journal(journal)
    t0 = time.perf_counter()
    cells: dict[tuple[float, float], dict[str, Any]] = {}
    for m in mus:
        for p in pulls:
            key = _journal_key(digest, m, p, seed, episodes, tolerance_N)
            if key in done:
                cells[(m, p)] = done[key]
    where = [(m, p) for m in mus for p in pulls if (m, p) not in cells]
    jobs = [(_search_job, (cfg, m, p, int(seed), int(episodes), float(tolerance_N))) for m, p in where]
    if progress and cells:
        print(f"  {len(cells)} of {len(cells) + len(where)} searches taken from {journal}", file=sys.stderr)

    def searched(k: int, cell: dict[str, Any]) -> None:
        m, p = where[k]
        if journal is not None:
            with journal.open("a") as f:
                f.write(json.dumps({"key": _journal_key(digest, m, p, seed, episodes, tolerance_N), **cell}) + "\n")
        if progress:
            q = cell["quantile_N"]
            print(f"  mu={m:g} pull={p:g}: {SHARE:.0%} grip {'inf' if q is None else format(q, '.3f')} N, "
                  f"{len(cell['probes'])} probes ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

    for (m, p), cell in zip(where, run_jobs(jobs, runner, searched)):
        cells[(m, p)] = cell
    record = assemble_reference(config, cells, seed, tolerance_N, episodes)
    checks = [r for r in record["mu"] if r["reference_force_N"] is not None]
    if progress:
        print(f"  checking the reference grip at {len(checks)} mu", file=sys.stderr, flush=True)
    results = run_jobs([(_check_job, (cfg, r["mu"], r["pull"], r["reference_force_N"], int(seed), int(episodes)))
                    for r in checks], runner, None)
    for r, check in zip(checks, results):
        r["time_to_lift_s"] = check["mean_time_to_lift_s"]
        r["check"] = check
        if check["held"] < held_needed(episodes) and progress:
            print(f"  warning: mu={r['mu']:g}: the reference grip {r['reference_force_N']:.3f} N held {check['held']} "
                  f"of {episodes} episodes when run again (needs {held_needed(episodes)})", file=sys.stderr)
    record["seconds"] = round(time.perf_counter() - t0, 1)
    record["runner"] = "this process" if runner is None else f"{runner.label}, {runner.capacity()} workers"
    return record


def assemble_reference(config: GraspLiftConfig, cells: dict[tuple[float, float], dict[str, Any]], seed: int,
                       tolerance_N: float, episodes: int) -> dict[str, Any]:
    """The reference record of ``config`` from its searches: ``cells[(mu, pull)]``, each a :func:`search_quantile`
    result on the same ``episodes`` reference episodes. Per mu: each pull's Q_p, the least of them (R; on a tie the
    faster pull, the shorter episode) and its pull. Without the check run :func:`compute_reference` adds (``check``,
    ``time_to_lift_s``)."""
    from .controllers import max_pull_speed

    mus = sorted({m for m, _ in cells})
    pulls = sorted({p for _, p in cells})
    if any((m, p) not in cells for m in mus for p in pulls):
        raise ValueError("cells must hold every (mu, pull) of their grid")
    top = max_pull_speed(config)
    rows = []
    for m in mus:
        per_pull = [{"pull": p, "pull_speed_m_s": p * top, "quantile_N": cells[(m, p)]["quantile_N"],
                     "probes": cells[(m, p)]["probes"]} for p in pulls]
        finite = [c for c in per_pull if c["quantile_N"] is not None]
        best = min(finite, key=lambda c: (c["quantile_N"], -c["pull"])) if finite else None
        rows.append({"mu": m, "reference_force_N": None if best is None else best["quantile_N"],
                     "pull": None if best is None else best["pull"],
                     "pull_speed_m_s": None if best is None else best["pull_speed_m_s"], "per_pull": per_pull})
    fingerprint = task_fingerprint(config)
    return {
        "format": FORMAT,
        "definition": (f"R(mu) = min over pull p of the least fixed pinch force (to tolerance_N, by bisection) with "
                       f"which the fixed-force controller at pull p lifts and holds at least ceil({SHARE:g} n) of the "
                       "n reference episodes within the time limit: the least fixed grip that holds "
                       f"{SHARE:.0%} of the episodes at the pull speed that needs least. Between grid mu, R x mu is "
                       "interpolated linearly."),
        "share": SHARE,
        "tolerance_N": float(tolerance_N),
        "episodes": int(episodes),
        "held_needed": held_needed(episodes),
        "seeds": {"first": int(seed), "count": int(episodes),
                  "rule": "episode i at every mu and pull: reset seed first + i, options {'mu': mu}"},
        "pulls": pulls,
        "top_pull_speed_m_s": top,
        "task_digest": fingerprint_digest(fingerprint),
        "task": fingerprint,
        "computed_on": to_dict(config),
        "mu": rows,
    }


def write_reference(record: dict[str, Any], path: str | Path) -> Path:
    """Write a :func:`compute_reference` record to ``path`` (JSON, atomically)."""
    path = Path(path)
    written = atomic_write_text(path, json.dumps(nan_to_none(record), indent=1) + "\n")
    _load.cache_clear()
    return written


def format_reference(record: dict[str, Any]) -> str:
    """A text table of a reference record: per mu, each pull's 95 % quantile, R, its pull and time to lift."""
    pulls = record["pulls"]
    head = f"{'mu':>4} " + " ".join(f"{'p=' + format(p, 'g'):>7}" for p in pulls) + \
        f" {'R N':>7} {'R*mu':>6} {'pull':>5} {'t_lift s':>8} {'held':>6} {'score':>6}"
    lines = [head, "-" * len(head)]
    for r in record["mu"]:
        q = {c["pull"]: c["quantile_N"] for c in r["per_pull"]}
        cells = " ".join(f"{'inf' if q[p] is None else format(q[p], '.3f'):>7}" for p in pulls)
        if r["reference_force_N"] is None:
            lines.append(f"{r['mu']:>4g} {cells} {'-':>7}")
            continue
        check = r.get("check") or {}
        ttl = r.get("time_to_lift_s")
        lines.append(f"{r['mu']:>4g} {cells} {r['reference_force_N']:>7.3f} {r['reference_force_N'] * r['mu']:>6.3f} "
                     f"{r['pull']:>5g} {'-' if ttl is None else format(ttl, '.2f'):>8} "
                     f"{check.get('held', 0):>3}/{record['episodes']:<2} {check.get('score', math.nan):>6.3f}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
# the lookup
# ------------------------------------------------------------------------------------------------


def default_reference_path(config: GraspLiftConfig) -> Path:
    """The shipped table for ``config``'s scene: ``configs/reference/<scene>.json``."""
    return CONFIG_DIR / "reference" / f"{config.scene}.json"


@functools.lru_cache(maxsize=8)
def _load(path: str, mtime_ns: int) -> dict[str, Any]:
    try:
        record = json.loads(Path(path).read_text())
    except ValueError as exc:
        raise ConfigError(f"{path}: not a reference table (not JSON: {exc})") from None
    if not isinstance(record, dict) or record.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a reference table (format {FORMAT!r} expected)")
    return record


def load_reference(path: str | Path) -> dict[str, Any]:
    """A reference table written by :func:`write_reference` (read once per file version)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"no reference table at {path}; compute one with msdgrasp reference --out {path}")
    return _load(str(path.resolve()), path.stat().st_mtime_ns)


def reference_table(config: GraspLiftConfig, path: str | Path | None = None) -> dict[str, Any]:
    """The reference table for the task ``config`` (default: :func:`default_reference_path`); a
    :class:`ConfigError` (one line, naming the first field that differs) where it was computed for another task."""
    path = Path(path) if path is not None else default_reference_path(config)
    record = load_reference(path)
    ours = task_fingerprint(config)
    if fingerprint_digest(ours) != record["task_digest"]:
        differs = _first_difference(record["task"], ours)
        raise ConfigError(f"{path} holds the reference forces of another task ({differs}); compute this task's with "
                          "msdgrasp reference --out FILE")
    return record


def _grid_force(row: dict[str, Any], path: Path) -> float:
    if row["reference_force_N"] is None:
        raise ConfigError(f"{path}: at mu = {row['mu']:g} no fixed grip holds {SHARE:.0%} of the reference episodes at "
                          "any pull of the grid; no reference force there")
    return float(row["reference_force_N"])


def reference_force_N(config: GraspLiftConfig, mu: float, path: str | Path | None = None) -> float:
    """The reference force R(mu), N, of the task ``config``: the table's value at a grid mu; between grid points
    R x mu interpolated linearly in mu (Coulomb friction: the minimal force times mu is nearly constant). A mu outside
    the grid's range, or a task whose fingerprint differs from the table's, is a one-line :class:`ConfigError`."""
    path = Path(path) if path is not None else default_reference_path(config)
    record = reference_table(config, path)
    rows = record["mu"]
    grid = [float(r["mu"]) for r in rows]
    lo, hi = grid[0], grid[-1]
    if isinstance(mu, bool) or not isinstance(mu, (int, float, np.floating)) or not math.isfinite(mu) \
            or not lo - 1e-9 <= mu <= hi + 1e-9:
        raise ConfigError(f"mu = {mu!r} is outside the reference table's friction grid; allowed [{lo:g}, {hi:g}] "
                          f"({path})")
    mu = float(mu)
    k = int(np.searchsorted(grid, mu - 1e-9))
    if abs(grid[k] - mu) <= 1e-9:
        return _grid_force(rows[k], path)
    m0, m1 = grid[k - 1], grid[k]
    f0, f1 = _grid_force(rows[k - 1], path), _grid_force(rows[k], path)
    t = (mu - m0) / (m1 - m0)
    return ((1.0 - t) * f0 * m0 + t * f1 * m1) / mu


def force_score(peak_pinch_N: float, mu: float, config: GraspLiftConfig, path: str | Path | None = None) -> float:
    """A peak pinch (N, e.g. a policy's mean peak pinch at friction ``mu``) over the reference force R(mu): 1.0 is the
    least fixed grip that holds 95 % of the episodes at the best pull speed."""
    if isinstance(peak_pinch_N, bool) or not isinstance(peak_pinch_N, (int, float, np.floating)) \
            or not math.isfinite(peak_pinch_N) or peak_pinch_N < 0:
        raise ConfigError(f"peak_pinch_N = {peak_pinch_N!r} is out of range; allowed a finite force >= 0 N")
    return float(peak_pinch_N) / reference_force_N(config, mu, path)


def references_at(config: GraspLiftConfig, mus: Sequence[float]) -> tuple[dict[str, float | None], dict[str, Any]]:
    """The reference force (N) of the task ``config`` at each of ``mus`` (keyed ``f"{mu:g}"``; None outside the
    table's friction grid) and what a force ratio then reads against: ``{"kind": "reference", "table", "digest",
    "definition"}`` or, for a task with no reference table, ``{"kind": "nominal oracle", "why"}`` (the caller's ratios
    then divide by the oracle's minimal fixed force at pull 0.5 on the nominal tissue, which a slower pull undercuts,
    and say so)."""
    try:
        record = reference_table(config)
    except ConfigError as exc:
        return {f"{m:g}": None for m in mus}, {"kind": "nominal oracle", "why": str(exc)}
    forces: dict[str, float | None] = {}
    for m in mus:
        try:
            forces[f"{m:g}"] = reference_force_N(config, m)
        except ConfigError:  # (outside the table's friction grid: no reference there)
            forces[f"{m:g}"] = None
    return forces, {"kind": "reference", "table": default_reference_path(config).name,
                    "digest": record["task_digest"], "definition": record["definition"]}
