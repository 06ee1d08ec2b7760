"""Specs of the paper-experiment commands (cli/experiments.py): outputs that load, with physics in them."""

from __future__ import annotations

import csv
import json

import numpy as np

from msdgrasp.cli.main import main


def _read_csv(path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k != "phase"}


def test_grasp_sphere_writes_a_rising_force_curve_with_a_hertz_like_onset(tmp_path, capsys):
    """Fig. 7: closing the jaws on the free sphere, the pinch force rises with the jaw displacement, convex at
    first as the contact patches grow (Hertz, F ~ d^1.5: F(d/4) = 0.35 F(d/2); require < 0.5; measured
    0.41). Later the Maxwell branch relaxes (tau 10 s against a 17 s closing) and the patches reach the
    jaw faces, and the curve bends over (measured 42 N at half travel, 64 N at the end)."""
    assert main(["experiment", "grasp-sphere", "--out", str(tmp_path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    data = _read_csv(tmp_path / "grasp_sphere.csv")
    assert (tmp_path / "grasp_sphere.png").stat().st_size > 10_000
    d, f = data["jaw_displacement_mm"], data["pinch_force_N"]
    assert np.all(np.diff(d) >= 0) and d[-1] > 10.0
    quarter, half = np.searchsorted(d, d[-1] / 4), np.searchsorted(d, d[-1] / 2)
    assert 0.0 < f[quarter] < 0.5 * f[half] < 0.5 * f[-1]
    assert np.all(np.diff(f) > -0.05 * f.max())  # rises, up to the steps of node-based contact
    assert abs(summary["final_pinch_N"] - f[-1]) < 1e-4 * f[-1]


def test_grasp_protocol_writes_one_curve_per_mu_and_more_friction_holds_longer(tmp_path, capsys):
    """Fig. 9: the spleen protocol at two frictions; each CSV covers close, hold and pull, and the pull
    force the grasp transmits before it is lost is larger at the higher friction."""
    assert main(["experiment", "grasp", "--mu", "0.3", "--mu", "0.8", "--pull-time", "4", "--quiet",
                 "--out", str(tmp_path)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["runs"]) == 2 and (tmp_path / "grasp.png").is_file()
    peak = {}
    for mu in ("0.3", "0.8"):
        data = _read_csv(tmp_path / f"grasp_mu{mu}.csv")
        assert data["time_s"][-1] > 12.0  # 5 s close + 7 s hold, then the pull
        peak[mu] = np.max(np.abs(data["pull_force_N"]))
    assert peak["0.8"] > peak["0.3"] > 0.0


def test_pinch_hold_refuses_a_missing_tissue_config_in_one_line(tmp_path, capsys):
    assert main(["experiment", "pinch-hold", "--config", str(tmp_path / "nope.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--config" in err[0] and "nope.yaml" in err[0]
