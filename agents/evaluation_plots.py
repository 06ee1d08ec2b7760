"""The evaluation's plots: success and peak pinch against friction, one curve per policy (``success_vs_mu.png``,
``pinch_vs_mu.png``), each point with its 95 % interval."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..envs.core import GraspLiftConfig
from ..physics.config import needs_extra, save_figure
from .controllers import display_name


_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")
_LINES = ("-", "--", "-.", ":")


def _style(k: int) -> dict[str, Any]:
    """Distinct marker and line style per policy (curves often coincide, e.g. at success rate 1)."""
    return {"marker": _MARKERS[k % len(_MARKERS)], "linestyle": _LINES[k % len(_LINES)],
            "markersize": 7 - 0.6 * (k % 4), "alpha": 0.9}


def _dodge(k: int, n: int) -> float:
    """Sideways offset of policy k of n, so that coinciding points of different policies stay visible."""
    return (k - (n - 1) / 2) * 0.006


def _errorbars(ax, results, key: str, ci_key: str, suffix: str = "") -> list[str]:
    """One error-bar curve per policy of ``row[key]`` with ``row[ci_key]`` as its interval (policies
    dodged sideways); returns the line colours."""
    colours = []
    for k, pol in enumerate(results):
        rows = pol["rows"]
        mus = np.array([r["mu"] for r in rows]) + _dodge(k, len(results))
        value = np.array([r[key] for r in rows])
        ci = np.array([r[ci_key] for r in rows])
        line = ax.errorbar(mus, value, yerr=[value - ci[:, 0], ci[:, 1] - value], capsize=2, elinewidth=0.8,
                           label=display_name(pol["name"]) + suffix, **_style(k))
        colours.append(line[0].get_color())
    return colours


def _finish(ax, fig, xlabel: str, ylabel: str, title: str, results, intervals: str, path: Path) -> Path:
    n = sorted({r["episodes"] for pol in results for r in pol["rows"]})
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title} (n = {'/'.join(map(str, n))} episodes per point, {intervals})", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)  # beside, not over, the data
    fig.tight_layout()
    return save_figure(fig, path)


def plot_success(results: list[dict[str, Any]], config: GraspLiftConfig, path: Path) -> Path:
    """Success rate against mu per policy, the training range of mu shaded; written to ``path``."""
    with needs_extra("train", "the evaluation's plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = config.randomization.mu_range
    fig, ax = plt.subplots(figsize=(10.0, 4.4))
    ax.axvspan(lo, hi, color="tab:gray", alpha=0.15, label=f"training range of mu [{lo:g}, {hi:g}]")
    _errorbars(ax, results, "success_rate", "success_ci95")
    ax.set_ylim(-0.05, 1.05)
    return _finish(ax, fig, "friction coefficient mu", "success rate (slip-free lift)",
                   "Grasp-and-lift success vs friction", results, "95% Wilson intervals", path)


def plot_pinch(results: list[dict[str, Any]], oracle_curve: dict[str, Any], path: Path) -> Path:
    """Mean peak pinch (N) against mu per policy, failed episodes marked, beside the oracle's minimal force;
    written to ``path``."""
    with needs_extra("train", "the evaluation's plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10.0, 4.4))
    colours = _errorbars(ax, results, "mean_peak_pinch_N", "peak_pinch_ci95_N", " (mean peak, all episodes)")
    failed_label = "a failed episode's peak pinch"
    for k, (pol, colour) in enumerate(zip(results, colours)):
        dodge = _dodge(k, len(results))
        for r in pol["rows"]:  # failed episodes are in the mean: show them
            bad = [p for p, ok in zip(r["per_episode"]["peak_pinch_N"], r["per_episode"]["success"]) if not ok]
            if bad:
                ax.scatter([r["mu"] + dodge] * len(bad), bad, marker="x", s=14, color=colour, linewidths=0.8,
                           label=failed_label, zorder=3)
                failed_label = None
    limit = oracle_curve["search_limit_N"]
    held = [f if f < limit - 1e-9 else np.nan for f in oracle_curve["minimal_force_N"]]
    ax.plot(oracle_curve["mu"], held, color="black", linestyle="--", marker="+",
            label=f"minimal slip-free force (oracle bisection; none up to {limit:g} N where missing)")
    ax.set_ylim(bottom=0)
    return _finish(ax, fig, "friction coefficient mu", "peak pinch force (N)", "Peak pinch force vs friction",
                   results, "95% bootstrap intervals; x: failed episodes", path)
