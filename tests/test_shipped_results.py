"""The leaderboard tables in README.md and docs/benchmark.md are what ``msdgrasp leaderboard`` makes of the suite
results shipped in results/v2/: README.md's own command is run on them, and every number of its table (and of
docs/benchmark.md's tables) must be the one the leaderboard computes, so a table left stale by new results fails."""

from __future__ import annotations

import glob
import json
import re
import shlex
from pathlib import Path
from typing import Any

import pytest

from msdgrasp.cli.main import main as msdgrasp_cli

ROOT = Path(__file__).resolve().parents[1]
TEACHER = "teacher (told mu)=slipfeedback:estimator=builtin,told=1,gate=0.9,gain=0.5,pull=0.3"


def readme_command() -> list[str]:
    """The ``msdgrasp leaderboard`` command of README.md's results section, as argv after ``msdgrasp``."""
    found = re.findall(r"`(msdgrasp leaderboard results/v2/[^`]+)`", (ROOT / "README.md").read_text())
    assert len(found) == 1, "README.md names one leaderboard command on results/v2/"
    return shlex.split(found[0])[1:]


def run_board(argv: list[str], out: Path, extra: list[str] = ()) -> dict[str, Any]:
    """Run the command line as a shell would (its globs expanded from the repository root) into ``out``."""
    args: list[str] = []
    for a in argv:
        if a.endswith(".json") and any(c in a for c in "*?["):
            hits = sorted(glob.glob(str(ROOT / a)))
            assert hits, f"{a} matches no shipped file"
            args += hits
        else:
            args.append(a)
    args[args.index("--out") + 1] = str(out)
    assert msdgrasp_cli([*args, *extra]) == 0
    return json.loads((out / "leaderboard.json").read_text())


def table_rows(path: Path) -> list[list[str]]:
    """The cells of the table rows between ``<!-- leaderboard -->`` and ``<!-- /leaderboard -->`` in ``path``."""
    text = path.read_text()
    block = text[text.index("<!-- leaderboard -->"):text.index("<!-- /leaderboard -->")]
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in block.splitlines()
            if line.startswith("| ") and not line.startswith("|---")]


def aggregate_cells(track: dict[str, Any], conditions: list[str]) -> dict[str, str]:
    """The aggregate table's cells for ``track`` as the documents write them (lowest bound: value, k/n, where)."""
    worst = min(range(len(conditions)), key=lambda c: track["cells"][c]["success_lower_bound"])
    cell = track["cells"][worst]
    lo, hi = track["success_mean_ci95"]
    flo, fhi = track["force_ratio_iqm_ci95"]
    pi = track.get("p_improvement")
    return {"runs": str(track["runs"]),
            "success": f"{track['success_mean']:.3f} [{lo:.3f}, {hi:.3f}]",
            "lowest": f"{track['lowest_lower_bound']:.2f} ({cell['successes']}/{cell['episodes']}, "
                      + ", ".join(conditions[worst].split(", ")[:1]) + ")",
            "force": f"{track['force_ratio_iqm']:.2f} [{flo:.2f}, {fhi:.2f}]",
            "lift": f"{track['time_to_lift_s']:.1f} s",
            "pi": f"{pi['value']:.2f} [{pi['ci95'][0]:.2f}, {pi['ci95'][1]:.2f}]" if pi else "-",
            "profile": f"{track['profile']['1.25']:.2f}"}


def check_aggregate_table(rows: list[list[str]], board: dict[str, Any], labels: dict[str, str]) -> None:
    """Each track's row (found by its label, the text before `` (``) holds the leaderboard's numbers."""
    for track in board["tracks"]:
        row = [r for r in rows if r[0].split(" (")[0] == labels[track["track"]]]
        assert len(row) == 1, f"no single row for {track['track']!r}"
        expected = aggregate_cells(track, board["conditions"])
        assert row[0][2:] == list(expected.values()), f"{track['track']}: table {row[0][2:]} != {expected}"


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """README's command, plus the teacher's track and every run against the estimating controller (docs/benchmark.md's
    tables): neither changes another track's numbers (every bootstrap starts from the same fixed seed)."""
    return run_board(readme_command(), tmp_path_factory.mktemp("board"),
                     ["--track", TEACHER, "--against", "estimating controller"])


LABELS = {"recurrent": "recurrent", "default training": "default training", "PPO from scratch": "PPO from scratch",
          "estimating controller": "estimating controller", "slip-reactive": "slip-reactive",
          "teacher (told mu)": "teacher"}


def test_shipped_results_are_the_protocols(board: dict[str, Any]) -> None:
    assert board["suite"] == "in_range" and board["protocol"] and board["seeds"]["sealed"]
    assert len(board["conditions"]) == 8 and all(c["episodes"] in (76, 380) for t in board["tracks"]
                                                  for c in t["cells"])
    size = sum(p.stat().st_size for p in (ROOT / "results").rglob("*"))
    assert size < 2e6, f"results/ holds {size / 1e6:.1f} MB"


def test_readme_table_is_the_leaderboard_of_the_shipped_results(board: dict[str, Any]) -> None:
    rows = table_rows(ROOT / "README.md")
    readme = {**board, "tracks": [t for t in board["tracks"] if t["track"] != "teacher (told mu)"]}
    check_aggregate_table(rows, readme, LABELS)
    assert len(rows) == 1 + len(readme["tracks"]), "README's table has a row the command does not make"


def test_benchmark_tables_are_the_leaderboard_of_the_shipped_results(board: dict[str, Any]) -> None:
    by_name = {t["track"]: t for t in board["tracks"]}
    tracks = [by_name[n] for n in ("recurrent", "default training", "PPO from scratch", "estimating controller",
                                   "teacher (told mu)", "slip-reactive")]  # docs/benchmark.md's order
    rows = table_rows(ROOT / "docs" / "benchmark.md")
    check_aggregate_table(rows, {**board, "tracks": tracks}, LABELS)
    # per condition: success / Wilson lower bound / force ratio / time to lift of every track
    for c, cond in enumerate(board["conditions"]):
        row = [r for r in rows if r[0] == cond]
        assert len(row) == 1, f"no row for condition {cond!r}"
        expected = [f"{x['successes']}/{x['episodes']} / {x['success_lower_bound']:.3f} / {x['force_ratio']:.2f} / "
                    f"{x['time_to_lift_s']:.1f}" for x in (t["cells"][c] for t in tracks)]
        assert row[0][1:] == expected
    # per run: successes / mean peak pinch / over the estimating controller's (! where it holds fewer)
    text = (ROOT / "docs" / "benchmark.md").read_text()
    per_run = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
               if line.startswith("| ") and line.count("|") == len(board["conditions"]) + 3]
    for t in tracks:
        for run in t["per_run"]:
            row = [r for r in per_run if r[:2] == [t["track"], run["policy"]]]
            assert len(row) == 1, f"no per-run row for {run['policy']!r}"
            expected = [f"{x['successes']}/{x['episodes']} / {x['mean_peak_pinch_N']:.2f}" + (
                f" / {a['pinch_over_against']:.2f}x" + ("" if a["holds_as_many"] else " !") if a else "")
                for x, a in zip(run["cells"], run.get("against", [None] * len(run["cells"])))]
            assert row[0][2:] == expected, f"{run['policy']}: {row[0][2:]} != {expected}"
