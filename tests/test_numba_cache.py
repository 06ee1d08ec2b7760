"""numba's cache of the physics kernels is keyed on all physics sources, so it cannot go stale.

numba itself stamps a cached function with its own file only: ``integrator.simulate`` inlines kernels of
``contact.py`` and ``forces.py``, and an edit there would leave the cached ``simulate`` running the old code.
"""

from __future__ import annotations

import shutil

from msdgrasp.physics import integrator, numba_cache
from msdgrasp.physics.numba_cache import LOCATORS, PHYSICS_DIR, sources_digest


def test_the_simulate_kernel_is_stamped_with_all_physics_sources():
    locator = integrator.simulate._cache._impl._locator
    assert isinstance(locator, LOCATORS)
    assert locator.get_source_stamp() == sources_digest(PHYSICS_DIR)


def test_editing_a_callee_file_changes_the_stamp(tmp_path):
    copy = tmp_path / "physics"
    shutil.copytree(PHYSICS_DIR, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = sources_digest(copy)
    assert before == sources_digest(PHYSICS_DIR)
    contact = copy / "contact.py"
    contact.write_text(contact.read_text() + "\n# an edit of a callee only\n")
    assert sources_digest(copy) != before


def test_functions_outside_physics_keep_numba_s_own_locators(tmp_path):
    src = tmp_path / "elsewhere.py"
    src.write_text("def f(x):\n    return x + 1\n")
    namespace: dict = {}
    exec(compile(src.read_text(), str(src), "exec"), namespace)
    for cls in LOCATORS:
        assert cls.from_function(namespace["f"], str(src)) is None


def test_install_is_idempotent():
    numba_cache.install()
    numba_cache.install()
    classes = numba_cache.CacheImpl._locator_classes
    assert sum(c in LOCATORS for c in classes) == len(LOCATORS)


def test_the_task_kernels_are_stamped_with_the_physics_sources_and_their_own_file(tmp_path):
    """envs/task.py compiles physics readout columns into its kernels: an edit of either invalidates them."""
    from msdgrasp.envs import task

    locator = task.update_batch._cache._impl._locator
    assert isinstance(locator, LOCATORS)
    stamp = locator.get_source_stamp()
    assert stamp != sources_digest(PHYSICS_DIR)  # the task's own file counts too
    edited = tmp_path / "task.py"
    edited.write_text(open(task.__file__).read() + "\n# an edit of the task only\n")
    numba_cache.key_on_physics(edited)
    assert numba_cache._keyed_file_digest(edited.resolve()) != stamp
