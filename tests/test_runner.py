"""The local runner's worker processes: the jobs are the parallelism, so each worker's torch runs one thread."""

from __future__ import annotations

import pytest

from msdgrasp.agents.parallel import Runner


def test_a_process_workers_torch_runs_on_one_thread():
    torch = pytest.importorskip("torch")
    with Runner.processes(2) as runner:
        threads = runner.run([(torch.get_num_threads, ())] * 2)
    assert threads == [1, 1]
