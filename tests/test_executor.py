"""Executors: identical results on any of them, a lost worker's chunk retried once, an error
raised by the work never re-run, and failures reported by chunk with the work's traceback.

The local worker processes are forked from multiprocessing's fork server and import this module
to find the functions they run: it imports only the executor at the top (the stages, ~2 s of
imports per process, only where a test needs them).
"""

from __future__ import annotations

import os
import traceback
from pathlib import Path

import numpy as np
import pytest

from pipeline.io.errors import UserError
from pipeline.io.executor import ChunkFailed, ProcessExecutor, SerialExecutor, make_executor


def _square(x):
    return x * x


def _always_fails(x):
    raise ValueError(f"bad chunk {x}")


def _environment_variable(name):
    return os.environ.get(name)


def _count_call(folder, value):
    """Append ``value`` to ``folder/calls`` (one line per call, from any process)."""
    with open(Path(folder) / "calls", "a") as calls:
        calls.write(f"{value}\n")


def calls(folder):
    path = Path(folder) / "calls"
    return path.read_text().split() if path.exists() else []


def _type_error_in_chunk_2(path_and_value):
    """A deterministic bug in chunk 2; every call is counted."""
    folder, value = path_and_value
    _count_call(folder, value)
    if value == 2:
        return value + "2"  # TypeError, raised here
    return value


def _dies_once(path_and_value):
    """Chunk 2's worker process dies the first time (a marker file records it)."""
    folder, value = path_and_value
    _count_call(folder, value)
    marker = Path(folder) / f"died_{value}"
    if value == 2 and not marker.exists():
        marker.write_text("x")
        os._exit(1)  # the worker process dies
    return value


def _always_dies(value):
    os._exit(1)


@pytest.fixture(scope="module", params=["serial", "processes"])
def executor(request):
    made = SerialExecutor() if request.param == "serial" else ProcessExecutor(2)
    yield made
    made.close()


def test_results_keep_the_order_of_the_items(executor):
    assert executor.map(_square, [3, 1, 2]) == [9, 1, 4]


def test_an_error_raised_by_the_work_is_not_rerun_and_keeps_its_traceback(executor, tmp_path):
    items = [(str(tmp_path), v) for v in range(4)]
    with pytest.raises(ChunkFailed, match="chunk 2 failed: TypeError") as error:
        executor.map(_type_error_in_chunk_2, items)
    assert error.value.chunk == 2 and not error.value.lost
    assert isinstance(error.value.__cause__, TypeError)
    assert calls(tmp_path).count("2") == 1  # run once, not retried
    # where it was raised, in the worker for processes: in the text a failed run saves
    assert "in _type_error_in_chunk_2" in "".join(traceback.format_exception(error.value))


def test_a_chunk_that_fails_is_reported_with_its_id(executor):
    with pytest.raises(ChunkFailed, match="chunk 0 failed: ValueError: bad chunk 7") as error:
        executor.map(_always_fails, [7, 8])
    assert error.value.chunk == 0


def test_a_dead_worker_is_replaced_and_its_chunk_retried(tmp_path):
    pool = ProcessExecutor(2)
    try:
        assert pool.map(_dies_once, [(str(tmp_path), v) for v in range(4)]) == [0, 1, 2, 3]
        assert calls(tmp_path).count("2") == 2  # lost once, retried once
        assert pool.map(_square, [5]) == [25]  # the fresh pool serves the next map
    finally:
        pool.close()


def test_a_chunk_whose_worker_dies_twice_is_reported_as_lost():
    pool = ProcessExecutor(1)
    try:
        with pytest.raises(ChunkFailed, match="chunk 0 lost its worker twice") as error:
            pool.map(_always_dies, [0])
        assert error.value.lost
    finally:
        pool.close()


def test_dask_reruns_a_lost_worker_s_chunk_but_not_an_error_of_the_work(tmp_path):
    pytest.importorskip("dask.distributed")
    made = make_executor("dask-local", 2)
    try:
        items = [(str(tmp_path / "bug"), v) for v in range(4)]
        (tmp_path / "bug").mkdir()
        with pytest.raises(ChunkFailed, match="chunk 2 failed: TypeError") as error:
            made.map(_type_error_in_chunk_2, items)
        assert calls(tmp_path / "bug").count("2") == 1
        assert "in _type_error_in_chunk_2" in "".join(traceback.format_exception(error.value))
        items = [(str(tmp_path), v) for v in range(4)]
        assert made.map(_dies_once, items) == [0, 1, 2, 3]
        assert calls(tmp_path).count("2") == 2
    finally:
        made.close()


def test_workers_see_the_environment_of_their_pool_not_of_the_fork_server(monkeypatch):
    first = ProcessExecutor(2)
    try:
        assert first.map(_environment_variable, ["SAFETY_TEST_SETTING"]) == [None]
    finally:
        first.close()  # the fork server keeps running, with the environment it started with
    monkeypatch.setenv("SAFETY_TEST_SETTING", "set after the server started")
    second = ProcessExecutor(2)
    try:
        names = ["SAFETY_TEST_SETTING", "OPENBLAS_NUM_THREADS"]
        assert second.map(_environment_variable, names) == ["set after the server started", "1"]
    finally:
        second.close()


def test_unknown_executor_is_a_user_error():
    with pytest.raises(UserError, match="unknown executor 'spark'"):
        make_executor("spark", 2)


def test_monte_carlo_and_optimization_are_identical_on_every_executor(synthesized):
    from pipeline import load_scenario
    from pipeline.io.artifacts import read_stored
    from pipeline.runtime.registry import RESULT_TYPES
    from stages.montecarlo import validate_closed_loop
    from stages.optimize import ConstraintMargins, OptimizeOptions, optimize

    _, out = synthesized
    scenario = load_scenario("quadrotor_hill_flythrough", check_demos=False)
    feedback = read_stored(out / "artifacts" / "feedback", RESULT_TYPES).result
    r_d = feedback.required_radius(scenario.clearance)
    margins = ConstraintMargins.of_tube(feedback.certified_tube, r_d)
    runs, optimized = {}, {}
    for name in ("local", "processes", "dask-local"):
        if name == "dask-local":
            pytest.importorskip("dask.distributed")
        made = make_executor(
            None if name == "local" else ("local" if name == "processes" else name),
            1 if name == "local" else 2,
        )
        try:
            runs[name] = validate_closed_loop(
                scenario, out / "controller.json", samples=300, seed=5, chunk=100, executor=made
            )
            optimized[name] = optimize(
                scenario, margins, OptimizeOptions(), demos=[1, 6], executor=made
            )
        finally:
            made.close()
    reference = runs["local"]
    for name, result in runs.items():
        assert result.failures == reference.failures, name
        np.testing.assert_array_equal(result.clearance, reference.clearance)
        np.testing.assert_array_equal(result.tube_tightness, reference.tube_tightness)
        assert result.failure_bound == reference.failure_bound
        for a, b in zip(optimized[name].trajectories, optimized["local"].trajectories, strict=True):
            np.testing.assert_array_equal(a.u, b.u)
