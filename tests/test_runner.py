"""The local runner's worker processes: the jobs are the parallelism, so each worker's torch runs one thread."""

from __future__ import annotations

import os

import pytest

from msdgrasp.agents.learners.base import TrainOverrides
from msdgrasp.agents.parallel import Runner


def test_a_process_workers_torch_runs_on_one_thread():
    torch = pytest.importorskip("torch")
    with Runner.processes(2) as runner:
        threads = runner.run([(torch.get_num_threads, ())] * 2)
    assert threads == [1, 1]


def test_the_initializer_sets_an_already_imported_torch_to_one_thread(monkeypatch):
    torch = pytest.importorskip("torch")
    from msdgrasp.agents.parallel import _one_thread

    before = torch.get_num_threads()
    monkeypatch.setenv("OMP_NUM_THREADS", "4")  # (restored after the test)
    try:
        torch.set_num_threads(2)
        _one_thread()
        assert torch.get_num_threads() == 1
        assert os.environ["OMP_NUM_THREADS"] == "1"
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("learner", ["ppo", "recurrent"])
def test_a_parallel_seed_runs_torch_on_one_thread_whatever_its_config_says(learner):
    import dataclasses

    from msdgrasp.agents.learners import get_learner

    lrn = get_learner(learner)
    config = dataclasses.replace(lrn.make_config(None, TrainOverrides()), torch_threads=4)
    assert lrn.one_core(config).torch_threads == 1
