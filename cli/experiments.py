"""Command-line handlers of the paper's experiments and the calibration (``msdgrasp experiment ...``,
``msdgrasp calibrate``): read the arguments, call the physics, write the outputs atomically, print a JSON
summary. The physics modules hold no argument parsing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..experiments.calibration import FitSettings, fit_compression, tissue_config_dict, validate_curves
from ..physics.config import (TISSUE_FILE, ConfigError, atomic_write_text, builtin_config, check_range, from_dict,
                              read_config_file, require_extra, write_yaml)
from ..experiments.compression import (
    CompressionConfig,
    compression_verdicts,
    load_tissue_params,
    plot_compression,
    read_compression_csv,
    run_compression,
    write_compression_csv,
)
from ..experiments.grasp import (
    GraspProtocol,
    grasp_verdicts,
    plot_grasp,
    plot_sphere_grasp,
    run_grasp,
    run_sphere_grasp,
    write_grasp_csv,
    write_sphere_grasp_csv,
)
from ..physics.mesh_io import mesh_spec
from ..physics.scenario import sphere_scene, spleen_scene


def resolution_arg(value: str | int | None) -> str | int | None:
    """A mesh resolution argument: a name (coarse, ...) or a node count."""
    if value is None:
        return None
    return int(value) if str(value).isdigit() else value


def _require_viz(what: str, progress: bool) -> None:
    """The plot and the progress bar of an experiment: a missing one stops it before the run, not after."""
    require_extra("viz", f"msdgrasp experiment {what}", "matplotlib", *(("tqdm",) if progress else ()))


def compress_cli(args: argparse.Namespace) -> int:
    """``msdgrasp experiment compress``: sphere between plates at each rate (CSV + PNG)."""
    _require_viz("compress", progress=not args.quiet)
    cfg_path = args.config or builtin_config("tissue/sphere.yaml")
    params = load_tissue_params(cfg_path)
    overrides = {} if args.diameter_mm is None else {"diameter_m": args.diameter_mm * 1e-3}
    mesh = mesh_spec(cfg_path).build(resolution_arg(args.resolution), **overrides)
    cfg = from_dict(
        CompressionConfig,
        {
            "rates_mm_per_min": list(args.rate or (6.0, 60.0)),
            "deformation_fraction": args.deformation,
            "samples": args.samples,
            **({} if args.plate_mu is None else {"plate_mu": args.plate_mu}),
        },
        where="compress",
    )
    curves = run_compression(mesh, params, cfg, progress=not args.quiet)
    out = Path(args.out)
    csv = write_compression_csv(curves, out / "compress.csv")
    png = plot_compression(curves, out / "compress.png", title=f"Compression of {mesh.name} ({mesh.n_nodes} nodes)")
    height_mm = float(np.ptp(mesh.nodes[:, 2])) * 1e3
    verdicts = compression_verdicts(curves, height_mm, (params.relaxation_strength, params.relaxation_time_s))
    summary = {
        "csv": str(csv),
        "png": str(png),
        "final_force_N": {f"{c.rate_mm_per_min:g}": round(float(c.force_N[-1]), 4) for c in curves},
        "final_deformation_mm": round(float(curves[0].deformation_mm[-1]), 3),
        "min_volume_ratio": round(min(float(c.min_volume_ratio.min()) for c in curves), 4),
        "verdicts": verdicts,
    }
    _print_verdicts(verdicts)
    print(json.dumps(summary, indent=2))
    return 0


def _print_verdicts(verdicts: list[dict]) -> None:
    """One line per claim of the paper on stderr (stdout carries the JSON summary)."""
    for v in verdicts:
        print(f"{v['verdict']:>5}  {v['claim']}: {v['numbers']}", file=sys.stderr)


def grasp_cli(args: argparse.Namespace) -> int:
    """``msdgrasp experiment grasp``: the spleen protocol per mu (CSV each, one PNG, a summary JSON)."""
    _require_viz("grasp", progress=not args.quiet)
    protocol = GraspProtocol(**({"pull_time_s": args.pull_time} if args.pull_time is not None else {}))
    mus = args.mu or [0.4, 0.6, 0.8]
    for mu in mus:
        check_range("--mu", mu, 0.0, 10.0, lo_inclusive=False)  # (the env's mu range)
    scene = spleen_scene(args.config, args.grasper, resolution_arg(args.resolution))
    runs = run_grasp(scene, mus, protocol, progress=not args.quiet)
    out = Path(args.out)
    files = []
    for r in runs:
        files.append(str(write_grasp_csv(r, out / f"grasp_mu{r.mu:g}.csv")))
    files.append(str(plot_grasp(runs, out / "grasp.png", protocol)))
    verdicts = grasp_verdicts(
        runs, scene.model.params.relaxation_time_s if scene.model.params.relaxation_strength > 0 else None)
    summary = {"files": files, "runs": [r.summary for r in runs], "verdicts": verdicts}
    _print_verdicts(verdicts)
    atomic_write_text(out / "grasp_summary.json", json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


def grasp_sphere_cli(args: argparse.Namespace) -> int:
    """``msdgrasp experiment grasp-sphere``: pinch force vs jaw displacement on the sphere (CSV + PNG)."""
    _require_viz("grasp-sphere", progress=False)
    scene = sphere_scene(args.config, args.grasper, resolution_arg(args.resolution))
    data = run_sphere_grasp(scene)
    out = Path(args.out)
    csv = write_sphere_grasp_csv(data, out / "grasp_sphere.csv")
    png = plot_sphere_grasp(data, out / "grasp_sphere.png",
                            f"Three-jaw grasp of the test sphere ({scene.mesh.n_nodes} nodes; cf. paper Fig. 7)")
    print(json.dumps({"csv": str(csv), "png": str(png), "final_pinch_N": float(data["pinch_force_N"][-1]),
                      "final_displacement_mm": float(data["jaw_displacement_mm"][-1])}, indent=2))
    return 0


def calibrate_cli(args: argparse.Namespace) -> int:
    """``msdgrasp calibrate --data CSV [--config YAML] [--out YAML] [--max-evals N] [--fit SET] [--quiet]``."""
    max_evals = args.max_evals
    if isinstance(max_evals, bool) or not isinstance(max_evals, int) or max_evals < 10:
        raise ConfigError(f"--max-evals must be an integer >= 10, got {max_evals!r}")
    out = Path(args.out)
    if out.is_dir():
        raise ConfigError(f"--out {out} is a folder; give the path of the tissue config (YAML) to write")
    cfg_path = Path(args.config) if args.config is not None else builtin_config("tissue/sphere.yaml")
    base = load_tissue_params(cfg_path)
    spec = mesh_spec(cfg_path)
    mesh = spec.build()
    mesh_section = read_config_file(cfg_path, TISSUE_FILE)["mesh"]
    if spec.is_file:  # the written config lives elsewhere: it names the mesh file by its absolute path
        mesh_section = {**mesh_section, "shape": spec.shape}

    data_path = Path(args.data)
    curves = read_compression_csv(data_path)
    z = mesh.nodes[:, 2]
    validate_curves(curves, float(z.max() - z.min()), where=str(data_path))

    try:
        settings = FitSettings(base_params=base, max_evals=max_evals, progress=not args.quiet, fit=args.fit)
        result = fit_compression(curves, mesh, settings)
    except FloatingPointError as exc:
        raise ConfigError(f"{exc}; config {cfg_path}") from None
    doc = tissue_config_dict(result, mesh_section, data_path)
    written = write_yaml(out, doc)
    # the written file must load back
    load_tissue_params(written)
    summary = {"out": str(written), **result.summary()}
    print(json.dumps(summary, indent=2))
    return 0


def fem_cli(args: argparse.Namespace) -> int:
    """``msdgrasp experiment fem``: the MSD against a finite-element reference on the same meshes (JSON + CSV + PNG)."""
    from ..experiments.fem import CASES, CUBE_CELLS, ComparisonSettings, compare, plot_comparison, write_comparison_csv
    from ..physics.config import check_range

    cases = tuple(args.case or ComparisonSettings().cases)
    for c in cases:
        if c not in CASES:
            raise ConfigError(f"--case {c!r} is not allowed; choose from {', '.join(CASES)}")
    resolutions = tuple(args.resolution or ("coarse", "fine"))
    for r in resolutions:
        if r not in CUBE_CELLS:
            raise ConfigError(f"--resolution {r!r} is not allowed; choose from {', '.join(CUBE_CELLS)}")
    check_range("--poisson", args.poisson, 0.0, 0.5, hi_inclusive=False)
    require_extra("fem", "msdgrasp experiment fem", "skfem")
    require_extra("viz", "msdgrasp experiment fem", "matplotlib")
    params = load_tissue_params(args.config or builtin_config("tissue/spleen.yaml"))
    result = compare(params, ComparisonSettings(cases=cases, resolutions=resolutions, poisson=args.poisson,
                                                hertz=not args.no_hertz, quadratic=not args.no_quadratic,
                                                converge=not args.no_converge,
                                                large=not args.small_strain_only))
    out = Path(args.out)
    csv = write_comparison_csv(result["rows"], out / "fem.csv")
    png = plot_comparison(result, out / "fem.png")
    summary = {"csv": str(csv), "png": str(png), **result}
    atomic_write_text(out / "fem.json", json.dumps(summary, indent=2))
    _print_verdicts(result["verdicts"])
    print(json.dumps({k: v for k, v in summary.items() if k != "curves"}, indent=2))
    return 0
