"""The paper's grasp experiments: the spleen protocol of Fig. 9 and the sphere pinch test of Fig. 7.

Spleen protocol: anchored at the hilum, settled under gravity, the three jaws around the inferior pole
close at constant speed for 5 s, stop for 7 s, then the grasper pulls away from the anchors at constant
speed until the grasp is lost (no jaw touches the tissue any more), the tissue tears from its anchors
(anchor force above a threshold), or the time limit. All friction coefficients run as one batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from annotated_types import Ge

from ..physics.config import (
    ConfigError, Int, NonNegative, Positive, atomic_write_text, check_range, config_dataclass, needs_extra, save_figure,
)
from ..physics.contact import J_CONTACT, J_NORMAL, J_SLIP, J_STICK, J_TX, J_TZ
from .compression import verdict
from ..physics.scenario import GraspScene

PHASES = ("close", "hold", "pull")


@config_dataclass
class GraspProtocol:
    close_time_s: Positive = 5.0
    hold_time_s: NonNegative = 7.0
    #: time limit of the pull phase, s
    pull_time_s: Positive = 20.0
    #: jaw radius rate while closing, m/s
    closing_speed_m_s: Positive = 0.002
    #: grasper speed while pulling, m/s
    pull_speed_m_s: Positive = 0.004
    #: a sample every this many 1 ms physics steps
    record_every: Annotated[Int, Ge(1)] = 10
    #: anchor reaction (N) beyond which the tissue counts as torn from its anchors
    tear_force_N: Positive = 10.0
    #: cumulative slip (m, mean over the jaws) that marks the onset of sliding
    slip_onset_m: Positive = 0.5e-3


COLUMNS = (
    "time_s", "phase", "pinch_force_N", "normal_force_N", "tangential_force_N", "pull_force_N",
    "contact_nodes", "sticking_nodes", "slipping_nodes", "slip_mm", "pull_mm", "radius_mm",
    "anchor_force_N", "peak_stress_kPa",
    "normal_force_jaw0_N", "normal_force_jaw1_N", "normal_force_jaw2_N",
    "tangential_force_jaw0_N", "tangential_force_jaw1_N", "tangential_force_jaw2_N",
    "min_volume_ratio",
    # the jaws' force split by where it acts (Simulation.jaw_face_forces): their gripping faces' normal force and
    # friction (summed over the jaws), and the push of their side and end walls
    "face_normal_force_N", "face_tangential_force_N", "wall_force_N",
)


@dataclass
class GraspRun:
    mu: float
    data: dict[str, np.ndarray]
    summary: dict = field(default_factory=dict)


def _checked_mus(scene: GraspScene, mus) -> list[float]:
    """The friction coefficients, each >= 0, at least one; the grasper's axis must reach the tissue."""
    mus = [float(m) for m in mus]
    if not mus:
        raise ConfigError("mu: give at least one friction coefficient")
    for k, m in enumerate(mus):
        check_range(f"mu[{k}]", m, 0.0, None)
    if np.any(scene.reach < scene.grasper.min_radius_m):
        raise ConfigError(
            "no contact: the grasper axis misses the tissue (jaw reach "
            f"{np.round(scene.reach * 1e3, 2).tolist()} mm vs minimum radius {scene.grasper.min_radius_m * 1e3:.2f} mm)"
        )
    return mus


def _frame(sim, scene: GraspScene) -> dict[str, np.ndarray]:
    """What one recorded step reads off the simulation, per run of the batch."""
    jo = sim.jaw_out
    ft = jo[:, :, J_TX : J_TZ + 1]
    face_n, face_t, wall = sim.jaw_face_forces()
    return {"jo": jo, "ft_mag": np.linalg.norm(ft, axis=2), "pull_force": ft.sum(axis=1) @ scene.pull_direction,
            "contact": jo[:, :, J_CONTACT].sum(axis=1), "pulled": (sim.g_tip - scene.pose.tip) @ scene.pull_direction,
            "anchor": np.linalg.norm(sim.anchor_out, axis=1), "finite": sim.finite(),
            "vratio": sim.min_volume_ratio(), "face_n": face_n.sum(axis=1),
            "face_t": np.linalg.norm(face_t, axis=2).sum(axis=1), "wall": np.linalg.norm(wall, axis=2).sum(axis=1)}


def _row(sim, f: dict[str, np.ndarray], b: int, phase: int, slip_mm: float) -> list:
    """Run ``b``'s row of :data:`COLUMNS` from a frame."""
    jo, normal = f["jo"][b], float(f["jo"][b, :, J_NORMAL].sum())
    return [float(sim.t[b]), PHASES[phase], normal, normal, float(f["ft_mag"][b].sum()), float(f["pull_force"][b]),
            int(f["contact"][b]), int(jo[:, J_STICK].sum()), int(jo[:, J_SLIP].sum()), slip_mm,
            float(f["pulled"][b] * 1e3), float(sim.g_radius[b] * 1e3), float(f["anchor"][b]),
            float(jo[:, 8].max() * 1e-3), *[float(v) for v in jo[:, J_NORMAL]], *[float(v) for v in f["ft_mag"][b]],
            float(f["vratio"][b]), float(f["face_n"][b]), float(f["face_t"][b]), float(f["wall"][b])]


def _ended(f: dict[str, np.ndarray], b: int, phase: int, had_contact: bool, protocol: GraspProtocol) -> str | None:
    """The outcome that ends run ``b`` at this frame, or None."""
    if phase == 2 and had_contact and f["contact"][b] == 0:
        return "grasp lost"
    if f["anchor"][b] > protocol.tear_force_N:
        return "torn from anchors"
    return None


def run_grasp(
    scene: GraspScene, mus, protocol: GraspProtocol = GraspProtocol(), *, progress: bool = False
) -> list[GraspRun]:
    """Run the close/hold/pull protocol for each friction coefficient (one batch); 1 ms physics steps."""
    mus = _checked_mus(scene, mus)
    B = len(mus)
    sim = scene.simulation(B)
    sim.set_friction(mus)
    n_close = int(round(protocol.close_time_s * 1e3))
    n_hold = int(round(protocol.hold_time_s * 1e3))
    total = n_close + n_hold + int(round(protocol.pull_time_s * 1e3))
    rows: list[list[list]] = [[] for _ in range(B)]
    active = np.ones(B, dtype=bool)
    outcome = ["time limit"] * B
    end_time = [protocol.close_time_s + protocol.hold_time_s + protocol.pull_time_s] * B
    slip_cum = np.zeros((B, 3))
    had_contact = np.zeros(B, dtype=bool)
    bar = None
    if progress:
        with needs_extra("viz", "the progress bar"):
            from tqdm.auto import tqdm
        bar = tqdm(total=total, desc=f"grasp mu={mus}", unit="ms", mininterval=0.5, leave=False)
    step = 0
    while step < total and np.any(active):
        phase = 0 if step < n_close else (1 if step < n_close + n_hold else 2)
        boundary = (n_close, n_close + n_hold, total)[phase]
        todo = min(protocol.record_every, boundary - step)
        sim.command(
            closing_speed=protocol.closing_speed_m_s if phase == 0 else 0.0,
            pull_velocity=scene.pull_direction * (protocol.pull_speed_m_s if phase == 2 else 0.0),
        )
        sim.step(todo, indices=np.flatnonzero(active))  # (a run that has ended stands still: nothing reads it again)
        step += todo
        if bar is not None:
            bar.update(todo)
        slip_cum += sim.jaw_slip_distance
        f = _frame(sim, scene)
        for b in np.flatnonzero(active):
            end = "numerical failure" if not f["finite"][b] else None
            if end is None:
                had_contact[b] |= f["contact"][b] > 0
                rows[b].append(_row(sim, f, b, phase, float(slip_cum[b].mean() * 1e3)))
                end = _ended(f, b, phase, bool(had_contact[b]), protocol)
            if end is not None:
                active[b], outcome[b], end_time[b] = False, end, float(sim.t[b])
    if bar is not None:
        bar.close()
    runs = []
    for b, mu in enumerate(mus):
        cols = list(zip(*rows[b])) if rows[b] else [[] for _ in COLUMNS]
        data = {name: np.array(col) if name != "phase" else np.array(col, dtype=object)
                for name, col in zip(COLUMNS, cols)}
        run = GraspRun(mu, data)
        run.summary = summarize_grasp(run, protocol, outcome[b], end_time[b])
        runs.append(run)
    return runs


def summarize_grasp(run: GraspRun, protocol: GraspProtocol, outcome: str, end_time: float) -> dict:
    d = run.data
    t = d["time_s"]
    phase = d["phase"]
    close = phase == "close"
    hold = phase == "hold"
    pull = phase == "pull"

    def at(mask, col, fn):
        return float(fn(d[col][mask])) if np.any(mask) else float("nan")

    slip_pull = d["slip_mm"] - (d["slip_mm"][~pull][-1] if np.any(~pull) else 0.0)
    onset = np.flatnonzero(pull & (slip_pull >= protocol.slip_onset_m * 1e3))
    peak_i = int(np.argmax(np.where(pull, d["pull_force_N"], -np.inf))) if np.any(pull) else None
    return {
        "mu": run.mu,
        "outcome": outcome,
        "end_time_s": end_time,
        "normal_end_close_N": at(close, "normal_force_N", lambda a: a[-1]),
        "normal_end_hold_N": at(hold, "normal_force_N", lambda a: a[-1]),
        "normal_peak_N": at(close | hold, "normal_force_N", np.max),
        "tangential_peak_N": float(d["pull_force_N"][peak_i]) if peak_i is not None else float("nan"),
        "tangential_peak_time_s": float(t[peak_i]) if peak_i is not None else float("nan"),
        "pull_at_peak_mm": float(d["pull_mm"][peak_i]) if peak_i is not None else float("nan"),
        "slip_onset_time_s": float(t[onset[0]]) if onset.size else float("nan"),
        "pull_at_slip_onset_mm": float(d["pull_mm"][onset[0]]) if onset.size else float("nan"),
        "normal_at_slip_onset_N": float(d["normal_force_N"][onset[0]]) if onset.size else float("nan"),
        "peak_stress_kPa": float(np.max(d["peak_stress_kPa"])) if len(t) else float("nan"),
        "min_volume_ratio": float(np.min(d["min_volume_ratio"])) if len(t) else float("nan"),
    }


def grasp_verdicts(runs: list[GraspRun], relaxation_time_s: float | None = None) -> list[dict]:
    """The paper's claims about the spleen protocol (Fig. 9) checked on the runs, one dict per claim
    (claim, verdict "holds" / "FAILS", numbers). ``relaxation_time_s``: the tissue's Maxwell time constant,
    compared with the one read off the hold."""
    runs = sorted(runs, key=lambda r: r.mu)
    out = _closing_verdicts(runs, relaxation_time_s)
    if len(runs) >= 2:
        out += _friction_order_verdicts(runs)
    out += _coulomb_verdicts(runs)
    vmin = min(r.summary["min_volume_ratio"] for r in runs)
    return out + [verdict("no tet inverts", vmin > 0.0, f"smallest tet volume ratio {vmin:.3f}")]


def _closing_and_hold(run: GraspRun) -> tuple[float | None, float | None, float | None]:
    """A run's R^2 of a line through the closing's normal force, and the hold's relative drop and its time constant
    (to 63.2 % of the drop, an exponential's), None where the run has too few samples."""
    d = run.data
    close, hold = d["phase"] == "close", d["phase"] == "hold"
    t_c, n_c = d["time_s"][close], d["normal_force_N"][close]
    touch = n_c > 0.05 * max(float(n_c.max()), 1e-9) if n_c.size else n_c
    r2 = drop = tau = None
    if np.count_nonzero(touch) >= 3:
        resid = n_c[touch] - np.polyval(np.polyfit(t_c[touch], n_c[touch], 1), t_c[touch])
        r2 = 1.0 - float(resid @ resid) / max(float(np.sum((n_c[touch] - n_c[touch].mean()) ** 2)), 1e-30)
    n_h, t_h = d["normal_force_N"][hold], d["time_s"][hold]
    if n_h.size >= 3 and n_c.size:
        f0, f_end = float(n_c[-1]), float(n_h[-1])
        drop = (f0 - f_end) / f0 if f0 > 0 else 0.0
        k = np.flatnonzero(n_h <= f0 - 0.632 * (f0 - f_end))
        tau = float(t_h[k[0]] - t_c[-1]) if k.size and f0 > f_end else float("nan")
    return r2, drop, tau


def _closing_verdicts(runs: list[GraspRun], relaxation_time_s: float | None) -> list[dict]:
    """The closing's linear rise and the hold's stress relaxation."""
    out = []
    per_run = [_closing_and_hold(r) for r in runs]
    lin = [r2 for r2, _, _ in per_run if r2 is not None]
    drops = [drop for _, drop, _ in per_run if drop is not None]
    taus = [tau for _, drop, tau in per_run if drop is not None]
    if lin:
        out.append(verdict("normal force rises nearly linearly while the jaws close", min(lin) > 0.95,
                           "R^2 of a line " + ", ".join(f"{v:.3f}" for v in lin)))
    if drops:
        tau_txt = ", ".join(f"{v:.2f}" for v in taus)
        ok = min(drops) > 0.1
        if relaxation_time_s is not None and all(np.isfinite(taus)):
            ok = ok and all(abs(v / relaxation_time_s - 1.0) < 0.3 for v in taus)
            tau_txt += f" s (Maxwell tau {relaxation_time_s:g} s)"
        out.append(verdict("stress relaxation: the normal force drops once the jaws stop", ok,
                           "drop over the hold " + ", ".join(f"{v:.0%}" for v in drops) + "; time constant " + tau_txt))
    return out


def _friction_order_verdicts(runs: list[GraspRun]) -> list[dict]:
    """Across the runs' mu (ascending): the same normal force, later slip, a larger peak pull."""
    mus = [r.mu for r in runs]
    normal = np.array([r.summary["normal_end_hold_N"] for r in runs])
    spread = float(np.ptp(normal) / np.mean(normal))
    onset = np.array([r.summary["slip_onset_time_s"] for r in runs])
    peak = np.array([r.summary["tangential_peak_N"] for r in runs])
    return [verdict("higher mu does not change the normal force", spread < 0.05,
                    f"normal force at the end of the hold {np.round(normal, 3).tolist()} N at mu {mus} "
                    f"(spread {spread:.1%})"),
            verdict("higher mu delays slip", bool(np.all(np.isfinite(onset)) and np.all(np.diff(onset) > 0)),
                    f"slip onset {np.round(onset, 2).tolist()} s"),
            verdict("higher mu: a larger peak tangential force", bool(np.all(np.diff(peak) > 0)),
                    f"peak pull force {np.round(peak, 3).tolist()} N")]


def _coulomb_verdicts(runs: list[GraspRun]) -> list[dict]:
    """T / N = mu on the jaw faces at the pull's peak (a side or end wall's push is no friction: reported apart)."""
    ratio, walls = [], []
    for r in runs:
        d = r.data
        pull = np.flatnonzero(d["phase"] == "pull")
        if pull.size:
            i = pull[int(np.argmax(d["face_tangential_force_N"][pull]))]
            ratio.append(float(d["face_tangential_force_N"][i] / max(d["face_normal_force_N"][i], 1e-12)) / r.mu)
            walls.append(float(d["wall_force_N"][i]))
    if not ratio:
        return []
    return [verdict("Coulomb: T / N = mu at gross slip (jaw faces)", all(0.8 <= v <= 1.1 for v in ratio),
                    "peak face T / N / mu " + ", ".join(f"{v:.2f}" for v in ratio) + " (0.8-1.1); jaw walls' "
                    "push at that instant " + ", ".join(f"{v:.3f}" for v in walls) + " N")]


def write_columns_csv(data: dict, columns: list[str] | tuple[str, ...], path: str | Path) -> Path:
    """A CSV of equal-length columns (floats as %.6g, strings as they are), written atomically."""
    def cell(v) -> str:
        return v if isinstance(v, str) else (f"{v:.6g}" if isinstance(v, float) else str(v))

    rows = range(len(data[columns[0]]))
    lines = [",".join(columns)] + [",".join(cell(data[c][i]) for c in columns) for i in rows]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def write_grasp_csv(run: GraspRun, path: str | Path) -> Path:
    return write_columns_csv(run.data, COLUMNS, path)


def plot_grasp(runs: list[GraspRun], path: str | Path, protocol: GraspProtocol) -> Path:
    with needs_extra("viz", "the grasp plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 6.5), sharex=True)
    for r in runs:
        ax1.plot(r.data["time_s"], r.data["normal_force_N"], label=f"mu = {r.mu:g}")
        ax2.plot(r.data["time_s"], r.data["pull_force_N"], label=f"mu = {r.mu:g}")
    for ax in (ax1, ax2):
        for tb in (protocol.close_time_s, protocol.close_time_s + protocol.hold_time_s):
            ax.axvline(tb, color="0.6", lw=0.8, ls="--")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    ax1.set_ylabel("normal force, sum of jaws (N)")
    ax2.set_ylabel("tangential force along pull (N)")
    ax2.set_xlabel("time (s)")
    ax1.set_title("Spleen grasp: close 5 s, hold 7 s, pull (cf. paper Fig. 9)")
    return save_figure(fig, path)


# ------------------------------------------------------------------------------------------------
# sphere pinch test (paper Fig. 7)
# ------------------------------------------------------------------------------------------------


def run_sphere_grasp(
    scene: GraspScene, travel_m: float | None = None, closing_speed_m_s: float = 1e-3, record_every: int = 10
) -> dict[str, np.ndarray]:
    """Close the jaws on the free sphere at constant speed; pinch force vs jaw displacement."""
    diameter = float(np.ptp(scene.x_start[:, 0]))
    travel = 0.35 * diameter if travel_m is None else travel_m
    check_range("travel_m", travel, 0.0, scene.start_radius - scene.grasper.min_radius_m, lo_inclusive=False)
    sim = scene.simulation(1)
    sim.command(closing_speed=closing_speed_m_s)
    n = int(round(travel / closing_speed_m_s * 1e3))
    rows = [(0.0, 0.0, scene.start_radius * 1e3, 0.0, 0)]
    for _ in range(0, n, record_every):
        sim.step(record_every)
        rows.append((
            float(sim.t[0]), (scene.start_radius - sim.g_radius[0]) * 1e3, sim.g_radius[0] * 1e3,
            float(sim.pinch_force[0]), int(sim.jaw_out[0, :, J_CONTACT].sum()),
        ))
    arr = np.array(rows, dtype=float)
    return {"time_s": arr[:, 0], "jaw_displacement_mm": arr[:, 1], "radius_mm": arr[:, 2],
            "pinch_force_N": arr[:, 3], "contact_nodes": arr[:, 4]}


def plot_sphere_grasp(data: dict[str, np.ndarray], path: str | Path, title: str) -> Path:
    """Pinch force vs jaw displacement of :func:`run_sphere_grasp` (paper Fig. 7)."""
    with needs_extra("viz", "the grasp plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.plot(data["jaw_displacement_mm"], data["pinch_force_N"])
    ax.set_xlabel("jaw displacement (mm)")
    ax.set_ylabel("pinch force, sum of jaws (N)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def write_sphere_grasp_csv(data: dict[str, np.ndarray], path: str | Path) -> Path:
    return write_columns_csv(data, list(data), path)
