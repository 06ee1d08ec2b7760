"""Fit uniform-mode tissue constants to measured compression curves at several rates.

The paper tuned K1, K2, dl_c (spring law, Eq. 4-6) and b0, b1 (nodal damping, Eq. 7), taken uniform over
the sample, by minimising the squared error between measured and simulated force-deformation curves of
the unconstrained compression test at two rates (MATLAB ``fmincon``). Its rate dependence then comes from
the nodal damping, an absolute drag that loads only the moving plate (the sample is not quasi-static).
Two sets of unknowns (:data:`FIT_SETS`):

* ``"viscoelastic"`` (the default): K1, K2, dl_c and the Maxwell branch of every spring (relaxation
  strength g = k_v / K1 and time constant tau, a standard linear solid); the nodal damping stays as the
  base parameters give it (small: it only settles vibrations). The faster test is stiffer because the
  material is, in the mean of the two plate forces;
* ``"paper"``: the paper's five constants K1, K2, dl_c, b0, b1.

The fit uses :func:`scipy.optimize.least_squares` (trust-region reflective, box bounds):

* the unknowns are ``log(p / p_init)``, so all are positive, of order one and equally scaled
  (``x_scale = 1``); a step of ``diff_step`` in a log-parameter is a relative change;
* one residual evaluation is ONE :func:`~.experiments.run_compression` call that simulates all measured
  rates together (the rates are a batch there), to the largest measured deformation; the simulated force
  is interpolated at the measured deformations and ``simulated - measured`` of all curves is concatenated;
* the Jacobian is a forward difference in log space computed here (so every simulation is counted and
  ``max_evals`` is a hard budget on simulations, which ``least_squares`` itself does not count);
* evaluations are cached by parameter vector; a guess so stiff that the explicit scheme would need more
  than ``max_substeps`` substeps per 1 ms step, or one whose simulation turns non-finite, gets large
  residuals instead of a (slow or failed) simulation;
* gravity is off (the sample's weight is negligible against the test forces), as in ``run_compression``.

The CLI (``msdgrasp calibrate``) reads a CSV of curves, fits, prints a JSON summary and writes a tissue
config (``mesh:``, ``tissue:`` in uniform mode, ``calibration:``) that loads back with
:func:`~.experiments.load_tissue_params` / :func:`~.mesh_io.mesh_from_config`.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..physics.config import ConfigError, from_dict, to_dict
from .compression import (
    CompressionConfig,
    CompressionCurve,
    compression_model,
    run_compression,
)
from ..physics.mesh import TetMesh
from ..physics.tissue import TissueModel, TissueParams

#: the paper's five constants, in this order (TissueParams field names, SI units)
PARAM_NAMES: tuple[str, ...] = ("k1_n_per_m", "k2_n_per_m3", "dl_c_m", "b0_n_s_per_m", "b1_n_s_per_m2")
#: the Maxwell branch of every spring: k_v = g K1 and its time constant, s
RELAXATION_NAMES: tuple[str, ...] = ("relaxation_strength", "relaxation_time_s")
#: every constant a fit may adjust
ALL_NAMES: tuple[str, ...] = PARAM_NAMES + RELAXATION_NAMES
#: named sets of fitted constants
FIT_SETS: dict[str, tuple[str, ...]] = {
    "viscoelastic": ("k1_n_per_m", "k2_n_per_m3", "dl_c_m") + RELAXATION_NAMES,
    "paper": PARAM_NAMES,
}

#: Default bounds: wide (several decades around any plausible value for a ~5 cm soft sample on a coarse
#: to fine mesh) but strictly positive, since the fit runs in log space. K2 and b1 may physically be 0;
#: their floors are small enough to make the term negligible at the deformations of a compression test.
#: dl_c is further capped at :data:`DLC_MAX_EDGE_FRACTION` x the mean spring rest length of the mesh
#: (see :func:`default_bounds`): few springs of a compression test stretch or shorten that much, so a
#: larger dl_c is not identifiable from the data, and it would only slow the simulation down (the
#: automatic substep count follows the tangent stiffness K1 + 3 K2 dl_c^2 even where it is not reached).
DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "k1_n_per_m": (1e-2, 1e6),  # N/m
    "k2_n_per_m3": (1e-2, 1e14),  # N/m^3
    "dl_c_m": (1e-6, 1e-1),  # m (upper bound also capped by the mesh, see above)
    "b0_n_s_per_m": (1e-6, 1e4),  # N s/m
    "b1_n_s_per_m2": (1e-4, 1e7),  # N s/m^2
    "relaxation_strength": (1e-3, 1e2),  # k_v / K1
    "relaxation_time_s": (1e-2, 1e4),  # s
}

DLC_MAX_EDGE_FRACTION = 0.5


def default_bounds(mesh: TetMesh) -> dict[str, tuple[float, float]]:
    """:data:`DEFAULT_BOUNDS` with the dl_c upper bound capped by the mesh's mean edge length."""
    e = mesh.edges
    mean_len = float(np.mean(np.linalg.norm(mesh.nodes[e[:, 1]] - mesh.nodes[e[:, 0]], axis=1)))
    lo, hi = DEFAULT_BOUNDS["dl_c_m"]
    return {**DEFAULT_BOUNDS, "dl_c_m": (lo, max(10.0 * lo, min(hi, DLC_MAX_EDGE_FRACTION * mean_len)))}


#: smallest number of points per measured curve
MIN_POINTS = 3
#: largest deformation/height run_compression accepts
MAX_DEFORMATION_FRACTION = 0.6


class _BudgetExhausted(Exception):
    """Raised inside the residual function when ``max_evals`` simulations have been run."""


@dataclass
class CalibrationResult:
    """Outcome of :func:`fit_compression`."""

    #: fitted constants (the fit's names, see :data:`FIT_SETS`; SI units)
    params: dict[str, float]
    #: root-mean-square of simulated - measured force over all points, N
    rmse_N: float
    #: Pearson correlation between all measured and simulated forces
    correlation: float
    #: RMSE per rate (mm/min -> N)
    rmse_per_rate: dict[float, float]
    #: simulations run (cache hits not counted)
    n_evals: int
    success: bool
    message: str
    #: uniform-mode parameters: the fitted constants, every other field from the base parameters
    tissue_params: TissueParams
    #: starting point of the fit
    init: dict[str, float] = field(default_factory=dict)
    #: simulated force at the measured deformations, one array per measured curve
    simulated_force_N: list[np.ndarray] = field(default_factory=list)
    wall_s: float = 0.0

    def summary(self) -> dict:
        """JSON-safe summary."""
        return {
            "params": {k: float(v) for k, v in self.params.items()},
            "rmse_N": float(self.rmse_N),
            "correlation": float(self.correlation),
            "rmse_per_rate_N": {f"{r:g}": float(v) for r, v in self.rmse_per_rate.items()},
            "n_evals": int(self.n_evals),
            "success": bool(self.success),
            "message": self.message,
            "init": {k: float(v) for k, v in self.init.items()},
            "wall_s": round(float(self.wall_s), 3),
        }


# =================================================================================================
# validation
# =================================================================================================


def validate_curves(curves: Sequence[CompressionCurve], height_m: float | None = None, where: str = "data") -> None:
    """Raise :class:`ConfigError` unless the curves are usable for a fit.

    Each curve: a rate in (0, 6000] mm/min, at least :data:`MIN_POINTS` finite points, deformation >= 0
    and non-decreasing (strictly larger at the end than at the start), forces >= 0 (a load-cell offset of
    up to 1 % of the curve's peak force is tolerated). With ``height_m``, the largest deformation must not
    exceed :data:`MAX_DEFORMATION_FRACTION` of the sample height.
    """
    if len(curves) == 0:
        raise ConfigError(f"{where}: no data rows (need at least {MIN_POINTS} points per rate)")
    for c in curves:
        tag = f"{where}: rate {c.rate_mm_per_min:g} mm/min"
        rate = c.rate_mm_per_min
        if not (math.isfinite(rate) and 0.0 < rate <= 6000.0):
            raise ConfigError(f"{tag}: rate_mm_per_min must be in (0, 6000], got {rate!r}")
        d = np.asarray(c.deformation_mm, dtype=np.float64)
        f = np.asarray(c.force_N, dtype=np.float64)
        if d.shape != f.shape or d.ndim != 1:
            raise ConfigError(f"{tag}: deformation_mm and force_N must be 1-D arrays of equal length")
        if len(d) < MIN_POINTS:
            raise ConfigError(f"{tag}: only {len(d)} point(s); need at least {MIN_POINTS} per curve")
        if not (np.all(np.isfinite(d)) and np.all(np.isfinite(f))):
            raise ConfigError(f"{tag}: deformation_mm/force_N contain non-finite values")
        if np.any(d < 0):
            raise ConfigError(f"{tag}: deformation_mm must be >= 0, got {float(d.min()):g}")
        steps = np.diff(d)
        if np.any(steps < 0):
            k = int(np.argmax(steps < 0)) + 1
            raise ConfigError(
                f"{tag}: deformation_mm must increase along the curve, but point {k} "
                f"({d[k]:g} mm) is below point {k - 1} ({d[k - 1]:g} mm)"
            )
        if not d[-1] > d[0]:
            raise ConfigError(f"{tag}: deformation_mm does not increase (all points at {d[0]:g} mm)")
        tol = 0.01 * float(np.max(np.abs(f)))
        if np.any(f < -tol):
            raise ConfigError(f"{tag}: force_N must be >= 0 (compression), got {float(f.min()):g} N")
        if not np.max(f) > 0:
            raise ConfigError(f"{tag}: force_N is zero everywhere; nothing to fit")
        if height_m is not None:
            frac = float(d.max()) * 1e-3 / height_m
            if frac > MAX_DEFORMATION_FRACTION:
                raise ConfigError(
                    f"{tag}: largest deformation {d.max():g} mm is {frac:.0%} of the sample height "
                    f"{height_m * 1e3:g} mm; at most {MAX_DEFORMATION_FRACTION:.0%} can be simulated"
                )


def _check_params(name: str, values: Mapping[str, float] | None, names: Sequence[str]) -> dict[str, float]:
    if values is None:
        return {}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"{name}: unknown key(s) {unknown}; the fitted constants are {list(names)}")
    return dict(values)


def fit_names(fit: str | Sequence[str]) -> tuple[str, ...]:
    """The constants a fit adjusts: a name of :data:`FIT_SETS` or a list of :data:`ALL_NAMES`."""
    if isinstance(fit, str):
        if fit not in FIT_SETS:
            raise ConfigError(f"fit = {fit!r} is not allowed; choose one of {sorted(FIT_SETS)} "
                              f"or a list of {list(ALL_NAMES)}")
        return FIT_SETS[fit]
    names = tuple(fit)
    bad = [k for k in names if k not in ALL_NAMES]
    if bad or not names or len(set(names)) != len(names):
        raise ConfigError(f"fit = {list(names)}: give distinct constants of {list(ALL_NAMES)}")
    return names


# =================================================================================================
# the fit
# =================================================================================================


def _uniform_params(base: TissueParams, values: Mapping[str, float]) -> TissueParams:
    data = {**to_dict(base), "stiffness_mode": "uniform", **{k: float(v) for k, v in values.items()}}
    return from_dict(TissueParams, data, where="calibration")


def equivalent_uniform(mesh: TetMesh, params: TissueParams) -> dict[str, float]:
    """Uniform constants equivalent (on average) to ``params`` on ``mesh``: the uniform-mode values as
    they are, or the means of the per-spring / per-node arrays a modulus-mode tissue builds."""
    relax = {k: float(getattr(params, k)) for k in RELAXATION_NAMES}
    if params.stiffness_mode == "uniform":
        return {**{k: float(getattr(params, k)) for k in PARAM_NAMES}, **relax}
    model = TissueModel.from_params(mesh, params)
    return {
        "k1_n_per_m": float(model.k1.mean()),
        "k2_n_per_m3": float(model.k2.mean()),
        "dl_c_m": float(model.dlc.mean()),
        "b0_n_s_per_m": float(model.b0.mean()),
        "b1_n_s_per_m2": float(model.b1.mean()),
        **relax,
    }

#: a starting value is kept at least this factor inside its bounds: trust-region reflective makes
#: almost no progress from a start on (or a hair inside) a bound
_START_MARGIN = 1.5


def _neutral_start(
    start: dict[str, float], lo: Mapping[str, float], hi: Mapping[str, float], max_def_m: float, keep: set[str],
    durations_s: Sequence[float] = (1.0,),
) -> dict[str, float]:
    """Replace values the fit cannot move from (0 or at a bound) by neutral ones; keep inside bounds.

    A base value at or below its lower bound (K2 = 0, b0 = 0 or b1 = 0 in the base parameters) would
    start the log-space fit where the parameter has no effect, so its derivative is zero and it never
    moves. Such values (unless given explicitly in ``keep``) become: K2 = 0.3 K1 / dl_c^2 (the cubic term
    30 % of the linear one at dl_c), b0 = K1 x 20 ms, b1 = b0 / largest measured deformation (the
    displacement term equal to b0 at that displacement), relaxation strength g = 0.5 with tau = the
    geometric mean of the tests' durations (between the rates, where a Maxwell branch tells them apart).
    Only the fitted constants (the keys of ``lo``) are changed.
    """
    out = dict(start)

    def low(k: str) -> bool:
        return k in lo and k not in keep and out[k] <= lo[k] * _START_MARGIN

    if low("relaxation_strength"):
        out["relaxation_strength"] = 0.5
        if "relaxation_time_s" in lo and "relaxation_time_s" not in keep:
            out["relaxation_time_s"] = float(np.exp(np.mean(np.log(durations_s))))

    if low("k2_n_per_m3"):
        out["k2_n_per_m3"] = 0.3 * out["k1_n_per_m"] / out["dl_c_m"] ** 2
    if low("b0_n_s_per_m"):
        out["b0_n_s_per_m"] = 0.02 * out["k1_n_per_m"]
    if low("b1_n_s_per_m2"):
        out["b1_n_s_per_m2"] = out["b0_n_s_per_m"] / max(max_def_m, 1e-6)
    for k in lo:
        a, b = lo[k] * _START_MARGIN, hi[k] / _START_MARGIN
        out[k] = float(np.clip(out[k], a, b)) if a < b else float(math.sqrt(lo[k] * hi[k]))
    return out


@dataclass(frozen=True)
class FitSettings:
    """How :func:`fit_compression` fits: what it adjusts, from where, within what, and its budget (SI units)."""

    #: every non-fitted field (density/mass, spring dashpot, ...); None: ``TissueParams()``. Non-fitted constants
    #: of :data:`ALL_NAMES` keep the base parameters' uniform equivalent
    base_params: TissueParams | None = None
    #: starting values (any subset of the fitted constants). None: the base parameters' uniform equivalent
    #: (:func:`equivalent_uniform`), then scaled to the data by one simulation: K1, K2 (and b0, b1 where fitted)
    #: multiplied by the least-squares factor between measured and simulated forces (with dl_c fixed that scales
    #: the whole force law, so the quasi-static force scales by the same factor). Given keys are used as they are
    #: (no scaling). Zero K2/b0/b1/g in the base parameters get neutral starting values (:func:`_neutral_start`);
    #: every start is kept a factor 1.5 inside its bounds
    init: Mapping[str, float] | None = None
    #: ``{name: (lo, hi)}`` overriding :func:`default_bounds` (:data:`DEFAULT_BOUNDS`, dl_c capped at half the mean
    #: edge length); must be > 0 (log space)
    bounds: Mapping[str, tuple[float, float]] | None = None
    #: hard budget of simulations (Jacobian columns included), >= 2
    max_evals: int = 200
    #: print one line per simulation to stderr
    progress: bool = False
    #: forward-difference step in log-parameter (a relative change of the parameter)
    diff_step: float = 0.02
    #: guesses needing more substeps per ``dt_s`` than this (or 4x the starting guess's, whichever is larger) get
    #: large residuals instead of a simulation
    max_substeps: int = 32
    #: force samples per simulated curve (interpolated at the measured deformations)
    samples: int = 150
    #: outer step of the simulations, s
    dt_s: float = 1e-3
    #: ``least_squares`` stopping tolerances (relative cost change; step size in log-parameter). The defaults stop
    #: once an iteration improves the cost by less than 0.1 %: a calibration against noisy data gains nothing from
    #: more digits, and each iteration costs 6 simulations
    ftol: float = 1e-3
    xtol: float = 1e-3
    #: the constants fitted: a set of :data:`FIT_SETS` or a list of :data:`ALL_NAMES`
    fit: str | Sequence[str] = "viscoelastic"


def _box(names: Sequence[str], bounds: Mapping[str, tuple[float, float]] | None,
         mesh: TetMesh) -> tuple[dict[str, float], dict[str, float]]:
    """(lo, hi) of each fitted constant: :func:`default_bounds` overridden by ``bounds``, checked."""
    bnd = {**default_bounds(mesh), **_check_params("bounds", bounds, names)}
    lo: dict[str, float] = {}
    hi: dict[str, float] = {}
    for name in names:
        try:
            a, b = (float(v) for v in bnd[name])
        except (TypeError, ValueError):
            raise ConfigError(f"bounds.{name} must be a pair (lo, hi), got {bnd[name]!r}") from None
        if not (math.isfinite(a) and math.isfinite(b) and 0.0 < a < b):
            raise ConfigError(f"bounds.{name} = ({a:g}, {b:g}) must satisfy 0 < lo < hi (finite)")
        lo[name], hi[name] = a, b
    return lo, hi


@dataclass
class _Measured:
    """The measured curves as the fit reads them, and the compression that simulates them all in one call."""

    curves: Sequence[CompressionCurve]
    d_mm: list[np.ndarray]
    f_N: list[np.ndarray]
    #: every curve's forces, concatenated (the residuals' order)
    f_all: np.ndarray
    #: largest measured deformation, m
    max_def_m: float
    #: each test's duration to that deformation, s
    durations_s: list[float]
    config: CompressionConfig
    #: the residual of a guess that is not simulated (unstable or too stiff), N
    penalty: float

    @classmethod
    def of(cls, curves: Sequence[CompressionCurve], mesh: TetMesh, settings: FitSettings) -> _Measured:
        z = mesh.nodes[:, 2]
        height = float(z.max() - z.min())
        validate_curves(curves, height)
        rates = tuple(float(c.rate_mm_per_min) for c in curves)
        if len(set(rates)) != len(rates):
            raise ConfigError(f"data: each rate must appear in one curve only, got rates {rates}")
        d_mm = [np.asarray(c.deformation_mm, dtype=np.float64) for c in curves]
        f_N = [np.asarray(c.force_N, dtype=np.float64) for c in curves]
        f_all = np.concatenate(f_N)
        max_def_m = max(float(d.max()) for d in d_mm) * 1e-3
        # simulate a hair beyond the last measured point (np.interp would clamp at the end anyway)
        frac = min(MAX_DEFORMATION_FRACTION, 1.005 * max_def_m / height)
        config = CompressionConfig(rates_mm_per_min=rates, deformation_fraction=frac, samples=int(settings.samples),
                                   dt_s=settings.dt_s)
        return cls(curves, d_mm, f_N, f_all, max_def_m, [max_def_m / (r * 1e-3 / 60.0) for r in rates], config,
                   10.0 * float(np.max(np.abs(f_all))) + 1.0)


class _Simulations:
    """The fit's simulations of the measured tests: residuals per guess, counted against the budget."""

    def __init__(self, mesh: TetMesh, base: TissueParams, data: _Measured, settings: FitSettings) -> None:
        self.mesh, self.base, self.data, self.settings = mesh, base, data, settings
        self.n_evals = 0
        self.substep_cap = int(settings.max_substeps)

    def substeps(self, values: dict[str, float]) -> int:
        """Substeps per outer step the explicit scheme needs for ``values``."""
        model = compression_model(self.mesh, _uniform_params(self.base, values))
        return max(1, math.ceil(self.settings.dt_s / (0.9 * model.critical_dt())))

    def residuals(self, values: dict[str, float]) -> np.ndarray | None:
        """Residuals for ``values`` (every constant of ALL_NAMES; one run_compression call), or None if
        unstable / too stiff."""
        if self.substeps(values) > self.substep_cap:
            return None
        if self.n_evals >= self.settings.max_evals:
            raise _BudgetExhausted
        self.n_evals += 1
        try:
            with np.errstate(all="ignore"):
                sim = run_compression(self.mesh, _uniform_params(self.base, values), self.data.config)
        except FloatingPointError:
            return None
        d = self.data
        r = np.concatenate([np.interp(dm, c.deformation_mm, c.force_N) - f for c, dm, f in zip(sim, d.d_mm, d.f_N)])
        return r if np.all(np.isfinite(r)) else None


def _start(sims: _Simulations, names: tuple[str, ...], box: tuple[dict, dict],
           init_given: dict[str, float]) -> dict[str, float]:
    """The fit's starting point, every constant of ALL_NAMES (see :attr:`FitSettings.init`); sets the substep cap
    from it."""
    lo, hi = box
    data = sims.data
    start = equivalent_uniform(sims.mesh, sims.base)  # every constant of ALL_NAMES; the non-fitted ones stay
    start.update(init_given)
    start = _neutral_start(start, lo, hi, data.max_def_m, set(init_given), data.durations_s)
    sims.substep_cap = max(int(sims.settings.max_substeps), 4 * sims.substeps(start))
    if init_given:
        return start
    r0 = sims.residuals(start)
    if r0 is None:
        return start
    f_sim = r0 + data.f_all
    denom = float(f_sim @ f_sim)
    scale = float(np.clip((f_sim @ data.f_all) / denom, 1e-3, 1e3)) if denom > 0 else 1.0
    for k in ("k1_n_per_m", "k2_n_per_m3", "b0_n_s_per_m", "b1_n_s_per_m2"):
        if k in names:
            start[k] = start[k] * scale
    if sims.settings.progress:
        print(f"calibrate: start scaled to the data by {scale:.4g}", file=sys.stderr)
    return _neutral_start(start, lo, hi, data.max_def_m, set(), data.durations_s)


class _LogProblem:
    """The least-squares problem in ``x = log(p / start)`` of the fitted constants: cached residuals, the best
    point seen, a forward-difference Jacobian that counts its simulations."""

    def __init__(self, sims: _Simulations, names: tuple[str, ...], box: tuple[dict, dict],
                 start: dict[str, float]) -> None:
        lo, hi = box
        self.sims, self.names = sims, names
        self.ref = np.array([start[k] for k in names])
        self.xlo = np.log(np.array([lo[k] for k in names]) / self.ref)
        self.xhi = np.log(np.array([hi[k] for k in names]) / self.ref)
        self.fixed = {k: v for k, v in start.items() if k not in names}
        self.cache: dict[bytes, np.ndarray] = {}
        self.best: dict = {"cost": math.inf, "values": None}

    @staticmethod
    def key(x: np.ndarray) -> bytes:
        return np.round(np.asarray(x, dtype=np.float64), 12).tobytes()

    def values_of(self, x: np.ndarray) -> dict[str, float]:
        return {k: float(v) for k, v in zip(self.names, self.ref * np.exp(x))}

    def fun(self, x: np.ndarray) -> np.ndarray:
        key = self.key(x)
        if key in self.cache:
            return self.cache[key]
        values = self.values_of(x)
        r = self.sims.residuals({**self.fixed, **values})
        if r is None:
            r = np.full(len(self.sims.data.f_all), self.sims.data.penalty)
        cost = 0.5 * float(r @ r)
        if cost < self.best["cost"]:
            self.best.update(cost=cost, values=values, x=np.array(x, dtype=np.float64))
        if self.sims.settings.progress:
            rms = math.sqrt(2.0 * cost / len(r))
            print(
                f"calibrate: sim {self.sims.n_evals:4d}  rmse {rms:.4g} N  "
                + "  ".join(f"{k.split('_')[0]}={v:.4g}" for k, v in values.items()),
                file=sys.stderr,
            )
        self.cache[key] = r
        return r

    def jac(self, x: np.ndarray) -> np.ndarray:
        f0 = self.fun(x)
        J = np.empty((len(f0), len(x)))
        step = self.sims.settings.diff_step
        for i in range(len(x)):
            h = step if x[i] + step <= self.xhi[i] else -step
            xp = np.array(x, dtype=np.float64)
            xp[i] += h
            J[:, i] = (self.fun(xp) - f0) / h
        return J

    def solve(self) -> tuple[bool, str]:
        """Run ``least_squares`` from the start (x = 0, strictly inside the box: see _neutral_start) within the
        budget; (success, message)."""
        from scipy.optimize import least_squares

        s = self.sims.settings
        try:
            sol = least_squares(self.fun, np.zeros(len(self.names)), jac=self.jac, bounds=(self.xlo, self.xhi),
                                method="trf", x_scale=1.0, ftol=s.ftol, xtol=s.xtol, gtol=1e-8, max_nfev=s.max_evals)
        except _BudgetExhausted:
            return False, f"stopped after max_evals = {s.max_evals} simulations (best point so far returned)"
        return bool(sol.status > 0), str(sol.message)


def _result(problem: _LogProblem, success: bool, message: str, t_start: float) -> CalibrationResult:
    """The :class:`CalibrationResult` of the best point ``problem`` has seen."""
    best = problem.best
    if best["values"] is None:
        raise FloatingPointError(
            "calibration: no stable simulation at any evaluated parameter set (check the start values)"
        )
    data = problem.sims.data
    fitted = best["values"]
    r_best = problem.cache[problem.key(best["x"])]
    if np.all(r_best == data.penalty):
        success = False
        message = "every simulation was unstable or too stiff; " + message
    f_sim_all = r_best + data.f_all
    ok = np.std(f_sim_all) > 0 and np.std(data.f_all) > 0
    corr = float(np.corrcoef(data.f_all, f_sim_all)[0, 1]) if ok else float("nan")
    per_rate, sims = {}, []
    k0 = 0
    for c, f in zip(data.curves, data.f_N):
        r = r_best[k0 : k0 + len(f)]
        per_rate[float(c.rate_mm_per_min)] = float(np.sqrt(np.mean(r**2)))
        sims.append(f + r)
        k0 += len(f)
    return CalibrationResult(
        params=dict(fitted),
        rmse_N=float(np.sqrt(np.mean(r_best**2))),
        correlation=corr,
        rmse_per_rate=per_rate,
        n_evals=problem.sims.n_evals,
        success=success,
        message=message,
        tissue_params=_uniform_params(problem.sims.base, {**problem.fixed, **fitted}),
        init={k: float(v) for k, v in zip(problem.names, problem.ref)},
        simulated_force_N=sims,
        wall_s=time.perf_counter() - t_start,
    )


def fit_compression(curves: Sequence[CompressionCurve], mesh: TetMesh,
                    settings: FitSettings = FitSettings()) -> CalibrationResult:
    """Fit uniform-mode constants (``settings.fit``: a set of :data:`FIT_SETS` or a list of :data:`ALL_NAMES`) to
    measured compression curves.

    ``curves``: measured curves (one per rate): deformation in mm, force in N, constant plate speed from zero
    deformation, as :func:`~.experiments.read_compression_csv` returns them. ``mesh``: the sample's mesh; its
    z-extent is the sample height. ``settings``: :class:`FitSettings`.
    """
    t_start = time.perf_counter()
    max_evals = settings.max_evals
    if isinstance(max_evals, bool) or not isinstance(max_evals, (int, np.integer)) or max_evals < 2:
        raise ConfigError(f"max_evals must be an integer >= 2, got {max_evals!r}")
    base = settings.base_params or TissueParams()
    names = fit_names(settings.fit)
    init_given = _check_params("init", settings.init, names)
    box = _box(names, settings.bounds, mesh)
    for name, v in init_given.items():
        if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and v > 0):
            raise ConfigError(f"init.{name} must be a finite number > 0, got {v!r}")
    sims = _Simulations(mesh, base, _Measured.of(curves, mesh, settings), settings)
    problem = _LogProblem(sims, names, box, _start(sims, names, box, init_given))
    return _result(problem, *problem.solve(), t_start)


# =================================================================================================
# CLI
# =================================================================================================


def tissue_config_dict(
    result: CalibrationResult, mesh_section: Mapping, data_path: str | Path | None = None
) -> dict:
    """The tissue config written by the CLI: ``mesh`` (as given), ``tissue`` (uniform), ``calibration``."""
    tp = result.tissue_params
    tissue = {"stiffness_mode": "uniform"}
    if tp.mass_kg is not None:
        tissue["mass_kg"] = tp.mass_kg
    else:
        tissue["density_kg_m3"] = tp.density_kg_m3
    tissue.update({k: float(getattr(tp, k)) for k in ALL_NAMES})
    tissue["spring_damping_time_s"] = tp.spring_damping_time_s
    tissue["gravity_m_per_s2"] = list(tp.gravity_m_per_s2)
    calib = {
        "data": str(Path(data_path).resolve()) if data_path is not None else None,
        "rmse_N": float(result.rmse_N),
        "correlation": float(result.correlation),
        "rmse_per_rate_N": {f"{r:g}": float(v) for r, v in result.rmse_per_rate.items()},
        "n_evals": int(result.n_evals),
        "success": bool(result.success),
        "message": result.message,
        "note": "fitted with gravity off; uniform-mode constants are specific to this mesh and resolution",
    }
    return {"mesh": dict(mesh_section), "tissue": tissue, "calibration": calib}
