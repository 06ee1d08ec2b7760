"""The cold-compilation benchmark (`python -m msdgrasp.benchmarks.compile_time`) on toy workloads: it compiles in
a child with an empty cache, splits a caller's time from its callees' and counts signatures."""

from __future__ import annotations

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
                                           (["--out", "no/such/folder/c.json"], "does not exist"),
                                           (["--package", "no_such_build"], "'no_such_build' is not an importable")])
def test_bad_options_are_one_line_exit_2_before_anything_runs(argv, message, capsys, monkeypatch):
    monkeypatch.setattr(compile_time, "measure", lambda code: pytest.fail("ran"))
    with pytest.raises(SystemExit) as exc:
        compile_time.main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_a_workload_runs_on_the_build_it_names():
    assert "from msdgrasp." in compile_time.workload("env")
    other = compile_time.workload("float32", "msd_base")
    assert "msdgrasp" not in other and other.count("from msd_base.") == 3
