"""Where embarrassingly parallel work runs: one small interface, three implementations.

``make_executor(spec, jobs)`` returns an object with ``map(function, items) -> list`` (results in
the order of ``items``) and ``close()``:

- ``None`` / ``"local"``: in this process when ``jobs == 1``, else ``jobs`` local processes
  (``concurrent.futures`` with BLAS threads pinned to 1, forked from multiprocessing's fork
  server, a clean single-threaded process that imported the modules registered with
  ``preload_in_workers`` once per process and stays, idle, until the process exits, so a pool
  starts without each worker importing the stages again (spawned where the platform has no
  fork server); each worker takes the run's environment and exits when the run's process
  dies, so a killed run leaves no worker behind);
- ``"dask-local"``: a ``dask.distributed`` LocalCluster with ``jobs`` workers;
- ``"dask://HOST:PORT"``: an existing Dask scheduler (``pip install .[dask]``).

A chunk whose worker is lost (killed, out of memory: ``BrokenProcessPool``) is retried once,
alone on a fresh pool; lost again, it raises ``ChunkFailed`` naming the chunk, so no work is
ever silently dropped. (Dask's scheduler reruns a lost worker's tasks itself, up to
``distributed.scheduler.allowed-failures`` times; a ``KilledWorker`` after that, or a closed
connection, is retried once the same way.) An exception raised by the
work itself (a bug, bad input) is never re-run: ``map`` raises ``ChunkFailed`` at once, the
work's exception, with its traceback (the worker's, for a worker), as its ``__cause__``, and the
chunks not yet started are cancelled.

Ctrl-C is the run's alone: the terminal sends SIGINT to the whole process group, but the fork
server and the local workers never act on it (the server starts with SIGINT blocked, the workers
ignore it), so they print no ``KeyboardInterrupt`` of their own; the run's process gets it, and
``map`` then ends its workers at once (they would otherwise finish their chunks) and re-raises.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.forkserver
import multiprocessing.resource_tracker
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

from threadpoolctl import threadpool_limits

from pipeline.io.errors import UserError

PINNED_THREADS = {
    name: "1"
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
}


class ChunkFailed(RuntimeError):
    """Chunk ``chunk`` (its index in the submitted items) raised ``error`` (its ``__cause__``),
    or its worker was lost twice (``lost``)."""

    def __init__(self, chunk: int, error: BaseException, *, lost: bool = False) -> None:
        self.chunk = chunk
        self.lost = lost
        what = "lost its worker twice (retried once)" if lost else "failed"
        super().__init__(f"chunk {chunk} {what}: {type(error).__name__}: {error}")


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
            except Exception as error:  # no worker to lose: the work's own error
                raise ChunkFailed(index, error) from error
            if done:
                done(index)
        return results

    def close(self) -> None:
        pass


PARENT_POLL_SECONDS = 0.5


def _running(pid: int) -> bool:
    """Is process ``pid`` running (not gone, not a zombie waiting for its parent)?"""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:  # no /proc: kill(pid, 0) is all there is
        return True


def _worker_setup(run: int, environment: dict[str, str]) -> None:
    """Worker initializer: the run's ``environment`` as the pool started (a forked worker has
    the fork server's, from when it started; what is read at call time, e.g. the kernel cache
    folder, must be the run's), single-threaded BLAS whatever the server loaded, and exit as
    soon as the run's process ``run`` is gone (e.g. ``kill -9``), so that no orphaned worker
    keeps computing (the fork server, the worker's parent, exits once its workers have). A
    daemon thread polls it. SIGINT is ignored: Ctrl-C is the run's to handle (module docstring)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # blocked when forked (below)
    os.environ.clear()
    os.environ.update(environment)
    threadpool_limits(limits=1)
    warnings.simplefilter("ignore")  # a worker prints nothing: its result says how it went

    def watch() -> None:
        while _running(run):
            time.sleep(PARENT_POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-run", daemon=True).start()


_PRELOAD: set[str] = {__name__}  # modules the fork server imports when it starts


def preload_in_workers(module: str) -> None:
    """Have the fork server import ``module`` (one whose functions run in worker processes), so
    that its workers start with it imported. The first pool of a process starts the server:
    modules registered later are imported by each worker that needs them (as without)."""
    _PRELOAD.add(module)


# fork server where the platform has one (Linux, macOS), else spawned workers
START_METHOD = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


def _start_fork_server(preload: list[str]) -> None:
    """Start multiprocessing's fork server, if not running, with SIGINT blocked, and wait until it
    has imported the modules ``preload``.

    Blocked: the server (and every worker it forks) inherits the blocked signal, so a Ctrl-C while
    it imports (seconds: cvxpy, scipy) or while a worker unpickles its task prints no traceback;
    the server ignores SIGINT itself once ready. Blocked, not ignored, here: a SIGINT meanwhile
    is delivered to this process when unblocked. The resource tracker is started first: starting
    it unblocks SIGINT whatever the mask was.

    Waited for with a process that does nothing (``int()``): the server serves requests only once
    its imports are done, and a request it serves after this process has exited (interrupted
    while waiting) forks a child that cannot unpickle a pool worker's queues, whose semaphores
    are gone, and prints that traceback; this one needs nothing from here, and just exits."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(preload)
    multiprocessing.resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        multiprocessing.forkserver.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
    ready = context.Process(target=int, name="fork-server-ready", daemon=True)
    ready.start()
    ready.join()


class ProcessExecutor:
    """``jobs`` local processes with single-threaded BLAS, forked from the fork server (which
    imported the ``preload_in_workers`` modules when this process's first pool started it)."""

    def __init__(self, jobs: int) -> None:
        self.jobs = jobs
        self._pool: ProcessPoolExecutor | None = None

    def _start(self) -> ProcessPoolExecutor:
        if self._pool is None:
            saved = {name: os.environ.get(name) for name in PINNED_THREADS}
            os.environ.update(PINNED_THREADS)  # inherited by the fork server if it starts now
            try:
                context = multiprocessing.get_context(START_METHOD)
                if START_METHOD == "forkserver":
                    _start_fork_server(sorted(_PRELOAD))
                self._pool = ProcessPoolExecutor(
                    max_workers=self.jobs,
                    mp_context=context,
                    initializer=_worker_setup,
                    initargs=(os.getpid(), dict(os.environ)),
                )
                self._pool.submit(int).result()  # a worker starts under the pinned env
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
        try:
            pool = self._start()
            futures: list[Future[Any]] = [pool.submit(function, item) for item in items]
            results = []
            for index, future in enumerate(futures):
                try:
                    result = future.result()
                except BrokenProcessPool:  # a worker died: once more, alone, on a fresh pool
                    self._discard(pool)
                    result = self._retry(function, items[index], index)
                except Exception as error:  # raised by the work: never re-run
                    for queued in futures:
                        queued.cancel()
                    raise ChunkFailed(index, error) from error
                results.append(result)
                if done:
                    done(index)
            return results
        except KeyboardInterrupt:
            self._terminate()
            raise

    def _retry(self, function: Callable[[Any], Any], item: Any, index: int) -> Any:
        pool = self._start()
        try:
            return pool.submit(function, item).result()
        except BrokenProcessPool as error:
            self._discard(pool)
            raise ChunkFailed(index, error, lost=True) from error
        except Exception as error:
            raise ChunkFailed(index, error) from error

    def _discard(self, pool: ProcessPoolExecutor) -> None:
        """Forget the broken ``pool`` (once: the chunks after a lost one find it broken too, and
        keep the fresh pool their predecessor's retry started)."""
        if self._pool is pool:
            self._pool = None
            pool.shutdown(wait=False)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def _terminate(self) -> None:
        """Stop now (Ctrl-C): cancel the queued chunks and end the workers, which ignore SIGINT
        and would otherwise finish their running chunks first."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        workers = list((pool._processes or {}).values())  # no public handle on them
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            worker.terminate()
        for worker in workers:
            worker.join(timeout=5)


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
        from distributed import KilledWorker
        from distributed.comm import CommClosedError

        futures = [self.client.submit(function, item, pure=False) for item in items]
        results = []
        for index, future in enumerate(futures):
            try:
                result = future.result()
            except (KilledWorker, CommClosedError):  # its worker was lost: once more
                try:
                    result = self.client.submit(function, items[index], pure=False).result()
                except (KilledWorker, CommClosedError) as error:
                    raise ChunkFailed(index, error, lost=True) from error
                except Exception as error:
                    raise ChunkFailed(index, error) from error
            except Exception as error:  # raised by the work: never re-run
                self.client.cancel(futures)
                raise ChunkFailed(index, error) from error
            results.append(result)
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
