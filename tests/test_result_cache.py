"""The disk cache of deterministic simulation results (the oracle's minimal forces): a value computed once is read
back exactly by any later process, and anything it was computed from, changed, computes it anew."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from msdgrasp.agents import controllers, result_cache
from msdgrasp.agents.result_cache import cached_float
from msdgrasp.envs.core import GraspLiftConfig


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MSDGRASP_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


class Counter:
    def __init__(self, value: float) -> None:
        self.value, self.calls = value, 0

    def __call__(self) -> float:
        self.calls += 1
        return self.value


def test_a_value_is_computed_once_and_read_back_bit_for_bit(cache):
    compute = Counter(0.1 + 0.2)  # a float whose shortest repr needs all 17 digits
    for _ in range(3):
        assert cached_float("probe", {"mu": 0.5}, compute) == 0.1 + 0.2
    assert compute.calls == 1
    [entry] = (cache / "probe").glob("*.json")
    stored = json.loads(entry.read_text())
    assert stored["for"]["key"] == {"mu": 0.5} and stored["for"]["package"] == result_cache.package_digest()


def test_another_process_reads_what_one_computed(cache):
    script = textwrap.dedent("""
        from msdgrasp.agents.result_cache import cached_float
        def fail():
            raise SystemExit("computed again")
        print(repr(cached_float("probe", {"mu": 0.25}, fail)))
    """)
    assert cached_float("probe", {"mu": 0.25}, lambda: 1.0 / 3.0) == 1.0 / 3.0
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert float(out.stdout) == 1.0 / 3.0


@pytest.mark.parametrize("change", ["key", "kind", "package", "stack"])
def test_anything_the_value_was_computed_from_changed_computes_it_anew(cache, monkeypatch, change):
    first, second = Counter(1.0), Counter(2.0)
    assert cached_float("probe", {"mu": 0.5}, first) == 1.0
    kind, key = "probe", {"mu": 0.5}
    if change == "key":
        key = {"mu": 0.6}
    elif change == "kind":
        kind = "other"
    elif change == "package":  # an edit of any keyed file of the package
        monkeypatch.setattr(result_cache, "package_digest", lambda: "edited")
    else:
        other = {**result_cache.stack(), "numba": "0.0"}
        monkeypatch.setattr(result_cache, "stack", lambda: other)
    assert cached_float(kind, key, second) == 2.0 and second.calls == 1


def test_the_package_digest_covers_every_file_of_the_keyed_folders_and_nothing_compiled(tmp_path, monkeypatch):
    for folder in result_cache.KEYED_FOLDERS:
        (tmp_path / folder / "sub").mkdir(parents=True)
        (tmp_path / folder / "sub" / "a.yaml").write_text("x: 1\n")
    (tmp_path / "cli").mkdir()
    monkeypatch.setattr(result_cache, "PACKAGE_DIR", tmp_path)
    digest = result_cache.package_digest.__wrapped__
    base = digest()
    (tmp_path / "cli" / "main.py").write_text("# the command line changes no result\n")
    (tmp_path / "physics" / "__pycache__").mkdir()
    (tmp_path / "physics" / "__pycache__" / "k.nbi").write_bytes(b"compiled")
    assert digest() == base
    for folder in result_cache.KEYED_FOLDERS:
        (tmp_path / folder / "sub" / "a.yaml").write_text("x: 2\n")
        assert digest() != base, folder
        (tmp_path / folder / "sub" / "a.yaml").write_text("x: 1\n")
    assert digest() == base


def test_an_unreadable_or_foreign_entry_is_computed_again_and_rewritten(cache):
    assert cached_float("probe", {"mu": 0.5}, Counter(1.0)) == 1.0
    [entry] = (cache / "probe").glob("*.json")
    for bad in ("{not json", json.dumps({"for": {"key": "another"}, "value": 9.0}), json.dumps({"value": 9.0})):
        entry.write_text(bad)
        again = Counter(1.0)
        assert cached_float("probe", {"mu": 0.5}, again) == 1.0 and again.calls == 1
        assert json.loads(entry.read_text())["value"] == 1.0


def test_the_cache_is_off_where_asked_and_for_files_outside_the_package(tmp_path, monkeypatch):
    monkeypatch.setenv("MSDGRASP_CACHE_DIR", "")
    off = Counter(1.0)
    cached_float("probe", {"mu": 0.5}, off)
    cached_float("probe", {"mu": 0.5}, off)
    assert off.calls == 2 and not any(tmp_path.iterdir())
    monkeypatch.setenv("MSDGRASP_CACHE_DIR", str(tmp_path / "cache"))
    uncached = Counter(1.0)
    cached_float("probe", {"mu": 0.5}, uncached, cacheable=False)
    cached_float("probe", {"mu": 0.5}, uncached, cacheable=False)
    assert uncached.calls == 2 and not (tmp_path / "cache").exists()


def test_a_cache_that_cannot_be_written_warns_and_the_value_stands(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("MSDGRASP_CACHE_DIR", str(blocker / "cache"))  # under a file: no folder can be made
    with pytest.warns(RuntimeWarning, match="cannot write"):
        assert cached_float("probe", {"mu": 0.5}, Counter(1.5)) == 1.5


def test_the_oracles_minimal_force_is_cached_on_the_package_files_only(cache, monkeypatch, tmp_path):
    """The bisection runs once per (config, mu) across processes; a config naming its own tissue or grasper file
    runs it every time (the key cannot see that file's edits)."""
    calls = []

    def search(config, mu, pull, tolerance):
        calls.append((config, mu))
        return 1.25

    monkeypatch.setattr(controllers, "_minimal_force_search", search)
    own = GraspLiftConfig(tissue_config=str(tmp_path / "my_tissue.yaml"))
    for config, expected_calls in ((GraspLiftConfig(), 1), (own, 2)):
        calls.clear()
        for _ in range(2):
            controllers._minimal_force_cached.cache_clear()  # a new process: only the disk remembers
            assert controllers.minimal_force(config, 0.5) == 1.25
        assert len(calls) == expected_calls
    controllers._minimal_force_cached.cache_clear()
