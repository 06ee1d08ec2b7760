"""docs/benchmark.md's "Evaluate your own policy" code runs as written (on 1 episode per mu instead of 19) and does
what the section says: a plain object evaluated through the Python API, then through the command line's in_range
suite, whose result the leaderboard reads."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def own_policy_code() -> str:
    """The first python block under the "Evaluate your own policy" heading of docs/benchmark.md."""
    text = (ROOT / "docs" / "benchmark.md").read_text()
    section = text[text.index("## Evaluate your own policy"):]
    section = section[:section.index("\n## ")]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert blocks, "no python block under 'Evaluate your own policy'"
    return blocks[0]


def test_own_policy_code_is_short() -> None:
    code = own_policy_code()
    assert len([line for line in code.splitlines() if line.strip()]) <= 22
    assert "episodes = 19" in code  # the protocol's count, which the next test lowers


@pytest.mark.slow
def test_own_policy_code_runs(tmp_path: Path) -> None:
    code = own_policy_code().replace("episodes = 19", "episodes = 1", 1)
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for mu in ("0.2", "0.3", "0.5", "0.8"):
        assert f"mu {mu}: success" in proc.stdout
    suite = json.loads((tmp_path / "mine" / "suite_in_range.json").read_text())
    assert [r["spec"] for r in suite["results"]] == ["steady"]
    assert len(suite["conditions"]) == 8 and all(c["episodes"] == 4 for c in suite["results"][0]["cells"])
    # the leaderboard takes it as a track of its own
    from msdgrasp.agents.leaderboard import write_leaderboard

    board = write_leaderboard(tmp_path / "mine" / "suite_in_range.json", ["mine=steady"], None, tmp_path / "board")
    assert board["tracks"][0]["policies"] == ["steady"] and board["tracks"][0]["runs"] == 1
