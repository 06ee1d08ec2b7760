"""The paper's grasp experiments: the spleen protocol of Fig. 9 and the sphere pinch test of Fig. 7.

Spleen protocol: anchored at the hilum, settled under gravity, the three jaws around the inferior pole
close at constant speed for 5 s, stop for 7 s, then the grasper pulls away from the anchors at constant
speed until the grasp is lost (no jaw touches the tissue any more), the tissue tears from its anchors
(anchor force above a threshold), or the time limit. All friction coefficients run as one batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .config import ConfigError, atomic_write_text, check_range, save_figure
from .contact import J_CONTACT, J_NORMAL, J_SLIP, J_STICK, J_TX, J_TZ
from .scenario import GraspScene

PHASES = ("close", "hold", "pull")


@dataclass(frozen=True)
class GraspProtocol:
    close_time_s: float = 5.0
    hold_time_s: float = 7.0
    #: time limit of the pull phase, s
    pull_time_s: float = 20.0
    #: jaw radius rate while closing, m/s
    closing_speed_m_s: float = 0.002
    #: grasper speed while pulling, m/s
    pull_speed_m_s: float = 0.004
    #: a sample every this many 1 ms physics steps
    record_every: int = 10
    #: anchor reaction (N) beyond which the tissue counts as torn from its anchors
    tear_force_N: float = 10.0
    #: cumulative slip (m, mean over the jaws) that marks the onset of sliding
    slip_onset_m: float = 0.5e-3

    def __post_init__(self) -> None:
        for name in ("close_time_s", "pull_time_s", "closing_speed_m_s", "pull_speed_m_s", "tear_force_N",
                     "slip_onset_m"):
            check_range(name, getattr(self, name), 0.0, None, lo_inclusive=False)
        check_range("hold_time_s", self.hold_time_s, 0.0, None)
        if not isinstance(self.record_every, int) or self.record_every < 1:
            raise ConfigError(f"record_every must be an integer >= 1, got {self.record_every!r}")


COLUMNS = (
    "time_s", "phase", "pinch_force_N", "normal_force_N", "tangential_force_N", "pull_force_N",
    "contact_nodes", "sticking_nodes", "slipping_nodes", "slip_mm", "pull_mm", "radius_mm",
    "anchor_force_N", "peak_stress_kPa",
    "normal_force_jaw0_N", "normal_force_jaw1_N", "normal_force_jaw2_N",
    "tangential_force_jaw0_N", "tangential_force_jaw1_N", "tangential_force_jaw2_N",
)


@dataclass
class GraspRun:
    mu: float
    data: dict[str, np.ndarray]
    summary: dict = field(default_factory=dict)


def run_grasp(
    scene: GraspScene, mus, protocol: GraspProtocol = GraspProtocol(), *, progress: bool = False
) -> list[GraspRun]:
    """Run the close/hold/pull protocol for each friction coefficient (one batch); 1 ms physics steps."""
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
    B = len(mus)
    sim = scene.simulation(B)
    sim.set_friction(mus)
    pull_dir = scene.pull_direction
    n_close = int(round(protocol.close_time_s * 1e3))
    n_hold = int(round(protocol.hold_time_s * 1e3))
    n_pull = int(round(protocol.pull_time_s * 1e3))
    total = n_close + n_hold + n_pull
    rec = protocol.record_every
    rows: list[list[list]] = [[] for _ in range(B)]
    active = np.ones(B, dtype=bool)
    outcome = ["time limit"] * B
    end_time = [protocol.close_time_s + protocol.hold_time_s + protocol.pull_time_s] * B
    slip_cum = np.zeros((B, 3))
    had_contact = np.zeros(B, dtype=bool)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=total, desc=f"grasp mu={mus}", unit="ms", mininterval=0.5, leave=False)
    step = 0
    while step < total and np.any(active):
        phase = 0 if step < n_close else (1 if step < n_close + n_hold else 2)
        boundary = n_close if phase == 0 else (n_close + n_hold if phase == 1 else total)
        todo = min(rec, boundary - step)
        sim.command(
            closing_speed=protocol.closing_speed_m_s if phase == 0 else 0.0,
            pull_velocity=pull_dir * (protocol.pull_speed_m_s if phase == 2 else 0.0),
        )
        sim.step(todo)
        step += todo
        if bar is not None:
            bar.update(todo)
        jo = sim.jaw_out
        slip_cum += sim.jaw_slip_distance
        ft = jo[:, :, J_TX : J_TZ + 1]
        ft_mag = np.linalg.norm(ft, axis=2)
        pull_force = ft.sum(axis=1) @ pull_dir
        contact = jo[:, :, J_CONTACT].sum(axis=1)
        pulled = (sim.g_tip - scene.pose.tip) @ pull_dir
        anchor = np.linalg.norm(sim.anchor_out, axis=1)
        finite = sim.finite()
        for b in np.flatnonzero(active):
            if not finite[b]:
                active[b] = False
                outcome[b] = "numerical failure"
                end_time[b] = float(sim.t[b])
                continue
            had_contact[b] |= contact[b] > 0
            rows[b].append([
                float(sim.t[b]), PHASES[phase], float(jo[b, :, J_NORMAL].sum()), float(jo[b, :, J_NORMAL].sum()),
                float(ft_mag[b].sum()), float(pull_force[b]), int(contact[b]), int(jo[b, :, J_STICK].sum()),
                int(jo[b, :, J_SLIP].sum()), float(slip_cum[b].mean() * 1e3), float(pulled[b] * 1e3),
                float(sim.g_radius[b] * 1e3), float(anchor[b]), float(sim.jaw_out[b, :, 8].max() * 1e-3),
                *[float(v) for v in jo[b, :, J_NORMAL]], *[float(v) for v in ft_mag[b]],
            ])
            if phase == 2 and had_contact[b] and contact[b] == 0:
                active[b] = False
                outcome[b] = "grasp lost"
                end_time[b] = float(sim.t[b])
            elif anchor[b] > protocol.tear_force_N:
                active[b] = False
                outcome[b] = "torn from anchors"
                end_time[b] = float(sim.t[b])
    if bar is not None:
        bar.close()
    runs = []
    for b, mu in enumerate(mus):
        cols = list(zip(*rows[b])) if rows[b] else [[] for _ in COLUMNS]
        data = {name: np.array(col) if name != "phase" else np.array(col, dtype=object) for name, col in zip(COLUMNS, cols)}
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
    }


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
