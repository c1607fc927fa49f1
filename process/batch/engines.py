"""Where a batch run's tasks execute: in this process, a local process pool, or Dask.

Every engine takes plain picklable calls (:meth:`Engine.submit`: a module-level function and
small records of paths and settings) and hands back :class:`concurrent.futures.Future` objects,
so :mod:`.runner` drives all three the same way. An engine never retries: the runner does
(once), so that a task that raises and a worker that dies are handled alike and reported.

* :class:`InProcessEngine` runs each task when :meth:`Engine.wait` asks for one (no cluster,
  one at a time, in submission order).
* :class:`ProcessPoolEngine` is a :class:`~concurrent.futures.ProcessPoolExecutor` (``spawn``:
  no forked copies of this process's threads). A pool process that dies breaks the pool and
  fails every task in flight; the pool is rebuilt at the next submission.
* :class:`DaskEngine` is a ``distributed.Client`` on a running scheduler (``tcp://host:8786``)
  or on a ``LocalCluster`` it starts (:meth:`DaskEngine.local`). Dask reschedules a task whose
  worker died ``distributed.scheduler.allowed-failures`` times by itself before it reports
  ``KilledWorker``; the local cluster sets that to 0 so the runner's one retry is the only one.

Dask rather than Ray: ``docs/cluster.md``.
"""

from __future__ import annotations

import abc
import concurrent.futures as cf
import logging
import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Collection
from typing import Any, Final, Literal

from mocaprig.errors import ProcessingError, ValidationError

__all__ = [
    "ClusterChoice",
    "DaskEngine",
    "Engine",
    "EngineKind",
    "InProcessEngine",
    "ProcessPoolEngine",
    "open_engine",
]

_log = logging.getLogger(__name__)

#: What runs the tasks.
EngineKind = Literal["in-process", "local", "dask"]
#: ``--cluster`` choices besides a scheduler address.
ClusterChoice = Literal["auto", "in-process", "local"]
#: The environment variable naming a Dask scheduler for ``--cluster auto``.
SCHEDULER_ENV: Final = "DASK_SCHEDULER_ADDRESS"


class Engine(abc.ABC):
    """Runs picklable calls and gives back futures; a context manager (closes on exit)."""

    kind: EngineKind
    workers: int
    address: str | None = None

    @abc.abstractmethod
    def submit(self, fn: Callable[..., Any], /, *args: Any) -> cf.Future[Any]:
        """Start ``fn(*args)``; its result or exception comes back through the future."""

    def wait(self, futures: Collection[cf.Future[Any]]) -> set[cf.Future[Any]]:
        """Block until at least one of ``futures`` is done; return the done ones."""
        done, _ = cf.wait(futures, return_when=cf.FIRST_COMPLETED)
        return set(done)

    def cancel(self, future: cf.Future[Any]) -> None:
        """Drop a task whose result is no longer wanted (one not started yet never runs)."""
        future.cancel()

    def close(self) -> None:  # noqa: B027 (engines without resources have nothing to close)
        """Release the workers."""

    def describe(self) -> str:
        """``"<kind> (<workers> workers[, address])"``."""
        where = f", {self.address}" if self.address else ""
        return f"{self.kind} ({self.workers} worker{'s' if self.workers != 1 else ''}{where})"

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class InProcessEngine(Engine):
    """Runs the tasks in this process, one at a time, when :meth:`wait` needs a result."""

    kind: EngineKind = "in-process"

    def __init__(self) -> None:
        self.workers = 1
        self._queue: deque[tuple[cf.Future[Any], Callable[..., Any], tuple[Any, ...]]] = deque()

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> cf.Future[Any]:
        fut: cf.Future[Any] = cf.Future()
        self._queue.append((fut, fn, args))
        return fut

    def wait(self, futures: Collection[cf.Future[Any]]) -> set[cf.Future[Any]]:
        done = {f for f in futures if f.done()}
        while not done and self._queue:
            fut, fn, args = self._queue.popleft()
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn(*args))
                except Exception as err:
                    fut.set_exception(err)
            done = {f for f in futures if f.done()}
        if not done:
            msg = "waiting on tasks that were never submitted to this engine"
            raise ProcessingError(msg)
        return done


class ProcessPoolEngine(Engine):
    """A local pool of ``workers`` processes (module doc)."""

    kind: EngineKind = "local"

    def __init__(self, workers: int) -> None:
        if workers < 1:
            msg = f"--workers must be >= 1, got {workers}"
            raise ValidationError(msg)
        self.workers = workers
        self._pool = self._start()

    def _start(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(
            max_workers=self.workers, mp_context=multiprocessing.get_context("spawn")
        )

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> cf.Future[Any]:
        try:
            return self._pool.submit(fn, *args)
        except cf.BrokenExecutor:
            _log.warning("a pool process died; starting a new pool of %d", self.workers)
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._start()
            return self._pool.submit(fn, *args)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskEngine(Engine):
    """Tasks on a Dask ``distributed`` cluster (module doc). Build it with :meth:`connect` or
    :meth:`local`."""

    kind: EngineKind = "dask"

    def __init__(self, client: Any, *, cluster: Any = None) -> None:
        self._client = client
        self._cluster = cluster
        # Our future -> Dask's, while it runs (Dask forgets a task whose future is dropped).
        self._tasks: dict[cf.Future[Any], Any] = {}
        self.address = str(client.scheduler.address)
        self.workers = max(1, len(client.scheduler_info().get("workers", {})))

    @classmethod
    def connect(cls, address: str, *, timeout_s: float = 30.0) -> DaskEngine:
        """A client of the scheduler at ``address`` (``tcp://host:8786``).

        Raises:
            ProcessingError: Dask is not installed, or no scheduler answers there.
        """
        distributed = _distributed()
        try:
            client = distributed.Client(address, timeout=f"{timeout_s}s")
        except (OSError, TimeoutError, ValueError) as err:
            msg = (
                f"--cluster {address}: no Dask scheduler answers ({err}); start one with "
                "`dask scheduler` and workers with `dask worker ADDRESS` (docs/cluster.md)"
            )
            raise ProcessingError(msg) from err
        return cls(client)

    @classmethod
    def local(cls, workers: int) -> DaskEngine:
        """A ``LocalCluster`` of ``workers`` single-threaded worker processes (a worker that
        dies is restarted by its nanny; its task is reported, not silently rescheduled)."""
        import dask

        distributed = _distributed()
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
            cluster = distributed.LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",  # any free port: several clusters may run here
            )
            client = distributed.Client(cluster)
        return cls(client, cluster=cluster)

    def submit(self, fn: Callable[..., Any], /, *args: Any) -> cf.Future[Any]:
        out: cf.Future[Any] = cf.Future()
        out.set_running_or_notify_cancel()
        task = self._client.submit(fn, *args, pure=False)

        self._tasks[out] = task

        def finished(f: Any) -> None:
            self._tasks.pop(out, None)
            try:
                out.set_result(f.result())
            except BaseException as err:  # a KilledWorker or CancelledError too
                out.set_exception(err)

        task.add_done_callback(finished)
        return out

    def cancel(self, future: cf.Future[Any]) -> None:
        task = self._tasks.pop(future, None)
        if task is not None:
            task.cancel()

    def close(self) -> None:
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()


def _distributed() -> Any:
    try:
        import distributed
    except ImportError as err:
        msg = (
            "Dask is not installed; install it to use a cluster: pip install 'dask[distributed]' "
            "(or run without --cluster ADDRESS)"
        )
        raise ProcessingError(msg) from err
    return distributed


def open_engine(cluster: str = "auto", *, workers: int | None = None) -> Engine:
    """The engine ``--cluster`` and ``--workers`` name.

    ``auto``: the Dask scheduler in ``$DASK_SCHEDULER_ADDRESS`` when set, else a local pool
    when ``workers`` > 1, else in-process. ``in-process``; ``local``: a process pool of
    ``workers`` (default: the CPU count); anything else is a Dask scheduler address.

    Raises:
        ValidationError: ``workers`` below 1, or a choice that is no address.
        ProcessingError: no scheduler at the address.
    """
    if workers is not None and workers < 1:
        msg = f"--workers must be >= 1, got {workers}"
        raise ValidationError(msg)
    if cluster == "auto":
        env = os.environ.get(SCHEDULER_ENV)
        if env:
            return DaskEngine.connect(env)
        return ProcessPoolEngine(workers) if workers and workers > 1 else InProcessEngine()
    if cluster == "in-process":
        return InProcessEngine()
    if cluster == "local":
        return ProcessPoolEngine(workers or os.cpu_count() or 1)
    if ":" not in cluster:
        msg = (
            f"--cluster {cluster}: give auto, in-process, local or a Dask scheduler address "
            "(tcp://host:8786)"
        )
        raise ValidationError(msg)
    if workers is not None:
        _log.warning("--workers %d is ignored with a scheduler: its workers run the tasks", workers)
    return DaskEngine.connect(cluster)
