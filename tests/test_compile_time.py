"""The cold-compilation benchmark (`python -m msdgrasp.benchmarks.compile_time`) on toy workloads: it compiles in
a child with an empty cache, splits a caller's time from its callees' and counts signatures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from msdgrasp.benchmarks import compile_time

TOY = """
import os
from numba import njit
assert os.listdir(os.environ["NUMBA_CACHE_DIR"]) == []  # an empty cache of its own
@njit
def g(x):
    return x + 1
@njit
def f(x):
    return g(x) * 2
f(1)
f(1.5)
"""


def test_a_callers_exclusive_time_leaves_out_its_callees_and_every_signature_counts():
    report = compile_time.measure(TOY, timeout_s=300)
    f, g = report["functions"]["__main__.f"], report["functions"]["__main__.g"]
    assert f["signatures"] == g["signatures"] == 2  # int and float
    assert g["inclusive_s"] == pytest.approx(g["exclusive_s"], abs=2e-3)  # g calls nothing jitted
    assert f["inclusive_s"] >= g["inclusive_s"] > 0.0
    assert f["exclusive_s"] == pytest.approx(f["inclusive_s"] - g["inclusive_s"], abs=5e-3)
    assert report["compile_s"] == pytest.approx(sum(r["exclusive_s"] for r in report["functions"].values()), abs=0.02)
    assert report["compile_s"] <= report["wall_s"] + 0.01
    md = compile_time.markdown({"what": "toy", **report}, top=1)
    assert md.count("| __main__.") == 1


def test_a_failing_workload_says_why():
    with pytest.raises(RuntimeError, match="ZeroDivisionError"):
        compile_time.measure("1 / 0\n", timeout_s=120)


@pytest.mark.parametrize("argv, message", [(["--top", "0"], "--top must be >= 1, got 0"),
                                           (["--what", "gpu"], "invalid choice: 'gpu'"),
                                           (["--out", "."], "is a folder"),
                                           (["--out", "conftest.py/c.json"], "cannot create folder"),
                                           (["--package", "no_such_build"], "'no_such_build' is not an importable")])
def test_bad_options_are_one_line_exit_2_before_anything_runs(argv, message, capsys, monkeypatch):
    monkeypatch.chdir(Path(__file__).parent)
    monkeypatch.setattr(compile_time, "measure", lambda code: pytest.fail("ran"))
    with pytest.raises(SystemExit) as exc:
        compile_time.main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_a_workload_runs_on_the_build_it_names():
    assert "from msdgrasp." in compile_time.workload("env")
    other = compile_time.workload("float32", "msd_base")
    assert "msdgrasp" not in other and other.count("from msd_base.") == 3


def test_msdgrasp_bench_compile_prints_the_json_and_writes_it_with_its_table(tmp_path, capsys, monkeypatch):
    from msdgrasp.cli.main import main

    seen = []
    fake = {"wall_s": 2.0, "compile_s": 1.5, "functions": {"m.f": {"inclusive_s": 1.5, "exclusive_s": 1.0,
                                                                     "signatures": 1},
                                                             "m.g": {"inclusive_s": 0.5, "exclusive_s": 0.5,
                                                                     "signatures": 2}}}
    monkeypatch.setattr(compile_time, "measure", lambda code, env=None: seen.append((code, env)) or fake)
    out = tmp_path / "new" / "compile.json"  # (its folder is made)
    assert main(["bench", "compile", "--out", str(out)]) == 0
    # as a first run is (its compile helper on) for the wall time, then in one process for the table
    env = compile_time.workload("env")
    assert seen == [(env, None), (env, {"MSDGRASP_COMPILE_HELPER": "0"})]
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text()) == {"what": "env", "package": "msdgrasp", "first_run_wall_s": 2.0,
                                                      **fake}
    table = out.with_suffix(".md").read_text()
    assert "| m.f | 1.0 | 1.5 | 1 |" in table and table.startswith("Cold first run of `env`: 2.0 s wall")
    assert main(["bench", "compile", "--out", str(tmp_path)]) == 2 and "is a folder" in capsys.readouterr().err
