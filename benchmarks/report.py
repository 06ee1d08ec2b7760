"""The benchmark report of ``msdgrasp bench``: the speed targets (TARGETS), pass/fail flags, the machine, a
markdown table and the log-log scaling plot (benchmarks/bench.py measures; this module only reads reports).
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

import numpy as np

from .harness import round_sig

#: batch size of the batched physics measurements: a full lane block (physics/integrator.py), so the
#: per-tissue figure is what the SIMD-across-tissues path delivers
BATCH = 64
#: vector-env sizes of the env benchmark (``--quick`` skips the largest)
ENV_SIZES = (1, 16, 64, 256)

TARGETS = {
    "coarse_us_per_ms": 10.0,  # >= 100x real time
    "fine_us_per_ms": 200.0,  # >= 5x real time
    "contact_overhead": 0.50,  # contact adds <= 50 %
    "coarse_contact_us_per_ms": 10.0,  # >= 100x real time with contact
    "mujoco_speedup": 10.0,  # >= 10x faster than MuJoCo flex at equal nodes
    "env_single_steps_per_s": 1000.0,
    "env_batched_steps_per_s": 2000.0,
    "gpu_agent_steps_per_s": 200_000.0,  # float64, with contact, batch >= 4096
}


# ------------------------------------------------------------------------------------------------
# targets, report
# ------------------------------------------------------------------------------------------------


def _target(value, limit, kind: str, unit: str, note: str = "", cpu_value=None) -> dict:
    def ok(v):
        return None if v is None else bool(v <= limit if kind == "<=" else v >= limit)

    d = {"value": value, "target": f"{kind} {round_sig(limit)}", "unit": unit, "pass": ok(value)}
    if cpu_value is not None:  # the same from process CPU time (less sensitive to a busy machine)
        d["value_cpu_time"] = cpu_value
        d["pass_cpu_time"] = ok(cpu_value)
    if note:
        d["note"] = note
    return d


def evaluate_targets(report: dict) -> dict:
    """Pass/fail flags against TARGETS (wall-clock medians; CPU-time values alongside)."""
    t: dict[str, dict] = {}
    ph = report.get("physics", {})
    nc = {r["resolution"]: r for r in ph.get("no_contact", [])}
    co = {r["resolution"]: r for r in ph.get("contact", [])}
    if "coarse" in nc:
        r = nc["coarse"]
        t["coarse_physics_le_10us_per_ms"] = _target(r["single_us_per_ms"], TARGETS["coarse_us_per_ms"], "<=",
                                                     "us per simulated ms", ">= 100x real time, one tissue",
                                                     r["single_cpu_us_per_ms"])
    if "fine" in nc:
        r = nc["fine"]
        t["fine_physics_le_200us_per_ms"] = _target(r["single_us_per_ms"], TARGETS["fine_us_per_ms"], "<=",
                                                    "us per simulated ms", ">= 5x real time, one tissue",
                                                    r["single_cpu_us_per_ms"])
    if "coarse" in co:
        r = co["coarse"]
        if "overhead_single" in r:
            cpu = round_sig(r["single_cpu_us_per_ms"] / nc["coarse"]["single_cpu_us_per_ms"] - 1.0)
            t["coarse_contact_overhead_le_50pct"] = _target(r["overhead_single"], TARGETS["contact_overhead"], "<=",
                                                            "fraction", "contact / no-contact - 1, one tissue", cpu)
        t["coarse_contact_ge_100x_realtime"] = _target(r["single_us_per_ms"], TARGETS["coarse_contact_us_per_ms"],
                                                       "<=", "us per simulated ms", "one tissue, jaws closed",
                                                       r["single_cpu_us_per_ms"])
        t[f"coarse_contact_ge_100x_realtime_batch{BATCH}"] = _target(
            r[f"batch{BATCH}_per_tissue_us_per_ms"], TARGETS["coarse_contact_us_per_ms"], "<=",
            "us per simulated ms", f"per tissue in a batch of {BATCH} on one core, jaws closed")
    mj = ph.get("mujoco") or {}
    rows = [r for r in mj.get("rows", []) if r.get("speedup_vs_mujoco")]
    if rows:
        worst = min(rows, key=lambda r: r["speedup_vs_mujoco"])
        t["mujoco_speedup_ge_10x"] = _target(worst["speedup_vs_mujoco"], TARGETS["mujoco_speedup"], ">=",
                                             "MuJoCo time / ours", f"one tissue, worst of {len(rows)} resolutions "
                                             f"({worst['resolution']})")
        batched = [r for r in rows if r.get("speedup_batch_per_tissue")]
        if batched:
            worst_b = min(batched, key=lambda r: r["speedup_batch_per_tissue"])
            t[f"mujoco_speedup_ge_10x_batch{BATCH}"] = _target(
                worst_b["speedup_batch_per_tissue"], TARGETS["mujoco_speedup"], ">=", "MuJoCo time / ours",
                f"ours per tissue in a batch of {BATCH}, worst resolution ({worst_b['resolution']})")
    env = report.get("env")
    if env:
        s = env["single"]
        t["env_single_ge_1000_steps_per_s"] = _target(s["steps_per_s"], TARGETS["env_single_steps_per_s"], ">=",
                                                      "agent steps/s", "GraspLiftEnv, coarse", s.get("cpu_steps_per_s"))
        batched = [r for r in env["vector"] if r["n_envs"] > 1]
        if batched:
            best = max(batched, key=lambda r: r["total_steps_per_s"])
            t["env_batched_ge_2000_steps_per_s"] = _target(best["total_steps_per_s"],
                                                           TARGETS["env_batched_steps_per_s"], ">=",
                                                           "aggregate agent steps/s",
                                                           f"best batched vector env (N={best['n_envs']})",
                                                           best.get("cpu_total_steps_per_s"))
    # judged on the whole task step (physics, observation, reward, autoreset): the target's "agent step"
    gpu = (report.get("gpu") or {}).get("task_rows") or []
    big = [r for r in gpu if r["contact"] and r["batch"] >= 4096 and r["dtype"] == "float64"]
    if report.get("gpu", {}).get("available") and big:
        best = max(big, key=lambda r: r["agent_steps_per_s"])
        t["gpu_ge_200k_agent_steps_per_s"] = _target(best["agent_steps_per_s"], TARGETS["gpu_agent_steps_per_s"],
                                                     ">=", "agent steps/s",
                                                     f"task step, float64, contact, batch {best['batch']}")
    return t


def machine_info() -> dict:
    import numba

    info = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    try:
        info["load_average_1min"] = round_sig(os.getloadavg()[0])
    except OSError:
        pass
    return info


def _no_contact_section(ph: dict) -> list[str]:
    b = BATCH
    lines = ["## Physics without contact (us of compute per simulated ms)", "",
             f"| resolution | nodes | springs | n_sub | single | x real time | batch {b} total | per tissue "
             f"| ns per spring and substep: single / batch {b} |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in ph["no_contact"]:
        lines.append(f"| {r['resolution']} | {r['nodes']} | {r['springs']} | {r['n_sub']} | "
                     f"{r['single_us_per_ms']} | "
                     f"{r['single_realtime_factor']} | {r[f'batch{b}_total_us_per_ms']} | "
                     f"{r[f'batch{b}_per_tissue_us_per_ms']} | {r.get('single_ns_per_spring_substep', '-')} / "
                     f"{r.get(f'batch{b}_ns_per_spring_substep', '-')} |")
    s = ph["scaling"]
    lines += ["", f"Log-log exponent of cost vs nodes: {s['exponent_us_per_ms_vs_nodes']} per simulated ms, "
                  f"{s['exponent_us_per_substep_vs_nodes']} per substep.", ""]
    return lines


def _contact_section(ph: dict) -> list[str]:
    b = BATCH
    lines = ["## Physics with contact (jaws closed on the inferior pole)", "",
             f"| resolution | nodes | n_sub | contact nodes | single | x real time | overhead "
             f"| batch {b} total | per tissue |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in ph["contact"]:
        lines.append(f"| {r['resolution']} | {r['nodes']} | {r['n_sub']} | {r['contact_nodes']} | "
                     f"{r['single_us_per_ms']} | {r['single_realtime_factor']} | {r.get('overhead_single', '-')} | "
                     f"{r[f'batch{b}_total_us_per_ms']} | {r[f'batch{b}_per_tissue_us_per_ms']} |")
    lines.append("")
    for r in ph["contact"]:
        if r.get("float32"):
            f = r["float32"]
            lines += [f"float32 (`Simulation(precision=\"float32\")`, {r['resolution']}): "
                      f"{f['single_us_per_ms']} us per simulated ms for one tissue, "
                      f"{f[f'batch{b}_per_tissue_us_per_ms']} per tissue of {b}; against float64 from the same "
                      f"grasp over {f['compare_ms']} ms: positions within {f['max_position_error_m']} m, pinch "
                      f"within {f['pinch_rel_error']} relative, {f['same_contact_state']} of the nodes in the "
                      "same contact state.", ""]
    return lines


def _numpy_section(nr: dict) -> list[str]:
    cc = nr["cross_check"]
    lines = ["## NumPy reference", "",
             f"Cross-check ({cc['resolution']}): max rel. force diff {cc['max_rel_diff_forces']:.2e}, "
             f"Maxwell {cc['max_rel_diff_maxwell_forces']:.2e}, displacement after {cc['state_steps_ms']} ms "
             f"{cc['max_rel_diff_displacement']:.2e}.", "",
             "| resolution | nodes | NumPy us/ms | ours us/ms | ours/NumPy |", "|---|---|---|---|---|"]
    for r in nr["rows"]:
        lines.append(f"| {r['resolution']} | {r['nodes']} | {r['numpy_us_per_ms']} | {r['numba_us_per_ms']} | "
                     f"{r['ratio_ours_over_numpy']} |")
    return lines + [""]


def _mujoco_section(mj: dict) -> list[str]:
    b = BATCH
    lines = ["## MuJoCo flex", ""]
    if not mj["available"]:
        return lines + [f"Not available: {mj['reason']}", ""]
    lines += [f"MuJoCo {mj['version']}: {mj['model']}.", "",
              f"| resolution | nodes | MuJoCo us/ms | ours us/ms | ours/MuJoCo | ours, batch {b}, per tissue "
              "| MuJoCo/ours (batched) | finite |", "|---|---|---|---|---|---|---|---|"]
    for r in mj["rows"]:
        if "error" in r:
            lines.append(f"| {r['resolution']} | - | error: {r['error']} | | | | | |")
        else:
            lines.append(f"| {r['resolution']} | {r['nodes']} | {r['mujoco_us_per_ms']} | "
                         f"{r['ours_us_per_ms']} | {r['ratio_ours_over_mujoco']} | "
                         f"{r.get(f'ours_batch{b}_per_tissue_us_per_ms', '-')} | "
                         f"{r.get('speedup_batch_per_tissue', '-')} | {r['finite']} |")
    return lines + [""]


def _env_section(env: dict) -> list[str]:
    lines = ["## Env (agent steps/s, coarse spleen, random actions)", "",
             "| env | N | total steps/s | per env steps/s |", "|---|---|---|---|",
             f"| GraspLiftEnv | 1 | {env['single']['steps_per_s']} | {env['single']['steps_per_s']} |"]
    for r in env["vector"]:
        lines.append(f"| GraspLiftVectorEnv | {r['n_envs']} | {r['total_steps_per_s']} | "
                     f"{r['per_env_steps_per_s']} |")
    return lines + [""]


def _gpu_section(gpu: dict) -> list[str]:
    lines = ["## GPU (agent steps/s of a device-resident batch, 33 physics ms per agent step)", ""]
    if not gpu["available"]:
        lines += [f"Not measured: {gpu['reason']}.", ""]
    if gpu["rows"]:
        lines += ["| batch | contact | dtype | agent steps/s | ms per agent step |", "|---|---|---|---|---|"]
        lines += [f"| {r['batch']} | {'yes' if r['contact'] else 'no'} | {r['dtype']} | {r['agent_steps_per_s']} "
                  f"| {r['ms_per_agent_step']} |" for r in gpu["rows"]]
        lines.append("")
    if gpu.get("task_rows"):
        lines += ["The whole task step (CudaGraspLiftCore: physics, observation, reward, autoreset):", "",
                  "| batch | envs in contact | dtype | agent steps/s | ms per agent step |",
                  "|---|---|---|---|---|"]
        lines += [f"| {r['batch']} | {r['contact_fraction']} | {r['dtype']} | {r['agent_steps_per_s']} "
                  f"| {r['ms_per_agent_step']} |" for r in gpu["task_rows"]]
        lines.append("")
    return lines


def _cpu_reference_section(cpu: dict, gpu: dict | None) -> list[str]:
    measured = gpu or {}
    gpu_rows = measured.get("rows", []) if measured.get("available") else []
    gpu_task = measured.get("task_rows", []) if measured.get("available") else []
    lines = [f"Beside it, {cpu['device']} of the same machine: the same grasped tissues and task step (GPU / CPU: "
             "over the float64 GPU row with contact at the same batch):", "",
             "| what | batch | agent steps/s | ms per agent step | GPU / CPU |", "|---|---|---|---|---|"]
    for kind, rows, against in (("physics", cpu["rows"], gpu_rows), ("task", cpu["task_rows"], gpu_task)):
        for r in rows:
            ratio = speedup(r, against)
            lines.append(f"| {kind} | {r['batch']} | {r['agent_steps_per_s']} | {r['ms_per_agent_step']} "
                         f"| {'-' if ratio is None else f'{ratio}x'} |")
    return lines + [""]


def _learners_section(learners: dict) -> list[str]:
    lines = ["## Learners on the GPU task (agent steps/s, training included)", ""]
    if "env_steps_per_s" not in learners:
        return lines + [f"Not measured: {learners['reason']}.", ""]
    return lines + [f"Batch {learners['batch']}, {learners['agent_steps']} agent steps, "
                    f"torch on {learners['torch_device']}.",
                    "", "| env alone | rsl-rl PPO | SB3 PPO | SB3 / rsl-rl |", "|---|---|---|---|",
                    f"| {learners['env_steps_per_s']} | {learners['rsl_steps_per_s']} | "
                    f"{learners['sb3_steps_per_s']} | {learners['sb3_over_rsl']} |", ""]


def _precision_section(prec: dict) -> list[str]:
    lines = ["## float32 against float64 (the GPU task, same seed and scripted grasp, one episode)", ""]
    if "max_position_diff_m" not in prec:
        return lines + [f"Not measured: {prec['reason']}.", ""]
    where = "a GPU" if prec["available"] else f"numba's CUDA simulator ({prec['reason'].split(':')[0]})"
    lines += [f"On {where}: spleen resolution {prec['resolution']}, {prec['num_envs']} envs, "
              f"{prec['agent_steps']} agent steps, {prec['env_steps_in_contact']} env steps with contact.",
              "", "| measure | value |", "|---|---|"]
    lines += [f"| {k} | {prec[k]:.3g} |" for k in ("max_position_diff_m", "max_reward_diff", "max_obs_diff",
                                                  "max_pinch_rel_diff", "contact_state_agreement")]
    lines += [f"| {k} | {prec[k]} |" for k in ("envs_ended_on_another_step", "envs_with_another_outcome")]
    return lines + [""]


def _targets_section(targets: dict) -> list[str]:
    lines = ["## Targets", "", "| target | value (wall) | limit | pass | value (CPU time) | pass (CPU) |",
             "|---|---|---|---|---|---|"]
    yn = {True: "yes", False: "NO", None: "-"}
    for k, v in targets.items():
        lines.append(f"| {k} | {v['value']} | {v['target']} | {yn[v['pass']]} | {v.get('value_cpu_time', '-')} | "
                     f"{yn[v.get('pass_cpu_time')]} |")
    return lines + [""]


def markdown(report: dict) -> str:
    """The bench report as markdown: the machine, then a section per part the report holds."""
    lines = [f"# msdgrasp bench {report['what']}{' (quick)' if report['quick'] else ''}", ""]
    m = report["machine"]
    lines += [f"Python {m['python']}, NumPy {m['numpy']}, numba {m['numba']}, {m['cpu_count']} CPUs, "
              f"{m['platform']}; load {m.get('load_average_1min', '?')}; total {report['elapsed_s']} s.", ""]
    ph = report.get("physics", {})
    # (physics part, its section): each where the report holds it
    for key, section in (("no_contact", _no_contact_section), ("contact", _contact_section)):
        if ph.get(key):
            lines += section(ph)
    for key, section in (("numpy_reference", _numpy_section), ("mujoco", _mujoco_section)):
        if ph.get(key):
            lines += section(ph[key])
    if report.get("env"):
        lines += _env_section(report["env"])
    gpu = report.get("gpu")
    if gpu is not None:
        lines += _gpu_section(gpu)
    if report.get("gpu_cpu_reference") is not None:
        lines += _cpu_reference_section(report["gpu_cpu_reference"], gpu)
    for key, section in (("learners", _learners_section), ("precision", _precision_section)):
        if report.get(key) is not None:
            lines += section(report[key])
    if report["targets"]:
        lines += _targets_section(report["targets"])
    return "\n".join(lines)


def speedup(cpu_row: dict, gpu_rows: list[dict]) -> float | None:
    """GPU agent steps/s over ``cpu_row``'s: the float64 GPU row with contact at the same batch (None: none)."""
    same = [g for g in gpu_rows if g["batch"] == cpu_row["batch"] and g["contact"] and g["dtype"] == "float64"]
    return round_sig(same[0]["agent_steps_per_s"] / cpu_row["agent_steps_per_s"]) if same else None


def plot_gpu(report: dict, path: Path) -> Path | None:
    """Agent steps/s vs batch size, log-log: the GPU rows (physics with and without contact, float64 and
    float32; the whole task step) beside the CPU reference. None where neither was measured."""
    gpu = report.get("gpu") or {}
    gpu_rows = (gpu.get("rows", []) + gpu.get("task_rows", [])) if gpu.get("available") else []
    cpu = report.get("gpu_cpu_reference") or {}
    if not gpu_rows and not cpu.get("rows"):
        return None
    from ..physics.config import needs_extra, save_figure

    with needs_extra("viz", "the benchmark plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))

    def series(rows, label, style):
        pts = sorted((r["batch"], r["agent_steps_per_s"]) for r in rows)
        if pts:
            ax.loglog(*zip(*pts), style, label=label)

    for dtype, color in (("float64", "C0"), ("float32", "C1")):
        for contact, ls in ((True, "-"), (False, "--")):
            series([r for r in gpu_rows if r.get("what") != "task" and r["dtype"] == dtype and r["contact"] == contact],
                   f"GPU physics, {dtype}, {'contact' if contact else 'no contact'}", color + "o" + ls)
        series([r for r in gpu_rows if r.get("what") == "task" and r["dtype"] == dtype], f"GPU task step, {dtype}",
               color + "s:")
    series(cpu.get("rows", []), "CPU physics (one core), contact", "ko-")
    series(cpu.get("task_rows", []), "CPU task step (one core)", "ks:")
    ax.axhline(TARGETS["gpu_agent_steps_per_s"], color="0.5", lw=0.8, ls=":")
    ax.text(1, TARGETS["gpu_agent_steps_per_s"], " target 200k (float64, contact, batch >= 4096)", va="bottom",
            fontsize=8)
    ax.set_xlabel("batch (tissues)")
    ax.set_ylabel("agent steps/s (33 physics ms each)")
    ax.set_title(f"{gpu.get('resolution') or cpu.get('resolution')} spleen: throughput vs batch"
                 + ("" if gpu_rows else " (CPU only: no GPU here)"))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def plot_scaling(report: dict, path: Path) -> Path | None:
    ph = report.get("physics", {})
    if not ph.get("no_contact") and not ph.get("contact"):
        return None
    from ..physics.config import needs_extra, save_figure

    with needs_extra("viz", "the benchmark plots"):
        import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    b = BATCH

    def series(rows, key, label, style):
        pts = [(r["nodes"], r[key]) for r in rows if r.get(key)]
        if pts:
            n, c = zip(*pts)
            ax.loglog(n, c, style, label=label)

    nc = ph.get("no_contact", [])
    series(nc, "single_us_per_ms", "no contact, 1 tissue", "o-")
    series(nc, f"batch{b}_per_tissue_us_per_ms", f"no contact, batch {b} (per tissue)", "s--")
    series(ph.get("contact", []), "single_us_per_ms", "contact, 1 tissue", "^-")
    if ph.get("numpy_reference"):
        series(ph["numpy_reference"]["rows"], "numpy_us_per_ms", "NumPy reference", "x:")
    mj = ph.get("mujoco") or {}
    if mj.get("available"):
        series([r for r in mj["rows"] if "error" not in r], "mujoco_us_per_ms", "MuJoCo flex", "d:")
    ax.axhline(1000.0, color="k", lw=0.8, ls="--")
    ax.text(ax.get_xlim()[0], 1000.0, " real time", va="bottom", fontsize=8)
    ax.axhline(TARGETS["fine_us_per_ms"], color="0.5", lw=0.8, ls=":")
    ax.axhline(TARGETS["coarse_us_per_ms"], color="0.5", lw=0.8, ls=":")
    exp = (ph.get("scaling") or {}).get("exponent_us_per_ms_vs_nodes")
    ax.set_xlabel("nodes")
    ax.set_ylabel("compute per simulated ms (us)")
    ax.set_title("MSD spleen cost vs mesh size" + (f" (slope {exp})" if exp else ""))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)
