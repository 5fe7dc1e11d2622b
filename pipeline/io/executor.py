"""Where embarrassingly parallel work runs: one small interface, three implementations.

``make_executor(spec, jobs)`` returns an object with ``map(function, items) -> list`` (results in
the order of ``items``) and ``close()``:

- ``None`` / ``"local"``: in this process when ``jobs == 1``, else ``jobs`` local processes
  (``concurrent.futures``, spawned with BLAS threads pinned to 1; each exits when its parent
  dies, so a killed run leaves no worker behind);
- ``"dask-local"``: a ``dask.distributed`` LocalCluster with ``jobs`` workers;
- ``"dask://HOST:PORT"``: an existing Dask scheduler (``pip install .[dask]``).

A chunk that raises (or whose worker dies) is retried once; a second failure raises
``ChunkFailed`` naming the chunk, so no work is ever silently dropped.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

from pipeline.io.errors import UserError

PINNED_THREADS = {
    name: "1"
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
}


class ChunkFailed(RuntimeError):
    """A chunk failed twice; ``chunk`` is its index in the submitted items."""

    def __init__(self, chunk: int, error: BaseException) -> None:
        self.chunk = chunk
        super().__init__(
            f"chunk {chunk} failed twice (retried once): {type(error).__name__}: {error}"
        )


class Executor(Protocol):
    def map(
        self,
        function: Callable[[Any], Any],
        items: Sequence[Any],
        done: Callable[[int], None] | None = None,
    ) -> list[Any]: ...

    def close(self) -> None: ...


class SerialExecutor:
    """Runs every chunk here, in order (the reference the others must reproduce)."""

    def map(
        self,
        function: Callable[[Any], Any],
        items: Sequence[Any],
        done: Callable[[int], None] | None = None,
    ) -> list[Any]:
        results = []
        for index, item in enumerate(items):
            try:
                results.append(function(item))
            except Exception:
                try:
                    results.append(function(item))
                except Exception as error:
                    raise ChunkFailed(index, error) from error
            if done:
                done(index)
        return results

    def close(self) -> None:
        pass


PARENT_POLL_SECONDS = 0.5


def _exit_with_parent(parent: int) -> None:
    """Worker initializer: exit as soon as the parent process is gone (e.g. ``kill -9``), so that
    no orphaned worker keeps computing. A daemon thread polls the parent's pid."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


class ProcessExecutor:
    """``jobs`` spawned local processes with single-threaded BLAS."""

    def __init__(self, jobs: int) -> None:
        self.jobs = jobs
        self._pool: ProcessPoolExecutor | None = None

    def _start(self) -> ProcessPoolExecutor:
        if self._pool is None:
            saved = {name: os.environ.get(name) for name in PINNED_THREADS}
            os.environ.update(PINNED_THREADS)  # inherited by the spawned workers
            try:
                self._pool = ProcessPoolExecutor(
                    max_workers=self.jobs,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_exit_with_parent,
                    initargs=(os.getpid(),),
                )
                self._pool.submit(int).result()  # start the workers under the pinned env
            finally:
                for name, value in saved.items():
                    if value is None:
                        os.environ.pop(name, None)
                    else:
                        os.environ[name] = value
        return self._pool

    def map(
        self,
        function: Callable[[Any], Any],
        items: Sequence[Any],
        done: Callable[[int], None] | None = None,
    ) -> list[Any]:
        futures: list[Future[Any]] = [self._start().submit(function, item) for item in items]
        results = []
        for index, future in enumerate(futures):
            try:
                result = future.result()
            except BrokenProcessPool:
                self._pool = None  # a worker died: a fresh pool for the retry
                result = self._retry(function, items[index], index)
            except Exception:
                result = self._retry(function, items[index], index)
            results.append(result)
            if done:
                done(index)
        return results

    def _retry(self, function: Callable[[Any], Any], item: Any, index: int) -> Any:
        try:
            return self._start().submit(function, item).result()
        except BrokenProcessPool as error:
            self._pool = None
            raise ChunkFailed(index, error) from error
        except Exception as error:
            raise ChunkFailed(index, error) from error

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None


class DaskExecutor:
    """A ``dask.distributed`` client: ``address`` of a scheduler, or a LocalCluster."""

    def __init__(self, address: str | None, jobs: int) -> None:
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:
            raise UserError(
                "the Dask executor needs dask.distributed", expected="`pip install .[dask]`"
            ) from None
        self._cluster = None
        if address is None:
            self._cluster = LocalCluster(
                n_workers=jobs, threads_per_worker=1, processes=True, dashboard_address=None
            )
            self.client = Client(self._cluster)
        else:
            try:
                self.client = Client(address, timeout=10)
            except OSError as error:
                raise UserError(
                    f"cannot reach the Dask scheduler at {address} ({error})",
                    expected="a running scheduler, e.g. `dask scheduler`",
                ) from None

    def map(
        self,
        function: Callable[[Any], Any],
        items: Sequence[Any],
        done: Callable[[int], None] | None = None,
    ) -> list[Any]:
        futures = [self.client.submit(function, item, retries=1, pure=False) for item in items]
        results = []
        for index, future in enumerate(futures):
            try:
                results.append(future.result())
            except Exception as error:
                raise ChunkFailed(index, error) from error
            if done:
                done(index)
        return results

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def make_executor(spec: str | None, jobs: int = 1) -> Executor:
    """An executor from the ``--executor`` text (see the module docstring)."""
    if spec in (None, "", "local"):
        return SerialExecutor() if jobs <= 1 else ProcessExecutor(jobs)
    if spec == "dask-local":
        return DaskExecutor(None, max(jobs, 1))
    if spec.startswith("dask://"):
        return DaskExecutor("tcp://" + spec.removeprefix("dask://"), jobs)
    raise UserError(
        f"unknown executor '{spec}'", expected="'local', 'dask-local' or 'dask://HOST:PORT'"
    )
