"""How a study hands its cases to Dask (rigctl.apps.study.execution): the longest first, one per task
while they are long, several per task once they are known to be short (the scheduler's round trip
paid per chunk, not per case), every case run exactly once either way. The cluster here is Dask's
in-process one (threads, no process started)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rigctl.apps.study.execution import chunk_size, run_on_dask, submission_order
from rigctl.apps.study.spec import spec_from_dict


def test_the_cases_go_out_largest_move_count_first_and_otherwise_in_spec_order() -> None:
    spec = spec_from_dict({"run": {"command": "plan reachable", "args": {"disk": True}},
                           "parameters": {"d12": [0.1, 0.3], "moves": [2, 14, 6]}}, Path("/tmp"))
    order = [(c.parameters["moves"], c.parameters["d12"]) for c in submission_order(spec.cases)]
    assert order == [(14, 0.1), (14, 0.3), (6, 0.1), (6, 0.3), (2, 0.1), (2, 0.3)]


def test_a_chunk_is_one_case_until_cases_are_known_short_and_shrinks_towards_the_end() -> None:
    assert chunk_size(1000, 2, None) == 1  # nothing finished yet: nothing known
    assert chunk_size(1000, 2, 0.5) == 1  # long cases: one per task
    assert chunk_size(1000, 2, 0.001) == 250  # 0.25 s of 1 ms cases, = 1000 / (2 x 2 workers)
    assert chunk_size(400, 2, 0.001) == 100  # a quarter of what is left, no more
    assert chunk_size(3, 2, 0.001) == 1  # the last cases one by one: no long last chunk


def _row(item: int, wall_s: float) -> dict:
    return {"item": item, "wall_s": wall_s}


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        yield client


@pytest.mark.parametrize("cases, wall_s", [(400, 0.001), (40, 1.0)])
def test_every_case_runs_once_and_only_short_ones_share_tasks(client, cases, wall_s) -> None:
    rows, futures = [], []
    run_on_dask(client, _row, list(range(cases)), (), (wall_s,), 2, rows.append, futures)
    assert sorted(r["item"] for r in rows) == list(range(cases))
    if wall_s < 0.25:  # 1 ms cases: a task's round trip paid per chunk, not per case
        assert len(futures) <= cases // 4
    else:  # long cases: one task each, each in the table as soon as it ends
        assert len(futures) == cases
