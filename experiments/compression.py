"""The paper's experiments, as functions returning arrays (the CLI writes CSV/PNG from them).

* :func:`run_compression`: unconstrained compression of the spherical test sample between two rigid,
  frictionless plates at constant rates (the paper's Fig. 3 and 5).
* :func:`run_grasp`: the spleen grasp protocol (Fig. 9): jaws close for 5 s, hold for 7 s, then the
  grasper pulls away from the anchors until the grasp is lost or a time limit.
* :func:`run_sphere_grasp`: the sample grasped with an increasing pinch (Fig. 7).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
from annotated_types import Ge, Gt, Le, MinLen

from ..physics.config import (
    Bool, ConfigError, Int, NonNegative, Real, atomic_write, config_dataclass, from_dict, needs_extra, save_figure,
)
from ..physics.mesh import TetMesh
from ..physics.scenario import load_params
from ..physics.simulation import Plate, Simulation
from ..physics.tissue import TissueModel, TissueParams

ProgressFactory = Callable[[int, str], object] | None


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    with needs_extra("viz", "the progress bar"):
        from tqdm.auto import tqdm
    return tqdm(total=total, desc=desc, unit="ms", mininterval=0.5, leave=False)


# =================================================================================================
# compression
# =================================================================================================


@config_dataclass
class CompressionConfig:
    """Unconstrained compression of the sphere between two rigid plates (bottom fixed, top moving down)."""

    rates_mm_per_min: Annotated[tuple[Annotated[Real, Gt(0), Le(6000)], ...], MinLen(1)] = (6.0, 60.0)
    #: final plate travel as a fraction of the sphere diameter
    deformation_fraction: Annotated[Real, Gt(0), Le(0.6)] = 0.30
    #: force samples recorded per curve
    samples: Annotated[Int, Ge(2)] = 150
    #: plate/sample friction. A real test's plates hold the sample (friction or bonded faces); with lubricated
    #: (frictionless) plates the coarse sphere, pressed at two pole nodes, tilts as a rigid body (7 deg at 0.4 mm
    #: of travel at 6 mm/min), the force collapses and the two rates end with different contact sets. At 0.5
    #: the sample stays upright and the rate effect follows the standard linear solid (compression_verdicts)
    plate_mu: NonNegative = 0.5
    #: include gravity (the sample's weight is negligible against the test forces)
    gravity: Bool = False
    dt_s: Annotated[Real, Gt(0), Le(0.01)] = 1e-3


@dataclass
class CompressionCurve:
    """One compression curve. ``force_N`` is the mean of the two plate forces (what a load cell under a
    quasi-static sample reads at either plate); a simulated curve also keeps each plate's force (their
    difference is the sample's inertia and drag), the smallest tet volume ratio (<= 0: inverted) and the
    sample's tilt (the angle of the line through its two pole nodes from the compression axis, deg)."""

    rate_mm_per_min: float
    time_s: np.ndarray
    deformation_mm: np.ndarray
    force_N: np.ndarray
    force_top_N: np.ndarray | None = None
    force_bottom_N: np.ndarray | None = None
    min_volume_ratio: np.ndarray | None = None
    tilt_deg: np.ndarray | None = None


def compression_model(mesh: TetMesh, params: TissueParams, gravity: bool = False) -> TissueModel:
    if not gravity:
        params = from_dict(TissueParams, {**params.__dict__, "gravity_m_per_s2": (0.0, 0.0, 0.0)})
    return TissueModel.from_params(mesh, params)


def run_compression(
    mesh: TetMesh,
    params: TissueParams,
    config: CompressionConfig = CompressionConfig(),
    *,
    progress: bool = False,
    substeps: int | str = "auto",
) -> list[CompressionCurve]:
    """Compress the sample at each rate; force = mean normal force of the two plates, N (each plate's
    force and the smallest tet volume ratio are recorded too).

    Each rate is one tissue of a batch: the rates step together in one kernel call; a tissue whose
    plate reached the final deformation stops there (neither stepped nor recorded again).
    """
    model = compression_model(mesh, params, config.gravity)
    z = mesh.nodes[:, 2]
    zmin, zmax = float(z.min()), float(z.max())
    height = zmax - zmin
    rates = np.asarray(config.rates_mm_per_min, dtype=np.float64)
    speeds = rates * 1e-3 / 60.0  # m/s
    B = len(rates)
    plates = [
        Plate(point=(0.0, 0.0, zmin), normal=(0.0, 0.0, 1.0), mu=config.plate_mu),
        Plate(point=(0.0, 0.0, zmax), normal=(0.0, 0.0, -1.0), mu=config.plate_mu),
    ]
    sim = Simulation(model, B, dt=config.dt_s, substeps=substeps, plates=plates)
    sim.pl_vel[:, 1, 2] = -speeds
    final = config.deformation_fraction * height
    durations = final / speeds
    n_total = int(math.ceil(durations.max() / config.dt_s))
    sample_every = np.maximum(1, np.round(durations / config.dt_s / config.samples).astype(int))
    chunk = int(np.min(sample_every))
    sample_every = chunk * np.maximum(1, np.round(sample_every / chunk).astype(int))
    poles = (int(np.argmin(z)), int(np.argmax(z)))  # the sample's bottom and top nodes at rest
    # (time s, deformation mm, top force N, bottom force N, smallest tet volume ratio, tilt deg)
    records: list[list[tuple[float, ...]]] = [[(0.0, 0.0, 0.0, 0.0, 1.0, 0.0)] for _ in range(B)]
    bar = _progress(n_total, "compress", progress)
    steps = 0
    running = np.ones(B, dtype=bool)  # rates whose plate has not yet reached the final deformation
    while steps < n_total:
        todo = min(chunk, n_total - steps)
        # only the rates still compressing: a finished rate's tissue would only relax under its stopped plate,
        # and the slowest rate takes 10x the others' time in the paper's protocol (each tissue's trajectory is
        # bitwise the same in any batch, so the curves do not change)
        sim.step(todo, indices=np.flatnonzero(running))
        steps += todo
        if bar is not None:
            bar.update(todo)
        ratios = sim.min_volume_ratio()  # once per chunk, for every rate
        for b in range(B):
            defl = -(sim.pl_point[b, 1, 2] - zmax)
            if not running[b] or defl > final + 1e-12:
                continue
            if steps % sample_every[b] == 0 or abs(defl - final) < 0.5 * speeds[b] * config.dt_s:
                top = float(-sim.plate_out[b, 1, 2])  # top plate pushes the sample down (-z)
                bottom = float(sim.plate_out[b, 0, 2])
                axis = sim.x[b, poles[1]] - sim.x[b, poles[0]]
                tilt = math.degrees(math.acos(min(1.0, abs(axis[2]) / max(float(np.linalg.norm(axis)), 1e-300))))
                records[b].append((float(sim.t[b]), defl * 1e3, top, bottom, float(ratios[b]), tilt))
        running &= -(sim.pl_point[:, 1, 2] - zmax) < final
    if bar is not None:
        bar.close()
    if not np.all(sim.finite()):
        raise FloatingPointError("compression simulation became non-finite (unstable parameters?)")
    curves = []
    for b in range(B):
        arr = np.array(records[b])
        curves.append(CompressionCurve(float(rates[b]), arr[:, 0], arr[:, 1], 0.5 * (arr[:, 2] + arr[:, 3]),
                                       arr[:, 2], arr[:, 3], arr[:, 4], arr[:, 5]))
    return curves


def write_compression_csv(curves: Sequence[CompressionCurve], path: str | Path) -> Path:
    """Columns: rate, time, deformation, ``force_N`` (mean of the plates), and for simulated curves
    ``force_top_N``, ``force_bottom_N``, ``min_volume_ratio`` and ``tilt_deg``."""
    full = all(c.force_top_N is not None and c.tilt_deg is not None for c in curves)
    lines = ["rate_mm_per_min,time_s,deformation_mm,force_N"
             + (",force_top_N,force_bottom_N,min_volume_ratio,tilt_deg" if full else "")]
    for c in curves:
        for k, (t, d, f) in enumerate(zip(c.time_s, c.deformation_mm, c.force_N)):
            extra = (f",{c.force_top_N[k]:.6f},{c.force_bottom_N[k]:.6f},{c.min_volume_ratio[k]:.6f},"
                     f"{c.tilt_deg[k]:.4f}" if full else "")
            lines.append(f"{c.rate_mm_per_min:g},{t:.6f},{d:.6f},{f:.6f}{extra}")
    return atomic_write(path, lambda p: p.write_text("\n".join(lines) + "\n"))


def read_compression_csv(path: str | Path) -> list[CompressionCurve]:
    """Read curves written by :func:`write_compression_csv` (or measured data in the same columns)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"data file not found: {path}")
    try:
        header = path.read_text(encoding="utf-8").splitlines()[:1]
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); the data is a CSV file") from None
    need = ["rate_mm_per_min", "deformation_mm", "force_N"]
    cols = [h.strip() for h in header[0].split(",")] if header else []
    missing = [c for c in need if c not in cols]
    if missing:
        raise ConfigError(f"{path}: missing column(s) {missing}; the header must contain {need} (time_s optional)")
    try:
        data = np.genfromtxt(path, delimiter=",", names=True, dtype=float)
    except ValueError as exc:
        raise ConfigError(f"{path}: cannot parse numbers: {' '.join(str(exc).split())}") from None
    data = np.atleast_1d(data)
    for c in need:
        if not np.all(np.isfinite(data[c])):
            raise ConfigError(f"{path}: column {c} has empty or non-numeric values")
    curves = []
    for rate in np.unique(data["rate_mm_per_min"]):
        sel = data[data["rate_mm_per_min"] == rate]
        if rate <= 0:
            raise ConfigError(f"{path}: rate_mm_per_min must be > 0, got {rate}")
        t = sel["time_s"] if "time_s" in cols else sel["deformation_mm"] / (rate / 60.0)
        curves.append(CompressionCurve(float(rate), t, sel["deformation_mm"], sel["force_N"]))
    return curves


def plot_compression(curves: Sequence[CompressionCurve], path: str | Path, title: str = "") -> Path:
    with needs_extra("viz", "the compression plot"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.2))
    for c in curves:
        ax.plot(c.deformation_mm, c.force_N, label=f"{c.rate_mm_per_min:g} mm/min")
    ax.set_xlabel("deformation (mm)")
    ax.set_ylabel("force, mean of the two plates (N)")
    ax.set_title(title or "Unconstrained compression of the test sample")
    ax.grid(alpha=0.3)
    ax.legend()
    return save_figure(fig, path)


def verdict(claim: str, holds: bool, numbers: str) -> dict:
    """One checked claim of the paper: {claim, verdict "holds" / "FAILS", numbers}."""
    return {"claim": claim, "verdict": "holds" if holds else "FAILS", "numbers": numbers}


def sls_hertz_rate_ratio(deformation_m: float, slow_m_s: float, fast_m_s: float, g: float, tau_s: float) -> float:
    """F_fast / F_slow at the same plate travel for a Hertz contact (F ~ E d^1.5) of a standard linear solid,
    relaxation modulus E(t) = E_inf (1 + g e^(-t / tau)), compressed at constant speed: Lee and Radok's
    hereditary integral F(t) ~ int_0^t E(t - s) d(d^1.5)/ds ds with d = v s, evaluated numerically."""
    def integral(v: float) -> float:
        t = deformation_m / v
        s = np.linspace(0.0, t, 4001)
        # d(d^1.5)/ds = 1.5 v^1.5 s^0.5
        y = (1.0 + g * np.exp(-(t - s) / tau_s)) * 1.5 * v**1.5 * np.sqrt(s)
        return float(np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(s)))  # (trapezoid rule; numpy 1.26 has no trapezoid)
    return integral(fast_m_s) / integral(slow_m_s)


#: plate travel (mm) where the fast test must be at least RATE_SMALL_MIN x the slow one's force, and compressions
#: (fraction of the height) where it must be within RATE_SLS_RTOL of the standard-linear-solid prediction
RATE_SMALL_MM = (1.5, 2.5, 5.0)
RATE_SMALL_MIN = 1.2
RATE_SLS_MARKS = (0.05, 0.10, 0.15, 0.20)
RATE_SLS_RTOL = 0.10


def compression_verdicts(curves: Sequence[CompressionCurve], height_mm: float,
                         relaxation: tuple[float, float] | None = None) -> list[dict]:
    """The paper's compression claims checked on simulated curves (one dict per claim: claim, verdict,
    numbers). Rates: the slowest and the fastest curve; forces: the mean of the two plates. ``relaxation``
    (g, tau s) of the sample's Maxwell branch gives the rate effect's prediction (:func:`sls_hertz_rate_ratio`)."""
    slow = min(curves, key=lambda c: c.rate_mm_per_min)
    fast = max(curves, key=lambda c: c.rate_mm_per_min)
    reach = min(c.deformation_mm[-1] for c in curves)
    out = _rate_verdicts(slow, fast, reach, height_mm, relaxation) if fast is not slow else []
    return out + _plate_verdicts(curves) + _shape_verdicts(slow, reach, height_mm)


def _rate_verdicts(slow: CompressionCurve, fast: CompressionCurve, reach: float, height_mm: float,
                   relaxation: tuple[float, float] | None) -> list[dict]:
    """The rate effect: the fast curve stiffer from small strain, and as the standard linear solid predicts."""
    out = []
    marks = [f for f in RATE_SLS_MARKS if f * height_mm <= reach + 1e-9]
    small = [d for d in RATE_SMALL_MM if d <= reach + 1e-9]

    def rate_ratio(d_mm: float) -> float:
        return float(np.interp(d_mm, fast.deformation_mm, fast.force_N)
                     / np.interp(d_mm, slow.deformation_mm, slow.force_N))

    if small:
        ratios = [rate_ratio(d) for d in small]
        out.append(verdict(
            f"rate dependence (Fig. 5): {fast.rate_mm_per_min:g} mm/min stiffer than {slow.rate_mm_per_min:g} from "
            f"small strain", min(ratios) >= RATE_SMALL_MIN,
            "force ratio " + ", ".join(f"{r:.2f} at {d:g} mm" for d, r in zip(small, ratios))
            + f" (>= {RATE_SMALL_MIN})"))
    if marks and relaxation is not None and relaxation[0] > 0:
        g, tau = relaxation
        ratios = [rate_ratio(f * height_mm) for f in marks]
        pred = [sls_hertz_rate_ratio(f * height_mm * 1e-3, slow.rate_mm_per_min * 1e-3 / 60.0,
                                     fast.rate_mm_per_min * 1e-3 / 60.0, g, tau) for f in marks]
        out.append(verdict(
            f"rate dependence follows the standard linear solid (g = {g:g}, tau = {tau:g} s; Lee-Radok on Hertz)",
            all(abs(r / p - 1.0) <= RATE_SLS_RTOL for r, p in zip(ratios, pred)),
            ", ".join(f"{r:.2f} vs {p:.2f} at {f:.0%}" for f, r, p in zip(marks, ratios, pred))
            + f" (within {RATE_SLS_RTOL:.0%})"))
    return out


def _plate_verdicts(curves: Sequence[CompressionCurve]) -> list[dict]:
    """What the plates see: the sample upright, both plates carrying one force, no tet inverted."""
    out = []
    if all(c.tilt_deg is not None for c in curves):
        tilt = max(float(np.max(c.tilt_deg)) for c in curves)
        out.append(verdict("the sample stays upright between the plates", tilt < 2.0,
                           f"largest tilt of the pole-to-pole line {tilt:.2f} deg (< 2)"))
    if all(c.force_top_N is not None for c in curves):
        worst = 0.0
        for c in curves:
            # relative to the force once it is a few per cent of the curve's largest (the first contact
            # of a node can bounce: a relative error of a near-zero force means nothing)
            sel = c.force_N > 0.05 * c.force_N.max()
            if np.any(sel):
                worst = max(worst, float(np.max(np.abs(c.force_top_N[sel] - c.force_bottom_N[sel]) / c.force_N[sel])))
        out.append(verdict("quasi-static: both plates carry the same force (rate effect from the material)",
                            worst < 0.05,
                            f"largest |top - bottom| / mean {worst:.1%} (forces above 5% of the largest)"))
        vmin = min(float(np.min(c.min_volume_ratio)) for c in curves)
        out.append(verdict("no tet inverts", vmin > 0.0, f"smallest tet volume ratio {vmin:.3f}"))
    return out


def _shape_verdicts(slow: CompressionCurve, reach: float, height_mm: float) -> list[dict]:
    """The slow curve's shape: stiffening with deformation, Hertz's exponent at small strain."""
    out = []
    d, f = slow.deformation_mm, slow.force_N
    if reach >= 0.15 * height_mm:
        secant = [float(np.interp(x * height_mm, d, f) / (x * height_mm)) for x in (0.05, 0.10, 0.15)]
        out.append(verdict("stiffening: the secant stiffness grows with deformation", secant[0] < secant[1] < secant[2],
                            "secant N/mm " + ", ".join(f"{s:.3f}" for s in secant) + " at 5/10/15%"))
    sel = (d >= 1.0) & (d <= 7.0) & (f > 0)
    if np.count_nonzero(sel) >= 3:
        n = float(np.polyfit(np.log(d[sel]), np.log(f[sel]), 1)[0])
        out.append(verdict("Hertz-like contact: force ~ deformation^1.5 at small strain (1-7 mm)",
                            abs(n - 1.5) <= 0.15,
                            f"exponent {n:.2f} at {slow.rate_mm_per_min:g} mm/min (Hertz 1.5 +/- 0.15)"))
    return out


def load_tissue_params(path: str | Path) -> TissueParams:
    """A tissue config file (YAML) -> TissueParams: its ``tissue:`` section, strictly (the file's sections and
    the keys are checked, :func:`~msdgrasp.physics.scenario.load_params`)."""
    return load_params(path, "tissue", TissueParams)
